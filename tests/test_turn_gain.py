"""A robot that turns at a share of its drive's turn rate (a skid-steer's ground slip; actuator.py
turn_gain): the laws that know the share ask its drive for the route's turn rate over it and hold the
route in the corners, where laws planning with gain 1 fall outward. Closed loop on the simulator, no
learned model: the nominal model alone."""
import numpy as np
import pytest

from bench.closed_loop import ClosedLoop
from common.robot import robot_from_preset
from services.controller.actuator import ActuatorLag
from services.controller.fl import FLGains
from services.controller.ilc import ILCLaw, ILCMemory
from services.controller.laws import FLLaw
from services.controller.nmpc import LBNMPCLaw
from services.controller.settings import NMPCSettings

ROUTE = [[0, 0], [15, 0], [22, 7], [22, 20], [10, 26]]
SHARE = 0.5      # the robot's turn rate over its drive's, at low speed


def _robot():
    return robot_from_preset("grizzly", {"turn_efficiency": SHARE, "turn_loss_per_mps2": 0.0,
                                         "noise_v_mps": 0.0, "noise_w_radps": 0.0})


def _max_lateral(make_law, gain: float) -> float:
    cl = ClosedLoop(ROUTE, preset=_robot(), seed=3, teach_speed=0.6)
    path = cl.teach()
    lag = ActuatorLag(0.45, 0.4, 0.1, turn_gain=gain)
    r = cl.repeat(1, 1.2, law=make_law(gain, path), lag=lag)
    assert r.finished
    return r.max_lateral


@pytest.mark.parametrize("name, make_law", [
    ("fl", lambda g, path: FLLaw(FLGains(), g)),
    ("ilc", lambda g, path: ILCLaw(FLGains(), ILCMemory("route", len(path)), g)),
    ("lb-nmpc", lambda g, path: LBNMPCLaw(NMPCSettings(actuator_tau_s=(0.45, 0.4), turn_gain=g), 0.1))])
def test_a_law_that_knows_the_turn_gain_holds_the_corners(name, make_law):
    unaware, aware = _max_lateral(make_law, 1.0), _max_lateral(make_law, SHARE)
    assert aware < 0.6 * unaware, (name, aware, unaware)


def test_fl_and_ilc_command_the_robots_wanted_turn_rate_over_the_gain():
    """Eq. 3.5 gives the robot's turn rate; the drive is asked for it over the gain, the feedforward too."""
    from services.controller.laws import StepContext
    from common.path import Path
    path = Path("p", np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)]))
    ctx = StepContext(now_s=0.0, path=path, vertex=3, pose=np.array([3.0, 0.2, 0.1]), s_m=3.0, e_lat_m=0.2,
                      e_head_rad=0.1, v_mps=1.0, speed_at=lambda s: 1.0, prev_cmd=(1.0, 0.0), prev_pose=None,
                      w_limit=5.0, w_limit_at=lambda v: 5.0)
    w1 = FLLaw(FLGains()).angular(ctx).w_radps
    assert FLLaw(FLGains(), 0.5).angular(ctx).w_radps == pytest.approx(2.0 * w1)
    mem = ILCMemory("p", 10)
    mem.w_ff[3] = 0.1
    res = ILCLaw(FLGains(), mem, 0.5).angular(ctx)
    assert res.w_radps == pytest.approx(2.0 * (w1 + 0.1)) and res.feedforward_radps == pytest.approx(0.2)
