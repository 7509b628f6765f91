"""`lbc bench localizer --source sim|kitti`: frames per second and per-frame latency of the vision
localizer on one core (DESIGN.md keys `fps`, `latency_ms_p50`, `latency_ms_p99`; target >= 20 Hz).

kitti: the real KITTI excerpt through the VT&R core (see bench/localizer_kitti.py).
sim: rendered 640x480 stereo along a simulated route. Teach once, then repeat with lateral offsets of
up to 0.5 m; each repeat frame is timed from the StereoFrame message as the bus delivers it (capture)
to the LocState ready to publish: image decode, keypoints, VO, keyframe refinement and the conversion
to the vertex frame (`VisionSource.on_frame`). Rendering is the simulator's cost and is not timed; the
bus hop is `lbc bench bus`'s (well under a millisecond). Also reported: how often the repeat frames
were refined against the map, and the lateral error of the estimate against simulator truth (the
robot's ground contact point, in the vertex's level frame). With `--terrain` a side slope (13 deg,
falling to the right of the first straight) and a rut (deeper after the teach pass) tilt and lower the
rendered camera as the simulator's terrain does (`Terrain.attitude`), in teach and repeat alike.
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.localizer_kitti import bench_kitti
from bench.report import run_and_print, single_core
from common import se2
from common.codec import decode, encode
from common.messages import StereoFrame
from common.camera import StereoConfig
from common.scenario import TerrainPatch
from services.bridge.render import StereoRenderer
from services.bridge.terrain import Attitude, Terrain
from services.bridge.teach_driver import smooth_waypoints
from services.bridge.world import build_world
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision_source import VisionSource

log = logging.getLogger("bench.localizer")
WAYPOINTS = [[0.0, 0.0], [8.0, 0.0], [14.0, 4.0], [22.0, 4.0]]
# --terrain: the route starts on level ground (the map's first keyframe defines level)
TERRAIN = [TerrainPatch(kind="side_slope", center=(8.5, -1.0), radius_m=5.5, slope_deg=13.0, downhill_deg=-90.0),
           TerrainPatch(kind="rut", center=(18.0, 4.0), radius_m=3.0, depth_m=0.04, growth_m_per_pass=0.02)]


def offset_route(ref: np.ndarray, amplitude_m: float) -> np.ndarray:
    """The route shifted sideways by amplitude * sin(pi s / L) (0 at both ends), heading along it."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
    off = amplitude_m * np.sin(np.pi * s / s[-1])
    xy = ref[:, :2] + off[:, None] * np.column_stack([-np.sin(ref[:, 2]), np.cos(ref[:, 2])])
    d = np.gradient(xy, axis=0)
    return np.column_stack([xy, np.arctan2(d[:, 1], d[:, 0])])


def drive_over(terrain: Terrain, route: np.ndarray) -> list[Attitude]:
    """The body's attitude at every pose of one trial along `route`; ruts it crossed deepen after it."""
    terrain.begin_trial()
    out = []
    for x, y, theta in route:
        terrain.effect(x, y)                 # marks the patches crossed
        out.append(terrain.attitude(x, y, theta))
    terrain.end_trial()
    return out


def bench_sim(speed_mps: float = 0.5, seed: int = 1, terrain: bool = False) -> dict:
    pinned, limit = single_core()
    renderer = StereoRenderer(StereoConfig(), build_world(WAYPOINTS, seed), seed)
    ref = smooth_waypoints(WAYPOINTS, 3.0, False, step_m=speed_mps * 0.1)
    drive = offset_route(ref, 0.5)
    ground = Terrain(TERRAIN if terrain else [], seed)
    teach_att, repeat_att = drive_over(ground, ref), drive_over(ground, drive)
    with tempfile.TemporaryDirectory() as tmp, limit:
        src = VisionSource(VisionSettings(), tmp)
        src.start_teach(0)
        kf_truth, render_s = [], []
        for k, (p, att) in enumerate(zip(ref, teach_att)):
            n = len(src.teach.keyframes) if src.teach is not None else 0
            src.on_frame(renderer.frame(stamp_s=0.1 * k, tick=k, trial=0, x=p[0], y=p[1], theta=p[2],
                                        v=speed_mps, attitude=att), "bench")
            if len(src.teach.keyframes) > n:
                kf_truth.append(p)
        path = src.finish_teach("bench", loop=False, taught_by="bench")
        src.start_repeat(path, 1)
        lat_ms, statuses, err = [], [], []
        for k, (p, att) in enumerate(zip(drive, repeat_att)):
            t0 = time.perf_counter()
            payload = encode(renderer.frame(stamp_s=0.1 * k, tick=k, trial=1, x=p[0], y=p[1], theta=p[2],
                                            v=speed_mps, attitude=att))
            render_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            loc = src.on_frame(decode(StereoFrame, payload), "bench")
            lat_ms.append(1e3 * (time.perf_counter() - t0))
            statuses.append(loc.status)
            if loc.status == "ok":
                err.append(loc.T_vertex_robot[1] - se2.between(kf_truth[loc.vertex], p)[1])
    lat, err = np.array(lat_ms), np.array(err)
    log.info("%d repeat frames, %d keyframes, %s", len(drive), len(path), pinned)
    return {"fps": round(1e3 / float(lat.mean()), 1), "latency_ms_p50": round(float(np.percentile(lat, 50)), 2),
            "latency_ms_p99": round(float(np.percentile(lat, 99)), 2),
            "render_ms_p50": round(1e3 * float(np.median(render_s)), 2),
            "refined_fraction": round(statuses.count("ok") / len(statuses), 4),
            "repeat_status": {s: statuses.count(s) for s in sorted(set(statuses))},
            "lateral_err_mean_m": round(float(err.mean()), 4), "lateral_err_std_m": round(float(err.std()), 4),
            "frames": len(drive), "keyframes": len(path), "route_m": round(path.length_m, 1),
            "image": f"{renderer.calib.width_px}x{renderer.calib.height_px}", "pinned": pinned,
            "terrain": terrain, "tilt_max_deg": round(_tilt_max_deg(teach_att + repeat_att), 2),
            "sink_max_m": round(max(0.0, -min(a.z_m for a in teach_att + repeat_att)), 4)}


def _tilt_max_deg(attitudes: list[Attitude]) -> float:
    """Largest angle between the body's z axis and the vertical over the poses."""
    return max(math.degrees(math.acos(min(1.0, math.cos(a.roll_rad) * math.cos(a.pitch_rad)))) for a in attitudes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench localizer", description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("sim", "kitti"), default="sim")
    parser.add_argument("--repeats", type=int, default=3, help="kitti: passes over the sequence")
    parser.add_argument("--speed", type=float, default=0.5, help="sim: driving speed (m/s), sets the blur")
    parser.add_argument("--terrain", action="store_true",
                        help="sim: a side slope and a rut on the route tilt and lower the camera")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="kitti: a folder of the KITTI layout (calib.txt, poses.txt, image_l/, image_r/); "
                             "default ../shared/data/kitti_seq1")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[bench.localizer] %(message)s", stream=sys.stderr)
    if args.data is not None and args.source != "kitti":
        parser.error("--data goes with --source kitti")
    if args.terrain and args.source != "sim":
        parser.error("--terrain goes with --source sim")
    if args.source == "kitti":
        return run_and_print(lambda: bench_kitti(args.repeats, data=args.data))
    return run_and_print(lambda: bench_sim(args.speed, terrain=args.terrain))


if __name__ == "__main__":
    raise SystemExit(main())
