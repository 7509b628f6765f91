"""Scenario files (a public interface) and the typed service configs made from them."""
import tomllib

import pytest

from common.config import ConfigError, dump_toml, load_config
from common.bins import BinPolicy
from common.scenario import load_scenario, parse_scenario
from services.controller.turn_speed import TURN_SHARE
from services.controller.uncertainty import PriorStd
from deploy.configs import service_configs
from deploy.experiment import check_supported

# The example from DESIGN.md, verbatim: every key in it must be accepted as written.
DESIGN_EXAMPLE = '''
name = "husky-sideslope"
seed = 1
[robot]
preset = "husky"                 # husky | roc6 | grizzly | mats
# optional overrides of any preset parameter, e.g. tau_v_s = 0.3
[path]
waypoints = [[0,0],[10,0],[20,6],[30,6]]   # metres, smoothed into the taught route
loop = false
[[terrain]]                      # any number of patches
kind = "side_slope"              # side_slope | slip | rough | rut
center = [15.0, 2.0]
radius_m = 5.0
slope_deg = 12.0                 # side_slope: tilt; downhill direction below
downhill_deg = 90.0
# slip: traction = 0.6 ; rough: amplitude ; rut: grows with each pass
[localization]
source = "vision"                # vision | pose
noise_m = 0.02
delay_s = 0.2
[controller]
algorithm = "rc-lb-nmpc"         # fl | ilc | lb-nmpc | mm-lb-nmpc | c-lb-nmpc | rc-lb-nmpc
horizon = 10
[constraints]
lateral_m = 0.3
heading_deg = 15.0
[scheduler]
enabled = true                   # thesis table 5.1 names: gamma1, gamma2, lambda_L, ...
v_init = 0.5
v_max = 2.0
[trials]
count = 10
speed = 0.5                      # fixed speed when the scheduler is off
# speeds = [0.35, 0.45, 0.55]    # optional: one fixed speed per trial (ILC exp. 2)
learning = true                  # false: the same controller with learning switched off
'''


def test_design_example_is_accepted_as_written():
    sc = parse_scenario(tomllib.loads(DESIGN_EXAMPLE))
    assert sc.name == "husky-sideslope" and sc.seed == 1
    assert sc.robot.preset == "husky" and sc.robot.params.mass_kg == 50.0
    assert sc.path.waypoints == [(0.0, 0.0), (10.0, 0.0), (20.0, 6.0), (30.0, 6.0)]
    assert sc.terrain[0].kind == "side_slope" and sc.terrain[0].downhill_deg == 90.0
    assert sc.localization.source == "vision" and sc.localization.delay_s == 0.2
    assert sc.controller.algorithm == "rc-lb-nmpc" and sc.controller.horizon == 10
    assert sc.constraints.heading_deg == 15.0
    assert sc.scheduler.enabled and sc.scheduler.v_max == 2.0
    assert sc.trials.count == 10 and sc.trials.learning


def test_the_design_example_runs_as_written_and_contradictions_are_refused():
    sc = parse_scenario(tomllib.loads(DESIGN_EXAMPLE))
    check_supported(sc)     # vision, rc-lb-nmpc and the scheduler are all there
    both = tomllib.loads(DESIGN_EXAMPLE)
    both["trials"]["speeds"] = [0.5] * both["trials"]["count"]
    with pytest.raises(ConfigError, match="choose one"):
        check_supported(parse_scenario(both))


def _minimal(**extra):
    data = {"name": "t", "robot": {"preset": "husky"}, "path": {"waypoints": [[0, 0], [10, 0]]}}
    data.update(extra)
    return data


@pytest.mark.parametrize("data, match", [
    (_minimal(colour="red"), r"unknown key\(s\) \['colour'\]"),
    (_minimal(trials={"count": 2, "sped": 0.5}), r"trials: unknown key"),
    (_minimal(robot={"preset": "husky", "tau_v": 0.3}), r"robot: unknown key\(s\) \['tau_v'\]"),
    (_minimal(robot={"preset": "segway"}), r"unknown preset 'segway'"),
    (_minimal(robot={"preset": "husky", "mass_kg": -1.0}), r"mass_kg must be > 0"),
    (_minimal(terrain=[{"kind": "slip", "center": [0, 0], "radius_m": 2}]), r"needs 'traction'"),
    (_minimal(terrain=[{"kind": "slip", "center": [0, 0], "radius_m": 2, "traction": 0.5, "slope_deg": 3}]),
     r"'slope_deg' does not apply to a slip patch"),
    (_minimal(terrain=[{"kind": "lava", "center": [0, 0], "radius_m": 2}]), r"terrain\[0\]\.kind"),
    (_minimal(trials={"count": 3, "speeds": [0.3, 0.4]}), r"speeds has 2 entries"),
    (_minimal(localization={"noise_m": float("nan")}), r"localization\.noise_m: must be finite"),
    (_minimal(path={"waypoints": [[0, 0]]}), r"at least 2 points"),
    (_minimal(controller={"nmpc": {"horizon": 20}}), r"set the horizon as controller\.horizon"),
    (_minimal(controller={"nmpc": {"prior_std_base": [0.1, 0.1]}}), r"controller\.nmpc\.prior_std_base: expected 3 elements"),
    (_minimal(store={"c_bin": 0}), r"c_bin >= 1"),
    (_minimal(scheduler={"gamma1": -0.1}), r"gamma1 and gamma2 must be > 0"),
])
def test_bad_scenarios_name_the_offending_key(data, match):
    with pytest.raises(ConfigError, match=match):
        parse_scenario(data)


def test_the_sections_a_service_reads_are_its_own_settings():
    """One default per setting: the scenario's [controller.nmpc], [controller.ilc], [scheduler] and [store]
    tables are the services' own settings types, so every key a service takes is accepted as it is there."""
    sc = parse_scenario(_minimal(controller={"algorithm": "rc-lb-nmpc", "horizon": 12,
                                             "nmpc": {"tol": 1e-4, "prior_std_per_mps": [0.01, 0.02, 0.02]},
                                             "ilc": {"gamma_u": 0.9}},
                                 store={"c_vertex": 7}, scheduler={"enabled": True, "prune_min_m": 1.0}))
    cfg = service_configs(sc, "/tmp/unused")
    nmpc = cfg["controller"].nmpc
    assert nmpc.horizon == 12 and nmpc.tol == 1e-4 and nmpc.prior_std_per_mps == (0.01, 0.02, 0.02)
    assert nmpc.prior_std_base is None and nmpc.prior_std().base == PriorStd().base   # left to identification
    assert cfg["controller"].ilc.gamma_u == 0.9 and cfg["controller"].store.c_vertex == 7
    assert cfg["gp_store"].bins.c_vertex == 7 and cfg["gp_store"].bins.c_bin == BinPolicy().c_bin
    assert cfg["scheduler"].params.prune_min_m == 1.0


def test_the_schedulers_error_limits_stay_inside_the_corridor_with_their_deadband():
    """The corridor is an a-priori limit like the robot's speeds: a 0.12 m / 8 deg corridor (its narrowest
    stretch 0.1 m) caps the thesis's lambda_L = 0.15 m and lambda_H = 10 deg so that lambda * lambda_db
    (where eq. 4.2 starts to slow down) is the corridor; a wide corridor leaves them."""
    narrow = parse_scenario(_minimal(scheduler={"enabled": True},
                                     constraints={"lateral_m": 0.12, "heading_deg": 8.0,
                                                  "segments": [[5.0, 8.0, 0.1, -0.3, 12.0]]}))
    p = service_configs(narrow, "/tmp/unused")["scheduler"].params
    assert p.lambda_L * p.lambda_db == pytest.approx(0.1) and p.lambda_H * p.lambda_db == pytest.approx(8.0)
    wide = service_configs(parse_scenario(_minimal(scheduler={"enabled": True})), "/tmp/unused")["scheduler"].params
    assert (wide.lambda_L, wide.lambda_H) == (0.15, 10.0)


def test_robot_overrides_apply_to_the_preset():
    sc = parse_scenario(_minimal(robot={"preset": "grizzly", "name": "g1", "tau_v_s": 0.8}))
    assert sc.robot.name == "g1" and sc.robot.params.tau_v_s == 0.8 and sc.robot.params.mass_kg == 900.0


def test_rut_defaults_and_per_trial_speeds():
    sc = parse_scenario(_minimal(terrain=[{"kind": "rut", "center": [5, 0], "radius_m": 2}],
                                 trials={"count": 3, "speeds": [0.35, 0.45, 0.55]}))
    assert sc.terrain[0].growth_m_per_pass > 0 and sc.terrain[0].depth_m == 0.0
    assert [sc.trials.speed_of(i) for i in (1, 2, 3)] == [0.35, 0.45, 0.55]


def test_examples_load_and_are_runnable():
    import glob
    files = sorted(glob.glob("examples/*.toml"))
    assert files
    for f in files:
        check_supported(load_scenario(f))


def test_service_configs_round_trip_through_toml(tmp_path):
    sc = parse_scenario(_minimal(robot={"preset": "mats"},
                                 terrain=[{"kind": "side_slope", "center": [1, 1], "radius_m": 3, "slope_deg": 5,
                                           "downhill_deg": 0}]))
    for name, cfg in service_configs(sc, tmp_path).items():
        path = tmp_path / f"{name}.toml"
        path.write_text(dump_toml(cfg))
        assert load_config(type(cfg), path) == cfg, name
    bad = tmp_path / "bad.toml"
    bad.write_text(dump_toml(service_configs(sc, tmp_path)["controller"]) + "\nsurprise = 1\n")
    with pytest.raises(ConfigError, match="surprise"):
        load_config(type(service_configs(sc, tmp_path)["controller"]), bad)


def test_the_route_heading_window_is_a_car_like_robots_turning_radius_unless_set():
    """Under a corridor law a MATS (Ackermann, 0.30 /m at most) follows the taught heading averaged over
    its turning radius, a Husky (no curvature limit) the taught heading itself; the other laws track the
    taught heading; a scenario's own window wins, 0 included."""
    mats = service_configs(parse_scenario(_minimal(robot={"preset": "mats"})), "/tmp/unused")["controller"]
    assert mats.heading_window_m(True) == pytest.approx(1.0 / mats.limits.max_curvature_per_m)
    assert 3.0 < mats.heading_window_m(True) < 4.0 and mats.heading_window_m(False) == 0.0
    husky = service_configs(parse_scenario(_minimal()), "/tmp/unused")["controller"]
    assert husky.heading_window_m(True) == 0.0
    for window in (2.0, 0.0):
        own = parse_scenario(_minimal(robot={"preset": "mats"}, controller={"route_heading_window_m": window}))
        assert service_configs(own, "/tmp/unused")["controller"].heading_window_m(True) == window
        assert service_configs(own, "/tmp/unused")["controller"].heading_window_m(False) == window
    with pytest.raises(ValueError, match="route_heading_window_m"):
        parse_scenario(_minimal(controller={"route_heading_window_m": -1.0}))


def test_fl_leads_its_feedback_unless_the_scenario_says_fl_lead_false(tmp_path):
    """FL and ILC take eq. 3.5 at the led errors by default (fl.py); `fl_lead = false` reaches the
    controller service's config file and back."""
    on = service_configs(parse_scenario(_minimal()), str(tmp_path))["controller"]
    off = service_configs(parse_scenario(_minimal(controller={"fl_lead": False})), str(tmp_path))["controller"]
    assert on.fl.lead and not off.fl.lead
    path = tmp_path / "controller.toml"
    path.write_text(dump_toml(off))
    assert load_config(type(off), path).fl.lead is False


def test_the_turn_share_of_the_speed_cap_reaches_the_controller_and_zero_turns_it_off(tmp_path):
    """`[controller] turn_share` (services/controller/turn_speed.py) reaches the controller service's config
    file and back; 0 turns the cap off, and a share beyond 1 is refused."""
    default = service_configs(parse_scenario(_minimal()), str(tmp_path))["controller"]
    off = service_configs(parse_scenario(_minimal(controller={"turn_share": 0.0})), str(tmp_path))["controller"]
    assert default.turn_share == TURN_SHARE and off.turn_share == 0.0
    path = tmp_path / "controller.toml"
    path.write_text(dump_toml(off))
    assert load_config(type(off), path).turn_share == 0.0
    with pytest.raises(ValueError, match="turn_share"):
        parse_scenario(_minimal(controller={"turn_share": 1.5}))
