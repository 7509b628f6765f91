"""Turn a scenario into one typed config per service, written as TOML next to the run's outputs."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from common.config import dump_toml
from common.typecheck import to_dict
from common.scenario import ConstraintsSection, Scenario
from services.bridge.config import BridgeConfig, ClockConfig, TeachConfig
from services.controller.config import ControllerConfig, CorridorConfig, LimitsConfig, StoreClientConfig
from services.controller.fl import FLGains
from services.gp_store.config import FitConfig, StoreConfig
from services.scheduler.config import SchedulerConfig
from services.scheduler.core import SchedulerParams
from services.localizer.config import LocalizerConfig, PoseSourceConfig
from services.localizer.vision.settings import VisionSettings


def service_configs(sc: Scenario, data_dir: str | Path) -> dict[str, object]:
    rp = sc.robot.params
    robot = sc.robot.name
    bridge = BridgeConfig(
        robot_name=robot, backend="sim", seed=sc.seed, robot=rp, terrain=list(sc.terrain),
        teach=TeachConfig(waypoints=list(sc.path.waypoints), loop=sc.path.loop,
                          corner_radius_m=sc.path.corner_radius_m, speed_mps=sc.path.teach_speed_mps),
        clock=ClockConfig(mode=sc.sim.clock, period_s=sc.sim.period_s, physics_substeps=sc.sim.physics_substeps,
                          watchdog_s=sc.sim.watchdog_s, lockstep_timeout_s=sc.sim.lockstep_timeout_s),
        start_offset_m=sc.trials.start_offset_m, start_offset_deg=sc.trials.start_offset_deg,
        stereo=sc.localization.camera if sc.localization.source == "vision" else None)
    loc = sc.localization
    localizer = LocalizerConfig(
        robot_name=robot, source=loc.source, seed=sc.seed, data_dir=str(data_dir), period_s=sc.sim.period_s,
        vertex_spacing_m=sc.path.vertex_spacing_m,
        vision=VisionSettings(keyframe_dist_m=sc.path.vertex_spacing_m),   # keyframes are the route's vertices
        pose=PoseSourceConfig(noise_m=loc.noise_m, noise_heading_deg=loc.noise_heading_deg,
                              noise_tau_s=loc.noise_tau_s, jitter_m=loc.jitter_m, delay_s=loc.delay_s,
                              dropout_prob=loc.dropout_prob, dropout_s=loc.dropout_s, jumps=list(loc.jumps)))
    ctl = sc.controller
    controller = ControllerConfig(
        robot_name=robot, algorithm=ctl.algorithm, clock_mode=sc.sim.clock, period_s=sc.sim.period_s,
        loc_timeout_s=ctl.loc_timeout_s, stop_decel_mps2=ctl.stop_decel_mps2, turn_share=ctl.turn_share,
        route_heading_window_m=ctl.route_heading_window_m,
        limits=LimitsConfig(v_max_mps=rp.v_max_mps, w_max_radps=rp.w_max_radps,
                            max_curvature_per_m=rp.max_curvature if rp.drive == "ackermann" else 0.0,
                            curvature_rate_max_per_ms=rp.max_curvature_rate,
                            decel_max_mps2=rp.decel_max_mps2),
        fl=FLGains(ctl.fl_gamma1, ctl.fl_gamma2, ctl.curvature_feedforward, ctl.fl_lead),
        ilc=ctl.ilc,
        nmpc=replace(ctl.nmpc, horizon=ctl.horizon),
        store=StoreClientConfig(v_bin_mps=sc.store.v_bin_mps, c_vertex=sc.store.c_vertex,
                                c_velocity=sc.store.c_velocity, learn_from_teach=sc.trials.learn_from_teach),
        corridor=CorridorConfig(lateral_m=sc.constraints.lateral_m, heading_deg=sc.constraints.heading_deg,
                                segments=[list(map(float, seg)) for seg in sc.constraints.segments]),
        data_dir=str(Path(data_dir) / "controller"))
    st = sc.store
    gp_store = StoreConfig(
        name="store1", db_path=str(Path(data_dir) / "experiences.db"), paths=["*"],
        bins=st.bins(),
        # the experiment runner asks for a fit after every trial and waits for it: no automatic fits
        fit=FitConfig(restarts=st.fit_restarts, max_points=st.fit_max_points, seed=sc.seed, auto_after_trial=False))
    configs = {"bridge": bridge, "localizer": localizer, "controller": controller, "gp_store": gp_store}
    if sc.scheduler.enabled:
        params = {k: v for k, v in to_dict(sc.scheduler).items() if k != "enabled"}
        params["v_max"] = min(params["v_max"], rp.v_max_mps)    # the robot's own limit is an a-priori one
        # the robot's turn-rate limit, for the scheduler's guard; a w_max written in [scheduler] is a ceiling
        params["w_max"] = rp.w_max_radps if params.get("w_max") is None else min(params["w_max"], rp.w_max_radps)
        # ... and an Ackermann's curvature limit (G8); a kappa_max written in [scheduler] is a ceiling too
        k_robot = rp.max_curvature if math.isfinite(rp.max_curvature) else None
        k_set = params.get("kappa_max")
        params["kappa_max"] = k_robot if k_set is None else (k_set if k_robot is None else min(k_set, k_robot))
        # the corridor is an a-priori limit too: errors the scheduler tolerates (up to its deadband) stay in it
        lat_m, head_deg = narrowest_corridor(sc.constraints)
        params["lambda_L"] = min(params["lambda_L"], lat_m / params["lambda_db"])
        params["lambda_H"] = min(params["lambda_H"], head_deg / params["lambda_db"])
        configs["scheduler"] = SchedulerConfig(name="scheduler1", db_path=str(Path(data_dir) / "schedules.db"),
                                               params=SchedulerParams(**params), auto_after_trial=False)
    return configs


def narrowest_corridor(c: ConstraintsSection) -> tuple[float, float]:
    """(half-width m, heading limit deg) of the narrowest stretch of the corridor."""
    lat = min([c.lateral_m] + [min(seg[2], -seg[3]) for seg in c.segments if min(seg[2], -seg[3]) > 0])
    return lat, min([c.heading_deg] + [seg[4] for seg in c.segments])


def write_service_configs(configs: dict[str, object], directory: str | Path) -> dict[str, Path]:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, cfg in configs.items():
        paths[name] = directory / f"{name}.toml"
        paths[name].write_text(f"# generated from the scenario by lbc; one typed config per service\n{dump_toml(cfg)}")
    return paths
