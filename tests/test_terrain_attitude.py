"""The body's attitude on the terrain (services/bridge/terrain.py `Terrain.attitude`) against hand-worked
values and an independent construction of the slope plane's normal; the simulator's samples carry it;
the vision source reports the robot's pose in the level vertex frame when teach and repeat are tilted."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from common import se3
from common.robot import PRESETS
from common.camera import StereoConfig
from common.scenario import TerrainPatch
from services.bridge.render import calibration
from services.bridge.simulator import Simulator
from services.bridge.terrain import LEVEL, RUT_UNEVENNESS, Attitude, Terrain, footprint
from services.localizer.vision_source import cov_vertex_robot, level_from_robot, vertex_robot_se2


def slope(slope_deg: float, downhill_deg: float, radius_m: float = 10.0) -> TerrainPatch:
    return TerrainPatch(kind="side_slope", center=(0.0, 0.0), radius_m=radius_m, slope_deg=slope_deg,
                        downhill_deg=downhill_deg)


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues (OpenCV's): an independent rotation about `axis` by `angle` (right hand)."""
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)[0]


def body_in_world(a: Attitude, theta: float) -> np.ndarray:
    """The body axes in the world: roll about the heading's level x axis, then pitch about its level y."""
    fwd, left = np.array([math.cos(theta), math.sin(theta), 0.0]), np.array([-math.sin(theta), math.cos(theta), 0.0])
    yaw = np.column_stack([fwd, left, [0.0, 0.0, 1.0]])
    return rotation(left, a.pitch_rad) @ rotation(fwd, a.roll_rad) @ yaw


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, -150.0])
def test_downhill_on_the_left_rolls_the_left_side_down(theta_deg):
    a = Terrain([slope(10.0, theta_deg + 90.0)], seed=1).attitude(0.5, -0.3, math.radians(theta_deg))
    assert a.roll_rad == pytest.approx(math.radians(-10.0)) and a.pitch_rad == pytest.approx(0.0, abs=1e-12)
    assert a.z_m == 0.0                       # the slope is not drawn: the body stays on z = 0
    left_side = body_in_world(a, math.radians(theta_deg))[:, 1]
    assert left_side[2] < 0                   # robot y (left) points downhill


def test_downhill_ahead_pitches_the_nose_down_and_behind_up():
    ahead = Terrain([slope(10.0, 20.0)], seed=1).attitude(0.0, 0.0, math.radians(20.0))
    assert ahead.pitch_rad == pytest.approx(math.radians(10.0)) and ahead.roll_rad == pytest.approx(0.0, abs=1e-12)
    assert body_in_world(ahead, math.radians(20.0))[2, 0] < 0      # robot x (nose) points down
    behind = Terrain([slope(10.0, 200.0)], seed=1).attitude(0.0, 0.0, math.radians(20.0))
    assert behind.pitch_rad == pytest.approx(math.radians(-10.0))


@pytest.mark.parametrize("slope_deg, downhill_deg, theta_deg",
                         [(14.0, 37.0, 100.0), (25.0, -60.0, 10.0), (8.0, 180.0, 95.0)])
def test_the_body_lies_on_the_slope_plane_with_its_heading(slope_deg, downhill_deg, theta_deg):
    """Body z = the plane's normal (tilted towards downhill); body x = the heading, projected onto it."""
    a = Terrain([slope(slope_deg, downhill_deg)], seed=1).attitude(0.0, 0.0, math.radians(theta_deg))
    R = body_in_world(a, math.radians(theta_deg))
    s, d = math.radians(slope_deg), math.radians(downhill_deg)
    normal = np.array([math.sin(s) * math.cos(d), math.sin(s) * math.sin(d), math.cos(s)])
    assert np.allclose(R[:, 2], normal, atol=1e-12)
    heading = np.array([math.cos(math.radians(theta_deg)), math.sin(math.radians(theta_deg)), 0.0])
    along = heading - (heading @ normal) / normal[2] * np.array([0.0, 0.0, 1.0])    # vertical projection
    assert np.allclose(R[:, 0], along / np.linalg.norm(along), atol=1e-12)
    # the renderer's and the terrain's rotation agree with this construction
    assert np.allclose(np.column_stack([[math.cos(math.radians(theta_deg)), -math.sin(math.radians(theta_deg)), 0],
                                        [math.sin(math.radians(theta_deg)), math.cos(math.radians(theta_deg)), 0],
                                        [0, 0, 1]]).T @ a.R_level_body(), R, atol=1e-12)


def test_the_tilt_fades_with_the_footprint_and_the_strongest_slope_wins():
    patch = slope(12.0, 90.0, radius_m=4.0)
    t = Terrain([patch, slope(5.0, 0.0, radius_m=20.0)], seed=1)
    x = 3.4                                    # in the fading rim: 0.7 r < 3.4 < r
    w = footprint(patch, x, 0.0)
    assert 0.0 < w < 1.0
    assert t.attitude(x, 0.0, 0.0).roll_rad == pytest.approx(-math.asin(w * math.sin(math.radians(12.0))))
    far = t.attitude(10.0, 0.0, 0.0)           # only the gentle wide slope, downhill ahead
    assert far.pitch_rad == pytest.approx(math.radians(5.0)) and far.roll_rad == pytest.approx(0.0, abs=1e-12)
    assert Terrain([], seed=1).attitude(1.0, 2.0, 0.3) == LEVEL


def test_ruts_lower_the_body_by_their_depth_and_roll_it_to_the_deeper_track():
    rut = TerrainPatch(kind="rut", center=(0.0, 0.0), radius_m=30.0, depth_m=0.04, growth_m_per_pass=0.02)
    t = Terrain([rut], seed=3, track_m=0.55)
    rolls = []
    for x in np.linspace(-5.0, 5.0, 41):
        a = t.attitude(x, 0.0, 0.0)
        pl, pr = t.patterns[0](x, 0.275), t.patterns[0](x, -0.275)      # left, right track
        sink_l, sink_r = (0.04 * (1 + RUT_UNEVENNESS * p) for p in (pl, pr))
        assert a.z_m == pytest.approx(-0.5 * (sink_l + sink_r))
        assert a.roll_rad == pytest.approx(math.atan((sink_r - sink_l) / 0.55))
        assert (a.roll_rad < 0) == (pl > pr)                             # the deeper left track is lower
        assert a.pitch_rad == 0.0
        rolls.append(abs(a.roll_rad))
    assert 0.001 < max(rolls) < math.radians(4.0)       # a few degrees at most for a 4 cm rut
    # attitude marks nothing crossed; a trial through the rut deepens it, and the sink with it
    before = t.attitude(1.0, 0.0, 0.0)
    t.begin_trial()
    t.end_trial()
    assert t.attitude(1.0, 0.0, 0.0) == before
    t.begin_trial()
    t.effect(1.0, 0.0)
    t.end_trial()
    assert t.attitude(1.0, 0.0, 0.0).z_m == pytest.approx(before.z_m * 0.06 / 0.04)
    # the same seed gives the same ruts
    assert Terrain([rut], seed=3).attitude(1.0, 0.0, 0.0) == before


def test_simulator_samples_carry_the_attitude_where_the_robot_is():
    patches = [TerrainPatch(kind="side_slope", center=(1.0, 0.0), radius_m=20.0, slope_deg=12.0, downhill_deg=-90.0)]
    sim = Simulator(PRESETS["roc6"], patches, seed=2)
    sim.reset((0.0, 0.0, 0.0), 1)
    sim.command(0.5, 0.0)
    for _ in range(5):
        s = sim.step()
    assert s.attitude == sim.terrain.attitude(s.x, s.y, s.theta)
    assert s.roll_rad == pytest.approx(math.radians(12.0), abs=math.radians(1.0))   # right side down
    assert sim.terrain.track_m == PRESETS["roc6"].track_m


# --- the vision source under tilt ------------------------------------------------------------------
def T_world_robot(x, y, theta, a: Attitude) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = body_in_world(a, theta)
    T[:3, 3] = (x, y, a.z_m)
    return T


def test_vertex_pose_is_the_level_pose_of_the_ground_contact_point():
    """Keyframe and live robot on a 13 deg side slope, rolled and pitched differently: the SE(2) pose
    is the level one (truth), where the tilted keyframe's body frame would shrink the lateral offset."""
    T_rc = calibration(StereoConfig()).T_robot_camera
    T_cr = se3.inverse(T_rc)
    T_w_first = T_world_robot(-4.0, 1.0, 0.2, LEVEL)              # the map's first keyframe: level
    kf_tilt = Attitude(roll_rad=math.radians(13.0), pitch_rad=math.radians(-2.0), z_m=-0.01)
    live_tilt = Attitude(roll_rad=math.radians(11.0), pitch_rad=math.radians(3.0), z_m=-0.03)
    T_w_kf, T_w_live = T_world_robot(2.0, 0.5, 0.1, kf_tilt), T_world_robot(2.6, 0.9, 0.25, live_tilt)
    T_live_kf = se3.inverse(T_w_live @ T_rc) @ (T_w_kf @ T_rc)     # keyframe camera points -> live camera
    T_first_kf_cam = se3.inverse(T_w_first @ T_rc) @ (T_w_kf @ T_rc)
    T_level = level_from_robot(T_rc @ T_first_kf_cam @ T_cr)
    truth = np.array([math.cos(0.1) * 0.6 + math.sin(0.1) * 0.4, -math.sin(0.1) * 0.6 + math.cos(0.1) * 0.4, 0.15])
    assert np.allclose(vertex_robot_se2(T_live_kf, T_rc, T_level), truth, atol=1e-12)
    tilted = vertex_robot_se2(T_live_kf, T_rc, np.eye(4))          # the keyframe's body frame, not levelled
    assert abs(tilted[1] - truth[1]) > 0.005
    # on level ground the two agree, and the covariance follows the same conversion
    T_flat_live = se3.inverse(T_world_robot(2.6, 0.9, 0.25, LEVEL) @ T_rc) @ (T_world_robot(2.0, 0.5, 0.1, LEVEL)
                                                                              @ T_rc)
    assert np.allclose(vertex_robot_se2(T_flat_live, T_rc, np.eye(4)), truth, atol=1e-12)
    cov = cov_vertex_robot(T_live_kf, np.diag([1e-4] * 3 + [1e-6] * 3), T_rc, T_level)
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
