"""One self-contained HTML report of a repeat experiment: map, tracking errors, learning over
trials, speeds and solve times. Plots are embedded as base64 PNGs so the file can be mailed or
archived alone (no external JS/CSS, no network)."""
from __future__ import annotations

import base64
import html
import io
import logging
import math
import pathlib
from contextlib import contextmanager

import matplotlib

matplotlib.use("Agg")  # headless: runs on CI machines and robots without a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import Normalize, to_rgba  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle, Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from common.path import Path  # noqa: E402
from common.scenario import Scenario  # noqa: E402
from deploy.learned import DisturbanceSeries  # noqa: E402
from deploy.metrics import TIME_LOST_KEYS, TrialSeries  # noqa: E402

log = logging.getLogger(__name__)

_TERRAIN_COLOURS = {"side_slope": "tab:orange", "slip": "tab:blue", "rough": "tab:brown", "rut": "tab:purple"}
_CMAP = plt.get_cmap("viridis")
_CSS = """body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}
h1{margin-bottom:.2em}h2{border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;font-size:.85em}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#eee}td.k{text-align:left;font-weight:bold}tr.bad td,th.bad{background:#fde8e8}
summary{cursor:pointer;margin:.6em 0;color:#555}
img{max-width:100%}.cap{color:#555;font-size:.9em}
.warn{background:#fff3cd;border:1px solid #e0c36c;padding:.4em .8em}"""


@contextmanager
def _figure(nrows: int = 1, ncols: int = 1, size=(10, 4.5)):
    """A figure that is always closed, so long sweeps don't accumulate open figures."""
    fig, axes = plt.subplots(nrows, ncols, figsize=size, layout="constrained", squeeze=False)
    try:
        yield fig, axes.ravel()
    finally:
        plt.close(fig)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool) or isinstance(v, np.bool_):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.4g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x) for x in v)
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items() if x)
    return str(v)


def _no_data(ax, what: str) -> None:
    ax.text(0.5, 0.5, f"no {what}", ha="center", va="center", transform=ax.transAxes, color="grey")


def _trial_colorbar(fig, axes, norm: Normalize) -> None:
    sm = plt.cm.ScalarMappable(norm=norm, cmap=_CMAP)
    cb = fig.colorbar(sm, ax=axes, shrink=0.9, pad=0.01)
    cb.set_label("trial")
    cb.locator = MaxNLocator(integer=True)
    cb.update_ticks()


def _pastel(colour: str, amount: float = 0.25) -> tuple[float, float, float]:
    """`colour` mixed with white: light, but opaque."""
    r, g, b, _ = to_rgba(colour)
    return (1 - amount + amount * r, 1 - amount + amount * g, 1 - amount + amount * b)


def _plot_map(scenario: Scenario, path: Path, series: list[TrialSeries]) -> str:
    with _figure(size=(10, 6)) as (fig, (ax,)):
        # an opaque pastel fill and a solid outline in the kind's colour, larger patches first: a patch drawn
        # over another shows its own legend colour, not a blend of the two
        for patch in sorted(scenario.terrain, key=lambda p: -p.radius_m):
            ax.add_patch(Circle(patch.center, patch.radius_m, facecolor=_pastel(_TERRAIN_COLOURS[patch.kind]),
                                edgecolor=_TERRAIN_COLOURS[patch.kind], lw=1.5))
        handles = [Patch(facecolor=_pastel(_TERRAIN_COLOURS[k]), edgecolor=_TERRAIN_COLOURS[k], lw=1.5,
                         label=k.replace("_", " ")) for k in dict.fromkeys(p.kind for p in scenario.terrain)]
        driven = [s for s in series if s.x_m.size]
        for s in driven[1:-1]:  # middle trials faintly, for the spread between first and last
            ax.plot(s.x_m, s.y_m, color="grey", lw=0.6, alpha=0.4)
        if len(driven) > 2:
            handles.append(Line2D([], [], color="grey", lw=0.6, alpha=0.4, label="other trials"))
        for s, colour in zip(driven[:1] + driven[1:][-1:], ("tab:red", "tab:green")):
            handles += ax.plot(s.x_m, s.y_m, color=colour, lw=1.2, label=f"driven, trial {s.trial}")
        handles += ax.plot(path.poses[:, 0], path.poses[:, 1], "k--", lw=1.2, label="taught route")
        wp = np.asarray(scenario.path.waypoints, dtype=float)
        handles += ax.plot(wp[:, 0], wp[:, 1], "ks", ms=6, mfc="white", label="waypoints")
        handles += ax.plot(*path.poses[0, :2], "k^", ms=9, label="start")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        ax.set(xlabel="x (m)", ylabel="y (m)", title="Top view (world frame)")
        ax.grid(alpha=0.3)
        ax.legend(handles=handles, loc="best", fontsize=8, framealpha=0.85)
        return _png(fig)


def _plot_errors(series: list[TrialSeries], lat_lim: float, head_lim_deg: float, norm: Normalize) -> str:
    with _figure(2, 1, size=(10, 6.5)) as (fig, (ax_l, ax_h)):
        for ax, attr, scale, lim, label in ((ax_l, "lateral_m", 1.0, lat_lim, "lateral error (m)"),
                                            (ax_h, "heading_rad", 180 / math.pi, head_lim_deg, "heading error (deg)")):
            drawn = [s for s in series if s.distance_m.size]
            for s in drawn:
                ax.plot(s.distance_m, getattr(s, attr) * scale, color=_CMAP(norm(s.trial)), lw=1)
            if not drawn:
                _no_data(ax, "samples")
            for sign in (1, -1):
                ax.axhline(sign * lim, color="red", ls="--", lw=1, label="constraint" if sign > 0 else None)
            ax.axhline(0, color="k", lw=0.5)
            ax.set(ylabel=label)
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
        ax_h.set_xlabel("distance along route (m)")
        _trial_colorbar(fig, [ax_l, ax_h], norm)
        return _png(fig)


def _plot_features(series: list[TrialSeries], norm: Normalize) -> str:
    with _figure(1, 1, size=(10, 3.8)) as (fig, (ax,)):
        for s in series:
            ax.plot(s.loc_distance_m, s.loc_features, color=_CMAP(norm(s.trial)), lw=0.8)
            miss = ~s.loc_refined
            ax.plot(s.loc_distance_m[miss], np.zeros(int(miss.sum())), "x", color=_CMAP(norm(s.trial)), ms=5)
        ax.set(xlabel="distance along route (m)", ylabel="matched features", ylim=(0, None))
        ax.grid(alpha=0.3)
        _trial_colorbar(fig, [ax], norm)
        return _png(fig)


def _plot_learning(trials: list[dict], lat_lim: float, head_lim_deg: float) -> str:
    with _figure(1, 2, size=(10, 4)) as (fig, (ax_l, ax_h)):
        n = [t.get("trial") for t in trials]
        bad = [i for i, t in enumerate(trials) if (t.get("constraint_violations") or 0) > 0]
        aborted = [n[i] for i, t in enumerate(trials) if t.get("completed") is False]
        for ax, key, scale, lim, unit in ((ax_l, "lateral_m", 1.0, lat_lim, "m"),
                                          (ax_h, "heading_rad", 180 / math.pi, head_lim_deg, "deg")):
            peak = np.array([(t.get(f"max_{key}") or 0.0) * scale for t in trials])
            rms = np.array([(t.get(f"rms_{key}") or 0.0) * scale for t in trials])
            ax.plot(n, peak, "o-", label="max")
            ax.plot(n, rms, "s-", label="RMS")
            ax.axhline(lim, color="red", ls="--", lw=1, label="constraint")
            if bad:
                ax.plot([n[i] for i in bad], peak[bad], "o", ms=13, mfc="none", mec="red", mew=1.5,
                        label="violations > 0")
            for j, x in enumerate(aborted):
                ax.axvspan(x - 0.4, x + 0.4, color="grey", alpha=0.25, lw=0, label="not completed" if j == 0 else None)
            if not trials:
                _no_data(ax, "trials")
            ax.set(xlabel="trial", ylabel=f"{key.split('_')[0]} error ({unit})", ylim=(0, None))
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        return _png(fig)


def _plot_speed(series: list[TrialSeries], norm: Normalize, path: Path, schedules: dict) -> str:
    with _figure(size=(10, 4)) as (fig, (ax,)):
        for trial, v in sorted(schedules.items()):   # the speed scheduler's plan (thin steps)
            if len(v) == len(path):
                ax.step(path.s, v, where="mid", color=_CMAP(norm(trial)), lw=0.8, ls=":", zorder=4)
        for s in series:
            c = _CMAP(norm(s.trial))
            if s.distance_m.size:
                ax.plot(s.distance_m, s.speed_mps, color=c, lw=0.8, alpha=0.8)
            if s.cmd_distance_m.size:  # above the truth lines, which are noisier and would hide them
                ax.plot(s.cmd_distance_m, s.v_cmd_mps, color=c, lw=1.5, ls="--", zorder=3)
        if not any(s.distance_m.size or s.cmd_distance_m.size for s in series):
            _no_data(ax, "samples")
        handles = [Line2D([], [], color="k", label="truth speed"),
                   Line2D([], [], color="k", lw=1.5, ls="--", label="commanded speed")]
        if schedules:
            handles.append(Line2D([], [], color="k", lw=0.8, ls=":", label="scheduled speed"))
        ax.legend(handles=handles, fontsize=8)
        ax.set(xlabel="distance along route (m)", ylabel="speed (m/s)")
        ax.grid(alpha=0.3)
        _trial_colorbar(fig, [ax], norm)
        return _png(fig)


SHOWN_LOSS_S = 0.05     # a cause that cost no trial more than this is left out of the legend


def _plot_time_lost(trials: list[dict]) -> str:
    """Per trial, a bar of its travel time: the asked speed's share, then the seconds each cause held the
    robot below it (summary.json time_lost_s)."""
    with _figure(size=(10, 0.45 * max(len(trials), 2) + 1.6)) as (fig, (ax,)):
        rows = [t for t in trials if isinstance(t.get("time_lost_s"), dict)]
        causes = [k for k in TIME_LOST_KEYS if any(t["time_lost_s"].get(k, 0.0) > SHOWN_LOSS_S for t in rows)]
        y = np.arange(len(rows))
        left = np.array([t.get("travel_time_ideal_s") or 0.0 for t in rows])
        ax.barh(y, left, color="lightgrey", label="at the asked speed")
        colours = plt.get_cmap("tab10")
        for i, k in enumerate(causes):
            width = np.array([max(t["time_lost_s"].get(k, 0.0), 0.0) for t in rows])
            ax.barh(y, width, left=left, color=colours(i % 10), label="none (drive catching up)" if k == "none" else k)
            left = left + width
        ax.set_yticks(y, [f"trial {t.get('trial')}" for t in rows])
        ax.invert_yaxis()
        ax.set(xlabel="travel time (s)")
        ax.grid(alpha=0.3, axis="x")
        ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
        return _png(fig)


def _plot_solve(series: list[TrialSeries], trials: list[dict]) -> str:
    with _figure(1, 2, size=(10, 3.8)) as (fig, (ax_t, ax_h)):
        n = [t.get("trial") for t in trials]
        for key, marker in (("solve_ms_p50", "o-"), ("solve_ms_p99", "s-")):
            ax_t.plot(n, [t.get(key) or 0.0 for t in trials], marker, label=key.rsplit("_", 1)[1])
        if not trials:
            _no_data(ax_t, "trials")
        ax_t.set(xlabel="trial", ylabel="solve time (ms)", ylim=(0, None))
        ax_t.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax_t.legend(fontsize=8)
        ax_t.grid(alpha=0.3)
        solve = np.concatenate([s.solve_ms for s in series] or [np.empty(0)])
        solve = solve[np.isfinite(solve)]
        if solve.size:
            ax_h.hist(solve, bins=min(50, max(5, solve.size // 20)), color="tab:blue")
        else:
            _no_data(ax_h, "solve times")
        ax_h.set(xlabel="solve time (ms)", ylabel="control steps")
        ax_h.grid(alpha=0.3)
        return _png(fig)


def _plot_disturbance(dist: list[DisturbanceSeries], period_s: float) -> str:
    """Observed one-step disturbance of the last trial against the model learned before it, as rates
    (g / period): lateral slide (m/s) and heading rate (deg/s); plus RMSE of nominal vs learned per trial."""
    with _figure(3, 1, size=(10, 9)) as (fig, (ax_y, ax_h, ax_r)):
        last = next((d for d in reversed(dist) if len(d.observed)), None)
        if last is None:
            for ax in (ax_y, ax_h):
                _no_data(ax, "experiences")
        else:
            order = np.argsort(last.s_m)
            for ax, i, scale, unit in ((ax_y, 1, 1.0, "m/s"), (ax_h, 2, math.degrees(1.0), "deg/s")):
                k = scale / period_s
                ax.plot(last.s_m, last.observed[:, i] * k, ".", ms=2.5, color="0.45", label="observed")
                m, sd = last.mean[order, i] * k, last.std[order, i] * k
                ax.plot(last.s_m[order], m, color="tab:blue", lw=1.2,
                        label=f"predicted (model v{last.hyper_version}, trials < {last.trial})")
                ax.fill_between(last.s_m[order], m - 2 * sd, m + 2 * sd, color="tab:blue", alpha=0.15,
                                label="±2σ")
                ax.set(ylabel=f"{'lateral slide' if i == 1 else 'heading rate'} ({unit})")
                ax.grid(alpha=0.3)
                ax.legend(fontsize=8, loc="upper right")
            ax_h.set(xlabel="distance along route (m)")
            ax_y.set_title(f"trial {last.trial}: disturbance not explained by the unicycle model (eq. 5.17)")
        trials = [d.trial for d in dist]
        if trials:
            nominal = np.array([d.rmse()[0][2] for d in dist]) * math.degrees(1.0) / period_s
            learned = np.array([d.rmse()[1][2] for d in dist]) * math.degrees(1.0) / period_s
            ax_r.plot(trials, nominal, "o-", color="0.45", label="nominal model only")
            ax_r.plot(trials, learned, "s-", color="tab:blue", label="with the learned GP")
            ax_r.legend(fontsize=8)
        else:
            _no_data(ax_r, "trials")
        ax_r.set(xlabel="trial", ylabel="heading-rate residual RMSE (deg/s)", ylim=(0, None))
        ax_r.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax_r.grid(alpha=0.3)
        return _png(fig)


def _kv_table(rows: dict) -> str:
    body = "".join(f"<tr><td class=k>{html.escape(str(k))}</td><td>{html.escape(_fmt(v))}</td></tr>"
                   for k, v in rows.items())
    return f"<table>{body}</table>"


# what a reader looks at first, one column each; every summary.json entry follows, folded
KEY_COLUMNS = {"trial": "trial", "completed": "completed", "end_reason": "end", "max_lateral_m": "max lat (m)",
               "rms_lateral_m": "rms lat (m)", "max_heading_rad": "max head (deg)",
               "constraint_violations": "violations", "travel_time_s": "time (s)", "mean_speed_mps": "mean v (m/s)"}


def _bad(t: dict) -> bool:
    return (t.get("constraint_violations") or 0) > 0 or t.get("completed") is False


def _trial_table(trials: list[dict]) -> str:
    """The key columns as a table that fits the page, then every entry transposed (a row per entry, a
    column per trial: there are few trials and many entries) in a fold."""
    key_cols = [k for k in KEY_COLUMNS if any(k in t for t in trials)]
    head = "".join(f"<th>{html.escape(KEY_COLUMNS[k])}</th>" for k in key_cols)
    rows = []
    for t in trials:
        cells = "".join(f"<td>{html.escape(_key_cell(k, t.get(k)))}</td>" for k in key_cols)
        rows.append(f"<tr{' class=bad' if _bad(t) else ''}>{cells}</tr>")
    every = list(dict.fromkeys(k for t in trials for k in t))  # union, first-seen order
    full_head = "<th>entry</th>" + "".join(f"<th{' class=bad' if _bad(t) else ''}>trial {html.escape(_fmt(t.get('trial')))}"
                                          "</th>" for t in trials)
    full_rows = "".join(f"<tr><td class=k>{html.escape(str(k))}</td>"
                        + "".join(f"<td>{html.escape(_fmt(t.get(k)))}</td>" for t in trials) + "</tr>"
                        for k in every)
    return (f"<table><tr>{head}</tr>{''.join(rows)}</table>"
            f"<details><summary>all {len(every)} summary.json entries per trial</summary>"
            f"<div style='overflow-x:auto'><table><tr>{full_head}</tr>{full_rows}</table></div></details>")


def _key_cell(key: str, value) -> str:
    if key == "max_heading_rad" and isinstance(value, (int, float)) and not isinstance(value, bool):
        return _fmt(math.degrees(value))
    return _fmt(value)


def _model_section(model: dict, teach_learning: dict | None) -> list[str]:
    """The nominal model the controller identified on the teach pass (summary.json identified_model), and
    what the teach pass gave the learned model (teach_learning)."""
    rows = {"model (experiences carry this name)": model["model_tag"],
            "speed channel: lag, dead time (s), gain, acceleration limit (m/s^2)":
                (model["tau_v_s"], model["dead_time_v_s"], model["gain_v"], model["rate_limit_v_mps2"]),
            "turn-rate channel: lag, dead time (s), gain, acceleration limit (rad/s^2)":
                (model["tau_w_s"], model["dead_time_w_s"], model["gain_w"], model["rate_limit_w_radps2"]),
            "lags the NMPC uses (v, w), s": model["actuator_tau_s"],
            "steering-rate limit the NMPC uses, curvature per s (1/(m s); 0: none)":
                model.get("curvature_rate_max_per_ms", 0.0),
            "turn gain: the robot's turn rate over the drive's, against the localizer (+- std)":
                (model.get("turn_gain", 1.0), model.get("turn_gain_std", 0.0)),
            "a-priori std per period, base (m, m, rad)": model["prior_std_base"],
            "... per m/s": model["prior_std_per_mps"], "... per rad/s": model["prior_std_per_radps"],
            "scale of the default prior, from the teach residuals": model["prior_scale"],
            "places where the teach pass needed a wider spread than its prior at 1 s ahead (route m: factor)":
                _teach_places(model),
            "places where the teach pass's commands took 80 % or more of the steering margin beyond the "
            "route's turn (route m: largest share; C-/RC-LB-NMPC hold trial 1 to the teach speed there)":
                _stretches(model.get("place_turn_share") or [], model.get("place_bin_m", 2.0), 0.799, "{:.0%}"),
            "experiences from the teach pass, stored before trial 1 (GP fit version)":
                (teach_learning["experiences_stored"], teach_learning["hyper_version"]) if teach_learning else "none"}
    rows.update({f"note {i + 1}": n for i, n in enumerate(model.get("notes") or [])})
    return ["<h2>Nominal model</h2><p class=cap>Identified by the controller on the teach pass: each drive "
            "channel's first-order lag, dead time, gain and acceleration limit against the wheel odometry (and an "
            "Ackermann robot's steering-rate limit, from its limits); the share of the drive's turn rate the "
            "robot turns at, against the localizer's heading (ground slip, understeer); the "
            "a-priori uncertainty scaled to the model's one-period residuals on that pass. Hand-set "
            "actuator_tau_s / turn_gain / prior_std_* in [controller.nmpc] override it.</p>", _kv_table(rows)]


def _teach_places(model: dict, step: int = 10) -> str:
    """The stretches of route whose teach residuals needed a factor above 1 on the prior's spread `step`
    periods ahead (identification.place_factors), each with its largest factor."""
    rows, bin_m = model.get("place_spread_factors") or [], model.get("place_bin_m", 2.0)
    return _stretches([r[min(step, len(r)) - 1] if r else 1.0 for r in rows], bin_m, 1.0, "{:.2f}")


def _stretches(values: list[float], bin_m: float, above: float, fmt: str) -> str:
    """The runs of places (`bin_m` each) whose value is above `above`, as 'from-to: largest'."""
    out, b = [], 0
    while b < len(values):
        if values[b] <= above:
            b += 1
            continue
        e = b
        while e + 1 < len(values) and values[e + 1] > above:
            e += 1
        out.append(f"{b * bin_m:.0f}-{(e + 1) * bin_m:.0f}: {fmt.format(max(values[b:e + 1]))}")
        b = e + 1
    return ", ".join(out) or "none"


def _learning_off_notes(trials: list[dict]) -> list[str]:
    """A warning where the controller tracked without its learned model (the store's data missing)."""
    notes = [f"Learning was off in trial {t['trial']} from {t['learning_off_since_s']:.1f} s, for "
             f"{t['learning_off_s']:.1f} s in all: {t.get('learning_note') or 'store data missing'}. The "
             "controller tracked with its nominal model there."
             for t in trials if t.get("learning_off_since_s") is not None]
    return [f"<p class=warn>{html.escape(n)}</p>" for n in notes]


def _fit_notes(trials: list[dict]) -> list[str]:
    """A warning where the store refitted its fit after a trial (services/gp_store/authority.py)."""
    notes = [f"The model fitted after trial {t['trial']} was refitted by the store: {t['fit_note']}."
             for t in trials if t.get("fit_note")]
    return [f"<p class=warn>{html.escape(n)}</p>" for n in notes]


def _unanswered_notes(summary: dict) -> list[str]:
    """A warning where the lockstep bridge stepped ticks without their answer: that run depended on the
    wall clock (a hung or badly overloaded service), so another run of its seed can differ."""
    counts = [("teach", summary.get("teach_unanswered_ticks") or 0)] + [
        (f"trial {t['trial']}", t.get("unanswered_ticks") or 0) for t in summary.get("trials", [])]
    notes = [f"{what}: {n} ticks stepped without their answer (sim.lockstep_timeout_s)" for what, n in counts if n]
    if not notes:
        return []
    return [f"<p class=warn>{html.escape('; '.join(notes))}. This run depended on the wall clock; another "
            "run of its seed can differ.</p>"]


def _section(title: str, caption: str, png: str) -> str:
    return (f"<h2>{html.escape(title)}</h2><p class=cap>{html.escape(caption)}</p>"
            f"<img alt='{html.escape(title)}' src='data:image/png;base64,{png}'>")


def write_report(out_path: str | pathlib.Path, scenario: Scenario, path: Path, series: list[TrialSeries],
                 summary: dict, run_info: dict, disturbance: list[DisturbanceSeries] | None = None,
                 schedules: dict | None = None, route: Path | None = None) -> None:
    """Write the experiment report as one self-contained HTML file at `out_path`. `path` is the taught
    route from truth (what errors are measured against), `route` the localizer's own (the vertices
    schedules refer to; the same as `path` for the pose source)."""
    series = sorted(series, key=lambda s: s.trial)
    trials = sorted(summary.get("trials") or [], key=lambda t: t.get("trial", 0))
    lat_lim, head_lim = scenario.constraints.lateral_m, scenario.constraints.heading_deg
    numbers = [s.trial for s in series] + [t["trial"] for t in trials if "trial" in t] or [1]
    norm = Normalize(min(numbers), max(max(numbers), min(numbers) + 1))  # a span of one trial still maps
    name = summary.get("scenario") or scenario.name
    algorithm = summary.get("algorithm") or scenario.controller.algorithm
    header = {"scenario": name, "algorithm": algorithm, "robot preset": scenario.robot.preset,
              "robot name": scenario.robot.name, "trials": len(trials) or len(series),
              "route length (m)": path.length_m, "lateral constraint (m)": lat_lim,
              "heading constraint (deg)": head_lim}
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(name)} report</title>"
        f"<style>{_CSS}</style></head><body><h1>{html.escape(name)}</h1>",
        _kv_table(header),
        *_learning_off_notes(trials),
        *_fit_notes(trials),
        *_unanswered_notes(summary),
        _section("Map", "Top view, equal aspect, metres: taught route, waypoints, terrain patches (coloured by "
                 "kind) and the driven truth trajectory of the first and last trial.",
                 _plot_map(scenario, path, series)),
        _section("Tracking errors", "Truth lateral error (m, left positive) and heading error (deg) against "
                 "distance along the taught route (m), one line per trial; red dashes are the ± constraints.",
                 _plot_errors(series, lat_lim, head_lim, norm)),
        _section("Learning over trials", "Max and RMS lateral error (m) and heading error (deg) per trial; red "
                 "rings mark trials with constraint violations, grey bands trials that did not complete.",
                 _plot_learning(trials, lat_lim, head_lim)),
        _section("Speed", "Truth speed (solid), commanded speed (dashed) and, with the speed scheduler, its "
                 "schedule (dotted), m/s, against distance along the route (m), coloured by trial.",
                 _plot_speed(series, norm, route or path, schedules or {})),
        *([_section("Where the time went", "Per trial, the travel time the asked (or scheduled) speed would have "
                 "taken over the distance covered (grey), then the seconds lost beyond it by what held the "
                 "speed command below the asked one: RC-LB-NMPC's speed ladder by the check its next faster "
                 "rung failed, the place cap from the latest pass, the robot's turn or top speed, the slow-down "
                 "into the end; \"none\": commanded the asked speed while the drive was still catching up "
                 "(summary.json time_lost_s).", _plot_time_lost(trials))]
          if any(isinstance(t.get("time_lost_s"), dict) for t in trials) else []),
        *([_section("Localization", "Matched features per frame (inliers against the taught keyframe) "
                    "against distance along the route (m), coloured by trial; crosses at zero mark frames not "
                    "refined against the map (visual odometry only, or lost).", _plot_features(series, norm))]
          if any(np.isfinite(s.loc_features).any() for s in series) else []),
        _section("Solve time", "Controller solve time per control step (ms): per-trial median and 99th "
                 "percentile, and the histogram over all trials.", _plot_solve(series, trials)),
        _section("Learned disturbance", "What the nominal unicycle model misses, per control period, against "
                 "what the GP learned from earlier trials predicts for it (local windows and hyperparameters "
                 "as the controller uses them); bottom: heading-rate residual RMSE per trial without and with "
                 "the learned model (trial 1 has no model yet).",
                 _plot_disturbance(disturbance or [], scenario.sim.period_s)),
        *(_model_section(summary["identified_model"], summary.get("teach_learning")) if summary.get("identified_model") else []),
        "<h2>Trials</h2><p class=cap>Key figures per trial (truth against the taught route); highlighted "
        "trials violated a constraint or did not complete. Below, folded, every summary.json entry (angles in "
        "rad, times in s unless named otherwise).</p>",
        _trial_table(trials),
        "<h2>Run</h2>", _kv_table(run_info), "</body></html>",
    ]
    out = pathlib.Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(parts), encoding="utf-8")
    log.info("report written to %s", out)
