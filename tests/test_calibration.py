"""The online check of the predicted spread (services/controller/calibration.py), driven with errors of
known distribution: a calibrated spread stays as it is, an over-confident one is widened until about
1 % of the predictions leave their 3-sigma region, each horizon step on its own, and headings wrap."""
import math

import numpy as np
import pytest

from common.path import Path
from services.controller.calibration import (GROWTH, MARGIN, PLACE_BIN_M, WINDOW, Prediction, SpreadCalibration,
                                             teach_places, teach_speeds)
from services.controller.horizon_covariance import HorizonCovariance
from services.controller.uncertainty import propagate, route_sigmas


def prediction(step: int, cal: SpreadCalibration, sigma: float = 0.01, heading: float = 0.0) -> Prediction:
    """A prediction at the origin (route along x), its model spread widened as the laws widen it."""
    f = cal.spread_factors()[step - 1]
    return Prediction(step, 0.0, heading, sigma * f, sigma * f, float(cal.scales[step - 1]))


def run(true_over_model: float, n: int, seed: int = 0) -> tuple[SpreadCalibration, list[bool]]:
    """n one-step predictions whose real errors are `true_over_model` times the model's sigma."""
    rng = np.random.default_rng(seed)
    cal, outside = SpreadCalibration(horizon=1), []
    for k in range(n):
        cal.predict(k, [prediction(1, cal)])
        err = 0.01 * true_over_model * rng.standard_normal(2)
        outside.append(cal.realize(k + 1, err[0], err[1], 0.0, 0.0)[0] > 3.0)
    return cal, outside


def test_a_calibrated_spread_is_left_as_it_is():
    cal, outside = run(1.0, 5000)
    assert cal.scales[0] < 1.5
    assert np.mean(outside) < 0.01          # two components: ~0.5 % expected


def test_an_over_confident_spread_is_widened_until_its_3_sigma_holds():
    cal, outside = run(4.0, 6000)           # the real errors are 4x what the model claims
    assert 9.0 < cal.scales[0] < 60.0       # ~16 would be exact in the RMS sense
    assert 0 < sum(outside[:50]) < 10       # the first exceedances widen it at once ...
    assert np.mean(outside[-3000:]) <= 0.01   # ... and then at most 1 % leave their 3-sigma region


def test_the_factor_never_narrows_the_models_own_spread():
    cal, _ = run(0.2, 3000)                 # the model is too cautious: the check leaves it
    assert cal.scales[0] == 1.0


def test_each_horizon_step_is_widened_by_its_own_errors():
    """A model biased by 1 cm per period (the error grows linearly over the horizon) with independent
    noise growing with sqrt(j), which the model knows of: the late steps are widened most, the first
    (whose spread decides whether to stop) least."""
    rng = np.random.default_rng(1)
    cal = SpreadCalibration(horizon=10)
    for k in range(3000):
        preds = []
        for j in range(1, 11):
            p = prediction(j, cal, sigma=0.01 * math.sqrt(j))
            miss = 0.01 * j + 0.01 * math.sqrt(j) * rng.standard_normal()
            preds.append(Prediction(j, -miss, 0.0, p.sigma_lat_m, p.sigma_head_rad, p.scale))
        cal.predict(k, preds)
        cal.realize(k, 0.0, 0.0, 0.0, 0.0)      # where the robot really is: on the route
    assert cal.scales[0] < cal.scales[4] < cal.scales[-1]
    assert np.all(cal.outside[1:] / cal.checked[1:] < 0.03)


def test_only_estimates_that_were_predicted_are_checked_and_headings_wrap():
    cal = SpreadCalibration(horizon=2)
    assert cal.realize(5, 0.0, 0.0, 0.0, 0.0) == []
    cal.predict(4, [Prediction(1, 0.1, math.pi - 0.01, 0.01, 0.02, 1.0)])
    z = cal.realize(5, 0.1, -math.pi + 0.01, 0.0, 0.0)     # 0.02 rad apart across the wrap
    assert z == [pytest.approx(1.0)] and cal.checked[0] == 1 and cal.outside[0] == 0
    cal.predict(5, [Prediction(2, 0.0, 0.0, 0.01, 0.01, 1.0)])
    assert cal.realize(7, 0.03, 0.0, 0.03 ** 2, 0.0) == [pytest.approx(0.03 / math.sqrt(0.01 ** 2 + 0.03 ** 2))]


def test_a_burst_of_exceedances_from_one_disturbance_widens_the_spread_once():
    """Ten predictions in flight (made with the same factor) all meet one unexpected push of 4 sigma:
    the factor grows to what holds it, not ten times over."""
    cal = SpreadCalibration(horizon=1)
    for k in range(10):
        cal.predict(k, [prediction(1, cal)])
    for k in range(10):
        cal.realize(k + 1, 0.04, 0.0, 0.0, 0.0)
    assert cal.outside[0] == 10 and cal.scales[0] == pytest.approx(1.1 * (4.0 / 3.0) ** 2)


def test_a_widening_is_forgotten_a_window_after_the_errors_that_asked_for_it():
    """A 4-sigma surprise (a corner the model did not know) widens the spread at once; WINDOW calibrated
    predictions later the spread is the model's own again, not slowed for the rest of the trial."""
    cal = SpreadCalibration(horizon=1)
    cal.predict(0, [prediction(1, cal)])
    cal.realize(1, 0.04, 0.0, 0.0, 0.0)
    assert cal.scales[0] == pytest.approx(MARGIN * (4.0 / 3.0) ** 2)
    for k in range(1, WINDOW):
        cal.predict(k, [prediction(1, cal)])
        cal.realize(k + 1, 0.0, 0.0, 0.0, 0.0)
    assert cal.scales[0] > 1.5                 # the surprise is still among the last WINDOW predictions
    cal.predict(WINDOW, [prediction(1, cal)])
    cal.realize(WINDOW + 1, 0.0, 0.0, 0.0, 0.0)
    assert cal.scales[0] == 1.0


def test_the_teach_factors_hold_until_a_window_is_seen_and_a_later_trial_continues_the_window():
    cal = SpreadCalibration(horizon=2, scales=np.array([4.0, 9.0]))
    assert cal.spread_factors() == pytest.approx((2.0, 3.0))
    for k in range(WINDOW):
        cal.predict(k, [prediction(1, cal)])
        assert cal.scales[0] == 4.0            # calibrated errors: the teach floor stays while the window fills
        cal.realize(k + 1, 0.0, 0.0, 0.0, 0.0)
    assert cal.scales[0] == 1.0 and cal.scales[1] == 9.0   # step 2 was never checked
    cal.predict(WINDOW, [prediction(1, cal)])
    cal.realize(WINDOW + 1, 0.05, 0.0, 0.0, 0.0)   # 5 sigma of the model's own spread
    nxt = cal.continued()
    assert nxt.scales[0] == pytest.approx(MARGIN * 25.0 / 9.0) and nxt.checked[0] == 0
    assert len(nxt.recent[0]) == WINDOW


def drive_pass(cal: SpreadCalibration, miss_at, step_m: float = 0.25, length_m: float = 100.0,
               v_mps: float = 1.0) -> None:
    """One pass along a 100 m route at `v_mps`, a one-step prediction every `step_m` made at its place
    with the factor the calibration gives there; `miss_at(s)`: the real error in model sigmas (0.01 m)."""
    for k, s in enumerate(np.arange(0.0, length_m, step_m)):
        kappa = float(cal.factors_at(s)[0])
        f = math.sqrt(kappa)
        cal.predict(k, [Prediction(1, 0.0, 0.0, 0.01 * f, 0.01 * f, kappa, s_m=float(s), v_mps=v_mps)])
        cal.realize(k + 1, 0.01 * miss_at(s), 0.0, 0.0, 0.0)


def test_a_places_surprise_widens_the_spread_there_on_the_next_pass_and_nowhere_else():
    """A rough patch at 40-44 m the model does not know: 4-sigma errors there. The recent window has
    forgotten them by the end of the pass (the next trial would enter the patch unwidened); the place
    remembers them for the next pass, over the patch and its neighbouring bins only, and a later pass
    whose errors there are calibrated (the model has learned the patch) narrows it again."""
    rough = lambda s: 4.0 if 40.0 <= s < 44.0 else 0.0      # noqa: E731
    cal = SpreadCalibration(horizon=1)
    drive_pass(cal, rough)
    assert cal.scales[0] == 1.0 and cal.factors_at(None)[0] == 1.0
    second = cal.continued()
    assert second.factors_at(41.0)[0] == pytest.approx(MARGIN * 16.0 / 9.0)
    assert second.factors_at(40.0 - PLACE_BIN_M)[0] == pytest.approx(MARGIN * 16.0 / 9.0)   # a neighbour
    assert second.factors_at(80.0)[0] == 1.0 and second.factors_at(None)[0] == 1.0
    drive_pass(second, rough)
    assert second.outside[0] == 0                   # the patch's errors now lie inside their 3 sigma
    third = second.continued()
    drive_pass(third, lambda s: 0.0)
    assert third.continued().factors_at(41.0)[0] == 1.0


def test_the_teach_passs_needs_by_place_widen_the_first_trial_there_until_it_has_passed_itself():
    """The teach pass needed twice the spread at 40-42 m (identification.place_factors, 1 m rows): the
    first trial starts widened there and at the neighbouring bins (4x the variance, with the margin), not
    elsewhere; after its own calibrated pass the place narrows again."""
    rows = [[1.0, 1.0]] * 100
    rows[40] = rows[41] = [2.0, 1.5]
    places = teach_places(1.0, rows, 3)
    assert set(places) == {20}                      # 1 m rows into PLACE_BIN_M bins, calm places left out
    np.testing.assert_allclose(places[20], [4.0, 2.25, 2.25])   # squared, the last step's carried on
    first = SpreadCalibration(horizon=3, places=places)
    assert first.factors_at(41.0)[0] == pytest.approx(MARGIN * 4.0)
    assert first.factors_at(38.5)[1] == pytest.approx(MARGIN * 2.25)
    assert first.factors_at(60.0)[0] == 1.0
    drive_pass(first, lambda s: 0.0)
    assert first.continued().factors_at(41.0)[0] == 1.0


def test_a_calm_pass_vouches_for_a_place_only_up_to_a_little_above_its_speed():
    """The teach pass (1.0 m/s) needed twice the spread at 40-42 m. Trial 1 crosses it calmly at 1.4 m/s:
    its needs replace the teach pass's, for plans up to GROWTH x 1.4 m/s; a faster plan there is widened
    by the teach pass's needs again, as is any plan at a place the teach pass found rough but no trial
    has passed faster. A slower calm pass (0.5 m/s) replaces the needs with its own, which vouch only up
    to GROWTH x its speed, whatever faster passes before it drove. Places the teach pass found calm have
    no such limit."""
    rows = [[1.0]] * 50
    rows[20] = [2.0]
    first = SpreadCalibration(horizon=1, places=teach_places(2.0, rows, 1), speeds=teach_speeds(2.0, [1.0] * 50))
    b = first.beyond_at(41.0)
    assert b.speed_mps == pytest.approx(GROWTH * 1.0) and b.factors[0] == pytest.approx(MARGIN * 4.0)
    assert first.beyond_at(80.0).factors is None and first.beyond_at(80.0).speed_mps == math.inf
    drive_pass(first, lambda s: 0.0, v_mps=1.4)
    second = first.continued()
    assert second.factors_at(41.0)[0] == 1.0                      # the calm pass replaced the teach's needs
    b = second.beyond_at(41.0)
    assert b.speed_mps == pytest.approx(GROWTH * 1.4) and b.factors[0] == pytest.approx(MARGIN * 4.0)
    drive_pass(second, lambda s: 0.0, v_mps=0.5)                  # a calm crawl
    b = second.continued().beyond_at(41.0)
    assert b.speed_mps == pytest.approx(GROWTH * 0.5) and b.factors[0] == pytest.approx(MARGIN * 4.0)


def test_a_factor_learned_at_speed_widens_only_the_models_share_of_the_spread():
    """Errors 4x the model's share widen that share 16x in variance, not the localizer's own covariance
    carried along the plan: at standstill (the spread all the localizer's) the robot's 3-sigma region is
    the localizer's, where widening the whole spread had stopped a robot before it moved."""
    rng = np.random.default_rng(2)
    cal, model, loc = SpreadCalibration(horizon=1), 0.01, 0.02
    for k in range(3000):
        wide = math.sqrt(loc ** 2 + cal.scales[0] * model ** 2)
        cal.predict(k, [Prediction(1, 0.0, 0.0, wide, wide, float(cal.scales[0]), loc, loc)])
        err = 4.0 * model * rng.standard_normal(2)          # the localizer's error is in the estimate's
        cal.realize(k + 1, err[0], err[1], 0.0, 0.0)
    assert 9.0 < cal.scales[0] < 60.0
    cov = HorizonCovariance(var=None, Sigma0=np.eye(3), dt=0.1, gamma=2.0, factors=np.array(cal.spread_factors()))
    standstill = np.array([[0.0, loc, loc]])
    moving = np.array([[0.0, math.hypot(loc, model), math.hypot(loc, model)]])
    assert np.allclose(cov.widened(standstill, standstill), standstill)
    assert cov.widened(moving, standstill)[0, 1] == pytest.approx(math.sqrt(loc ** 2 + cal.scales[0] * model ** 2))


def test_the_localizers_share_is_its_covariance_carried_along_the_plan():
    """Against the sigma-point transform with no disturbance (an independent computation): the
    localizer's covariance at the captured pose, carried along a curved plan."""
    path = Path("arc", np.column_stack([np.linspace(0, 10, 101), np.zeros(101), np.zeros(101)]))
    v, w = np.full(15, 1.0), np.full(15, 0.3)
    X = np.zeros((16, 3))
    for j in range(15):
        X[j + 1] = X[j] + 0.1 * np.array([v[j] * math.cos(X[j, 2]), v[j] * math.sin(X[j, 2]), w[j]])
    P = np.diag([0.02 ** 2, 0.01 ** 2, math.radians(2.0) ** 2])
    reference = route_sigmas(propagate(X, None, np.zeros((15, 3)), np.zeros((15, 3)), v, w, P, 0.1, 2.0),
                             np.zeros(15))
    cov = HorizonCovariance(var=None, Sigma0=P, dt=0.1, gamma=2.0, Sigma_loc=P, captured_xy=(0.0, 0.0))
    assert np.allclose(cov.localizer_part(X, np.zeros(15)), reference, rtol=0.02)


def test_a_place_counts_from_where_the_robot_could_still_slow_down_for_it():
    """At 2 m/s a drive held to 0.5 m/s^2 needs 4 m to slow down: a plan made 6 m before the rough patch
    of the last pass (or before one the teach pass found rough) already allows for it; at a crawl, or
    further back, only the neighbouring places count."""
    rough = lambda s: 4.0 if 40.0 <= s < 44.0 else 0.0      # noqa: E731
    cal = SpreadCalibration(horizon=1, brake_mps2=0.5)
    drive_pass(cal, rough)
    second = cal.continued()
    assert second.brake_mps2 == 0.5
    assert second.factors_at(34.0, 2.0)[0] == pytest.approx(MARGIN * 16.0 / 9.0)
    assert second.factors_at(34.0, 0.0)[0] == 1.0 and second.factors_at(30.0, 2.0)[0] == 1.0
    rows = [[1.0]] * 50
    rows[20] = [2.0]
    teach = SpreadCalibration(horizon=1, places=teach_places(2.0, rows, 1), speeds=teach_speeds(2.0, [1.0] * 50),
                              brake_mps2=0.5)
    b = teach.beyond_at(34.0, 2.0)
    assert b.speed_mps == pytest.approx(GROWTH * 1.0) and b.factors[0] == pytest.approx(MARGIN * 4.0)
    assert teach.beyond_at(34.0, 0.0).factors is None and teach.factors_at(34.0, 0.0)[0] == 1.0


def test_the_corridor_share_is_the_larger_of_the_lateral_towards_its_side_and_the_heading():
    from services.controller.corridor import Corridor
    c = Corridor(np.arange(0.0, 50.0, 0.5), 0.2, math.radians(20.0))
    c.update(10.0, 20.0, 0.2, -0.4, math.radians(20.0))
    assert c.share(5.0, 0.1, 0.0) == pytest.approx(0.5)
    assert c.share(15.0, -0.1, 0.0) == pytest.approx(0.25)          # the right side is 0.4 m wide there
    assert c.share(15.0, -0.1, math.radians(-15.0)) == pytest.approx(0.75)
    c.update(30.0, 40.0, 0.3, 0.0, math.radians(20.0))                # the route on the corridor's right edge
    assert c.share(35.0, 0.15, 0.0) == pytest.approx(0.5) and c.share(35.0, -0.01, 0.0) == math.inf
    assert c.share(35.0, 0.0, 0.0) == 0.0


def test_a_pass_near_the_corridors_edge_holds_its_speed_there_and_a_calm_one_lets_it_grow_in_proportion():
    """The latest pass (1.0 m/s) took 90 % of the corridor at 40-42 m and 40 % at 60-62 m: a plan there is
    held to 1.0 m/s (errors grown in proportion to speed would pass GUARD_SHARE at once), to 2.0 m/s
    (GUARD_SHARE / 0.4), and nowhere else; at 2 m/s with a 0.5 m/s^2 brake the place is counted from
    4 m before it. A later pass that stays calm there lifts the hold."""
    from services.controller.calibration import GUARD_SHARE
    cal = SpreadCalibration(horizon=1, brake_mps2=0.5)
    for s in np.arange(0.0, 100.0, 0.25):
        share = 0.9 if 40.0 <= s < 42.0 else 0.4 if 60.0 <= s < 62.0 else 0.0
        cal.observe(float(s), share)
    drive_pass(cal, lambda s: 0.0)                                   # the pass's speeds: 1.0 m/s
    nxt = cal.continued()
    assert nxt.speed_cap_at(41.0).speed_mps == pytest.approx(1.0) and nxt.speed_cap_at(41.0).share == 0.9
    assert nxt.speed_cap_at(61.0).speed_mps == pytest.approx(GUARD_SHARE / 0.4)
    assert nxt.speed_cap_at(80.0).speed_mps == math.inf and nxt.speed_cap_at(None).speed_mps == math.inf
    assert nxt.speed_cap_at(36.5, 0.0).speed_mps == math.inf
    assert nxt.speed_cap_at(36.5, 2.0).speed_mps == pytest.approx(1.0)      # 4 m of braking before it
    for s in np.arange(0.0, 100.0, 0.25):
        nxt.observe(float(s), 0.1)
    drive_pass(nxt, lambda s: 0.0, v_mps=1.2)
    assert nxt.continued().speed_cap_at(41.0).speed_mps == pytest.approx(1.2 * GUARD_SHARE / 0.1)


def test_the_steering_margin_a_pass_took_caps_a_place_as_its_share_of_the_corridor_does():
    """A pass at 1.0 m/s whose commands took 95 % of the steering margin at 40-42 m (and 10 % of the
    corridor there): the next pass is held to 1.0 m/s there, and the cap says it was the steering margin."""
    cal = SpreadCalibration(horizon=1)
    for s in np.arange(0.0, 100.0, 0.25):
        cal.observe(float(s), 0.1)
        if 40.0 <= s < 42.0:
            cal.observe(float(s), 0.95, "steering margin")
    drive_pass(cal, lambda s: 0.0)
    cap = cal.continued().speed_cap_at(41.0)
    assert cap.speed_mps == pytest.approx(1.0) and cap.share == 0.95 and cap.what == "steering margin"
    assert cal.continued().speed_cap_at(70.0).what == "corridor"


def test_the_turn_share_is_the_averaged_correction_over_the_margin_the_route_leaves_and_nothing_at_a_crawl():
    """Worked by hand: an Ackermann (0.3 /m) at 1 m/s on a 0.1 /m curve has 0.2 rad/s of margin; commands
    0.25, 0.28, 0.31 (mean 0.28) correct by 0.18 of it: 0.9. One step back to -0.05 leaves a mean of 0.18:
    0.08 / 0.2. A skid-steer (1.2 rad/s) on a straight at 0.6 rad/s: 0.5. A route tighter than the
    limit: all of it. A crawl: nothing."""
    from services.controller.turn_share import TurnShare
    ackermann = TurnShare(0.1, lambda v: min(1.0, abs(v) * 0.3))
    shares = [ackermann.add(1.0, w, 0.1) for w in (0.25, 0.28, 0.31)]
    assert math.isnan(shares[0]) and math.isnan(shares[1]) and shares[2] == pytest.approx(0.9)
    assert ackermann.add(1.0, -0.05, 0.1) == pytest.approx(0.08 / 0.2)
    skid = TurnShare(0.1, lambda v: 1.2)
    assert [skid.add(1.5, 0.6) for _ in range(3)][-1] == pytest.approx(0.5)
    assert [skid.add(1.5, 1.1, 1.25) for _ in range(3)][-1] == 1.0
    crawl = TurnShare(0.1, lambda v: abs(v) * 0.3)
    assert all(math.isnan(crawl.add(0.05, 0.02)) for _ in range(5))


def test_the_teach_passs_steering_margin_caps_trial_1_where_it_took_most_of_it():
    """The teach pass (1 m rows, identification.place_turn_shares) took 95 % of its steering margin at
    40-41 m at 0.8 m/s and 40 % at 60-61 m at 0.9 m/s: trial 1 is held to 0.8 m/s at the first place and
    to 0.9 * 0.8 / 0.4 = 1.8 m/s at the second, and says it was the teach pass's margin; once trial 1
    has passed a place, its own shares replace the teach pass's there."""
    from services.controller.calibration import TEACH_STEERING, teach_shares, teach_speeds
    shares, speeds = [0.0] * 100, [0.8] * 100
    shares[40], shares[60], speeds[60] = 0.95, 0.4, 0.9
    cal = SpreadCalibration(horizon=1, speeds=teach_speeds(1.0, speeds), shares=teach_shares(1.0, shares))
    first = cal.speed_cap_at(41.0)
    assert first.speed_mps == pytest.approx(0.8) and first.share == 0.95 and first.what == TEACH_STEERING
    assert first.at_m == 40.0
    assert cal.speed_cap_at(61.0).speed_mps == pytest.approx(1.8)
    assert cal.speed_cap_at(80.0).speed_mps == math.inf
    for s in np.arange(0.0, 100.0, 0.25):
        cal.observe(float(s), 0.1)
    drive_pass(cal, lambda s: 0.0)
    assert cal.continued().speed_cap_at(41.0).what == "corridor"
