"""The vision map file: exact round trip, atomic replacement, and a clear MapFileError (never a crash)
for every kind of bad file."""
from __future__ import annotations

import os

import msgpack
import numpy as np
import pytest

from services.localizer.vision import Keyframe, MapFileError, StereoCamera, VisionMap, load_map, save_map
from services.localizer.vision.map_file import FORMAT, VERSION
from common.se3 import exp as se3_exp

CAM = StereoCamera(fu=707.1, fv=707.1, cu=601.9, cv=183.1, baseline_m=0.537, width=1226, height=370)


def _map(seed: int = 0, n_kf: int = 4) -> VisionMap:
    rng = np.random.default_rng(seed)
    kfs = []
    for i in range(n_kf):
        n = int(rng.integers(30, 60))
        uvd = np.column_stack([rng.uniform(0, 1226, n), rng.uniform(0, 370, n), rng.uniform(1, 100, n)])
        T = np.eye(4) if i == 0 else se3_exp(np.r_[rng.normal(0, 0.1, 2), 0.3, rng.normal(0, 0.02, 3)])
        kfs.append(Keyframe(i, CAM.triangulate(uvd), rng.integers(0, 256, (n, 32), dtype=np.uint8), uvd, T,
                            cov_uvd=rng.uniform(0.1, 1.0, (n, 3))))
    return VisionMap(kfs, CAM, {"route": "r1", "frames": 12, "note": "ü"})


def _doc(path) -> dict:
    return msgpack.unpackb(path.read_bytes(), raw=False)


def _write(path, doc) -> None:
    path.write_bytes(msgpack.packb(doc, use_bin_type=True))


def test_round_trip_is_exact(tmp_path):
    vm = _map()
    p = tmp_path / "routes" / "r1.vmap"
    save_map(p, vm)
    back = load_map(p)
    assert back.camera == vm.camera and back.meta == vm.meta and len(back) == len(vm)
    for a, b in zip(vm.keyframes, back.keyframes):
        assert a.index == b.index
        for name in ("points", "desc", "uvd", "cov_uvd", "T_prev_this", "T_first_this"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    # overwrite in place; no temporary files left behind
    save_map(p, _map(seed=1, n_kf=2))
    assert len(load_map(p)) == 2 and os.listdir(p.parent) == ["r1.vmap"]


def test_chained_poses():
    vm = _map()
    T = np.eye(4)
    for kf in vm.keyframes:
        T = T @ kf.T_prev_this
        np.testing.assert_allclose(kf.T_first_this, T, atol=1e-12)
    np.testing.assert_allclose(vm.T_i_j(1, 3), vm.keyframes[2].T_prev_this @ vm.keyframes[3].T_prev_this, atol=1e-12)


def test_missing_empty_truncated_and_random_files(tmp_path):
    with pytest.raises(MapFileError, match="no such file"):
        load_map(tmp_path / "nope.vmap")
    p = tmp_path / "m.vmap"
    p.write_bytes(b"")
    with pytest.raises(MapFileError, match="empty"):
        load_map(p)
    save_map(p, _map())
    blob = p.read_bytes()
    for cut in (1, 10, len(blob) // 2, len(blob) - 1):
        p.write_bytes(blob[:cut])
        with pytest.raises(MapFileError, match="truncated or corrupt|not a vision map"):
            load_map(p)
    rng = np.random.default_rng(7)
    for n in (1, 7, 64, 4096, 100_000):
        p.write_bytes(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        with pytest.raises(MapFileError):
            load_map(p)
    # flipped bytes inside a valid file: an error or a valid map, never an exception of another type
    for k in range(200):
        b = bytearray(blob)
        b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
        p.write_bytes(bytes(b))
        try:
            load_map(p)
        except MapFileError:
            pass


def test_foreign_and_wrong_version_files(tmp_path):
    p = tmp_path / "m.vmap"
    _write(p, {"format": "lbc.route", "version": 1, "vertices": []})
    with pytest.raises(MapFileError, match="not a vision map file.*lbc.route"):
        load_map(p)
    _write(p, [1, 2, 3])
    with pytest.raises(MapFileError, match="not a vision map file"):
        load_map(p)
    save_map(p, _map())
    doc = _doc(p)
    doc["version"] = VERSION + 1
    _write(p, doc)
    with pytest.raises(MapFileError, match=f"unsupported version {VERSION + 1}"):
        load_map(p)
    assert doc["format"] == FORMAT


@pytest.mark.parametrize("what, edit, message", [
    ("shape", lambda d: d["keyframes"][1]["desc"].update(shape=[5, 32]), "data bytes"),
    ("count", lambda d: d["keyframes"][1]["desc"].update(shape=[d["keyframes"][1]["desc"]["shape"][0] - 1, 32],
                                                         data=d["keyframes"][1]["desc"]["data"][:-32]),
     "inconsistent keypoint counts"),
    ("dtype", lambda d: d["keyframes"][0]["points"].update(dtype="<f4"), "dtype"),
    ("columns", lambda d: d["keyframes"][0]["uvd"].update(shape=[d["keyframes"][0]["uvd"]["shape"][0] * 3, 1]),
     r"expected \(N, 3\)"),
    ("nan", lambda d: d["keyframes"][2]["points"].update(
        data=np.full(d["keyframes"][2]["points"]["shape"], np.nan).tobytes()), "non-finite"),
    ("inf pose", lambda d: d["keyframes"][1]["T_prev_this"].update(data=np.full((4, 4), np.inf).tobytes()),
     "non-finite"),
    ("not rigid", lambda d: d["keyframes"][1]["T_prev_this"].update(data=(2 * np.eye(4)).tobytes()), "not a rigid"),
    ("index", lambda d: d["keyframes"][1].update(index=5), "index 5"),
    ("missing", lambda d: d["keyframes"][1].pop("points"), "missing points"),
    ("camera", lambda d: d["camera"].update(baseline_m=-1.0), "camera"),
    ("camera field", lambda d: d["camera"].pop("fu"), "camera"),
    ("no keyframes", lambda d: d.update(keyframes=[]), "no keyframes"),
    ("meta", lambda d: d.update(meta=[1]), "meta"),
])
def test_inconsistent_contents(tmp_path, what, edit, message):
    p = tmp_path / "m.vmap"
    save_map(p, _map())
    doc = _doc(p)
    edit(doc)
    _write(p, doc)
    with pytest.raises(MapFileError, match=message):
        load_map(p)


def test_unserializable_meta_is_refused_and_the_old_file_kept(tmp_path):
    p = tmp_path / "m.vmap"
    save_map(p, _map())
    vm = _map()
    vm.meta["bad"] = object()
    with pytest.raises(ValueError, match="not serializable"):
        save_map(p, vm)
    assert len(load_map(p)) == 4 and os.listdir(tmp_path) == ["m.vmap"]
    vm = _map()
    vm.keyframes[1].points[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        save_map(p, vm)


# ---------------------------------------------------------------- map building and repeat on a synthetic world
class World:
    """Random landmarks with fixed descriptors along a 40 m corridor; a frame's keypoints are the visible
    ones, projected (eq. 2.1) with (u, v, d) noise: the ground truth is known exactly."""

    def __init__(self, seed: int = 0, n: int = 1200):
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.P = np.column_stack([rng.uniform(-12, 12, n), rng.uniform(-4, 1.6, n), rng.uniform(-5, 80, n)])
        self.desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)

    def frame(self, T_w_c: np.ndarray):
        from services.localizer.vision import StereoKeypoints
        Pc = (self.P - T_w_c[:3, 3]) @ T_w_c[:3, :3]
        uvd = CAM.project(np.where(Pc[:, 2:3] > 0.5, Pc, 1.0))
        vis = (Pc[:, 2] > 1.0) & (Pc[:, 2] < 50) & (uvd[:, 0] > 0) & (uvd[:, 0] < CAM.width) & \
            (uvd[:, 1] > 0) & (uvd[:, 1] < CAM.height)
        noisy = uvd[vis] + self.rng.normal(0.0, 0.4, (int(vis.sum()), 3))
        noisy[:, 2] = np.maximum(noisy[:, 2], 0.5)
        var = np.full(noisy.shape, 0.36)
        return StereoKeypoints(noisy, self.desc[vis].copy(), CAM.triangulate(noisy), var)


def _pose(z: float, x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3_exp(np.array([0, 0, 0, 0, 0.05 * np.sin(z / 5.0), 0]))[:3, :3]
    T[:3, 3] = [x, 0.0, z]
    return T


def _rel_err(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    from common.se3 import inverse as inv_T, rotation_angle_deg
    D = T @ inv_T(T_true)
    return float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D)


def test_teach_and_repeat_on_a_synthetic_world():
    from services.localizer.vision import VisionSettings, VisualRepeat, VisualTeach
    from common.se3 import inverse as inv_T
    s = VisionSettings()
    w = World()
    teach = VisualTeach(CAM, s)
    kf_z = []
    for k in range(90):                        # 0.1 m per frame: a keyframe every 3rd frame (> 0.25 m)
        z = 0.1 * k
        step = teach.add(w.frame(_pose(z)))
        assert step.ok, step.reason
        if step.new_keyframe:
            kf_z.append(z)
        else:
            # the live pose in the keyframe against the truth
            assert _rel_err(step.T_kf_live, inv_T(_pose(kf_z[-1])) @ _pose(z))[0] < 0.01
    vm = teach.finish()
    assert len(vm) == len(kf_z) == 30 and np.allclose(np.diff(kf_z), 0.3)
    for kf, z in zip(vm.keyframes, kf_z):
        assert _rel_err(kf.T_first_this, _pose(z))[0] < 0.05
    # repeat 0.15 m to the side, halfway between teach frames
    rep = VisualRepeat(vm, s)
    rep.start(0)
    for k in range(80):
        z = 0.1 * k + 0.05
        r = rep.localize(w.frame(_pose(z, x=0.15)))
        assert r.status == "ok", (k, r.reason)
        assert abs(kf_z[r.keyframe] - z) <= 0.2, (z, r.keyframe)          # the nearest keyframe
        dt, dr = _rel_err(r.T_live_kf, inv_T(_pose(z, x=0.15)) @ _pose(kf_z[r.keyframe]))
        assert dt < 0.01 and dr < 0.05, (k, dt, dr)


def test_repeat_dead_reckons_then_declares_itself_lost():
    from services.localizer.vision import VisionSettings, VisualRepeat, VisualTeach
    from common.se3 import inverse as inv_T
    s = VisionSettings(max_vo_frames=4)
    w = World(seed=1)
    teach = VisualTeach(CAM, s)
    kf_z = [0.1 * k for k in range(60) if teach.add(w.frame(_pose(0.1 * k))).new_keyframe]
    vm = teach.finish()
    rng = np.random.default_rng(9)
    for kf in vm.keyframes[8:]:                    # the map is useless beyond keyframe 7 (~2.1 m)
        kf.desc[:] = rng.integers(0, 256, kf.desc.shape, dtype=np.uint8)
    rep = VisualRepeat(vm, s)
    rep.start(0)
    out = [rep.localize(w.frame(_pose(0.1 * k + 0.05))) for k in range(40)]
    status = [r.status for r in out]
    first_vo = status.index("vo")
    assert set(status[:first_vo]) == {"ok"}
    assert status[first_vo:first_vo + 4] == ["vo"] * 4 and status[first_vo + 4] == "lost", status
    for k in range(first_vo, first_vo + 4):
        r = out[k]
        assert r.T_live_kf is not None and "matches" in r.reason and r.vo_frames == k - first_vo + 1
        # dead-reckoning is still right here, and its covariance grows
        z = 0.1 * k + 0.05
        assert _rel_err(r.T_live_kf, inv_T(_pose(z)) @ _pose(kf_z[r.keyframe]))[0] < 0.03
        if k > first_vo:
            assert np.trace(r.cov) > np.trace(out[k - 1].cov)
    lost = out[first_vo + 4]
    assert lost.T_live_kf is None and lost.cov is None and "without a keyframe refinement" in lost.reason
    # afterwards it searches around keyframe 7..8: whatever it reports as "ok" is true
    for k, r in enumerate(out[first_vo + 5:], start=first_vo + 5):
        if r.status == "ok":
            z = 0.1 * k + 0.05
            assert r.keyframe < 8 and _rel_err(r.T_live_kf, inv_T(_pose(z)) @ _pose(kf_z[r.keyframe]))[0] < 0.03
