import base64
import math
import re

import matplotlib.pyplot as plt
import numpy as np
import pytest

from common.path import Path
from common.scenario import parse_scenario
from deploy.learned import DisturbanceSeries
from deploy.metrics import TrialSeries
from deploy.report import _fmt, write_report

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
N_IMAGES = 6  # map, tracking errors, learning, speed, solve time, learned disturbance


def make_scenario():
    return parse_scenario({
        "name": "demo_slope", "seed": 1, "robot": {"preset": "husky"},
        "path": {"waypoints": [[0, 0], [10, 0], [20, 5]]},
        "terrain": [{"kind": "side_slope", "center": [8, 1], "radius_m": 4, "slope_deg": 10, "downhill_deg": -90}],
        "trials": {"count": 2},
    })


def make_path():
    corners = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 5.0]])
    pts = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:]):
        n = int(np.ceil(np.linalg.norm(b - a) / 0.25))
        pts += list(a + np.linspace(0, 1, n + 1)[1:, None] * (b - a))
    xy = np.array(pts)
    d = np.diff(xy, axis=0)
    theta = np.arctan2(d[:, 1], d[:, 0])
    return Path("demo", np.column_stack([xy, np.append(theta, theta[-1])]))


def make_series(path, trial, gain=0.2, n=300):
    """Errors shrinking with the trial number, as a learning controller should show."""
    rng = np.random.default_rng(trial)
    dist = np.linspace(0, path.length_m, n)
    lateral = gain / trial * np.sin(dist / 3) + 0.005 * rng.standard_normal(n)
    heading = 0.5 * gain / trial * np.cos(dist / 3)
    pose = np.array([path.pose_at(d) for d in dist])
    x = pose[:, 0] - lateral * np.sin(pose[:, 2])
    y = pose[:, 1] + lateral * np.cos(pose[:, 2])
    speed = np.clip(0.5 * np.ones(n) + 0.02 * rng.standard_normal(n), 0, None)
    return TrialSeries(trial, np.arange(n) * 0.1, x, y, dist, lateral, heading, speed,
                       cmd_distance_m=dist, v_cmd_mps=np.full(n, 0.5), w_cmd_radps=np.zeros(n),
                       solve_ms=rng.gamma(4, 0.5, n))


def empty_series(trial):
    e = np.empty(0)
    return TrialSeries(trial, e, e, e, e, e, e, e, cmd_distance_m=e, v_cmd_mps=e, w_cmd_radps=e, solve_ms=e)


def entry(series, completed=True, violations=0):
    lat, head = series.lateral_m, series.heading_rad
    return {"trial": series.trial, "completed": completed,
            "max_lateral_m": float(np.abs(lat).max()) if lat.size else 0.0,
            "rms_lateral_m": float(np.sqrt(np.mean(lat ** 2))) if lat.size else 0.0,
            "max_heading_rad": float(np.abs(head).max()) if head.size else 0.0,
            "rms_heading_rad": float(np.sqrt(np.mean(head ** 2))) if head.size else 0.0,
            "travel_time_s": 30.0, "mean_speed_mps": 0.5, "constraint_violations": violations,
            "mean_matched_features": None, "solve_ms_p50": 2.0, "solve_ms_p99": 4.5,
            "experiences_total": series.trial, "end_reason": "finished" if completed else "<aborted>"}


def disturbance(trial, n=200, learned=True):
    rng = np.random.default_rng(trial)
    s = np.linspace(0, 20, n)
    g = np.column_stack([np.zeros(n), 0.01 * np.sin(s), 0.03 * np.exp(-(s - 10) ** 2)]) + 0.002 * rng.standard_normal((n, 3))
    mean = g * 0.9 if learned else np.zeros_like(g)
    return DisturbanceSeries(trial, trial - 1, 100 * (trial - 1), s, g, mean, np.full_like(g, 0.003))


MODEL = {"model_tag": "unicycle-dt100ms-tauv370ms-tauw393ms", "tau_v_s": 0.37, "tau_w_s": 0.393,
         "dead_time_v_s": 0.0, "dead_time_w_s": 0.0, "gain_v": 0.999, "gain_w": 1.0, "rate_limit_v_mps2": 0.82,
         "rate_limit_w_radps2": None, "actuator_tau_s": [0.37, 0.393], "prior_std_base": [0.002, 0.0015, 0.002],
         "prior_std_per_mps": [0.007, 0.006, 0.005], "prior_std_per_radps": [0.003, 0.003, 0.009],
         "prior_scale": [1.64, 0.74, 0.6], "spread_factors": [1.0, 1.2], "notes": ["w: <no> rate limit seen"],
         "place_bin_m": 2.0, "place_turn_share": [0.1, 0.85, 1.0, 0.5, 0.9]}


def render(tmp_path, series, entries, dist=None, model=None):
    out = tmp_path / "sub" / "report.html"
    summary = {"scenario": "demo_slope", "algorithm": "lb-nmpc", "trials": entries}
    if model is not None:
        summary["identified_model"] = model
    write_report(out, make_scenario(), make_path(), series, summary,
                 {"wall_time_s": 12.5, "robot": "husky", "command": "lbc run demo.toml <x>"}, dist)
    return out.read_text(encoding="utf-8")


def test_report_contents(tmp_path):
    path = make_path()
    series = [make_series(path, 1), make_series(path, 2)]
    refitted = {**entry(series[1]), "fit_note": "the heading model kept < 10% of the steering", "unanswered_ticks": 4}
    page = render(tmp_path, series, [{**entry(series[0], violations=3), "unanswered_ticks": 0}, refitted],
                  [disturbance(1, learned=False), disturbance(2)], MODEL)
    assert "Learned disturbance" in page
    warnings = re.findall(r"<p class=warn>(.*?)</p>", page)
    assert warnings == ["The model fitted after trial 2 was refitted by the store: the heading model kept &lt; 10% of the "
                        "steering.",
                        "trial 2: 4 ticks stepped without their answer (sim.lockstep_timeout_s). This run depended on "
                        "the wall clock; another run of its seed can differ."]
    model = page[page.index("<h2>Nominal model</h2>"):page.index("<h2>Trials</h2>")]
    assert "unicycle-dt100ms-tauv370ms-tauw393ms" in model and "0.37, 0, 0.999, 0.82" in model
    assert "0.393, 0, 1, n/a" in model and "&lt;no&gt; rate limit" in model
    assert "<td>2-6: 100%, 8-10: 90%</td>" in model     # the teach pass's steering margin, 80 % or more
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    assert "demo_slope" in page and "lb-nmpc" in page and "husky" in page
    images = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page)
    assert len(images) == N_IMAGES
    assert base64.b64decode(images[0]).startswith(PNG_SIGNATURE)
    table = page[page.index("<h2>Trials</h2>"):]
    for trial in (1, 2):
        assert f"<td>{trial}</td>" in table
    assert "n/a" in table                       # mean_matched_features None
    # the key columns first, in a table that fits the page; every entry, transposed, folded below it
    key_table, folded = table[:table.index("<details>")], table[table.index("<details>"):]
    assert key_table.count("<th>") <= 9 and "max head (deg)" in key_table and "solve_ms_p50" not in key_table
    assert _fmt(math.degrees(entry(series[0])["max_heading_rad"])) in key_table
    assert all(f"<td class=k>{k}</td>" in folded for k in entry(series[0]))
    assert folded.count("<th") == 1 + 2       # the entry column and one per trial
    assert "&lt;aborted&gt;" not in table       # both completed here ...
    assert "lbc run demo.toml &lt;x&gt;" in page  # ... but inserted strings are escaped
    assert "<script" not in page and "http" not in page


@pytest.mark.parametrize("case", ["empty_trial", "single_trial", "all_zero"])
def test_report_edge_cases(tmp_path, case):
    path = make_path()
    if case == "empty_trial":
        series = [make_series(path, 1), empty_series(2)]
        entries = [entry(series[0]), entry(series[1], completed=False)]
    elif case == "single_trial":
        series = [make_series(path, 1)]
        entries = [entry(series[0])]
    else:
        series = [make_series(path, 1, gain=0.0)]
        series[0].lateral_m[:] = 0.0
        entries = [entry(series[0])]
    before = len(plt.get_fignums())
    page = render(tmp_path, series, entries)
    assert len(plt.get_fignums()) == before     # every figure closed
    assert page.count("data:image/png;base64,") == N_IMAGES
    for e in entries:
        assert f"<td>{e['trial']}</td>" in page


def test_a_patch_drawn_over_another_keeps_its_legend_colour():
    import cv2
    from common.scenario import parse_scenario
    from deploy.report import _TERRAIN_COLOURS, _pastel, _plot_map
    sc = parse_scenario({"name": "overlap", "robot": {"preset": "husky"}, "path": {"waypoints": [[0, 0], [20, 0]]},
                         "terrain": [{"kind": "side_slope", "center": [10.0, 0.0], "radius_m": 5.0, "slope_deg": 8.0,
                                      "downhill_deg": 90.0},
                                     {"kind": "slip", "center": [10.0, 0.0], "radius_m": 3.0, "traction": 0.7}]})
    png = base64.b64decode(_plot_map(sc, make_path(), []))
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
    for kind in ("slip", "side_slope"):     # the inner patch's area shows its own legend colour, no blend
        want = np.round(np.array(_pastel(_TERRAIN_COLOURS[kind]))[::-1] * 255)
        assert np.count_nonzero(np.abs(bgr - want).max(axis=2) <= 2) > 2000, kind


def test_where_the_time_went_is_drawn_from_time_lost_s_and_listed_in_the_table(tmp_path):
    path = make_path()
    series = [make_series(path, 1), make_series(path, 2)]
    lost = [{"none": 0.8, "ladder-lateral": 12.5, "place-corridor": 0.0}, {"none": 0.7, "ladder-lateral": 3.0,
                                                                          "place-corridor": 4.25}]
    entries = [{**entry(s), "travel_time_ideal_s": 20.0, "time_lost_s": t} for s, t in zip(series, lost)]
    page = render(tmp_path, series, entries)
    assert "<h2>Where the time went</h2>" in page
    assert page.count("data:image/png;base64,") == N_IMAGES + 1
    table = page[page.index("<h2>Trials</h2>"):]
    assert "none 0.8, ladder-lateral 12.5" in table and "ladder-lateral 3, place-corridor 4.25" in table
