"""summary.json's figures from what the runner recorded (deploy/metrics.py)."""
import math
from types import SimpleNamespace as At

import numpy as np
import pytest

from common.path import Path
from deploy.metrics import TIME_LOST_KEYS, TrialRecord, outside_3sigma_fraction, time_lost


def _loop_with_a_crab_at_its_end(radius_m=5.0, n=126, crab_rad=0.1, crab_vertices=12) -> Path:
    """A circle taught counter-clockwise from (0, 0) heading east; over its last metres the robot crabbed
    (taught heading `crab_rad` off the tangent), so the last vertex's heading is not the first one's."""
    phi = -math.pi / 2 + 2 * math.pi * np.arange(n) / n
    theta = phi + math.pi / 2
    theta[-crab_vertices:] += crab_rad
    return Path("loop", np.column_stack([radius_m * np.cos(phi), radius_m * (1 + np.sin(phi)), theta]), loop=True)


def test_predictions_realized_where_a_loop_closes_are_checked_against_its_end():
    """A robot on the route, predicted exactly, with the last poses past the last vertex and nearer the
    first: none of its predictions left 3 sigma (the nearest vertex alone, the start's heading, would make
    the last ones about 3 deg off against a 1.7 deg 3-sigma)."""
    route = _loop_with_a_crab_at_its_end()
    poses = [tuple(p) for p in route.poses]
    x, y, th = route.poses[-1]
    tx, ty = math.cos(route.tangent_at(route.length_m)), math.sin(route.tangent_at(route.length_m))
    poses += [(x + d * tx, y + d * ty, th) for d in (0.1, 0.15, 0.2)]
    assert route.nearest_vertex(poses[-1][:2]) == 0            # the case: nearer the first vertex
    rec = TrialRecord(trial=1, speed_mps=1.0)
    rec.truth = [At(tick=k, stamp_s=0.1 * k, x_world_m=p[0], y_world_m=p[1], theta_world_rad=p[2])
                 for k, p in enumerate(poses)]
    rec.status = [At(tick=k, stamp_s=0.1 * k, state="tracking", vertex=min(k, len(route) - 1),
                     pred_x_m=[poses[k + 1][0]], pred_y_m=[poses[k + 1][1]], pred_theta_rad=[poses[k + 1][2]],
                     pred_sigma_lat_m=[0.01], pred_sigma_head_rad=[0.01]) for k in range(len(poses) - 1)]
    assert outside_3sigma_fraction(route, route, rec) == 0.0


def test_a_prediction_off_by_more_than_3_sigma_is_counted():
    route = _loop_with_a_crab_at_its_end()
    poses = [tuple(p) for p in route.poses[:40]]
    rec = TrialRecord(trial=1, speed_mps=1.0)
    rec.truth = [At(tick=k, stamp_s=0.1 * k, x_world_m=p[0], y_world_m=p[1], theta_world_rad=p[2])
                 for k, p in enumerate(poses)]
    pred = [list(p) for p in poses]
    pred[11][2] += 0.04                                        # 0.04 rad against a 0.03 rad 3-sigma
    pred[21][0] -= 0.02 * math.sin(pred[21][2])                # 2 cm to the left against 1.5 cm
    pred[21][1] += 0.02 * math.cos(pred[21][2])
    pred[31][2] += 0.025                                       # inside
    rec.status = [At(tick=k, stamp_s=0.1 * k, state="tracking", vertex=k, pred_x_m=[pred[k + 1][0]],
                     pred_y_m=[pred[k + 1][1]], pred_theta_rad=[pred[k + 1][2]],
                     pred_sigma_lat_m=[0.005], pred_sigma_head_rad=[0.01]) for k in range(len(poses) - 1)]
    assert outside_3sigma_fraction(route, route, rec) == pytest.approx(2 / 39)


def test_time_lost_is_split_by_what_held_the_speed_and_adds_up_to_the_travel_beyond_the_asked_speed():
    """A 1 m/s trial: 10 steps at 1 m/s, 10 held by the ladder's lateral check at 0.5 m/s, 5 by the place
    cap at 0.25 m/s, then the end of the route. Worked by hand: the ladder's steps lose 10 x (0.1 - 0.05)
    = 0.5 s, the place cap's 5 x (0.1 - 0.025) = 0.375 s; the ideal is the 1.625 m covered at 1 m/s."""
    speeds = [1.0] * 10 + [0.5] * 10 + [0.25] * 5
    causes = [""] * 10 + ["ladder-lateral"] * 10 + ["place-corridor"] * 5
    s, rec = 0.0, TrialRecord(trial=1, speed_mps=1.0)
    rec.truth = [At(tick=k) for k in range(len(speeds) + 2)]
    for k, (v, c) in enumerate(zip(speeds, causes)):
        rec.status.append(At(tick=k, stamp_s=0.1 * k, state="tracking", vertex=0, distance_m=s, speed_held_by=c))
        s += 0.1 * v
    rec.status.append(At(tick=len(speeds), stamp_s=0.1 * len(speeds), state="finished", vertex=0, distance_m=s,
                         speed_held_by=""))
    out = time_lost(rec, lambda vertex: 1.0)
    lost = out["time_lost_s"]
    assert set(lost) == set(TIME_LOST_KEYS)
    assert lost["none"] == pytest.approx(0.0, abs=1e-12)
    assert lost["ladder-lateral"] == pytest.approx(0.5)
    assert lost["place-corridor"] == pytest.approx(0.375)
    assert out["travel_time_ideal_s"] == pytest.approx(1.625)
    assert out["travel_time_ideal_s"] + sum(lost.values()) == pytest.approx(0.1 * len(speeds))
