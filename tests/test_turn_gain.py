"""A robot that turns at a share of its drive's turn rate (a skid-steer's ground slip; actuator.py
turn_gain): the laws that know the share ask its drive for the route's turn rate over it and hold the
route in the corners, where laws planning with gain 1 fall outward. Closed loop on the simulator, no
learned model: the nominal model alone."""
import numpy as np
import pytest

from bench.closed_loop import ClosedLoop
from common.robot import robot_from_preset
from services.controller.actuator import ActuatorLag
from services.controller.fl import FLGains, route_turn_rate
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
    r = cl.repeat(1, 1.2, law=make_law(lag, path), lag=lag)
    assert r.finished
    return r.max_lateral


@pytest.mark.parametrize("name, make_law", [
    ("fl", lambda lag, path: FLLaw(FLGains(), lag)),
    ("ilc", lambda lag, path: ILCLaw(FLGains(), ILCMemory("route", len(path)), lag)),
    ("lb-nmpc", lambda lag, path: LBNMPCLaw(NMPCSettings(actuator_tau_s=(0.45, 0.4), turn_gain=lag.turn_gain), 0.1))])
def test_a_law_that_knows_the_turn_gain_holds_the_corners(name, make_law):
    """A Grizzly turning at half its drive's rate, 1.2 m/s, no learning yet: FL and ILC (trial 1) 0.55 ->
    0.25 m, the route's own turn rate asked of the drive over the gain; LB-NMPC 0.24 -> 0.025 m, its
    model turning as the robot does."""
    unaware, aware = _max_lateral(make_law, 1.0), _max_lateral(make_law, SHARE)
    assert aware < 0.6 * unaware, (name, aware, unaware)


def test_fl_and_ilc_ask_the_drive_for_the_routes_turn_rate_over_the_gain():
    """Eq. 3.5's route turn rate is asked of the drive over the gain; the feedback and the learned
    feedforward are commands as they were (fl.py)."""
    from common.path import Path
    from services.controller.laws import StepContext
    from services.bridge.teach_driver import smooth_waypoints
    path = Path("p", smooth_waypoints([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0]], 3.0, False))
    i = int(np.argmax(np.abs(path.curvature)))
    kappa = float(path.curvature[i])
    assert abs(kappa) > 0.01
    ctx = StepContext(now_s=0.0, path=path, vertex=i, pose=path.poses[i], s_m=float(path.s[i]), e_lat_m=0.0,
                      e_head_rad=0.0, v_mps=1.0, speed_at=lambda s: 1.0, prev_cmd=(1.0, 0.0), prev_pose=None,
                      w_limit=5.0, w_limit_at=lambda v: 5.0)
    half = ActuatorLag(turn_gain=0.5)
    assert FLLaw(FLGains(), half).angular(ctx).w_radps == pytest.approx(2.0 * kappa)
    moved = StepContext(**{**ctx.__dict__, "e_lat_m": 0.2})
    fb = FLLaw(FLGains(curvature_feedforward=False)).angular(moved).w_radps
    route = route_turn_rate(1.0, 0.2, 0.0, kappa)
    assert FLLaw(FLGains(), half).angular(moved).w_radps == pytest.approx(fb + 2.0 * route)
    mem = ILCMemory("p", len(path))
    mem.w_ff[i] = 0.1
    res = ILCLaw(FLGains(), mem, half).angular(moved)
    assert res.w_radps == pytest.approx(fb + 2.0 * route + 0.1) and res.feedforward_radps == pytest.approx(0.1)
