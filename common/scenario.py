"""The scenario file: one TOML file describes one experiment. A public interface (DESIGN.md):
the keys written there are accepted as written; everything else here is an extension."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Literal

from common.camera import StereoConfig
from common.config import ConfigError, read_toml
from common.messages import check_name
from common.robot import RobotParams, robot_from_preset
from common.typecheck import TypeCheckError, from_dict, to_dict

ALGORITHMS = ("fl", "ilc", "lb-nmpc", "mm-lb-nmpc", "c-lb-nmpc", "rc-lb-nmpc")
Algorithm = Literal["fl", "ilc", "lb-nmpc", "mm-lb-nmpc", "c-lb-nmpc", "rc-lb-nmpc"]
TerrainKind = Literal["side_slope", "slip", "rough", "rut"]

# keys each terrain kind takes besides kind/center/radius_m, with defaults where optional
_TERRAIN_KEYS: dict[str, dict[str, float | None]] = {
    "side_slope": {"slope_deg": None, "downhill_deg": None},
    "slip": {"traction": None},
    "rough": {"amplitude": None},
    "rut": {"depth_m": 0.0, "growth_m_per_pass": 0.01, "max_depth_m": 0.1},
}


@dataclass(frozen=True, kw_only=True)
class RobotSection:
    preset: str
    name: str
    params: RobotParams


@dataclass(frozen=True, kw_only=True)
class PathSection:
    waypoints: list[tuple[float, float]]
    loop: bool = False
    vertex_spacing_m: float = 0.25
    teach_speed_mps: float = 0.5
    corner_radius_m: float = 3.0

    def __post_init__(self):
        if len(self.waypoints) < 2:
            raise ValueError("waypoints: need at least 2 points")
        if self.vertex_spacing_m <= 0 or self.teach_speed_mps <= 0 or self.corner_radius_m <= 0:
            raise ValueError("vertex_spacing_m, teach_speed_mps and corner_radius_m must be > 0")


@dataclass(frozen=True, kw_only=True)
class TerrainPatch:
    """A round patch of terrain. side_slope: tilt `slope_deg` falling towards `downhill_deg`
    (world frame, counter-clockwise from +x); slip: `traction` in (0, 1] scales achieved speeds;
    rough: `amplitude` = peak yaw-rate disturbance (rad/s) at 1 m/s; rut: `depth_m` grows by
    `growth_m_per_pass` with every trial that crosses it, up to `max_depth_m`."""
    kind: TerrainKind
    center: tuple[float, float]
    radius_m: float
    slope_deg: float | None = None
    downhill_deg: float | None = None
    traction: float | None = None
    amplitude: float | None = None
    depth_m: float | None = None
    growth_m_per_pass: float | None = None
    max_depth_m: float | None = None

    def __post_init__(self):
        if self.radius_m <= 0:
            raise ValueError("radius_m must be > 0")
        own = _TERRAIN_KEYS[self.kind]
        for name in ("slope_deg", "downhill_deg", "traction", "amplitude", "depth_m", "growth_m_per_pass",
                     "max_depth_m"):
            value = getattr(self, name)
            if name not in own and value is not None:
                raise ValueError(f"key {name!r} does not apply to a {self.kind} patch (it takes {list(own)})")
            if name in own and value is None:
                if own[name] is None:
                    raise ValueError(f"a {self.kind} patch needs {name!r}")
                object.__setattr__(self, name, own[name])
        if self.kind == "slip" and not 0.0 < self.traction <= 1.0:
            raise ValueError("traction must be in (0, 1]")
        if self.kind == "side_slope" and not 0.0 <= self.slope_deg < 45.0:
            raise ValueError("slope_deg must be in [0, 45)")


@dataclass(frozen=True, kw_only=True)
class LocalizationSection:
    source: Literal["vision", "pose"] = "pose"
    noise_m: float = 0.01           # std of the (slowly wandering) position error
    noise_heading_deg: float = 0.3
    noise_tau_s: float = 1.0        # its correlation time
    jitter_m: float = 0.002         # independent frame-to-frame position error
    delay_s: float = 0.0
    dropout_prob: float = 0.0       # chance per tick that a dropout starts
    dropout_s: float = 0.3          # length of each dropout
    # teach-pass failures (thesis 5.4.5): [at_m, length_m, lateral_m] stretches of the route where the
    # estimate is shifted sideways by lateral_m although the robot does not move (every trial alike)
    jumps: list[tuple[float, float, float]] = field(default_factory=list)
    # run.mcap keeps one stereo frame in this many (a 640x480 pair is 0.6 MB; ten a second would make
    # gigabytes); 1 records every frame
    record_stereo_every: int = 50
    # source = "vision": the simulated stereo camera the bridge renders (the noise, delay, dropout and
    # jump keys above belong to the pose source; vision has whatever errors its images give it)
    camera: StereoConfig = field(default_factory=StereoConfig)

    def __post_init__(self):
        if min(self.noise_m, self.noise_heading_deg, self.noise_tau_s, self.jitter_m, self.delay_s,
               self.dropout_s) < 0:
            raise ValueError("noise, jitter, correlation time, delay and dropout lengths must be >= 0")
        if not 0.0 <= self.dropout_prob <= 1.0:
            raise ValueError("dropout_prob must be in [0, 1]")
        if self.record_stereo_every < 1:
            raise ValueError("record_stereo_every must be >= 1")
        if any(length <= 0 for _, length, _ in self.jumps):
            raise ValueError("jumps: each [at_m, length_m, lateral_m] needs length_m > 0")


@dataclass(frozen=True, kw_only=True)
class ILCSection:
    """[controller.ilc]: eq. 3.14-3.16 (gains in rad/s per m and rad/s, lookahead in vertices)."""
    gamma_L: float = 0.8
    gamma_H: float = 0.4
    gamma_u: float = 1.0
    lookahead: int = 4
    ic_vertices: int = 8


@dataclass(frozen=True, kw_only=True)
class NMPCSection:
    """[controller.nmpc]: cost weights (eq. 5.16) and solver settings; the horizon is controller.horizon."""
    q_along: float = 1.0
    q_lat: float = 40.0
    q_head: float = 10.0
    r_w: float = 0.2
    r_dw: float = 1.0
    q_terminal: float = 100.0
    lookahead_m: float = 1.5
    max_iter: int = 10
    max_evals: int = 6
    delay_compensation: bool = True
    # MM-, C- and RC-LB-NMPC (chapters 6 and 7); see services/controller/nmpc.py NMPCSettings
    sp_gamma: float = 2.0
    mm_sigmas: float = 3.0
    alpha: float = 3.0
    r_v: float = 4.0
    r_dv: float = 2.0
    v_min_mps: float = 0.05
    slack_weight: float = 2000.0
    sqp_iter: int = 4
    prior_std_base: tuple[float, float, float] = (0.001, 0.002, 0.003)
    prior_std_per_mps: tuple[float, float, float] = (0.004, 0.008, 0.008)
    prior_std_per_radps: tuple[float, float, float] = (0.002, 0.004, 0.015)
    min_band_fraction: float = 0.2
    process_std: tuple[float, float, float] = (0.0005, 0.001, 0.002)
    actuator_tau_s: tuple[float, float] = (0.0, 0.0)   # the drive's lag (v, w), s; 0 = eq. 5.26 as is
    crab_reference: bool = False    # with a learned model, the heading cost's reference is the learned crab


@dataclass(frozen=True, kw_only=True)
class ControllerSection:
    algorithm: Algorithm = "fl"
    horizon: int = 10
    fl_gamma1: float = 1.0          # eq. 3.5 lateral gain (1/s^2)
    fl_gamma2: float = 1.8          # eq. 3.5 heading gain (1/s)
    curvature_feedforward: bool = True
    loc_timeout_s: float = 0.5      # stop when the newest estimate is older than this
    stop_decel_mps2: float = 0.4    # gentle deceleration into the end of the route
    ilc: ILCSection = field(default_factory=ILCSection)
    nmpc: NMPCSection = field(default_factory=NMPCSection)

    def __post_init__(self):
        if self.horizon < 1:
            raise ValueError("horizon must be >= 1")
        if self.fl_gamma1 <= 0 or self.fl_gamma2 <= 0 or self.loc_timeout_s <= 0 or self.stop_decel_mps2 <= 0:
            raise ValueError("fl_gamma1, fl_gamma2, loc_timeout_s and stop_decel_mps2 must be > 0")


@dataclass(frozen=True, kw_only=True)
class ConstraintsSection:
    """The safety corridor (thesis 7.2): half-width and heading limit along the whole route, and
    optionally other limits over stretches: segments = [[from_m, to_m, left_m, right_m, heading_deg]]
    (right_m is the signed limit to the right, e.g. -0.2)."""
    lateral_m: float = 0.3
    heading_deg: float = 15.0
    segments: list[list[float]] = field(default_factory=list)

    def __post_init__(self):
        if self.lateral_m <= 0 or self.heading_deg <= 0:
            raise ValueError("lateral_m and heading_deg must be > 0")
        for seg in self.segments:
            if len(seg) != 5 or not (seg[2] > seg[3] and seg[4] > 0 and seg[1] >= seg[0]):
                raise ValueError("each segment is [from_m, to_m, left_m, right_m, heading_deg] with "
                                 "left_m > right_m, heading_deg > 0 and to_m >= from_m")


@dataclass(frozen=True, kw_only=True)
class SchedulerSection:
    """[scheduler]: thesis chapter 4 (names of table 5.1; defaults of its section 4.3.2). lambda_L in m,
    lambda_H in degrees, lambda_omega in rad/s, accelerations in m/s^2; the first and last start_m /
    end_m metres are limited to v_start / v_end (eq. 4.3)."""
    enabled: bool = False
    v_init: float = 0.5
    v_max: float = 2.0
    gamma1: float = 0.2
    gamma2: float = 0.24
    lambda_L: float = 0.15
    lambda_H: float = 10.0
    lambda_feat: float = 30.0
    lambda_omega: float = 1.0
    lambda_db: float = 1.1
    a_max: float = 0.2
    a_min: float = -0.05
    v_start: float = 0.4
    start_m: float = 5.0
    v_end: float = 0.4
    end_m: float = 5.0
    prune_min_m: float = 2.0
    use_all_trials: bool = False     # beyond the thesis (4.4): never raise a vertex to where it failed


@dataclass(frozen=True, kw_only=True)
class StoreSection:
    """Experience management (thesis 5.3.2, defaults of 5.4.2) and offline GP fitting (5.2.3)."""
    v_bin_mps: float = 0.25
    c_bin: int = 4
    c_vertex: int = 5
    c_velocity: int = 1
    fit_restarts: int = 3
    fit_max_points: int = 1000

    def __post_init__(self):
        if self.v_bin_mps <= 0 or self.c_bin < 1 or self.c_vertex < 0 or self.c_velocity < 0:
            raise ValueError("v_bin_mps > 0, c_bin >= 1, c_vertex >= 0, c_velocity >= 0 required")
        if self.fit_restarts < 1 or self.fit_max_points < 10:
            raise ValueError("fit_restarts >= 1 and fit_max_points >= 10 required")


@dataclass(frozen=True, kw_only=True)
class TrialsSection:
    count: int = 1
    speed: float = 0.5
    speeds: list[float] | None = None
    learning: bool = True
    start_offset_m: float = 0.0       # lateral offset of the robot at the start of each repeat
    start_offset_deg: float = 0.0
    time_limit_factor: float = 3.0    # a trial is aborted after this many times its nominal time

    def __post_init__(self):
        if self.count < 1:
            raise ValueError("count must be >= 1")
        if self.speeds is not None and len(self.speeds) != self.count:
            raise ValueError(f"speeds has {len(self.speeds)} entries for count = {self.count} trials")
        for v in [self.speed] + list(self.speeds or []):
            if v <= 0:
                raise ValueError("trial speeds must be > 0")

    def speed_of(self, trial: int) -> float:
        return self.speeds[trial - 1] if self.speeds else self.speed


@dataclass(frozen=True, kw_only=True)
class SimSection:
    clock: Literal["lockstep", "realtime"] = "lockstep"
    period_s: float = 0.1
    physics_substeps: int = 10
    watchdog_s: float = 0.3
    lockstep_timeout_s: float = 2.0   # wall time to wait for a command before stepping anyway

    def __post_init__(self):
        if self.period_s <= 0 or self.physics_substeps < 1 or self.watchdog_s <= 0 or self.lockstep_timeout_s <= 0:
            raise ValueError("period_s, physics_substeps, watchdog_s and lockstep_timeout_s must be positive")


@dataclass(frozen=True, kw_only=True)
class Scenario:
    name: str
    seed: int = 0
    robot: RobotSection
    path: PathSection
    terrain: list[TerrainPatch] = field(default_factory=list)
    localization: LocalizationSection = field(default_factory=LocalizationSection)
    controller: ControllerSection = field(default_factory=ControllerSection)
    constraints: ConstraintsSection = field(default_factory=ConstraintsSection)
    scheduler: SchedulerSection = field(default_factory=SchedulerSection)
    store: StoreSection = field(default_factory=StoreSection)
    trials: TrialsSection = field(default_factory=TrialsSection)
    sim: SimSection = field(default_factory=SimSection)

    def __post_init__(self):
        check_name("scenario name", self.name.replace(".", "_"))
        check_name("robot.name", self.robot.name)
        if self.seed < 0:
            raise ValueError("seed must be >= 0")

    @property
    def path_id(self) -> str:
        return self.name.replace(".", "_")


def parse_scenario(data: dict, where: str = "<scenario>") -> Scenario:
    data = dict(data)
    robot_table = dict(data.get("robot") or {})
    if "preset" not in robot_table:
        raise ConfigError(f"{where}: robot.preset: missing (husky | roc6 | grizzly | mats)")
    preset = robot_table.pop("preset")
    name = robot_table.pop("name", preset if isinstance(preset, str) else "robot")
    if not isinstance(preset, str):
        raise ConfigError(f"{where}: robot.preset: expected a string")
    params = robot_from_preset(preset, robot_table, "robot")
    data["robot"] = {"preset": preset, "name": name, "params": to_dict(params)}
    try:
        sc = from_dict(Scenario, data)
    except TypeCheckError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    written = {f"{table}.{k}" for table in ("trials", "scheduler") for k in data.get(table) or {}}
    _check_speed_limits(sc, written, "v_max_mps" in robot_table, where)
    return sc


def _check_speed_limits(sc: Scenario, written: set[str], limit_overridden: bool, where: str) -> None:
    """Speeds the robot cannot drive would only make every trial time out: refuse them here, each
    when written or used. scheduler.v_max is a ceiling, clamped to the robot's limit by the deployment
    (DESIGN.md's own example sets 2 m/s on a husky), so it stays accepted."""
    limit = sc.robot.params.v_max_mps
    sched = sc.scheduler
    used_speed = not sched.enabled and not sc.trials.speeds
    asked = [(f"trials.speeds[{i}]", v) for i, v in enumerate(sc.trials.speeds or [])]
    asked += [("trials.speed", sc.trials.speed)] if used_speed or "trials.speed" in written else []
    asked += [("scheduler.v_init", sched.v_init)] if sched.enabled or "scheduler.v_init" in written else []
    for name, v in asked:
        if v > limit:
            origin = "set in [robot]" if limit_overridden else f"of the {sc.robot.preset} preset"
            raise ConfigError(f"{where}: {name} = {v:g} m/s exceeds the robot's speed limit, v_max_mps = "
                              f"{limit:g} m/s ({origin})")


def load_scenario(path: str | FsPath) -> Scenario:
    data = read_toml(path)
    try:
        return parse_scenario(data, str(path))
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
