"""`lbc bench store --n N`: the experience store service under a realistic load, over a real local router.

Rig (in a temporary directory, all real OS processes started by `deploy.launcher.Launcher`): a Zenoh
router, the localizer (it serves the taught route on `lbc/paths/<id>`, which the store checks every
experience against) and `gp_store` with the thesis defaults (v_bin 0.25 m/s, c_bin 4, c_vertex 5,
c_velocity 1). The taught route is straight, `--vertices` vertices (default 1000) 0.25 m apart. This
process plays a robot: a `Node` with an `ExperienceOutbox`, as the controller uses.

Workload: N experiences made the way repeated trials make them. Each trial drives the whole route at
10 Hz at one target speed from 0.3 to 1.5 m/s (0.2 m/s apart, in a seeded random order per cycle of
speeds), ramping up from standstill at 0.5 m/s^2, with a noisy commanded speed (sigma 0.03 m/s, so
speeds near a bin edge fall in both bins) and 0-10 % slip; the vertex is the one the robot is at.
Slow trials put ~8 experiences per vertex into a bin, fast ones ~2, so bins fill and c_bin evicts.
Trials repeat until N experiences exist (the last one is cut short).

Measured:
- ingest: every experience goes through `ExperienceOutbox.add`, flushed every `--batch` experiences;
  `ingest_per_s` = N / (time from the first add until the last acknowledgement, i.e. until every
  experience is durably committed). `resend_after_s` is set high (`--resend-after`) so the figure is
  the store's throughput, not re-sends under backlog; `resent` counts any that happened anyway. At most
  `--max-in-flight` experiences are unacknowledged at a time (the producer waits for acknowledgements
  beyond that; the default does not engage below 50000 experiences). `ingest_store_cpu_us`: CPU time
  of the gp_store process per experience over the same span. `retained` / `ingested` come from
  `lbc/store/stats`.
- window queries: `--queries` `session.get` on `lbc/store/<path>/window?vertex=i&speed=v` at a
  uniformly random populated (vertex, speed bin), speed uniform inside the bin, each timed until the
  reply stream has ended and the reply is decoded into an ExperienceWindow (what a caller waits);
  `--warmup` unrecorded ones first. `window_size_mean` is the mean number of experiences per window
  (a full window holds (2*5+1) * (2*1+1) * 4 = 132).
- `rss_mb`: VmRSS of the gp_store process after ingest and queries (`rss_idle_mb` before ingest,
  `rss_peak_mb` its VmHWM; `rss_zenoh_shm_mb` the part that is Zenoh's shared-memory transport
  buffers, mapped from /dev/shm and shared with the peers); `db_mb`: the SQLite file plus its WAL.

Progress goes to stderr; the last stdout line is one JSON object. Every child is stopped in a `finally`.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Callable

import numpy as np
import zenoh

from bench.report import run_and_print
from common import keys
from common.bins import BinPolicy
from common.bus import AliveWatcher, Node, query_one, setup_logging
from common.codec import DecodeError, decode
from common.config import dump_toml
from common.messages import ExperienceWindow, RouteMsg, StoreStats
from common.path import DEFAULT_SPACING_M, Path
from common.store_client import ExperienceOutbox

log = logging.getLogger("bench.store")

ROBOT = "r1"
PATH_ID = "bench_store"
SPACING_M = DEFAULT_SPACING_M
DT_S = 0.1                                   # 10 Hz control loop: one experience per tick
TRIAL_SPEEDS = (0.3, 0.5, 0.7, 0.9, 1.1, 1.3, 1.5)
ACCEL_MPS2 = 0.5
READY_TIMEOUT_S = 30.0
QUERY_TIMEOUT_S = 5.0


# --- workload ---------------------------------------------------------------------------------------
@dataclass
class Workload:
    trial: list[int]
    stamp_s: list[float]
    vertex: list[int]
    v_cmd: list[float]
    a: np.ndarray          # (n, 9): arrays, not lists of lists, so that --n 1000000 fits in memory
    g: np.ndarray          # (n, 3)
    trials: int

    def __len__(self) -> int:
        return len(self.vertex)


def make_workload(n: int, n_vertices: int, seed: int) -> Workload:
    """N experiences from repeated trials over the route (see the module docstring)."""
    rng = np.random.default_rng(seed)
    length_m = (n_vertices - 1) * SPACING_M
    trial, stamp, vertex, v_cmd = [], [], [], []
    a, g = np.empty((n, 9)), np.empty((n, 3))
    trials, t_global = 0, 0.0
    speeds: list[float] = []
    while len(vertex) < n:
        if not speeds:
            speeds = list(rng.permutation(TRIAL_SPEEDS))
        target = float(speeds.pop())
        trials += 1
        slip = rng.uniform(0.0, 0.1)
        s = t = 0.0
        v_prev = w_prev = v_act = w_act = 0.0
        while s < length_m and len(vertex) < n:
            v = max(0.0, min(target, 0.1 + ACCEL_MPS2 * t) + rng.normal(0.0, 0.03))
            w = rng.normal(0.0, 0.05)
            i = min(int(s / SPACING_M), n_vertices - 1)
            # a = (x, y, theta relative to the vertex, v_act, w_act, v_cmd, w_cmd at k-1, at k-2): eq. 5.15
            off = (s - i * SPACING_M, rng.normal(0.0, 0.02), rng.normal(0.0, 0.01))
            a[len(vertex)] = (*off, v_act, w_act, v, w, v_prev, w_prev)
            # g: body-frame x, y, heading residuals (slip, a side slope over part of the route, noise)
            g[len(vertex)] = (-slip * v * DT_S + rng.normal(0.0, 1e-3),
                              0.004 * math.sin(s / 20.0) * v + rng.normal(0.0, 1e-3),
                              rng.normal(0.0, 2e-3))
            trial.append(trials)
            stamp.append(t_global + t)
            vertex.append(i)
            v_cmd.append(v)
            v_act, w_act = v * (1.0 - slip), w
            v_prev, w_prev = v, w
            s += v_act * DT_S
            t += DT_S
        t_global += t + 60.0
    return Workload(trial, stamp, vertex, v_cmd, a, g, trials)


def populated_bins(w: Workload, v_bin: float) -> list[tuple[int, int]]:
    return sorted({(i, int(math.floor(v / v_bin))) for i, v in zip(w.vertex, w.v_cmd)})


# --- rig ------------------------------------------------------------------------------------------
def wait_until(check: Callable[[], bool], what: str, launcher, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Retry `check` (which itself blocks on an event or a reply) until true; fail fast if a child dies."""
    deadline = time.monotonic() + timeout_s
    while not check():
        for c in launcher.exited():
            raise RuntimeError(f"{what}: {c.name} exited with {c.proc.returncode}:\n{c.tail()}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not ready after {timeout_s:.0f} s")


def connect_node(endpoint: str, launcher) -> Node:
    """A client node; gives up (instead of retrying forever) if the router does not come up."""
    stop = threading.Event()
    timer = threading.Timer(READY_TIMEOUT_S, stop.set)
    timer.daemon = True
    timer.start()
    try:
        return Node("bench", ROBOT, endpoint, stop=stop)
    except ConnectionError as exc:
        tails = "\n".join(f"{c.name}: {c.tail()}" for c in launcher.exited())
        raise RuntimeError(f"{exc}\n{tails}") from None
    finally:
        timer.cancel()


def proc_status_mb(pid: int) -> dict[str, float]:
    out = {}
    try:
        for line in FsPath(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(rest.split()[0]) / 1024.0   # kB
    except OSError:
        pass
    return out


def shm_rss_mb(pid: int) -> float:
    """Resident pages of Zenoh's shared-memory segments (/dev/shm/*.zenoh) mapped into the process:
    part of VmRSS, but shared with every peer on the host rather than the store's own memory."""
    total, in_shm = 0, False
    try:
        for line in FsPath(f"/proc/{pid}/smaps").read_text().splitlines():
            head = line.split()
            if head and "-" in head[0] and not head[0].endswith(":"):
                in_shm = len(head) >= 6 and head[-1].startswith("/dev/shm/")
            elif in_shm and line.startswith("Rss:"):
                total += int(head[1])
    except OSError:
        return float("nan")
    return total / 1024.0


def file_mb(*paths: FsPath) -> float:
    return sum(p.stat().st_size for p in paths if p.exists()) / 2**20


def percentile(xs: list[float], q: int) -> float:
    return statistics.quantiles(xs, n=100, method="inclusive")[q - 1] if len(xs) > 1 else xs[0]


# --- measurement ------------------------------------------------------------------------------------
def ingest(node: Node, w: Workload, batch: int, resend_after_s: float, timeout_s: float,
           max_in_flight: int, store_pid: int) -> dict:
    outbox = ExperienceOutbox(node, ROBOT, resend_after_s=resend_after_s, max_batch=max(batch, 1),
                              max_pending=max(max_in_flight + batch, 200_000))
    n, sent = len(w), [0]
    flush = outbox.flush

    def counting_flush() -> int:   # wait_acked flushes too: count every send, re-sends included
        k = flush()
        sent[0] += k
        return k
    outbox.flush = counting_flush
    deadline = time.monotonic() + timeout_s
    cpu0 = cpu_s(store_pid)
    t0 = time.perf_counter()
    for k in range(n):
        outbox.add(stamp_s=w.stamp_s[k], trial=w.trial[k], path_id=PATH_ID, vertex=w.vertex[k],
                   v_cmd_mps=w.v_cmd[k], a=w.a[k].tolist(), g=w.g[k].tolist())
        if (k + 1) % batch == 0:
            outbox.flush()
            # a producer far ahead of the store only queues (and the outbox would drop beyond its cap)
            while outbox.pending >= max_in_flight:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{outbox.pending} experiences not acknowledged after {timeout_s:.0f} s")
                time.sleep(0.001)
                outbox.flush()
    outbox.flush()
    published_s = time.perf_counter() - t0
    while not outbox.wait_acked(1.0):   # 1 s slices: SIGTERM/Ctrl-C stays responsive
        if time.monotonic() > deadline:
            raise RuntimeError(f"{outbox.pending} of {n} experiences not acknowledged after {timeout_s:.0f} s")
    elapsed = time.perf_counter() - t0
    store_cpu_s = cpu_s(store_pid) - cpu0
    resent = sent[0] - n
    if outbox.rejected:
        raise RuntimeError(f"the store rejected {outbox.rejected} experiences (see its log)")
    if outbox.dropped or outbox.acked != n:
        raise RuntimeError(f"{outbox.acked} of {n} experiences acknowledged, {outbox.dropped} dropped by the outbox")
    return {"ingest_s": elapsed, "publish_s": published_s, "acked": outbox.acked, "resent": resent,
            "source": outbox.source, "store_cpu_s": store_cpu_s}


def cpu_s(pid: int) -> float:
    """User + system CPU time of a process so far (less disturbed by a busy machine than wall time)."""
    try:
        fields = FsPath(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


def window_query(session: zenoh.Session, vertex: int, speed: float) -> tuple[float, ExperienceWindow | None, str]:
    selector = f"{keys.store_window(PATH_ID)}?vertex={vertex}&speed={speed:.6f}"
    t0 = time.perf_counter_ns()
    window, error = None, ""
    for rep in session.get(selector, timeout=QUERY_TIMEOUT_S):
        if rep.ok is None:
            error = rep.err.payload.to_bytes().decode("utf-8", "replace")
            continue
        try:
            window = decode(ExperienceWindow, rep.ok.payload.to_bytes())
        except DecodeError as exc:
            error = f"bad window: {exc}"
    ms = (time.perf_counter_ns() - t0) / 1e6
    return ms, window, error or ("" if window is not None else "no reply")


def query_windows(session: zenoh.Session, bins: list[tuple[int, int]], v_bin: float, n: int, warmup: int,
                  rng: np.random.Generator) -> dict:
    times, sizes, errors, last_error = [], [], 0, ""
    for k in range(warmup + n):
        vertex, b = bins[int(rng.integers(len(bins)))]
        speed = (b + rng.uniform(0.05, 0.95)) * v_bin
        ms, window, error = window_query(session, vertex, speed)
        if k < warmup:
            continue
        if window is None:
            errors += 1
            last_error = error
            continue
        times.append(ms)
        sizes.append(len(window.vertices))
    if not times:
        raise RuntimeError(f"no window query succeeded: {last_error}")
    if errors:
        log.warning("%d window queries failed, last: %s", errors, last_error)
    return {"window_query_ms_p50": round(statistics.median(times), 4),
            "window_query_ms_p99": round(percentile(times, 99), 4),
            "window_query_ms_mean": round(statistics.fmean(times), 4),
            "window_query_ms_max": round(max(times), 4),
            "window_queries": len(times), "window_query_errors": errors,
            "window_size_mean": round(statistics.fmean(sizes), 2), "window_size_max": max(sizes)}


def _write_rig_files(base: FsPath, vertices: int, bins: BinPolicy) -> FsPath:
    """A straight taught route and the localizer's and store's configs under `base`; the DB's path."""
    from services.gp_store.config import FitConfig, StoreConfig
    from services.localizer.config import LocalizerConfig
    from services.localizer.routes import RouteStore

    poses = np.column_stack([np.arange(vertices) * SPACING_M, np.zeros(vertices), np.zeros(vertices)])
    RouteStore(base / "data" / "routes").save(Path(PATH_ID, poses, spacing_m=SPACING_M), 0.0)
    (base / "loc.toml").write_text(dump_toml(LocalizerConfig(robot_name=ROBOT, data_dir=str(base / "data"))))
    db_path = base / "data" / "experiences.db"
    (base / "store.toml").write_text(dump_toml(StoreConfig(
        name="bench", db_path=str(db_path), bins=bins, fit=FitConfig(auto_after_trial=False))))
    return db_path


def _wait_for_rig(node, watcher, launcher, vertices: int) -> None:
    """Until the localizer and the store are alive and the route is served."""
    want = {keys.alive(ROBOT, "localizer"), keys.alive(keys.STORE_ROBOT, "gp_store")}
    wait_until(lambda: watcher.wait_for(lambda alive: want <= alive, 0.5), "localizer and gp_store", launcher)

    def route_served() -> bool:
        try:
            return len(query_one(node.session, keys.route(PATH_ID), RouteMsg, timeout_s=1.0).x_m) == vertices
        except LookupError:
            return False
    wait_until(route_served, "route on lbc/paths", launcher)


def run_bench(args: argparse.Namespace) -> dict:
    from deploy.launcher import Launcher
    from deploy.router import free_port
    bins_cfg = BinPolicy()   # thesis defaults
    rng = np.random.default_rng(args.seed)
    log.info("generating %d experiences on a %d-vertex route", args.n, args.vertices)
    work = make_workload(args.n, args.vertices, args.seed)
    bins = populated_bins(work, bins_cfg.v_bin_mps)

    with tempfile.TemporaryDirectory(prefix="lbc-bench-store-") as tmp:
        base = FsPath(tmp)
        db_path = _write_rig_files(base, args.vertices, bins_cfg)
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        launcher = Launcher(endpoint, base / "logs")
        node = watcher = None
        try:
            t_setup = time.perf_counter()
            launcher.start_router(port)
            launcher.start_service("localizer", base / "loc.toml", args.service_log_level)
            launcher.start_service("gp_store", base / "store.toml", args.service_log_level)
            node = connect_node(endpoint, launcher)
            watcher = AliveWatcher(node.session, f"{keys.ROOT}/alive/**")
            _wait_for_rig(node, watcher, launcher, args.vertices)
            log.info("rig up in %.1f s (router %s)", time.perf_counter() - t_setup, endpoint)
            store_pid = next(c.proc.pid for c in launcher.children if c.name == "gp_store")
            rss_idle = proc_status_mb(store_pid).get("VmRSS", float("nan"))

            log.info("ingesting %d experiences (%d trials, %d bins) in batches of %d",
                     len(work), work.trials, len(bins), args.batch)
            ing = ingest(node, work, args.batch, args.resend_after, timeout_s=max(120.0, args.n / 100.0),
                         max_in_flight=args.max_in_flight, store_pid=store_pid)
            log.info("ingested in %.2f s (%.0f /s)", ing["ingest_s"], args.n / ing["ingest_s"])
            stats = query_one(node.session, keys.store_stats(), StoreStats, timeout_s=QUERY_TIMEOUT_S)
            path_stats = next((p for p in stats.paths if p.path_id == PATH_ID), None)
            if path_stats is None:
                raise RuntimeError(f"the store reports nothing for {PATH_ID}")

            log.info("%d window queries (+%d warmup)", args.queries, args.warmup)
            q = query_windows(node.session, bins, bins_cfg.v_bin_mps, args.queries, args.warmup, rng)
            mem = proc_status_mb(store_pid)
            shm_mb = shm_rss_mb(store_pid)
            db_mb = file_mb(db_path, db_path.with_name(db_path.name + "-wal"))
            if launcher.exited():
                c = launcher.exited()[0]
                raise RuntimeError(f"{c.name} exited with {c.proc.returncode} during the run:\n{c.tail()}")
        finally:
            if watcher is not None:
                watcher.close()
            if node is not None:
                node.close()
            launcher.stop()

    return {"n": args.n, "ingest_per_s": round(args.n / ing["ingest_s"], 1), **q,
            "rss_mb": round(mem.get("VmRSS", float("nan")), 2), "rss_peak_mb": round(mem.get("VmHWM", float("nan")), 2),
            "rss_idle_mb": round(rss_idle, 2), "rss_zenoh_shm_mb": round(shm_mb, 2), "db_mb": round(db_mb, 3),
            "ingest_s": round(ing["ingest_s"], 4), "publish_s": round(ing["publish_s"], 4),
            "ingest_store_cpu_us": round(ing["store_cpu_s"] / args.n * 1e6, 2),
            "ingested": path_stats.ingested, "retained": path_stats.retained, "bins": path_stats.bins,
            "acked": ing["acked"], "resent": ing["resent"], "batch": args.batch, "trials": work.trials,
            "vertices": args.vertices, "v_bin_mps": bins_cfg.v_bin_mps, "c_bin": bins_cfg.c_bin,
            "c_vertex": bins_cfg.c_vertex, "c_velocity": bins_cfg.c_velocity, "seed": args.seed}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench store", description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=25000, help="experiences to ingest")
    parser.add_argument("--queries", type=int, default=2000, help="timed window queries")
    parser.add_argument("--warmup", type=int, default=50, help="unrecorded window queries first")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--vertices", type=int, default=1000, help="vertices of the taught route (0.25 m apart)")
    parser.add_argument("--batch", type=int, default=100, help="experiences per outbox flush")
    parser.add_argument("--max-in-flight", type=int, default=50_000,
                        help="unacknowledged experiences at most before the producer waits")
    parser.add_argument("--resend-after", type=float, default=60.0,
                        help="the outbox's resend_after_s (high: measure the store, not re-sends)")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--service-log-level", default="WARNING")
    args = parser.parse_args(argv)
    setup_logging("bench", args.log_level)
    if args.n < 1 or args.queries < 1 or args.warmup < 0 or args.batch < 1 or args.vertices < 11 \
            or args.max_in_flight < args.batch:
        parser.error("--n, --queries and --batch must be >= 1, --warmup >= 0, --vertices >= 11 and "
                     "--max-in-flight >= --batch")

    return run_and_print(lambda: run_bench(args))


if __name__ == "__main__":
    raise SystemExit(main())
