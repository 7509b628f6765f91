"""SE(2) identities and the taught-route Path (projection, nearest vertex, relative pose)."""
import math

import numpy as np
import pytest

from common import se2
from common.path import Path, RouteRecorder

rng = np.random.default_rng(0)
POSES = np.column_stack([rng.uniform(-5, 5, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])


def test_inverse_and_identity():
    I = np.zeros(3)
    for T in POSES:
        np.testing.assert_allclose(se2.compose(T, se2.inverse(T)), I, atol=1e-12)
        np.testing.assert_allclose(se2.compose(se2.inverse(T), T), I, atol=1e-12)
        np.testing.assert_allclose(se2.compose(T, I), T, atol=1e-12)


def test_compose_is_associative_and_matches_matrices():
    A, B, C = POSES[:3]
    np.testing.assert_allclose(se2.compose(se2.compose(A, B), C), se2.compose(A, se2.compose(B, C)), atol=1e-12)
    M = se2.to_matrix(A) @ se2.to_matrix(B)
    np.testing.assert_allclose(se2.compose(A, B), se2.from_matrix(M), atol=1e-12)
    # vectorised over stacks equals the loop
    stacked = se2.compose(POSES[:-1], POSES[1:])
    for k in range(len(POSES) - 1):
        np.testing.assert_allclose(stacked[k], se2.compose(POSES[k], POSES[k + 1]), atol=1e-12)


def test_between_and_transform_points():
    A, B = POSES[:2]
    np.testing.assert_allclose(se2.compose(A, se2.between(A, B)), B, atol=1e-12)
    p = np.array([1.0, 2.0])
    np.testing.assert_allclose(se2.transform_points(se2.inverse(A), se2.transform_points(A, p)), p, atol=1e-12)


def test_wrap():
    assert se2.wrap(3 * math.pi) == pytest.approx(-math.pi)
    np.testing.assert_allclose(se2.wrap(np.array([0.1, 2 * math.pi + 0.1, -2 * math.pi - 0.1])), [0.1, 0.1, -0.1])


def test_adjoint_moves_perturbations_between_frames():
    """T exp(xi) = exp(Ad(T) xi) T to first order."""
    T = np.array([1.5, -0.7, 0.9])
    xi = np.array([1e-6, -2e-6, 1.5e-6])
    right = se2.compose(T, xi)
    left = se2.compose(se2.adjoint(T) @ xi, T)
    np.testing.assert_allclose(right, left, atol=1e-11)


def straight_then_arc(spacing=0.25, radius=5.0):
    pts = [(x, 0.0, 0.0) for x in np.arange(0, 10, spacing)]
    for a in np.arange(0, math.pi / 2, spacing / radius):
        pts.append((10 + radius * math.sin(a), radius - radius * math.cos(a), a))
    return Path("arc", np.array(pts), spacing_m=spacing)


def test_path_geometry():
    p = straight_then_arc()
    assert p.length_m == pytest.approx(10 + 5 * math.pi / 2, abs=0.3)
    assert abs(p.curvature[10]) < 1e-9
    assert p.curvature[len(p) - 10] == pytest.approx(1 / 5.0, rel=0.02)


def test_projection_on_straight_and_arc():
    p = straight_then_arc()
    pr = p.project((4.1, 0.3, 0.1))
    assert pr.lateral_m == pytest.approx(0.3) and pr.distance_m == pytest.approx(4.1)
    assert pr.heading_rad == pytest.approx(0.1)
    # a point 0.2 m outside the arc (to the right of the route) at 30 degrees
    a = math.radians(30)
    q = (10 + 5.2 * math.sin(a), 5 - 5.2 * math.cos(a), a)
    pr = p.project(q)
    assert pr.lateral_m == pytest.approx(-0.2, abs=2e-3)
    assert pr.distance_m == pytest.approx(10 + 5 * a, abs=0.02)
    assert abs(pr.heading_rad) < 0.02


def test_projection_agrees_with_se2_and_a_brute_force_foot_point():
    """project() works in scalars; the reference here is numpy and se2: the foot point on the nearest
    of the two segments at the nearest vertex, and T_vertex_robot from se2.between."""
    p = straight_then_arc()
    r = np.random.default_rng(3)
    for _ in range(300):
        i = int(r.integers(0, len(p)))
        T = p.poses[i] + r.normal(0.0, [0.3, 0.3, 1.0])
        pr = p.project(T, hint=int(np.clip(i + r.integers(-2, 3), 0, len(p) - 1)))
        assert pr.vertex == p.nearest_vertex(T)
        np.testing.assert_allclose(pr.T_vertex_robot, se2.between(p.poses[pr.vertex], T), atol=1e-12)
        feet = []
        for a in (pr.vertex - 1, pr.vertex):
            if 0 <= a < len(p) - 1:
                p0, d = p.poses[a, :2], p.poses[a + 1, :2] - p.poses[a, :2]
                t = np.clip(np.dot(T[:2] - p0, d) / np.dot(d, d), 0.0, 1.0)
                feet.append((np.sum((T[:2] - p0 - t * d) ** 2), a, t))
        _, a, t = min(feet)
        d = p.poses[a + 1, :2] - p.poses[a, :2]
        assert pr.segment == a
        e = T[:2] - p.poses[a, :2] - t * d
        normal = (d[0] * e[1] - d[1] * e[0]) / np.linalg.norm(d)
        interior_vertex = t in (0.0, 1.0) and not (a == 0 and t == 0.0) and not (a == len(p) - 2 and t == 1.0)
        assert pr.lateral_m == pytest.approx(math.copysign(np.linalg.norm(e), normal) if interior_vertex else normal,
                                             abs=1e-12)
        if 0.0 < t < 1.0:
            assert pr.distance_m == pytest.approx(p.s[a] + t * p.segment_lengths[a], abs=1e-12)


def test_lateral_error_is_continuous_outside_a_sharp_bend():
    """Outside a bend of a wobbly taught route the foot point is the vertex for both of its segments; the
    lateral error is the distance to it, whichever segment is nearer by a rounding error."""
    p = Path("bend", np.array([(0.0, 0.0, 0.0), (0.25, 0.0, 0.0), (0.5, 0.0, -0.6), (0.65, -0.2, -0.9)]))
    corner = np.array([0.5, 0.0])
    lats = [p.project((*(corner + 0.2 * np.array([math.cos(b), math.sin(b)])), 0.0)).lateral_m
            for b in np.linspace(math.pi / 2 - 0.9, math.pi / 2, 50)]     # sweep across the outside wedge
    np.testing.assert_allclose(lats, 0.2, atol=1e-9)
    assert p.project((0.4, -0.05, 0.0)).lateral_m < 0.0                 # inside the bend: the right side


def test_relative_pose_is_fig_2_5():
    p = straight_then_arc()
    i = p.nearest_vertex((4.1, 0.3))
    T = p.relative_pose(i, (4.1, 0.3, 0.1))
    np.testing.assert_allclose(T, [4.1 - p.poses[i, 0], 0.3, 0.1], atol=1e-12)
    np.testing.assert_allclose(se2.compose(p.poses[i], T), [4.1, 0.3, 0.1], atol=1e-12)


def test_windowed_search_agrees_with_kd_tree_and_respects_the_hint():
    p = straight_then_arc()
    for q in rng.uniform([0, -1], [15, 6], (200, 2)):
        i = p.nearest_vertex(q)
        assert p.nearest_vertex(q, hint=i) == i
    # a route passing the same place twice: the hint keeps us on the current pass
    loop = Path("loop", np.array([(5 * math.cos(a), 5 * math.sin(a), a + math.pi / 2)
                                  for a in np.arange(0, 2 * math.pi, 0.05)] + [(5.0, 0.2, math.pi / 2)]))
    assert loop.nearest_vertex((5.0, 0.1), hint=len(loop) - 3) >= len(loop) - 3
    assert loop.nearest_vertex((5.0, 0.1), hint=1) <= 3


def test_route_recorder_keyframe_rule():
    rec = RouteRecorder(0.25)
    for x in np.arange(0, 2.0, 0.01):
        rec.add((x, 0.0, 0.0))
    path = rec.finish("r", loop=False)
    assert len(path) == 8
    assert np.allclose(np.diff(path.poses[:, 0]), 0.25, atol=0.011)
    with pytest.raises(ValueError):
        RouteRecorder(0.25).finish("r", loop=False)


def test_path_rejects_bad_input():
    with pytest.raises(ValueError):
        Path("p", np.zeros((1, 3)))
    with pytest.raises(ValueError):
        Path("p", np.array([[0, 0, 0], [0, 0, 0.0]]))
    with pytest.raises(ValueError):
        Path("bad id!", np.array([[0, 0, 0], [1, 0, 0.0]]))
    with pytest.raises(ValueError):
        Path("p", np.array([[0, 0, 0], [1, np.nan, 0.0]]))


def test_the_reference_heading_averages_wiggles_shorter_than_its_window_and_keeps_a_turn():
    """A straight route that wiggles 3 cm either side over 3.33 m (heading +-3.2 deg, curvature +-0.11 /m)
    averaged over one wiggle: the reference heading is the straight's. The 35 vertices averaged span
    3.5 m and keep sin(pi 3.5 / 3.33) / (35 sin(pi 0.1 / 3.33)) = 4.8 % of the wiggle's heading; the
    curvature over 3.4 m keeps 2 %. On a 6 m arc the average of a heading that grows
    linearly is the heading itself: offset 0 and curvature 1/6 away from the arc's ends. Without a
    window the offset is 0 and the curvature the taught one."""
    lam, amp, k = 10.0 / 3.0, 0.03, 2 * math.pi * 3.0 / 10.0
    x = np.arange(0.0, 40.0, 0.1)
    wiggle = np.column_stack([x, amp * np.sin(k * x), np.arctan(amp * k * np.cos(k * x))])
    taught = Path("w", wiggle, spacing_m=0.1)
    smooth = Path("w", wiggle, spacing_m=0.1, heading_window_m=lam)
    s = np.arange(5.0, 35.0, 0.05)
    heading = smooth.pose_at(s)[:, 2] + smooth.heading_offset_at(s)
    assert np.max(np.abs(heading)) == pytest.approx(0.048 * amp * k, rel=0.05)
    inner = (smooth.s > 5.0) & (smooth.s < 35.0)
    one_metre = math.sin(k / 2) / (k / 2)        # what the taught curvature's 1 m window keeps
    assert np.max(np.abs(taught.curvature[inner])) == pytest.approx(one_metre * amp * k * k, rel=0.02)
    assert np.max(np.abs(smooth.curvature[inner])) < 0.03 * amp * k * k
    np.testing.assert_array_equal(taught.heading_offset_at(s), 0.0)
    a = np.arange(0.0, 2.0, 0.01)
    arc = Path("a", np.column_stack([6 * np.sin(a), 6 - 6 * np.cos(a), a]), spacing_m=0.06, heading_window_m=lam)
    mid = np.arange(3.0, 9.0, 0.1)
    np.testing.assert_allclose(arc.heading_offset_at(mid), 0.0, atol=1e-9)
    np.testing.assert_allclose(arc.curvature[(arc.s > 3.0) & (arc.s < 9.0)], 1 / 6, rtol=1e-3)
