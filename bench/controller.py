"""`lbc bench controller --algorithm lb-nmpc`: per-step solve time of the real-time controller, and the
same optimal-control problems solved by CasADi + IPOPT on identical inputs.

Setup, all from the project's own pure cores (bench/closed_loop.py): a robot (`--robot`, a Husky by
default) is taught a 30 m route with a side slope and a slip patch, and its nominal model (drive lags,
an Ackermann's steering-rate limit, the turn gain, the prior) is identified from that teach pass as the
controller does. Then it repeats the route with the FL tracker at three speeds, twice each,
so that every (vertex, speed bin) holds c_bin = 4 experiences. With c_vertex = 7 and c_velocity = 1
the full local window is 15 x 3 x 4 = 180 experiences (the thesis's "up to 180"). Hyperparameters are
fitted as the store fits them. Then one LB-NMPC repeat at the middle speed is timed step by step: the
time of `law.angular` (model lookup, GP build when the window changes and the node did not build it
after the previous command, problem set-up, the solve); `prepare_ms_p99` is that between-steps build.
The process is pinned to one CPU and BLAS to one thread. Every n-th problem is kept and solved again by
CasADi/IPOPT (same dynamics with the same GP mean written symbolically, same cost, same bounds, same
start; not for a rate-limited steering, whose turn CasADi's rollout here does not write);
`casadi_solve_ms_p50` is IPOPT's solve time (graph building excluded) and `cost_gap` the mean relative
difference of the optimal costs, (ours - IPOPT's) / IPOPT's: > 0 means ours is worse.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from bench.closed_loop import ClosedLoop
from bench.report import run_and_print, single_core
from common.messages import Experience, HyperMsg
from common.robot import PRESETS
from common.scenario import TerrainPatch
from services.controller.corridor import Corridor
from services.controller.gauss_newton import gauss_newton
from services.controller.horizon import HorizonProblem
from services.controller.laws import LawResult, StepContext
from services.controller.fl import FLGains
from services.controller.local_model import LocalModels
from services.controller.rest_fade import RestFaded
from services.controller.minmax import SIGNS
from services.controller.nmpc import build_problem
from services.controller.registry import STEERING_LAWS, LawInputs
from services.controller.robust_nmpc import CorridorStep, MinMaxStep
from services.controller.settings import NMPCSettings
from services.gp_store.config import FitConfig
from common.bins import BinPolicy
from services.gp_store.db import ExperienceDB
from services.gp_store.fitting import fit_route
from services.localizer.pose_source import PoseSourceSettings

log = logging.getLogger("bench.controller")
ROUTE = [[0, 0], [10, 0], [18, 6], [26, 6], [30, 2]]
TERRAIN = [TerrainPatch(kind="side_slope", center=(13.0, 2.0), radius_m=6.0, slope_deg=12.0, downhill_deg=-90.0),
           TerrainPatch(kind="slip", center=(20.0, 5.0), radius_m=4.0, traction=0.6)]
SPEEDS = (0.30, 0.55, 0.80)       # speed bins 1, 2, 3 with v_bin = 0.25
POLICY = BinPolicy(c_vertex=7)    # the full window of the docstring: 15 x 3 x 4
DT = 0.1


def build_memory(seed: int, workdir: str, preset: str = "husky"):
    """Teach, collect FL experiences at three speeds, store them and fit hyperparameters."""
    cl = ClosedLoop(ROUTE, TERRAIN, preset=preset, seed=seed, teach_speed=0.4, loc=PoseSourceSettings())
    path = cl.teach()
    db = ExperienceDB(os.path.join(workdir, "bench.db"), POLICY)
    seq, trial = 0, 0
    for _ in range(2):
        for speed in SPEEDS:
            trial += 1
            r = cl.repeat(trial, speed)
            db.ingest("bench", [Experience(stamp_s=o.stamp_s, robot="bench", trial=trial, path_id="route", seq=seq + i,
                                           vertex=o.vertex, v_cmd_mps=o.v_cmd_mps, a=o.a, g=o.g)
                                for i, o in enumerate(r.observations)])
            seq += len(r.observations)
    A, G, tiles = db.all_of("route")
    fit = fit_route("route", A, G, tiles, 3, 1000, seed, None, FitConfig().floors(teach_only=False))
    hyper = fit.message(version=1, stamp_s=0.0)
    # windows in memory, as the controller's prefetch cache holds them
    windows = {}
    for v in range(len(path)):
        for l in range(0, 5):   # the end-of-route slowdown drops into lower bins
            w = db.window("route", v, (l + 0.5) * POLICY.v_bin_mps)
            windows[(v, l)] = (w.A, w.G)
    db.close()
    return cl, path, hyper, windows, trial, len(A)


LAWS = [name for name, e in STEERING_LAWS.items() if e.learns == "gp"]     # the NMPC family


@dataclass
class Timing:
    times: np.ndarray        # ms per step: law.angular, the command's latency
    sizes: np.ndarray        # window size per step
    kept: list               # problems kept for the IPOPT comparison
    evals: np.ndarray        # residual evaluations (or iterations) per step
    statuses: list
    prepare_ms: np.ndarray   # ms per step spent after the command on the next window's GP (node.py)
    builds_in_step: int      # window GPs the steps still had to build themselves


class TimedLaw:
    """A law timed step by step as the node runs it: `angular` (the command's latency), then the next
    window's GP built after the command (not part of the step's time)."""

    def __init__(self, law, models: LocalModels, keep_every: int):
        self.law, self.models, self.keep_every = law, models, keep_every
        self.name = law.name
        self.times, self.sizes, self.evals, self.statuses, self.prepare = [], [], [], [], []
        self.kept: list = []     # (ctx, the law's last_step) for the IPOPT comparison

    def angular(self, ctx: StepContext) -> LawResult:
        t0 = time.perf_counter()
        res = self.law.angular(ctx)
        self.times.append((time.perf_counter() - t0) * 1e3)
        self.sizes.append(self.models.last_n)
        self.evals.append(res.solve.evaluations if res.solve is not None else 0)
        self.statuses.append(res.solve.status if res.solve is not None else "")
        if len(self.times) % self.keep_every == 0 and not res.stop_reason:
            self.kept.append((ctx, self.law.last_step, self.times[-1]))
        v = ctx.v_mps if res.v_mps is None else res.v_mps
        t1 = time.perf_counter()
        self.models.prepare(ctx.path, ctx.s_m + v * DT, v)
        self.prepare.append((time.perf_counter() - t1) * 1e3)
        return res


def time_controller(cl: ClosedLoop, hyper: HyperMsg, windows: dict, trial: int, settings: NMPCSettings,
                    keep_every: int, algorithm: str = "lb-nmpc") -> Timing:
    # the windows drawn as the node draws them (C/RC hold the window's speed bin: node.py)
    entry = STEERING_LAWS[algorithm]
    models = LocalModels(lambda v, s: windows[(v, int(math.floor(s / POLICY.v_bin_mps)))], lambda: hyper,
                         settings.horizon * DT, POLICY.v_bin_mps, hold_steps=entry.window_hold_steps,
                         variance_caps=settings.vouch_lengthscales if entry.uses_variance else None)
    law = entry.build(LawInputs(FLGains(), settings, DT, models.model_for, models.model_at))
    timed = TimedLaw(law, models, keep_every)
    corridor = Corridor(cl.path.s, 0.3, math.radians(20.0)) if entry.needs_corridor else None
    cl.repeat(trial + 1, SPEEDS[1], law=timed, corridor=corridor, lag=settings.lag(DT))
    return Timing(np.array(timed.times), np.array(timed.sizes), timed.kept, np.array(timed.evals), timed.statuses,
                  np.array(timed.prepare), models.builds - models.prepared)


def _casadi_gp_mean(model):
    """The GP posterior mean as a CasADi expression builder (None: the nominal model, zero)."""
    import casadi as ca
    if model is None:
        return None
    center, Xc, dims = model.mean_terms()
    v_floor = model.v_floor if isinstance(model, RestFaded) else 0.0     # the fade at rest

    def mean(a):
        out = []
        fade = ca.fmin(1.0, ca.fmax(a[3], 0.0) / v_floor) if v_floor > 0.0 else 1.0
        for inv_ell, sf2, alpha in dims:
            diff = (ca.repmat(ca.transpose(a - ca.DM(center)), Xc.shape[0], 1) - ca.DM(Xc)) * ca.repmat(
                ca.DM(inv_ell).T, Xc.shape[0], 1)
            k = sf2 * ca.exp(-0.5 * ca.sum2(diff ** 2))
            out.append(fade * ca.dot(k, ca.DM(alpha)))
        return out
    return mean


def _casadi_rollout(problem: HorizonProblem, gp_mean, w, v, D, sD, cD, sinD):
    """Predicted poses x_1..x_K as in HorizonProblem.rollout, with symbolic w, v and reference."""
    import casadi as ca
    K, dt = problem.K, problem.dt
    X = [ca.SX(problem.x0)]
    vb, wb = v, w
    lag = problem.lag
    if lag is not None:     # the drive's lag: the robot moves at L u + c xi0 (actuator.py)
        vb = ca.mtimes(ca.DM(lag.Lv), ca.vertcat(*[v[j] for j in range(K)])) + ca.DM(lag.cv)
        wb = ca.mtimes(ca.DM(lag.Lw), ca.vertcat(*[w[j] for j in range(K)])) + ca.DM(lag.cw)
    for j in range(K):
        xj = X[j]
        c, sn = ca.cos(xj[2]), ca.sin(xj[2])
        gx = gy = gth = 0
        if gp_mean is not None:
            dx, dy = xj[0] - D[j][0], xj[1] - D[j][1]
            if j == 0:
                v_act, w_act = problem.start.v_prev_act
                v_prev, w_prev = problem.u_prev
            else:
                xp = X[j - 1]
                v_act = (ca.cos(xp[2]) * (xj[0] - xp[0]) + ca.sin(xp[2]) * (xj[1] - xp[1])) / dt
                w_act = (xj[2] - xp[2]) / dt
                v_prev, w_prev = v[j - 1], w[j - 1]
            a = ca.vertcat(sD[j] + cD[j] * dx + sinD[j] * dy, -sinD[j] * dx + cD[j] * dy, xj[2] - D[j][2],
                           v_act, w_act, v[j], w[j], v_prev, w_prev)
            gx, gy, gth = gp_mean(a)
        X.append(ca.vertcat(xj[0] + vb[j] * dt * c + c * gx - sn * gy, xj[1] + vb[j] * dt * sn + sn * gx + c * gy,
                            xj[2] + wb[j] * dt + gth))
    return X


def _route_errors(X, D, cD, sinD, j):
    dx, dy = X[j][0] - D[j][0], X[j][1] - D[j][1]
    return [cD[j] * dx + sinD[j] * dy, -sinD[j] * dx + cD[j] * dy, X[j][2] - D[j][2]]


def casadi_solve(problem: HorizonProblem, model, u0: np.ndarray, w_limit: np.ndarray):
    """The same LB-NMPC problem in CasADi, solved by IPOPT; returns (solve seconds, optimal cost)."""
    import casadi as ca
    K, s = problem.K, problem.s
    w = ca.SX.sym("w", K)
    ref = problem.ref
    D = [[float(x) for x in row] for row in ref.poses]
    X = _casadi_rollout(problem, _casadi_gp_mean(model), w, problem.v, D, ref.s_m, ref.cos_dir, ref.sin_dir)
    res = []
    for j in range(1, K + 1):
        e = _route_errors(X, D, ref.cos_dir, ref.sin_dir, j)
        e[2] = e[2] - ref.head_offset[j - 1]          # the cost's heading reference (learned crab)
        res += [problem.sqrt_q[i] * e[i] for i in range(3)]
        if j == K:
            term = e[1] + s.lookahead_m * ca.sin(e[2])
    res += [problem.sqrt_r * (w[j] - problem.w_ref[j]) for j in range(K)]
    prev = problem.u_prev[1]
    for j in range(K):
        res.append(problem.sqrt_dr * (w[j] - prev))
        prev = w[j]
    res.append(problem.sqrt_qt * term)
    r = ca.vertcat(*res)
    nlp = {"x": w, "f": 0.5 * ca.dot(r, r)}
    solver = ca.nlpsol("ocp", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": 0, "ipopt.tol": 1e-10,
                                             "ipopt.sb": "yes"})
    t0 = time.perf_counter()
    out = solver(x0=u0, lbx=-w_limit, ubx=w_limit)
    seconds = time.perf_counter() - t0
    return seconds, float(out["f"])


def worst_case_cost(problem: HorizonProblem, bound: np.ndarray, w: np.ndarray) -> float:
    """Eq. 6.5-6.6 at w: the largest cost over the 2^3 boundary sequences E + s_l * bound."""
    return max(problem.cost(w, error_offset=signs * bound) for signs in SIGNS)


def casadi_solve_minmax(step: MinMaxStep, settings: NMPCSettings):
    """One MM-LB-NMPC step (`MMLBNMPCLaw.last_step`) in CasADi, solved by IPOPT in epigraph form:
    min t subject to t >= the cost of each of the 2^3 boundary sequences (the same fixed 3-sigma bounds,
    the same GP mean, weights and limits). Returns (solve seconds, optimal worst-case cost, ours)."""
    import casadi as ca
    p, bound = step.problem, step.bound
    ref = p.ref
    K, s = p.K, settings
    w = ca.SX.sym("w", K)
    t = ca.SX.sym("t")
    D = [[float(x) for x in row] for row in ref.poses]
    X = _casadi_rollout(p, _casadi_gp_mean(p.model), w, p.v, D, ref.s_m, ref.cos_dir, ref.sin_dir)
    E = [_route_errors(X, D, ref.cos_dir, ref.sin_dir, j) for j in range(1, K + 1)]
    for j in range(K):
        E[j][2] = E[j][2] - ref.head_offset[j]              # the cost's heading reference (learned crab)
    common = sum(s.r_w * (w[j] - p.w_ref[j]) ** 2 for j in range(K))
    prev = p.u_prev[1]
    for j in range(K):
        common += s.r_dw * (w[j] - prev) ** 2
        prev = w[j]
    g = []
    for signs in SIGNS:
        Eb = [[E[j][c] + signs[c] * bound[j, c] for c in range(3)] for j in range(K)]
        track = sum(p.sqrt_q[c] ** 2 * Eb[j][c] ** 2 for j in range(K) for c in range(3))
        term = Eb[-1][1] + s.lookahead_m * ca.sin(Eb[-1][2])
        g.append(0.5 * (track + common + s.q_terminal * term ** 2) - t)
    nlp = {"x": ca.vertcat(w, t), "f": t, "g": ca.vertcat(*g)}
    solver = ca.nlpsol("mm", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": 0, "ipopt.tol": 1e-10,
                                            "ipopt.sb": "yes"})
    ours = worst_case_cost(p, bound, step.w)
    lim = step.w_limit
    t0 = time.perf_counter()
    out = solver(x0=np.concatenate([step.w0, [ours]]), lbx=np.concatenate([-lim, [-np.inf]]),
                 ubx=np.concatenate([lim, [np.inf]]), ubg=0.0)
    seconds = time.perf_counter() - t0
    if not solver.stats()["success"]:
        return seconds, None, ours
    return seconds, float(out["f"]), ours


def casadi_solve_constrained(step: CorridorStep, settings: NMPCSettings):
    """One step of C-/RC-LB-NMPC (`RCLBNMPCLaw.last_step`) in CasADi, solved by IPOPT: both speeds
    free, the desired poses following the planned speeds along the route, the corridor tightened by
    alpha * sigma with the lateral sigma linear in the speeds as our SQP has it, violations through
    slacks at the same L1 price. Returns (solve seconds, optimal merit, our merit)."""
    import casadi as ca
    nlp = step.nlp
    p = nlp.problem
    path, K, dt, s = p.path, p.K, p.dt, settings
    v, w = ca.SX.sym("v", K), ca.SX.sym("w", K)
    sl = ca.SX.sym("slack", 3 * K)
    # the reference where the planned speeds take the robot (pose_at / tangent_at / curvature, interpolated)
    heads = np.unwrap(path.poses[:, 2])
    offset = 2 * np.pi * np.round((p.ref.poses[0, 2] - np.interp(p.ref.s_m[0], path.s, heads)) / (2 * np.pi))
    fx = ca.interpolant("rx", "linear", [path.s], path.poses[:, 0])
    fy = ca.interpolant("ry", "linear", [path.s], path.poses[:, 1])
    fth = ca.interpolant("rth", "linear", [path.s], heads + offset)
    fk = ca.interpolant("rk", "linear", [path.s], path.curvature)
    s_d = [ca.SX(p.ref.s_m[0])]
    vb = v
    if p.lag is not None:           # progress at the speeds the robot reaches (the drive's lag)
        vb = ca.mtimes(ca.DM(p.lag.Lv), ca.vertcat(*[v[j] for j in range(K)])) + ca.DM(p.lag.cv)
    for j in range(K):
        s_d.append(s_d[-1] + vb[j] * dt)
    D, cD, sinD = [], [], []
    for sj in s_d:
        D.append([fx(sj), fy(sj), fth(sj)])
        tx, ty = fx(sj + 0.01) - fx(sj - 0.01), fy(sj + 0.01) - fy(sj - 0.01)   # the segment's direction
        n = ca.sqrt(tx ** 2 + ty ** 2)
        cD.append(tx / n)
        sinD.append(ty / n)
    X = _casadi_rollout(p, _casadi_gp_mean(p.model), w, v, D, s_d, cD, sinD)
    E = [_route_errors(X, D, cD, sinD, j) for j in range(1, K + 1)]
    Ec = [[e[0], e[1], e[2] - p.ref.head_offset[j]] for j, e in enumerate(E)]   # the cost's heading reference
    res = [p.sqrt_q[i] * Ec[j][i] for j in range(K) for i in range(3)]
    res += [math.sqrt(s.r_w) * (w[j] - v[j] * fk(s_d[j])) for j in range(K)]
    res += [math.sqrt(s.r_v) * (v[j] - p.v[j]) for j in range(K)]
    res += [math.sqrt(s.r_dw) * (w[j] - (p.u_prev[1] if j == 0 else w[j - 1])) for j in range(K)]
    res += [math.sqrt(s.r_dv) * (v[j] - (p.u_prev[0] if j == 0 else v[j - 1])) for j in range(K)]
    res.append(p.sqrt_qt * (Ec[-1][1] + s.lookahead_m * ca.sin(Ec[-1][2])))
    r = ca.vertcat(*res)
    alpha, cap, sig = nlp.alpha, nlp.cap, nlp.sig_start
    sig_lat = ca.fmax(ca.DM(sig[:, 1]) + ca.mtimes(ca.DM(nlp.dsig_v), v - ca.DM(nlp.v_start)), 0)
    g, lbg, ubg = [], [], []
    for j in range(K):
        t_lat = ca.fmin(alpha * sig_lat[j], cap[j, 1])
        t_head = min(alpha * sig[j, 2], cap[j, 2])
        g += [E[j][1] + t_lat - sl[j], E[j][1] - t_lat + sl[K + j], E[j][2] + t_head - sl[2 * K + j],
              E[j][2] - t_head + sl[2 * K + j]]
        lbg += [-np.inf, nlp.lo_lat[j], -np.inf, -nlp.head_lim[j]]
        ubg += [nlp.hi_lat[j], np.inf, nlp.head_lim[j], np.inf]
    merit = 0.5 * ca.dot(r, r) + s.slack_weight * ca.sum1(sl)
    problem = {"x": ca.vertcat(v, w, sl), "f": merit, "g": ca.vertcat(*g)}
    solver = ca.nlpsol("rc", "ipopt", problem, {"ipopt.print_level": 0, "print_time": 0, "ipopt.tol": 1e-8,
                                            "ipopt.bound_relax_factor": 0.0,
                                            "ipopt.sb": "yes"})
    w_lim = nlp.w_limits(step.result.iterate.v)
    x0 = np.concatenate([step.start.v, step.start.w, np.zeros(3 * K)])
    lbx = np.concatenate([np.full(K, s.v_min_mps), -w_lim, np.zeros(3 * K)])
    ubx = np.concatenate([np.maximum(nlp.v_max, s.v_min_mps), w_lim, np.full(3 * K, np.inf)])
    t0 = time.perf_counter()
    out = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    seconds = time.perf_counter() - t0
    if not solver.stats()["success"]:
        return seconds, None, step.result.iterate.merit
    return seconds, float(out["f"]), step.result.iterate.merit


def _timing_result(args, settings: NMPCSettings, timing: Timing) -> dict:
    times, sizes, evals = timing.times, timing.sizes, timing.evals
    return {"algorithm": args.algorithm, "horizon": args.horizon, "window": round(float(sizes.mean()), 1),
            "window_max": int(sizes.max()), "solve_ms_p50": round(float(np.percentile(times, 50)), 3),
            "solve_ms_p99": round(float(np.percentile(times, 99)), 3),
            "solve_ms_mean": round(float(times.mean()), 3), "steps": len(times),
            "evaluations_p50": float(np.percentile(evals, 50)), "evaluations_p99": float(np.percentile(evals, 99)),
            "not_converged": sum(s != "converged" for s in timing.statuses), "max_evals": settings.max_evals,
            "prepare_ms_p99": round(float(np.percentile(timing.prepare_ms, 99)), 3),
            "window_builds_in_step": timing.builds_in_step, "casadi_solve_ms_p50": None, "cost_gap": None}


def _compare_robust(algorithm: str, kept: list, settings: NMPCSettings) -> dict:
    """Our whole step (covariance; for RC also the ladder) against IPOPT's solve of the step's NLP alone:
    MM's min-max in epigraph form, C/RC's corridor-constrained problem with the same slack price."""
    if algorithm == "mm-lb-nmpc":
        what, solve = "min-max", lambda step: casadi_solve_minmax(step, settings)
    else:
        what, solve = "constrained", lambda step: casadi_solve_constrained(step, settings)
    ratios, gaps, ipopt_ms, failed = [], [], [], 0
    for _ctx, step, ours_ms in kept:
        sec, ipopt_value, ours_value = solve(step)
        if ipopt_value is None:
            failed += 1
            continue
        ipopt_ms.append(sec * 1e3)
        ratios.append(sec * 1e3 / ours_ms)
        gaps.append((ours_value - ipopt_value) / max(abs(ipopt_value), 1e-12))
    log.info("IPOPT on %d %s problems (%d failed): %.1f ms median (ours %.1fx faster); objective gap "
             "median %.2e, max %.2e", len(ipopt_ms), what, failed, np.median(ipopt_ms), np.median(ratios),
             np.median(gaps), np.max(gaps))
    return {"casadi_solve_ms_p50": round(float(np.median(ipopt_ms)), 3), "cost_gap": float(np.mean(gaps)),
            "cost_gap_median": float(np.median(gaps)), "cost_gap_max": float(np.max(gaps)),
            "casadi_over_ours_time_ratio": round(float(np.median(ratios)), 2), "casadi_problems": len(ipopt_ms),
            "casadi_failed": failed}


def _compare_lb(kept: list, settings: NMPCSettings) -> dict:
    """The kept LB-NMPC problems solved again from the same warm start, fully by ours and by IPOPT."""
    ratios, gaps, ipopt_ms = [], [], []
    for ctx, step, _ in kept:
        problem, w_limit = build_problem(ctx, settings, DT, step.problem.model)   # fresh: no memoized rollouts
        t1 = time.perf_counter()
        ours = gauss_newton(problem.residual, step.w0, -w_limit, w_limit, max_iter=settings.max_iter,
                            tol=settings.tol)
        ours_ms = (time.perf_counter() - t1) * 1e3
        sec, ipopt_cost = casadi_solve(problem, step.problem.model, step.w0, w_limit)
        ipopt_ms.append(sec * 1e3)
        ratios.append(sec * 1e3 / ours_ms)
        gaps.append((ours.cost - ipopt_cost) / max(abs(ipopt_cost), 1e-12))
    log.info("IPOPT on %d problems: %.1f ms median (ours %.1fx faster); cost gap median %.2e, max %.2e",
             len(kept), np.median(ipopt_ms), np.median(ratios), np.median(gaps), np.max(gaps))
    return {"casadi_solve_ms_p50": round(float(np.median(ipopt_ms)), 3), "cost_gap": float(np.mean(gaps)),
            "cost_gap_max": float(np.max(gaps)), "casadi_over_ours_time_ratio": round(float(np.median(ratios)), 2),
            "casadi_problems": len(kept)}


def run_bench(args) -> dict:
    pinned, limit = single_core()
    with limit, tempfile.TemporaryDirectory() as work:
        t0 = time.perf_counter()
        cl, path, hyper, windows, trials, n = build_memory(args.seed, work, args.robot)
        model = cl.identified()
        settings = NMPCSettings(horizon=args.horizon).with_identified(model)
        log.info("route %.1f m, %d experiences retained from %d FL trials, hyperparameters in %.1f s (%.1f s); "
                 "nominal model %s", path.length_m, n, trials, hyper.fit_s, time.perf_counter() - t0, model.model_tag)
        timing = time_controller(cl, hyper, windows, trials, settings, args.keep_every, args.algorithm)
        log.info("%s: %d steps, window mean %.0f max %d", args.algorithm, len(timing.times), timing.sizes.mean(),
                 timing.sizes.max())
        result = _timing_result(args, settings, timing)
        result.update(pinned=pinned, robot=args.robot, model_tag=model.model_tag)
        if args.algorithm == "mm-lb-nmpc":
            # thesis 6.4.3: the min-max extension costs 5 % more than LB-NMPC; the same repeat timed again
            lb_times = time_controller(cl, hyper, windows, trials, settings, 10 ** 9, "lb-nmpc").times
            result["lb_nmpc_solve_ms_p50"] = round(float(np.percentile(lb_times, 50)), 3)
            result["mm_overhead"] = round(float(np.percentile(timing.times, 50) / np.percentile(lb_times, 50) - 1.0), 3)
        try:
            import casadi  # noqa: F401  (optional benchmark dependency)
        except ImportError:
            log.warning("casadi not installed (pip install casadi): no IPOPT comparison")
            return result
        if not timing.kept:
            log.warning("no problems kept for the IPOPT comparison (lower --keep-every)")
            return result
        if settings.curvature_rate_max_per_ms:
            log.warning("a rate-limited steering (%s): no IPOPT comparison", args.robot)
            return result
        if args.algorithm == "lb-nmpc":
            result.update(_compare_lb(timing.kept, settings))
        else:
            result.update(_compare_robust(args.algorithm, timing.kept, settings))
        return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench controller", description=__doc__.splitlines()[0])
    parser.add_argument("--algorithm", default="lb-nmpc", choices=LAWS)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--robot", default="husky", choices=sorted(PRESETS), help="the preset driven")
    parser.add_argument("--keep-every", type=int, default=20, help="compare every n-th problem with IPOPT")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[bench.controller] %(message)s", stream=sys.stderr)
    return run_and_print(lambda: run_bench(args))


if __name__ == "__main__":
    raise SystemExit(main())
