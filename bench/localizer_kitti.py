"""`lbc bench localizer_kitti`: per-frame cost and accuracy of the stereo VT&R core on real KITTI data.

Data: by default the 51-frame KITTI odometry excerpt in `../shared/data/kitti_seq1` (rectified 1226x370
pairs, 10 Hz, ~1.2 m apart, ~60 m; KITTI Vision Benchmark, Geiger et al., KIT / Toyota Technological
Institute, CC BY-NC-SA 3.0), read in place; `--data DIR` any folder of the same layout (`data` and
`data_dir` in the JSON name it). PNG decoding happens before timing (a camera driver delivers raw
pixels); everything after it is timed: stereo keypoint extraction plus registration.

Two passes, on one CPU (process pinned, OpenCV and BLAS limited to one thread):
- teach: every frame through `VisualTeach.add` (registration against the current keyframe with a
  constant-velocity prior; with KITTI's spacing every frame becomes a keyframe; the last keyframes
  bundle-adjusted together with the rig's disparity offset). Its keyframe chain is stereo VO:
  `vo_drift_pct` / `vo_drift_deg_per_m` compare its final pose with the ground truth;
  `disparity_offset_px` is the offset the pass estimated (disparities measured that much short).
- repeat: a map taught on the even frames, then every odd frame through `VisualRepeat.localize` (VO
  against the previous frame + refinement against the nearest keyframe: two registrations per frame).
  `reloc_within_tol` is the fraction of odd frames localized ("ok") within 0.15 m and 0.5 degrees of
  the ground-truth pose relative to their keyframe.
`fps`, `latency_ms_p50`, `latency_ms_p99` are those of the repeat pass (the run-time path); `teach_*`
those of the teach pass. `--repeats` runs both passes that many times (latencies pooled).
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from bench.report import run_and_print, single_core
from common.shared_data import shared_data_dir
from services.localizer.vision import StereoCamera, StereoFrontend, VisionSettings, VisualRepeat, VisualTeach
from common.se3 import inverse as inv_T
from common.se3 import rotation_angle_deg

log = logging.getLogger("bench.localizer_kitti")
RELOC_TOL_M, RELOC_TOL_DEG = 0.15, 0.5


@dataclass
class KittiSequence:
    camera: StereoCamera
    left: list[Path]
    right: list[Path]
    poses: np.ndarray            # (N, 4, 4) ground truth T_first_k (left camera k into the first one)

    def __len__(self) -> int:
        return len(self.left)

    def images(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return (cv2.imread(str(self.left[i]), cv2.IMREAD_GRAYSCALE),
                cv2.imread(str(self.right[i]), cv2.IMREAD_GRAYSCALE))


def load_kitti(folder: Path | None = None) -> KittiSequence:
    """calib.txt (P0, P1 rows), poses.txt (3x4 row-major per frame), image_l/ and image_r/ PNGs."""
    folder = Path(folder) if folder is not None else shared_data_dir() / "kitti_seq1"
    if not folder.is_dir():
        raise LookupError(f"KITTI data not found at {folder}")
    rows = [np.array(line.split(), dtype=float) for line in (folder / "calib.txt").read_text().splitlines()
            if line.strip()]
    left = sorted((folder / "image_l").glob("*.png"))
    right = sorted((folder / "image_r").glob("*.png"))
    raw = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    if not left or len(left) != len(right) or len(left) != len(raw):
        raise LookupError(f"KITTI data at {folder} is incomplete: {len(left)} left, {len(right)} right images, "
                          f"{len(raw)} poses")
    h, w = cv2.imread(str(left[0]), cv2.IMREAD_GRAYSCALE).shape
    poses = np.tile(np.eye(4), (len(raw), 1, 1))
    poses[:, :3, :] = raw
    return KittiSequence(StereoCamera.from_projections(rows[0], rows[1], w, h), left, right, poses)


def _teach(seq: KittiSequence, images, frames, settings: VisionSettings) -> tuple[list[float], object]:
    fe, teach, times = StereoFrontend(seq.camera, settings), VisualTeach(seq.camera, settings), []
    for i in frames:
        t0 = time.perf_counter()
        step = teach.add(fe.extract(*images[i]))
        times.append(time.perf_counter() - t0)
        if not step.ok:
            log.warning("teach frame %d: %s", i, step.reason)
    return times, teach.finish()


def bench_kitti(repeats: int = 1, settings: VisionSettings | None = None, data: Path | None = None) -> dict:
    """`data`: a folder of the KITTI layout (load_kitti); default the shared excerpt."""
    settings = settings or VisionSettings()
    pinned, limit = single_core()
    folder = Path(data).resolve() if data is not None else shared_data_dir() / "kitti_seq1"
    seq = load_kitti(folder)
    images = [seq.images(i) for i in range(len(seq))]
    n = len(seq)
    dist = float(np.sum(np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1)))
    teach_t, repeat_t, within, statuses = [], [], [], []
    with limit:
        for _ in range(repeats):
            times, vo_map = _teach(seq, images, range(n), settings)
            teach_t += times
            E = inv_T(seq.poses[n - 1]) @ vo_map.keyframes[-1].T_first_this
            drift_pct = 100.0 * float(np.linalg.norm(E[:3, 3])) / dist
            drift_deg_m = rotation_angle_deg(E) / dist
            offset_px = float(vo_map.meta.get("disparity_offset_px", 0.0))
            _, vmap = _teach(seq, images, range(0, n, 2), settings)
            fe, rep = StereoFrontend(vmap.camera, settings), VisualRepeat(vmap, settings)
            rep.start(0)
            for i in range(1, n, 2):
                t0 = time.perf_counter()
                step = rep.localize(fe.extract(*images[i]))
                repeat_t.append(time.perf_counter() - t0)
                statuses.append(step.status)
                if step.status == "ok":
                    D = step.T_live_kf @ inv_T(inv_T(seq.poses[i]) @ seq.poses[2 * step.keyframe])
                    within.append(np.linalg.norm(D[:3, 3]) <= RELOC_TOL_M and rotation_angle_deg(D) <= RELOC_TOL_DEG)
                else:
                    within.append(False)
    rt, tt = np.array(repeat_t) * 1e3, np.array(teach_t) * 1e3
    log.info("%d frames, %.1f m: teach %.1f ms p50, repeat %.1f ms p50 (%s)", n, dist, np.median(tt),
             np.median(rt), pinned)
    return {"fps": round(1e3 / float(rt.mean()), 1), "latency_ms_p50": round(float(np.percentile(rt, 50)), 2),
            "latency_ms_p99": round(float(np.percentile(rt, 99)), 2),
            "teach_fps": round(1e3 / float(tt.mean()), 1),
            "teach_latency_ms_p50": round(float(np.percentile(tt, 50)), 2),
            "teach_latency_ms_p99": round(float(np.percentile(tt, 99)), 2),
            "vo_drift_pct": round(drift_pct, 3), "vo_drift_deg_per_m": round(drift_deg_m, 5),
            "reloc_within_tol": round(float(np.mean(within)), 3),
            "disparity_offset_px": round(offset_px, 3),
            "repeat_status": {s: statuses.count(s) for s in sorted(set(statuses))},
            "frames": n, "distance_m": round(dist, 1), "repeats": repeats, "pinned": pinned,
            "data": folder.name, "data_dir": str(folder)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench localizer_kitti", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="passes over the sequence (latencies pooled)")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="a folder of the KITTI layout (calib.txt, poses.txt, image_l/, image_r/); "
                             "default ../shared/data/kitti_seq1")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[bench.localizer_kitti] %(message)s", stream=sys.stderr)
    return run_and_print(lambda: bench_kitti(args.repeats, data=args.data))


if __name__ == "__main__":
    raise SystemExit(main())
