"""Steps in the estimate the robot did not make (services/controller/estimate_jumps.py): found on routes
driven with the Frenet kinematics and a seeded localizer noise, told apart from a slide that starts,
and taken off the online check of the spread (calibration.py)."""
import math

import numpy as np
import pytest

from services.controller.calibration import Prediction, SpreadCalibration
from services.controller.estimate_jumps import EstimateJumps, Jump

DT, V = 0.1, 1.2


def drive(n: int, kappa: float = 0.0, slide_mps=lambda k: 0.0, seed: int = 0):
    """Route errors (s, e_lat, e_head) per tick of a robot weaving across a route of curvature `kappa`
    (Frenet kinematics, exact to first order per tick), with 3 mm of frame-to-frame localizer noise and
    a sideways slide in m/s from tick k on."""
    rng = np.random.default_rng(seed)
    s, e, h, out = 0.0, 0.0, 0.0, []
    for k in range(n):
        w = kappa * V + 0.15 * math.sin(0.2 * k)        # the robot's turn rate (rad/s): the route's, weaving
        ds = V * math.cos(h) / (1.0 - kappa * e) * DT
        e += V * math.sin(h) * DT + slide_mps(k) * DT
        h += (w - kappa * ds / DT) * DT
        s += ds
        out.append((s, e + 0.003 * rng.standard_normal(), h + 0.002 * rng.standard_normal()))
    return out


def detect(errors, shift=lambda k: 0.0, kappa: float = 0.0) -> tuple[EstimateJumps, int]:
    det, candidates = EstimateJumps(), 0
    for k, (s, e, h) in enumerate(errors):
        candidates += det.add(k, s, e + shift(k), h, kappa)
    return det, candidates


@pytest.mark.parametrize("kappa", [0.0, 0.2])
def test_a_stretch_where_the_estimate_is_shifted_sideways_is_two_jumps_of_its_size(kappa):
    det, _ = detect(drive(200, kappa), lambda k: 0.08 if 80 <= k < 100 else 0.0, kappa)
    assert [j.capture_tick for j in det.jumps] == [80, 100]
    assert [j.lateral_m for j in det.jumps] == pytest.approx([0.08, -0.08], abs=0.012)
    assert det.offset_between(70, 90) == pytest.approx(det.jumps[0].lateral_m)
    assert det.offset_between(79, 120) == pytest.approx(0.0, abs=0.02)
    assert det.offset_between(80, 90) == 0.0              # a plan started from the jumped estimate


@pytest.mark.parametrize("kappa", [0.0, 0.2])
def test_weaving_across_a_route_with_localizer_noise_has_no_jumps(kappa):
    for seed in range(5):
        assert detect(drive(600, kappa, seed=seed), kappa=kappa)[0].jumps == []


def test_a_slide_that_starts_at_once_and_keeps_going_is_motion_not_a_jump():
    det, candidates = detect(drive(200, slide_mps=lambda k: 0.4 if k >= 80 else 0.0))
    assert candidates >= 1 and det.jumps == []


def test_a_gap_in_the_estimates_gives_no_verdict():
    det = EstimateJumps()
    for k, (s, e, h) in enumerate(drive(60)):
        if k != 41:                                        # the estimate after the step is missing
            det.add(k, s, e + (0.08 if k >= 40 else 0.0), h)
    assert det.jumps == []


def test_a_check_across_a_jump_takes_it_off_and_asks_for_no_widening():
    """A plan from the estimate of tick 10 predicts the robot on the route at 11-13; the estimate steps
    0.08 m sideways at 12 while the robot stays on the route (1 cm spread)."""
    jumps = EstimateJumps()
    jumps.jumps.append(Jump(12, 0.08))
    scales = {}
    for with_jumps in (False, True):
        cal = SpreadCalibration(horizon=3)
        cal.predict(10, [Prediction(j, 0.0, 0.0, 0.01, 0.01, 1.0, from_tick=10) for j in (1, 2, 3)])
        for tick in (11, 12, 13):
            lateral = 0.08 if tick >= 12 else 0.0
            jumped = (lambda c0, t=tick: jumps.offset_between(c0, t)) if with_jumps else None
            cal.realize(tick, lateral, 0.0, 1e-6, 1e-6, jumped)
        scales[with_jumps] = cal.scales.copy()
    assert scales[True] == pytest.approx([1.0, 1.0, 1.0])
    assert scales[False][1] > 5.0 and scales[False][2] > 5.0      # (0.08 / 3)^2 / 0.01^2 = 7.1, x1.1


def test_the_core_sends_no_experience_across_a_jump_and_every_other_one():
    """A robot driven straight along a route by the core, its estimate shifted 0.08 m sideways from tick
    40 on: the experiences ending at the step and the one after it (whose measured velocity spans it) are
    not sent; with no jump, all are."""
    from tests.test_tracker import LIMITS, PATH, StopsAt, loc
    from services.controller.core import ControllerCore
    from services.controller.tracker import PathTracker
    sent = {}
    for shift in (0.0, 0.08):
        core = ControllerCore(PATH, PathTracker(PATH, StopsAt(math.inf), LIMITS, speed_mps=0.5), 0.1)
        rng, ticks = np.random.default_rng(2), []
        for k in range(80):
            t = 0.1 * k
            d, obs = core.step(t, k, loc(t, x=1.0 + 0.05 * k, y=(shift if k >= 40 else 0.0) + 0.002 * rng.standard_normal()))
            ticks += [k for _ in obs]
        sent[shift] = ticks
    assert len(sent[0.08]) == len(sent[0.0]) - 2
    assert 40 not in sent[0.08] and 41 not in sent[0.08]
