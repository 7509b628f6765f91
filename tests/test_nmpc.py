"""LB-NMPC core against independent references: finite-horizon LQR on linear models, finite-difference
Jacobians, and the thesis's illustrative example (eq. 5.22-5.25)."""
import dataclasses
import math

import numpy as np
import pytest

from common.gp import GaussianProcess, SEHyper, fit_hyperparameters
from common.path import Path
from services.controller.gauss_newton import gauss_newton
from services.controller.laws import StepContext
from services.controller.nmpc import build_problem
from services.controller.settings import NMPCSettings


def finite_horizon_lqr(A, B, Q, R, x0, K):
    """Optimal open-loop inputs of sum_{k=1..K} x_k'Q x_k + sum_{k=0..K-1} u_k'R u_k by the Riccati
    recursion (terminal weight Q), rolled forward with the time-varying feedback gains."""
    P = Q.copy()
    gains = []
    for _ in range(K):
        L = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        gains.append(L)
        P = Q + A.T @ P @ (A - B @ L)
    gains.reverse()
    x, u = x0.copy(), []
    for L in gains:
        uk = -L @ x
        u.append(uk)
        x = A @ x + B @ uk
    return np.concatenate(u)


def test_gauss_newton_on_a_linear_model_is_the_finite_horizon_lqr_solution():
    dt, K = 0.1, 10
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([[0.5 * dt * dt], [dt]])
    Q, R = np.diag([10.0, 1.0]), np.array([[0.1]])
    x0 = np.array([0.7, -0.3])
    sq, sr = np.sqrt(np.diag(Q)), math.sqrt(R[0, 0])

    def residual(u):
        x, rows, J_rows = x0.copy(), [], []
        S = np.zeros((2, K))
        for k in range(K):
            x = A @ x + B[:, 0] * u[k]
            S = A @ S
            S[:, k] += B[:, 0]
            rows.append(sq * x)
            J_rows.append(sq[:, None] * S)
        r = np.concatenate(rows + [sr * u])
        return r, np.vstack(J_rows + [sr * np.eye(K)])

    res = gauss_newton(residual, np.zeros(K), -np.full(K, 1e3), np.full(K, 1e3), tol=1e-12)
    np.testing.assert_allclose(res.u, finite_horizon_lqr(A, B, Q, R, x0, K), rtol=1e-9, atol=1e-12)
    assert res.iterations <= 2   # one exact step, then nothing left to move


def test_gauss_newton_shortens_an_overshooting_step_within_its_evaluation_budget():
    """Where the linearization over-predicts (here sin(4u): its full Gauss-Newton step lands beyond the
    minimum, at a higher cost), the damping must grow fast enough that a shorter step is accepted
    within the few evaluations a control period allows, instead of returning the start unchanged."""
    def residual(u):
        return np.array([math.sin(4.0 * u[0])]), np.array([[4.0 * math.cos(4.0 * u[0])]])

    u0 = np.array([0.3])
    c0 = 0.5 * math.sin(1.2) ** 2
    full = u0 - math.sin(1.2) / (4.0 * math.cos(1.2))
    assert 0.5 * math.sin(4.0 * full[0]) ** 2 > c0            # the plain step is rejected
    res = gauss_newton(residual, u0, np.array([-2.0]), np.array([2.0]), max_iter=5, max_evals=6)
    assert res.cost < 0.9 * c0 and res.u[0] < u0[0], res


STRAIGHT = Path("straight", np.column_stack([np.arange(0, 40, 0.25), np.zeros(160), np.zeros(160)]))


def ctx_at(path, pose, v=0.5, prev_cmd=(0.5, 0.0), model_prev=None, vertex=None):
    s = float(pose[0]) if path is STRAIGHT else path.project(pose).distance_m
    return StepContext(now_s=0.0, path=path, vertex=vertex if vertex is not None else path.nearest_vertex(pose),
                       pose=np.asarray(pose, dtype=float), s_m=s, e_lat_m=float(pose[1]), e_head_rad=float(pose[2]),
                       v_mps=v, speed_at=lambda _s: v, prev_cmd=prev_cmd, prev_pose=model_prev, w_limit=5.0,
                       w_limit_at=lambda _v: 5.0)


def test_robot_nmpc_without_learning_matches_the_lq_solution_of_its_linearization():
    """Small errors on a straight route: lateral/heading dynamics are e_L' = e_L + v dt e_H,
    e_H' = e_H + dt w; the NMPC's optimum must equal the linear-quadratic one (batch least squares
    with the same stage, input, input-rate and terminal weights)."""
    st = NMPCSettings(horizon=10, q_along=1.0, q_lat=40.0, q_head=10.0, r_w=0.2, r_dw=1.0, q_terminal=100.0,
                      lookahead_m=1.5, tol=1e-12, max_iter=50)
    dt, v, K = 0.1, 0.5, st.horizon
    e0 = np.array([2e-4, -1e-4])                  # lateral m, heading rad: deep in the linear regime
    problem, lim = build_problem(ctx_at(STRAIGHT, (5.0, e0[0], e0[1])), st, dt, None)
    ours = gauss_newton(problem.residual, np.zeros(K), -lim, lim, max_iter=50, tol=1e-12).u
    # batch LQ: e_j = Phi^j e0 + sum_i G_ji w_i
    Ad = np.array([[1.0, v * dt], [0.0, 1.0]])
    Bd = np.array([0.0, dt])
    rows_free, rows_w = [], []
    e, M = e0.copy(), np.zeros((2, K))
    for j in range(K):
        e = Ad @ e
        M = Ad @ M
        M[:, j] += Bd
        rows_free.append(e.copy())
        rows_w.append(M.copy())
    F, G = np.array(rows_free), np.array(rows_w)     # (K, 2), (K, 2, K)
    blocks_A, blocks_b = [], []
    for j in range(K):
        blocks_A += [math.sqrt(st.q_lat) * G[j, 0], math.sqrt(st.q_head) * G[j, 1]]
        blocks_b += [-math.sqrt(st.q_lat) * F[j, 0], -math.sqrt(st.q_head) * F[j, 1]]
    blocks_A += list(math.sqrt(st.r_w) * np.eye(K))
    blocks_b += [0.0] * K
    Dm = np.eye(K) - np.eye(K, k=-1)
    blocks_A += list(math.sqrt(st.r_dw) * Dm)
    blocks_b += [0.0] * K
    blocks_A.append(math.sqrt(st.q_terminal) * (G[-1, 0] + st.lookahead_m * G[-1, 1]))
    blocks_b.append(-math.sqrt(st.q_terminal) * (F[-1, 0] + st.lookahead_m * F[-1, 1]))
    lq = np.linalg.lstsq(np.array(blocks_A), np.array(blocks_b), rcond=None)[0]
    np.testing.assert_allclose(ours, lq, rtol=1e-3, atol=1e-7)


def test_jacobian_with_a_learned_model_matches_finite_differences():
    rng = np.random.default_rng(1)
    th = np.linspace(0, 0.8, 60)
    xy = np.cumsum(0.25 * np.column_stack([np.cos(th), np.sin(th)]), axis=0)
    path = Path("curve", np.column_stack([xy, th]))
    X = rng.normal(size=(120, 9)) * [2, 0.1, 0.05, 0.2, 0.3, 0.1, 0.3, 0.1, 0.3] + [5, 0, 0, 0.5, 0.1, 0.5, 0.1, 0.5, 0.1]
    Y = np.column_stack([0.01 * np.sin(X[:, 0]), 0.01 * np.cos(3 * X[:, 6]), 0.02 * np.tanh(2 * X[:, 4] - X[:, 6])])
    gp = GaussianProcess(X, Y, [SEHyper(np.array([1.5, .2, .1, .3, .4, .3, .35, .3, .4]), 0.02, 0.001)] * 3)
    pose = path.pose_at(5.3) + np.array([0.0, 0.05, 0.02])
    ctx = ctx_at(path, pose, prev_cmd=(0.5, 0.1), model_prev=pose - np.array([0.05, 0.0, 0.01]))
    ctx = dataclasses.replace(ctx, xi_now=(0.4, 0.05))
    # the last two with an Ackermann steering-rate limit that the random commands run into
    for model, tau, kr in ((None, (0.0, 0.0), 0.0), (gp, (0.0, 0.0), 0.0), (None, (0.45, 0.4), 0.0),
                           (gp, (0.45, 0.4), 0.0), (None, (0.45, 0.15), 0.37), (gp, (0.45, 0.15), 0.37)):
        problem, _ = build_problem(ctx, NMPCSettings(r_dw=1.0, q_terminal=50.0, actuator_tau_s=tau,
                                                     curvature_rate_max_per_ms=kr), 0.1, model)
        w = 0.2 * rng.normal(size=10)
        _, J = problem.residual(w)
        h = 1e-6
        J_fd = np.column_stack([(problem.residual(w + h * e)[0] - problem.residual(w - h * e)[0]) / (2 * h)
                                for e in np.eye(10)])
        np.testing.assert_allclose(J, J_fd, atol=1e-7)


# --- the thesis's illustrative example (eq. 5.22-5.25) --------------------------------------------
DT, ALPHA, BETA, N = 0.1, 0.99, 0.5, 240
K_FB = 2.0


def desired(k):
    return 1.0 if (k // 60) % 2 else 0.0          # a square wave the controllers know in advance


def disturbance(k):
    return 0.8 * math.sin(2 * math.pi * k / 75.0) + (0.5 if 100 <= k < 160 else 0.0)


def plant(z, u, k):
    return ALPHA * z + DT * BETA * u + DT * disturbance(k)   # eq. 5.22


def mpc_input(z, k, model, horizon=10, q=10.0, r=0.01):
    """NMPC of eq. 5.24 (model None) or LB-NMPC of eq. 5.25 (model g(z, u, k) a GP), solved by the
    project's Gauss-Newton with analytic Jacobians."""
    sq, sr = math.sqrt(q), math.sqrt(r)

    def residual(u):
        zj, dz = z, np.zeros(horizon)
        rows, J = [], []
        for j in range(horizon):
            if model is not None:
                g, Dg = model.mean_and_grad(np.array([zj, u[j], float(k + j)]))
                grad_z, grad_u = Dg[0, 0], Dg[0, 1]
                dz_new = dz * (1.0 + grad_z)
                dz_new[j] += DT + grad_u
                zj = zj + DT * u[j] + g[0]
            else:
                dz_new = dz.copy()
                dz_new[j] += DT
                zj = zj + DT * u[j]
            dz = dz_new
            rows.append(sq * (desired(k + j + 1) - zj))
            J.append(-sq * dz)
        return np.concatenate([rows, sr * u]), np.vstack([np.array(J), sr * np.eye(horizon)])

    return gauss_newton(residual, np.zeros(horizon), -np.full(horizon, 1e3), np.full(horizon, 1e3),
                        max_iter=20, tol=1e-6).u[0]


def run(controller):
    z, errs, data = 0.0, [], []
    for k in range(N):
        u = controller(z, k)
        z_next = plant(z, u, k)
        data.append((z, u, k, z_next - (z + DT * u)))          # eq. 5.17 against the nominal 5.24
        z = z_next
        errs.append(desired(k + 1) - z)
    return math.sqrt(float(np.mean(np.square(errs)))), np.array(data)


def learned_model(runs):
    D = np.vstack(runs)
    fit = fit_hyperparameters(D[:, :3], D[:, 3:], restarts=2, rng=np.random.default_rng(0), max_points=2000)
    return GaussianProcess(D[:, :3], D[:, 3:], fit.hypers)


@pytest.mark.slow
def test_illustrative_example_feedback_worse_than_nmpc_worse_than_lb_nmpc():
    """Learning over trials: the NMPC's run, then LB-NMPC runs each learning from all runs before it.
    (From the NMPC run alone the model is poor off that run's inputs: there the input always
    cancelled the disturbance, so g(z, u, k) cannot tell the two apart; one learned run later it can.)"""
    rms_fb, _ = run(lambda z, k: K_FB * (desired(k) - z))                        # eq. 5.23
    rms_nmpc, first = run(lambda z, k: mpc_input(z, k, None))
    runs = [first]
    rms_lb = []
    for _ in range(3):
        gp = learned_model(runs)
        rms, data = run(lambda z, k: mpc_input(z, k, gp))
        rms_lb.append(rms)
        runs.append(data)
    assert rms_fb > rms_nmpc > rms_lb[-1]
    assert max(rms_lb[1:]) <= 0.5 * rms_nmpc, (rms_fb, rms_nmpc, rms_lb)


def test_nmpc_drives_an_ackermann_robot_within_its_steering_limit():
    """The MATS preset through eq. 5.27: the NMPC plans unicycle rates, bounded by v tan(steer_max) / L."""
    from bench.closed_loop import ClosedLoop
    from common.robot import PRESETS
    from services.controller.nmpc import LBNMPCLaw
    mats = PRESETS["mats"]
    sim = ClosedLoop([[0, 0], [15, 0], [30, 10], [30, 25]], preset="mats", seed=1, teach_speed=0.8)
    sim.teach()
    commands = []

    class Recorded(LBNMPCLaw):
        def angular(self, ctx):
            res = super().angular(ctx)
            commands.append((ctx.v_mps, res.w_radps))
            return res

    r = sim.repeat(1, 1.0, law=Recorded(NMPCSettings(), 0.1))
    assert r.finished and r.max_lateral < 0.15
    v, w = np.array(commands).T
    assert np.all(np.abs(w) <= v * mats.max_curvature + 1e-9)
    assert np.max(np.abs(w) / np.maximum(v, 1e-3)) > 0.5 * mats.max_curvature   # it did steer hard somewhere


# --- the learned crab as the heading reference (NMPCSettings.crab_reference) --------------------------
TEACH_CRAB = -0.16          # rad: the heading the route was taught with, against its direction (+x)
SLIDE = 0.006               # m per period, to the robot's left: what the learned model has seen


def slide_model(n: int = 1200):
    """A GP that has seen a constant sideways slide everywhere near the route (body frame, as g is),
    densely enough along the route and in commanded speed and turn rate for its variance to be its
    own there (uncertainty.VOUCH_SCALES)."""
    rng = np.random.default_rng(4)
    lo = np.array([0.0, -0.3, -0.4, 0.3, -0.5, 0.3, -0.5, 0.3, -0.5])
    hi = np.array([30.0, 0.3, 0.4, 1.5, 0.5, 1.5, 0.5, 1.5, 0.5])
    X = lo + (hi - lo) * rng.uniform(size=(n, 9))
    Y = np.tile([0.0, SLIDE, 0.0], (n, 1)) + 1e-5 * rng.normal(size=(n, 3))
    h = SEHyper(np.array([20.0, 2.0, 2.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0]), 0.01, 1e-4)
    return GaussianProcess(X, Y, [h] * 3)


def test_crab_offsets_are_the_crab_that_cancels_the_learned_slide_against_the_taught_heading():
    from services.controller.nmpc import crab_offsets
    gp = slide_model()
    K = 10
    s_d = 5.0 + 0.1 * np.arange(K + 1)
    taught = np.column_stack([s_d, np.zeros(K + 1), np.full(K + 1, TEACH_CRAB)])
    v, w_ref = np.full(K, 1.0), np.zeros(K)
    off = crab_offsets(gp, s_d, taught, np.zeros(K + 1), v, w_ref, 0.1)
    # by hand: moving along +x at 1 m/s against a slide of SLIDE per 0.1 s takes heading -atan(SLIDE / 0.1)
    np.testing.assert_allclose(off, -math.atan2(SLIDE, 0.1) - TEACH_CRAB, atol=2e-3)
    slow = crab_offsets(gp, s_d, taught, np.zeros(K + 1), np.full(K, 0.1), w_ref, 0.1)
    assert np.all(slow == 0.0)                       # stopping: no course to hold


def test_with_the_crab_reference_the_plan_holds_the_route_where_the_taught_heading_pulls_it_off():
    """Repeating at 1 m/s a route taught with a bigger crab (a slower teach on a side slope): weighed
    against the taught heading the plan turns to it and leaves the route; against the learned crab it
    holds the route."""
    from services.controller.nmpc import LBNMPCLaw
    gp = slide_model()
    xs = np.arange(0.0, 30.0, 0.25)
    path = Path("slope", np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, TEACH_CRAB)]))
    crab = -math.atan2(SLIDE, 0.1)
    pose = np.array([10.0, 0.0, crab])              # on the route, holding it (the slide cancelled)
    lateral = {}
    for on in (True, False):
        law = LBNMPCLaw(NMPCSettings(crab_reference=on, max_iter=30, max_evals=40, tol=1e-6), 0.1, lambda c: gp)
        ctx = ctx_at(path, pose, v=1.0, prev_cmd=(1.0, 0.0), model_prev=pose - [0.1, 0.0, 0.0])
        law.angular(ctx)
        lateral[on] = law.last_plan.poses[1:, 1]   # y is the lateral error here
    assert np.max(np.abs(lateral[True])) < 0.005, lateral[True]
    assert lateral[False][-1] < -0.02, lateral[False]   # turned towards the taught crab: off to the right


def test_lb_nmpc_with_the_crab_reference_matches_ipopt_on_the_same_problem():
    """The offsets enter the cost only; CasADi/IPOPT on the NLP as bench/controller.py writes it (with
    the same offsets) finds the same optimum."""
    import pytest
    pytest.importorskip("casadi")
    from bench.controller import casadi_solve
    gp = slide_model()
    xs = np.arange(0.0, 30.0, 0.25)
    path = Path("slope", np.column_stack([xs, 0.02 * xs, np.full_like(xs, TEACH_CRAB)]))
    st = NMPCSettings(crab_reference=True, max_iter=50, max_evals=60, tol=1e-8)
    pose = np.array([10.0, 0.25, 0.05])
    ctx = ctx_at(path, pose, v=1.0, prev_cmd=(1.0, 0.0), model_prev=pose - [0.1, 0.0, 0.0])
    problem, w_limit = build_problem(ctx, st, 0.1, gp)
    assert np.all(np.abs(problem.ref.head_offset) > 0.05)
    res = gauss_newton(problem.residual, problem.w_ref.copy(), -w_limit, w_limit, max_iter=50, tol=1e-8, max_evals=60)
    _, ipopt = casadi_solve(problem, gp, problem.w_ref.copy(), w_limit)
    assert ipopt * (1 - 1e-6) <= res.cost <= 1.001 * ipopt, (res.cost, ipopt)


def test_with_a_route_heading_window_the_plan_holds_a_straight_taught_with_a_wiggling_heading():
    """A straight route whose taught heading wiggles +-0.1 rad over 3 m (the teach pass's yaw on rough
    ground): against the taught heading the plan turns +-0.07-0.08 rad/s after each wiggle and leaves
    the straight by 1-3 cm within the horizon; against the heading averaged over 3 m it holds the
    straight within 2.5 mm, turning less than 0.01 rad/s."""
    from services.controller.nmpc import LBNMPCLaw
    xs = np.arange(0.0, 30.0, 0.25)
    poses = np.column_stack([xs, np.zeros_like(xs), 0.1 * np.sin(2 * math.pi * xs / 3.0)])
    for x0 in (10.0, 10.75, 11.5, 12.25):
        pose = np.array([x0, 0.0, 0.0])
        plans = {}
        for window in (0.0, 3.0):
            law = LBNMPCLaw(NMPCSettings(max_iter=30, max_evals=40, tol=1e-6), 0.1, lambda c: None)
            ctx = ctx_at(Path("w", poses, heading_window_m=window), pose, v=1.0, prev_cmd=(1.0, 0.0),
                         model_prev=pose - [0.1, 0.0, 0.0])
            plans[window] = (law.angular(ctx).w_radps, np.max(np.abs(law.last_plan.poses[1:, 1])))
        assert abs(plans[0.0][0]) > 0.07 and plans[0.0][1] > 0.01
        assert abs(plans[3.0][0]) < 0.01 and plans[3.0][1] < 0.0025
