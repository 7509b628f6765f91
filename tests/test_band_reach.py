import math

import numpy as np

from services.controller.band_reach import reach_capped

K, DT = 10, 0.1
HI, LO, HEAD = np.full(K, 0.05), np.full(K, -0.05), np.full(K, math.radians(10))
CAP = np.column_stack([np.full(K, np.inf), np.full(K, 0.04), np.full(K, math.radians(8))])
CAP[0] = np.inf


def test_far_from_the_edges_the_cap_is_unchanged():
    out = reach_capped(CAP, (0.0, 0.0), np.full(K, 1.0), np.full(K, 1.2), DT, LO, HI, HEAD, np.zeros((K, 3)))
    np.testing.assert_array_equal(out, CAP)


def test_at_a_crawl_by_the_edge_the_band_starts_where_a_path_followers_correction_takes_the_mean():
    """Worked by hand: 0.1 m/s, so the correction turns at 1/m x 0.1 m/s = 0.1 rad/s (below half the
    1.2 rad/s limit), heading -0.01 i rad over period i, never beyond half the 10 deg band (0.0873 rad)."""
    e0, v = 0.03, 0.1
    out = reach_capped(CAP, (e0, 0.0), np.full(K, v), np.full(K, 1.2), DT, LO, HI, HEAD, np.zeros((K, 3)))
    heading = -np.minimum(0.01 * np.arange(K), 0.5 * math.radians(10))
    lowest = e0 + v * DT * np.cumsum(np.sin(heading))              # x_1 .. x_K
    assert math.isinf(out[0, 1]) and math.isinf(out[0, 2])         # the first step keeps its full spread
    np.testing.assert_allclose(out[1:, 1], np.minimum(0.04, 0.05 - lowest[1:]), atol=1e-12)
    assert abs(out[1, 1] - (0.05 - e0)) < 2e-4 and out[-1, 1] < 0.04  # by x_2 the mean has barely moved
    np.testing.assert_array_equal(out[:, 2], CAP[:, 2])             # heading error 0: nothing to reach


def test_a_heading_error_beyond_the_band_turns_back_at_the_correction_rate():
    """1 m/s, 9.5 deg outward: the correction turns back at min(0.6, 1.0) rad/s, 0.06 rad per period."""
    h0 = math.radians(9.5)
    out = reach_capped(CAP, (0.0, h0), np.full(K, 1.0), np.full(K, 1.2), DT, LO, HI, HEAD, np.zeros((K, 3)))
    least = np.maximum(h0 - 0.06 * np.arange(1, K + 1), 0.0)
    np.testing.assert_allclose(out[1:, 2], np.minimum(math.radians(8), np.maximum(HEAD[1:] - least[1:], 0)))
    assert out[1, 2] < math.radians(8) and out[-1, 2] == math.radians(8)


def test_a_first_step_already_outside_its_band_keeps_every_demand():
    """3 cm from a 5 cm edge with a 3-sigma of 2.5 cm at x_1: the robot is in trouble, nothing is relaxed."""
    t = np.full((K, 3), 0.025)
    out = reach_capped(CAP, (0.03, 0.0), np.full(K, 0.1), np.full(K, 1.2), DT, LO, HI, HEAD, t)
    np.testing.assert_array_equal(out, CAP)
