"""`lbc model fit-logs TRAIN... --test HELDOUT...`: would learning help this robot? From a robot's own
logs (deploy/robot_logs.py): identify the nominal model's drive lags on the training logs (as the
controller does on a teach pass, services/controller/identification.py), fit the GP disturbance model
(thesis 5.2) to that model's one-period residuals on the training logs, and report, on the held-out
logs, the RMSE of the heading-rate residual (the component the controller's turn corrections act on)
of the nominal model alone (which predicts zero), of the GP, and of a linear baseline (least squares on
the same inputs). JSON on the last line (keys in DESIGN.md); plots with --out.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.gp import GaussianProcess, fit_hyperparameters
from deploy.robot_logs import F1TENTH_WHEELBASE_M, LOADERS, DriveLog, load_f1tenth_csv, load_ros2_mcap, residuals
from services.controller.actuator import ActuatorLag
from services.controller.experience import body_velocity
from services.controller.identification import DriveFit, identify_drive

log = logging.getLogger("lbc.fit_logs")
HEADING = 2                  # the heading component of g
GP_MAX_POINTS = 1000         # the fit's subset (common.gp.fit_hyperparameters), as in the controller's fits


@dataclass(frozen=True)
class FitLogsResult:
    n_train: int
    n_test: int
    heading_rate_rmse_nominal: float
    heading_rate_rmse_gp: float
    heading_rate_rmse_linear: float
    heading_rate_rmse_unicycle: float     # the plain unicycle (no lag), for comparison with the identified model
    identified: dict
    test_t_s: np.ndarray
    test_residual: np.ndarray             # held-out heading-rate residual of the nominal model (rad/s)
    test_gp: np.ndarray                   # the GP's prediction of it
    test_gp_std: np.ndarray

    def as_json(self) -> dict:
        return {"n_train": self.n_train, "n_test": self.n_test,
                "heading_rate_rmse_nominal": round(self.heading_rate_rmse_nominal, 5),
                "heading_rate_rmse_gp": round(self.heading_rate_rmse_gp, 5),
                "heading_rate_rmse_linear": round(self.heading_rate_rmse_linear, 5),
                "heading_rate_rmse_unicycle": round(self.heading_rate_rmse_unicycle, 5),
                "gp_cut": round(1.0 - self.heading_rate_rmse_gp / self.heading_rate_rmse_nominal, 4),
                "identified": self.identified}


def _measured(lg: DriveLog) -> np.ndarray:
    """The drive's measured speeds, per channel from the log's odometry, or from the poses (ground speed,
    slip in) where the odometry has none: missing, or constant while the command varies (the F1/10 logs'
    odometry yaw rate is all zeros)."""
    from_poses = np.full_like(lg.y, np.nan)
    for k in range(1, len(lg.t_s)):
        from_poses[k] = body_velocity(lg.pose[k - 1], lg.pose[k], lg.dt)
    out = lg.y.copy()
    for i in range(2):
        col = lg.y[:, i]
        if not np.isfinite(col).all() or (np.nanstd(col) < 1e-9 < np.std(lg.u[:, i])):
            out[:, i] = from_poses[:, i]
    return out


def identify(logs: list[DriveLog]) -> DriveFit:
    """Both drive channels on the training logs, one after another (a missing row between two logs, so
    no step crosses from one to the next)."""
    gap = np.full((1, 2), np.nan)
    u = np.vstack([np.vstack([lg.u, gap]) for lg in logs])
    y = np.vstack([np.vstack([_measured(lg), gap]) for lg in logs])
    return identify_drive(u, y, logs[0].dt)


def _identified(fit: DriveFit, lag: ActuatorLag) -> dict:
    out = {"model_tag": lag.model_tag, "tau_v_s": lag.tau_v_s, "tau_w_s": lag.tau_w_s, "notes": list(fit.notes)}
    for name, ch in (("v", fit.v), ("w", fit.w)):
        if ch is not None:
            out.update({f"lag_{name}_s": round(ch.tau_s, 4), f"dead_time_{name}_s": round(ch.dead_time_s, 4),
                        f"gain_{name}": round(ch.gain, 4), f"fit_rmse_{name}": round(ch.rmse, 5)})
    return out


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def fit_logs(train: list[DriveLog], test: list[DriveLog], seed: int = 0, restarts: int = 2,
             nominal: str = "identified") -> FitLogsResult:
    """`nominal`: "identified" (the drive lags identified on the training logs) or "unicycle" (eq. 5.26
    driven by the commands as they are; what the GP learns then includes the drive's lag)."""
    dt = train[0].dt
    fit = identify(train)
    lag = fit.lag(dt) if nominal == "identified" else ActuatorLag(dt=dt)
    tr = [residuals(lg, lag) for lg in train]
    te = [residuals(lg, lag) for lg in test]
    A_tr, G_tr = np.vstack([a for a, _ in tr]), np.vstack([g for _, g in tr])
    A_te, G_te = np.vstack([a for a, _ in te]), np.vstack([g for _, g in te])
    # independent GP per output (eq. 5.21): the heading component alone is the same model as all three
    y_tr = G_tr[:, HEADING:HEADING + 1]
    hyp = fit_hyperparameters(A_tr, y_tr, restarts=restarts, rng=np.random.default_rng(seed), max_points=GP_MAX_POINTS)
    mean, var = GaussianProcess(A_tr, y_tr, hyp.hypers).predict(A_te)
    X_tr, X_te = np.column_stack([A_tr, np.ones(len(A_tr))]), np.column_stack([A_te, np.ones(len(A_te))])
    coef, *_ = np.linalg.lstsq(X_tr, y_tr[:, 0], rcond=None)
    hr = G_te[:, HEADING] / dt
    unicycle = np.concatenate([residuals(lg)[1][:, HEADING] for lg in test]) / dt
    return FitLogsResult(
        n_train=len(A_tr), n_test=len(A_te), heading_rate_rmse_nominal=_rms(hr),
        heading_rate_rmse_gp=_rms(hr - mean[:, 0] / dt), heading_rate_rmse_linear=_rms(hr - X_te @ coef / dt),
        heading_rate_rmse_unicycle=_rms(unicycle), identified=_identified(fit, lag),
        test_t_s=np.concatenate([lg.t_s[1:-1] for lg in test]), test_residual=hr, test_gp=mean[:, 0] / dt,
        test_gp_std=np.sqrt(np.maximum(var[:, 0], 0.0)) / dt)


def plot(result: FitLogsResult, out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(2, 1, figsize=(11, 6.5), layout="constrained")
    t, r, m, s = result.test_t_s, result.test_residual, result.test_gp, result.test_gp_std
    x = np.arange(len(t)) * 0.1 if len(t) else t
    axes[0].plot(x, r, color="grey", lw=0.7, label="held-out residual of the nominal model")
    axes[0].plot(x, m, color="tab:blue", lw=1.0, label="GP prediction")
    axes[0].fill_between(x, m - 2 * s, m + 2 * s, color="tab:blue", alpha=0.2, lw=0, label="GP 2 sigma")
    axes[0].set(xlabel="held-out samples x dt (s)", ylabel="heading-rate residual (rad/s)")
    axes[0].legend(fontsize=8, loc="upper right")
    names = ["nominal (zero)", "linear", "GP"]
    vals = [result.heading_rate_rmse_nominal, result.heading_rate_rmse_linear, result.heading_rate_rmse_gp]
    axes[1].bar(names, vals, color=["grey", "tab:orange", "tab:blue"])
    axes[1].set(ylabel="RMSE on the held-out logs (rad/s)",
                title=f"nominal model {result.identified['model_tag']}; {result.n_train} training, "
                      f"{result.n_test} held-out samples")
    path = out / "fit_logs.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc model fit-logs", description=__doc__.splitlines()[0])
    parser.add_argument("train", nargs="+", help="training logs (folders or files of --format)")
    parser.add_argument("--test", nargs="+", required=True, help="held-out logs")
    parser.add_argument("--format", choices=sorted(LOADERS), default="f1tenth-csv")
    parser.add_argument("--dt", type=float, default=0.1, help="the controller's period (s), the logs' grid")
    parser.add_argument("--wheelbase", type=float, default=F1TENTH_WHEELBASE_M,
                        help="f1tenth-csv: the wheelbase L of eq. 5.27 (m)")
    parser.add_argument("--pose-topic", default="/odom", help="ros2-mcap: nav_msgs/Odometry or PoseWithCovarianceStamped")
    parser.add_argument("--cmd-topic", default="/cmd_vel", help="ros2-mcap: geometry_msgs/Twist or TwistStamped")
    parser.add_argument("--nominal", choices=("identified", "unicycle"), default="identified",
                        help="the nominal model whose residuals are learned: with the drive lags identified on the "
                             "training logs (default), or the plain unicycle of eq. 5.26")
    parser.add_argument("--out", type=Path, default=None, help="write plots here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[lbc model fit-logs] %(message)s", stream=sys.stderr)

    def load(p: str) -> DriveLog:
        if args.format == "f1tenth-csv":
            return load_f1tenth_csv(p, args.dt, args.wheelbase)
        return load_ros2_mcap(p, args.dt, args.pose_topic, args.cmd_topic)
    t0 = time.perf_counter()
    try:
        train, test = [load(p) for p in args.train], [load(p) for p in args.test]
    except (OSError, ValueError) as exc:
        print(f"lbc model fit-logs: {exc}", file=sys.stderr)
        return 2
    for lg in train + test:
        log.info("%s: %d periods, %.0f m driven", lg.name, len(lg.t_s), lg.travel_m)
    result = fit_logs(train, test, nominal=args.nominal)
    log.info("nominal %s; heading-rate residual RMSE on the held-out logs: nominal %.4f, linear %.4f, GP %.4f "
             "rad/s (%.1f s)", result.identified["model_tag"], result.heading_rate_rmse_nominal,
             result.heading_rate_rmse_linear, result.heading_rate_rmse_gp, time.perf_counter() - t0)
    if args.out is not None:
        log.info("plots: %s", plot(result, args.out))
    print(json.dumps(result.as_json()))
    return 0
