"""The scenario file: one TOML file describes one experiment. A public interface (DESIGN.md):
the keys written there are accepted as written; everything else here is an extension."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Literal, get_args

from common.bins import BinPolicy
from common.camera import StereoConfig
from common.config import ConfigError, read_toml
from common.messages import check_name
from common.path import DEFAULT_SPACING_M
from common.robot import RobotParams, robot_from_preset
from common.typecheck import TypeCheckError, from_dict, to_dict
# the sections one service reads are that service's own settings types: each default lives there
from services.controller.fl import FLGains
from services.controller.ilc import ILCGains
from services.controller.settings import NMPCSettings
from services.controller.tracker import LOC_TIMEOUT_S, STOP_DECEL_MPS2
from services.controller.turn_speed import TURN_SHARE
from services.gp_store.config import FitConfig
from services.localizer.config import PoseSourceConfig
from services.scheduler.core import SchedulerParams

Algorithm = Literal["fl", "ilc", "lb-nmpc", "mm-lb-nmpc", "c-lb-nmpc", "rc-lb-nmpc"]
ALGORITHMS: tuple[str, ...] = get_args(Algorithm)   # each has a steering law: services/controller/registry.py
_FL = FLGains()
_POSE = PoseSourceConfig()
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
    vertex_spacing_m: float = DEFAULT_SPACING_M
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
    """[localization]: the source, and the `pose` source's errors (services/localizer/config.py)."""
    source: Literal["vision", "pose"] = "pose"
    noise_m: float = _POSE.noise_m
    noise_heading_deg: float = _POSE.noise_heading_deg
    noise_tau_s: float = _POSE.noise_tau_s
    jitter_m: float = _POSE.jitter_m
    delay_s: float = _POSE.delay_s
    dropout_prob: float = _POSE.dropout_prob
    dropout_s: float = _POSE.dropout_s
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
class ControllerSection:
    algorithm: Algorithm = "fl"
    horizon: int = 10
    fl_gamma1: float = _FL.gamma1   # eq. 3.5 lateral gain (1/s^2)
    fl_gamma2: float = _FL.gamma2   # eq. 3.5 heading gain (1/s)
    curvature_feedforward: bool = _FL.curvature_feedforward
    fl_lead: bool = _FL.lead        # FL and ILC: eq. 3.5 at the errors the drive's lag leads to (fl.py)
    loc_timeout_s: float = LOC_TIMEOUT_S      # stop when the newest estimate is older than this
    stop_decel_mps2: float = STOP_DECEL_MPS2  # gentle deceleration into the end of the route
    # the speed is capped where the route's turn takes more than this share of the robot's turn at its
    # limit (services/controller/turn_speed.py); 0: no cap
    turn_share: float = TURN_SHARE
    # the taught heading is averaged over this much route into the reference the controller follows
    # (common/path.py); unset: C-/RC-LB-NMPC on a car-like robot its turning radius, else none
    route_heading_window_m: float | None = None
    ilc: ILCGains = field(default_factory=ILCGains)
    nmpc: NMPCSettings = field(default_factory=NMPCSettings)    # its horizon is controller.horizon

    def __post_init__(self):
        if self.horizon < 1:
            raise ValueError("horizon must be >= 1")
        if self.fl_gamma1 <= 0 or self.fl_gamma2 <= 0 or self.loc_timeout_s <= 0 or self.stop_decel_mps2 <= 0:
            raise ValueError("fl_gamma1, fl_gamma2, loc_timeout_s and stop_decel_mps2 must be > 0")
        if self.route_heading_window_m is not None and not self.route_heading_window_m >= 0:
            raise ValueError("route_heading_window_m must be >= 0 (0: the taught heading as it is)")
        if not 0.0 <= self.turn_share <= 1.0:
            raise ValueError("turn_share must be in [0, 1] (0: no cap on the speed from the robot's turn)")


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
class SchedulerSection(SchedulerParams):
    """[scheduler]: thesis chapter 4, the scheduler's own parameters (services/scheduler/core.py), and
    whether it runs at all."""
    enabled: bool = False


@dataclass(frozen=True, kw_only=True)
class StoreSection(BinPolicy):
    """[store]: experience management (thesis 5.3.2, common/bins.py) and offline GP fitting (5.2.3)."""
    fit_restarts: int = FitConfig.restarts
    fit_max_points: int = FitConfig.max_points

    def __post_init__(self):
        super().__post_init__()
        if self.fit_restarts < 1 or self.fit_max_points < 10:
            raise ValueError("fit_restarts >= 1 and fit_max_points >= 10 required")

    def bins(self) -> BinPolicy:
        return BinPolicy(v_bin_mps=self.v_bin_mps, c_bin=self.c_bin, c_vertex=self.c_vertex,
                         c_velocity=self.c_velocity)


@dataclass(frozen=True, kw_only=True)
class TrialsSection:
    count: int = 1
    speed: float = 0.5
    speeds: list[float] | None = None
    learning: bool = True
    # the teach pass's disturbance observations are the first experiences (GP laws): trial 1 then knows
    # the slopes and slip the teach pass met; false: trial 1 starts from nothing (the thesis's first trial)
    learn_from_teach: bool = True
    start_offset_m: float = 0.0       # lateral offset of the robot at the start of each repeat
    start_offset_deg: float = 0.0
    time_limit_factor: float = 3.0    # a trial is aborted after this many times its nominal time
    #                                   (the route at the slower of the trial speed and the teach speed)

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
    # wall time to wait for a tick's answer before stepping without it: a guard against a hung service,
    # not a deadline (a loaded machine can take seconds per step; stepping early makes the run another run)
    lockstep_timeout_s: float = 30.0

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
    if "horizon" in ((data.get("controller") or {}).get("nmpc") or {}):
        raise ConfigError(f"{where}: controller.nmpc.horizon: set the horizon as controller.horizon")
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
