"""`python -m bench.kitti_truth_check`: the rotation of each stretch of a KITTI excerpt, three ways.

Ground truth (poses.txt), the localizer's teach chain (stereo VO with window adjustment), and a plain
OpenCV pipeline that shares no code with the localizer (SIFT matched left-right on one row, triangulated,
matched into the next left image, solvePnPRansac + solvePnPRefineLM). Rotations are summed as rotation
vectors of the frame-to-frame motions, in degrees about the camera's x (pitch), y (yaw), z (roll).
Where two independent estimates agree with each other and not with the ground truth, the ground truth
is what moved. Prints one JSON line per stretch, the whole excerpt, then the VO's end-point drift as
is and with its first stretch replaced by the ground truth's.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from bench.localizer_kitti import KittiSequence, load_kitti
from common.se3 import inverse as inv_T
from common.se3 import rotation_angle_deg
from services.localizer.vision import StereoFrontend, VisionSettings, VisualTeach

RATIO = 0.75          # Lowe's ratio test
ROW_TOL_PX = 1.0      # rectified pair: a left-right match lies on one row
PNP_GATE_PX = 1.0


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(cv2.Rodrigues(np.ascontiguousarray(R))[0].ravel())


class _OpenCvStereoVO:
    def __init__(self, seq: KittiSequence):
        self.seq, self.sift, self.bf = seq, cv2.SIFT_create(5000), cv2.BFMatcher()
        self._left: dict[int, tuple[np.ndarray, np.ndarray]] = {}   # the next frame's left image is the following motion's left
        cam = seq.camera
        self.K = np.array([[cam.fu, 0.0, cam.cu], [0.0, cam.fv, cam.cv], [0.0, 0.0, 1.0]])

    def _features(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kps, desc = self.sift.detectAndCompute(image, None)
        return np.float32([k.pt for k in kps]), desc

    def _left_features(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if i not in self._left:
            self._left = {i: self._features(self.seq.images(i)[0])}
        return self._left[i]

    def _matches(self, da: np.ndarray, db: np.ndarray) -> list:
        return [m for m, n in self.bf.knnMatch(da, db, k=2) if m.distance < RATIO * n.distance]

    def motion(self, i: int) -> np.ndarray:
        """T_i_(i+1): the left camera of frame i + 1 in that of frame i."""
        (pl, dl), (pr, dr) = self._left_features(i), self._features(self.seq.images(i)[1])
        pn, dn = self._left_features(i + 1)
        cam = self.seq.camera
        pairs = [(m.queryIdx, m.trainIdx) for m in self._matches(dl, dr)
                 if abs(pl[m.queryIdx][1] - pr[m.trainIdx][1]) < ROW_TOL_PX
                 and 2.0 < pl[m.queryIdx][0] - pr[m.trainIdx][0] < 200.0]
        il, ir = np.array(pairs).T
        z = cam.fu * cam.baseline_m / (pl[il, 0] - pr[ir, 0] + cam.doffs_px)
        pts = np.stack([(pl[il, 0] - cam.cu) * z / cam.fu, (pl[il, 1] - cam.cv) * z / cam.fv, z], 1)
        mm = self._matches(dl[il], dn)
        obj, img = pts[[m.queryIdx for m in mm]], pn[[m.trainIdx for m in mm]]
        _, r, t, inl = cv2.solvePnPRansac(obj, img, self.K, None, reprojectionError=PNP_GATE_PX,
                                          iterationsCount=500, flags=cv2.SOLVEPNP_ITERATIVE)
        r, t = cv2.solvePnPRefineLM(obj[inl[:, 0]], img[inl[:, 0]], self.K, None, r, t)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(r)[0], t.ravel()
        return inv_T(T)


def _vo_chain(seq: KittiSequence) -> list[np.ndarray]:
    settings = VisionSettings()
    fe, teach = StereoFrontend(seq.camera, settings), VisualTeach(seq.camera, settings)
    for i in range(len(seq)):
        teach.add(fe.extract(*seq.images(i)))
    chain = [kf.T_first_this for kf in teach.finish().keyframes]
    if len(chain) != len(seq):
        raise RuntimeError(f"teach made {len(chain)} keyframes of {len(seq)} frames; this check needs one per frame")
    return chain


def _drift(seq: KittiSequence, T_first_last: np.ndarray) -> dict:
    """The bench's figures (bench.localizer_kitti): final pose error over the distance driven."""
    dist = float(np.sum(np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1)))
    E = inv_T(seq.poses[-1]) @ T_first_last
    return {"drift_pct": round(100.0 * float(np.linalg.norm(E[:3, 3])) / dist, 3),
            "drift_deg_per_m": round(rotation_angle_deg(E) / dist, 5)}


def check(seq: KittiSequence, stretches: list[tuple[int, int]]) -> list[dict]:
    """One row per stretch, then the VO chain's drift as is and with its first stretch as the truth has it."""
    chain, cv_vo = _vo_chain(seq), _OpenCvStereoVO(seq)
    steps = {"truth": [inv_T(seq.poses[i]) @ seq.poses[i + 1] for i in range(len(seq) - 1)],
             "localizer_vo": [inv_T(chain[i]) @ chain[i + 1] for i in range(len(seq) - 1)],
             "opencv_stereo_pnp": [cv_vo.motion(i) for i in range(len(seq) - 1)]}
    rows = []
    for a, b in stretches:
        row = {"frames": [a, b], "distance_m": round(float(sum(
            np.linalg.norm(s[:3, 3]) for s in steps["truth"][a:b])), 2)}
        for name, s in steps.items():
            row[f"{name}_rotvec_deg"] = [round(float(x), 3) for x in sum(_rotvec_deg(T[:3, :3]) for T in s[a:b])]
        rows.append(row)
    k = stretches[0][1]
    rows.append({"localizer_vo": _drift(seq, chain[-1]),
                 f"localizer_vo_with_truth_until_frame_{k}": _drift(seq, seq.poses[k] @ inv_T(chain[k]) @ chain[-1])})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.kitti_truth_check", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, metavar="DIR", help="a folder of the KITTI layout")
    parser.add_argument("--split", type=int, nargs="*", default=[11, 22, 33, 44],
                        help="frames where one stretch ends and the next begins")
    args = parser.parse_args(argv)
    seq = load_kitti(args.data)
    edges = [0, *args.split, len(seq) - 1]
    for row in check(seq, [*zip(edges[:-1], edges[1:]), (0, len(seq) - 1)]):
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
