"""Typed bus messages. Field names carry units and frames; all stamps are robot-clock seconds.

Frames: `world` is the simulator's fixed frame (truth only); `odom` is the wheel-odometry frame;
`vertex` is the frame of a taught route vertex (x forward along the route, y to the left, z up),
so `T_vertex_robot` = (x_m, y_m, theta_rad) is the robot's SE(2) pose in the nearest vertex frame
(thesis fig. 2.5): y is the lateral error, theta the heading error.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import ClassVar, Literal

from common.codec import Message

NAME_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_name(kind: str, value: str) -> str:
    """Robot names and route ids become key-expression chunks: keep them plain."""
    if not NAME_RE.match(value):
        raise ValueError(f"{kind} {value!r} must be 1-64 characters of [A-Za-z0-9_-]")
    return value


ClockMode = Literal["lockstep", "realtime"]
TrialMode = Literal["idle", "teach", "repeat"]


@dataclass(frozen=True, kw_only=True)
class Clock(Message):
    """Published by the bridge once per control tick: the robot's time."""
    stamp_s: float
    tick: int
    period_s: float
    mode: ClockMode
    trial: int


@dataclass(frozen=True, kw_only=True)
class Odometry(Message):
    """Wheel odometry: what the wheels did, blind to slip."""
    stamp_s: float
    tick: int
    v_mps: float
    w_radps: float
    x_odom_m: float
    y_odom_m: float
    theta_odom_rad: float


ImageEncoding = Literal["mono8", "png"]


@dataclass(frozen=True, kw_only=True)
class StereoFrame(Message):
    """A rectified stereo pair with its calibration, stamped with the capture time.

    `encoding` "mono8": `left`/`right` are raw row-major uint8 of height x width; "png": each is a PNG
    file. Rectified pinhole model of thesis eq. 2.1-2.2 (left camera, x right, y down, z forward);
    `T_robot_camera` is the left camera's pose in the robot frame (4x4 row-major, metres)."""
    MAX_BYTES: ClassVar[int] = 4 * 1024 * 1024
    stamp_s: float
    tick: int
    trial: int
    width_px: int
    height_px: int
    encoding: ImageEncoding
    left: bytes
    right: bytes
    fu_px: float
    fv_px: float
    cu_px: float
    cv_px: float
    baseline_m: float
    T_robot_camera: tuple[float, ...]
    exposure_s: float

    def __post_init__(self):
        if len(self.T_robot_camera) != 16:
            raise ValueError("T_robot_camera must hold 16 values (4x4 row-major)")
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError("image size must be positive")
        if self.fu_px <= 0 or self.fv_px <= 0 or self.baseline_m <= 0:
            raise ValueError("focal lengths and baseline must be positive")
        if self.encoding == "mono8":
            n = self.width_px * self.height_px
            if len(self.left) != n or len(self.right) != n:
                raise ValueError(f"mono8 images must hold width*height = {n} bytes each, "
                                 f"got {len(self.left)} and {len(self.right)}")


@dataclass(frozen=True, kw_only=True)
class TruthPose(Message):
    """Simulator ground truth (sim backend only): pose in `world` and body velocity over ground."""
    stamp_s: float
    tick: int
    trial: int
    x_world_m: float
    y_world_m: float
    theta_world_rad: float
    v_mps: float
    w_radps: float
    lateral_slip_mps: float


# "vo": the vision localizer could not refine against the taught map this frame and carries its last
# fix forward on visual odometry alone, with a growing covariance (a pose, but a weaker one)
LocStatus = Literal["ok", "vo", "dropout", "lost", "initializing", "teach", "idle"]


@dataclass(frozen=True, kw_only=True)
class LocState(Message):
    """Localizer output, one per sensor tick. No pose unless status is 'ok' or 'vo' (never a made-up one);
    during teach ('teach') a source may give the pose relative to the newest vertex, which is not for
    tracking (the route is still being made) but lets the controller identify its nominal model.
    `cov_step_T_vertex_robot` is the covariance of the error of the motion between the estimate of
    capture tick k - 1 and this one (its error less the previous one's; vertex frame), which is what a
    one-period model residual sees of the localizer: far less than twice `cov_T_vertex_robot` where the
    error wanders slowly. None: the source does not know it."""
    SCHEMA_VERSION = 3
    stamp_s: float
    capture_stamp_s: float
    tick: int
    capture_tick: int
    trial: int
    path_id: str
    source: Literal["pose", "vision"]
    status: LocStatus
    reason: str
    vertex: int
    distance_m: float
    T_vertex_robot: tuple[float, float, float] | None
    cov_T_vertex_robot: tuple[float, ...] | None
    matched_features: int | None
    cov_step_T_vertex_robot: tuple[float, ...] | None = None

    def __post_init__(self):
        if self.has_pose and (self.T_vertex_robot is None or self.cov_T_vertex_robot is None):
            raise ValueError(f"status {self.status!r} requires T_vertex_robot and cov_T_vertex_robot")
        for name in ("cov_T_vertex_robot", "cov_step_T_vertex_robot"):
            cov = getattr(self, name)
            if cov is not None and len(cov) != 9:
                raise ValueError(f"{name} must hold 9 values (3x3 row-major)")
        if self.vertex < 0:
            raise ValueError("vertex must be >= 0")

    @property
    def has_pose(self) -> bool:
        return self.status in ("ok", "vo")


@dataclass(frozen=True, kw_only=True)
class VelocityCommand(Message):
    """Unicycle command in the robot frame; an Ackermann robot converts it itself (eq. 5.27)."""
    stamp_s: float
    tick: int
    trial: int
    v_mps: float
    w_radps: float
    source: str


# stopping: braking along the route after a safety stop (the command still steers), then stopped
ControllerState = Literal["idle", "waiting", "tracking", "holding", "stopping", "stopped", "finished", "error"]
# what held a tracking step's speed command below the asked speed: "" nothing; RC-LB-NMPC's speed ladder by the
# check its next faster rung failed ("ladder-lateral", "-heading", "-turn"; "-no-fit": no rung fits); the place
# cap from the latest pass's share of the corridor or of the steering margin; the turn the robot can make
# along the route (turn_speed.py); a heading error to turn away before the corridor's edge (tracker.py
# _recovery_cap); the robot's top speed; the slow-down into the end of the route
SpeedCause = Literal["", "ladder-lateral", "ladder-heading", "ladder-turn", "ladder-no-fit", "place-corridor",
                     "place-steering", "turn-cap", "recovery", "robot-limit", "route-end"]


@dataclass(frozen=True, kw_only=True)
class ControllerStatus(Message):
    """One per control step: what the controller saw, decided and how long it took."""
    SCHEMA_VERSION = 6
    stamp_s: float
    tick: int
    trial: int
    algorithm: str
    state: ControllerState
    reason: str
    path_id: str
    vertex: int
    distance_m: float
    lateral_m: float
    heading_rad: float
    v_cmd_mps: float
    w_cmd_radps: float
    solve_ms: float
    iterations: int
    loc_age_s: float
    rejected_msgs: int
    experiences_sent: int
    experiences_pending: int
    window_experiences: int
    hyper_version: int
    w_ff_radps: float                 # ILC feedforward of this step (0 for other laws)
    pred_x_m: list[float]             # predicted poses over the horizon (NMPC), in the route's frame
    pred_y_m: list[float]
    pred_theta_rad: list[float]
    # v2: the predicted uncertainty (MM/C/RC-LB-NMPC; 0 for other laws): the largest 1-sigma lateral and
    # heading spread over the horizon, and how the solver ended ("converged", "budget", "qp-failed", ...)
    sigma_lat_m: float
    sigma_head_rad: float
    solver_status: str
    # v3: the online check of the predicted spread (services/controller/calibration.py): its factor on each
    # step's predicted standard deviation, and the route-frame 1-sigma of each predicted pose as the law
    # used it (empty without a spread)
    spread_factors: list[float]
    pred_sigma_lat_m: list[float]
    pred_sigma_head_rad: list[float]
    # v4: learning switched off because the store's data is missing here (store unreachable): since when
    # (robot time; -1 while learning is on or not configured) and why; and, with a realtime clock, how late
    # this step started against its period (wall clock; 0 in lockstep)
    learning_off_since_s: float
    learning_note: str
    step_late_ms: float
    # v5: the speed the robot's turn allows here where it is below the asked one (0: it caps nothing here),
    # and the skid-steer's turn lost to skidding the controller has learned (services/controller/turn_speed.py)
    turn_cap_mps: float
    turn_loss_per_mps2: float
    # v6: what held the speed command below the asked speed this step (SpeedCause; "" nothing)
    speed_held_by: SpeedCause


@dataclass(frozen=True, kw_only=True)
class NominalModel(Message):
    """The controller's nominal model of one robot, identified from a teach pass (drive lags against
    the wheel odometry, the a-priori uncertainty from the model's residuals on that pass)."""
    SCHEMA_VERSION = 5    # v2: curvature_rate_max_per_ms; v3: turn_gain; v4: place_bin_m, place_spread_factors, place_speed_mps; v5: place_turn_share
    MAX_BYTES = 1024 * 1024   # a row of place factors per 2 m: a 1 km route's take ~140 kB
    stamp_s: float
    robot: str
    path_id: str                      # the teach pass it was identified on
    dt_s: float
    model_tag: str                    # the name experiences of this model carry (Experience.model)
    tau_v_s: float                    # first-order lag of each drive channel ...
    tau_w_s: float
    dead_time_v_s: float              # ... its dead time (whole periods) ...
    dead_time_w_s: float
    gain_v: float                     # ... its steady-state gain ...
    gain_w: float
    rate_limit_v_mps2: float | None   # ... and its acceleration limit (None: none seen); reported, not modelled
    rate_limit_w_radps2: float | None
    fit_rmse_v_mps: float             # one-step prediction error of the fits
    fit_rmse_w_radps: float
    samples_v: int
    samples_w: int
    actuator_tau_s: tuple[float, float]   # the lags the NMPC uses: lag + dead time per channel
    curvature_rate_max_per_ms: float      # Ackermann: the steering's rate limit the NMPC uses (0: none)
    turn_gain: float                      # the robot's turn rate over the drive's, against the localizer's heading
    turn_gain_std: float                  # its standard error (0: not identified, 1 kept)
    prior_std_base: tuple[float, float, float]       # uncertainty.PriorStd, body frame (along, lateral, heading)
    prior_std_per_mps: tuple[float, float, float]
    prior_std_per_radps: tuple[float, float, float]
    prior_scale: tuple[float, float, float]          # of the default prior's shape, from the teach residuals
    spread_factors: list[float]       # per horizon step, on the predicted spread, to start the online check from
    place_bin_m: float                # ... and per place_bin_m of the route from its start, per horizon step, the
    place_spread_factors: list[list[float]]   # factors the teach pass needed there (its memory of places)
    place_speed_mps: list[float]              # ... and the fastest it commanded there
    place_turn_share: list[float]             # ... and the largest share of its steering margin it took there
    residual_samples: int
    notes: list[str]                  # what could not be identified, and what was kept instead

    def __post_init__(self):
        check_name("robot", self.robot)
        check_name("path_id", self.path_id)
        check_name("model_tag", self.model_tag)
        if self.dt_s <= 0 or min(self.tau_v_s, self.tau_w_s, self.dead_time_v_s, self.dead_time_w_s,
                                 *self.actuator_tau_s, self.curvature_rate_max_per_ms, *self.prior_std_base,
                                 *self.prior_std_per_mps, *self.prior_std_per_radps, self.turn_gain_std) < 0:
            raise ValueError("dt_s > 0 and non-negative time constants, dead times and prior std required")
        if not self.turn_gain > 0:
            raise ValueError("turn_gain must be > 0")
        if not self.place_bin_m > 0 or any(len(r) != len(self.spread_factors) or min(r, default=1.0) < 1.0
                                           for r in self.place_spread_factors) \
                or len(self.place_speed_mps) != len(self.place_spread_factors) or min(self.place_speed_mps, default=0) < 0 \
                or len(self.place_turn_share) != len(self.place_speed_mps) \
                or not all(0.0 <= x <= 1.0 for x in self.place_turn_share):
            raise ValueError("place_bin_m > 0, place spread factors >= 1 (as many per place as spread_factors), "
                             "a speed >= 0 and a steering margin share in [0, 1] for each place")


@dataclass(frozen=True, kw_only=True)
class BridgeStatus(Message):
    """One per tick from the bridge: run state and the safety watchdog."""
    stamp_s: float
    tick: int
    trial: int
    mode: TrialMode
    running: bool
    watchdog_tripped: bool
    cmd_age_s: float
    v_cmd_applied_mps: float
    w_cmd_applied_radps: float
    rejected_msgs: int


TrialEventKind = Literal["started", "ended"]


# the bridge's reason for ending a lockstep repeat once the controller reported the route finished and
# the robot came to rest: a completed trial, whichever of that status and this event reaches a listener first
ENDED_AT_ROUTE_END = "end of route, at rest"
# a repeat whose controller has reported itself stopped (a safety stop) for this long, robot time, ends
# with CONTROLLER_STOPPED and the controller's reason: the runner's rule, and in lockstep the bridge's at
# the very tick, so that where the trial ends does not depend on when a stop request reaches the bridge
STOPPED_ENDS_TRIAL_S = 5.0
CONTROLLER_STOPPED = "controller stopped"


@dataclass(frozen=True, kw_only=True)
class TrialEvent(Message):
    SCHEMA_VERSION = 2    # v2: unanswered_ticks
    stamp_s: float
    trial: int
    mode: TrialMode
    event: TrialEventKind
    reason: str
    path_id: str
    # lockstep: ticks of the trial stepped without their answer (timeout); > 0 means the run depended on
    # the wall clock, so another run of its seed can differ
    unanswered_ticks: int = 0


ControlAction = Literal["prepare", "start", "stop", "ping"]


@dataclass(frozen=True, kw_only=True)
class ControlRequest(Message):
    """Trial control from the experiment runner or the CLI, sent as a query to each service.

    prepare: get ready for `mode` on `path_id` (teach records it, repeat loads it); start: the
    bridge starts the clock; stop: end the trial (teach: the localizer saves the route, a closed
    loop if `loop`). `max_duration_s` <= 0 means no time limit.
    """
    stamp_s: float
    action: ControlAction
    mode: TrialMode
    trial: int
    path_id: str
    speed_mps: float
    max_duration_s: float
    learning: bool
    loop: bool
    schedule: bool = False          # repeat at the scheduler's latest schedule for the route

    def __post_init__(self):
        check_name("path_id", self.path_id)
        if self.speed_mps < 0 or self.trial < 0:
            raise ValueError("speed_mps and trial must be >= 0")


@dataclass(frozen=True, kw_only=True)
class ControlReply(Message):
    stamp_s: float
    service: str
    ok: bool
    detail: str


@dataclass(frozen=True, kw_only=True)
class RouteMsg(Message):
    """A taught route: vertex poses in the frame the route was taught in (its first vertex)."""
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024
    path_id: str
    loop: bool
    vertex_spacing_m: float
    x_m: list[float]
    y_m: list[float]
    theta_rad: list[float]
    taught_by: str
    stamp_s: float

    def __post_init__(self):
        check_name("path_id", self.path_id)
        if not (len(self.x_m) == len(self.y_m) == len(self.theta_rad)):
            raise ValueError("x_m, y_m and theta_rad must have equal lengths")
        if len(self.x_m) < 2:
            raise ValueError("a route needs at least 2 vertices")
        if self.vertex_spacing_m <= 0:
            raise ValueError("vertex_spacing_m must be > 0")


@dataclass(frozen=True, kw_only=True)
class AliveEvent(Message):
    """A liveliness token appearing or disappearing, as recorded by the experiment runner."""
    stamp_s: float
    alive: bool


# --- experiences and the store (thesis 5.2.2, 5.3.2) ----------------------------------------------
A_DIM = 9   # disturbance dependency a_k (eq. 5.15), see services/controller/experience.py
G_DIM = 3   # disturbance g (eq. 5.17): body-frame x, y and heading residuals of one control period


def _check_vector(name: str, values, n: int) -> None:
    if len(values) != n:
        raise ValueError(f"{name} must hold {n} values, got {len(values)}")


@dataclass(frozen=True, kw_only=True)
class Experience(Message):
    """One disturbance observation g(a) (eq. 5.17) at route `vertex` under commanded speed `v_cmd_mps`."""
    stamp_s: float
    robot: str
    trial: int
    path_id: str
    seq: int
    vertex: int
    v_cmd_mps: float
    a: tuple[float, ...]
    g: tuple[float, ...]
    # the nominal model g is the residual of (services/controller/experience.py: model_tag); the store
    # keeps each model's experiences apart: a retuned drive lag makes the old residuals wrong. "": unknown
    # (recorded before tags existed)
    model: str = ""

    def __post_init__(self):
        check_name("robot", self.robot)
        check_name("path_id", self.path_id)
        if self.model:
            check_name("model", self.model)
        _check_vector("a", self.a, A_DIM)
        _check_vector("g", self.g, G_DIM)
        if self.vertex < 0 or self.seq < 0:
            raise ValueError("vertex and seq must be >= 0")


@dataclass(frozen=True, kw_only=True)
class ExperienceBatch(Message):
    """Experiences from one producer (`source`, unique per process run); the store acknowledges each
    `seq` once it is durably committed, and the producer re-sends what was not acknowledged."""
    MAX_BYTES: ClassVar[int] = 4 * 1024 * 1024
    stamp_s: float
    robot: str
    source: str
    experiences: list[Experience]

    def __post_init__(self):
        check_name("source", self.source)


@dataclass(frozen=True, kw_only=True)
class ExperienceAck(Message):
    MAX_BYTES: ClassVar[int] = 4 * 1024 * 1024
    stamp_s: float
    store: str
    source: str
    seqs: list[int]
    rejected: list[int]
    reason: str


@dataclass(frozen=True, kw_only=True)
class ExperienceWindow(Message):
    """A store's answer to a window query: every experience in the bins of vertices
    [vertex_lo, vertex_hi] x speed bins [bin_lo, bin_hi]; `a` and `g` are row-major float64."""
    MAX_BYTES: ClassVar[int] = 16 * 1024 * 1024
    stamp_s: float
    path_id: str
    vertex_lo: int
    vertex_hi: int
    bin_lo: int
    bin_hi: int
    v_bin_mps: float
    vertices: list[int]
    speed_bins: list[int]
    a_f64: bytes
    g_f64: bytes

    def __post_init__(self):
        n = len(self.vertices)
        if len(self.speed_bins) != n or len(self.a_f64) != 8 * A_DIM * n or len(self.g_f64) != 8 * G_DIM * n:
            raise ValueError(f"window arrays do not hold {n} experiences of {A_DIM}+{G_DIM} float64")
        import numpy as np  # local: messages stay importable without numpy-heavy modules
        if not (np.all(np.isfinite(np.frombuffer(self.a_f64))) and np.all(np.isfinite(np.frombuffer(self.g_f64)))):
            raise ValueError("window holds non-finite values")


@dataclass(frozen=True, kw_only=True)
class HyperDim(Message):
    lengthscales: list[float]
    signal_std: float
    noise_std: float

    def __post_init__(self):
        _check_vector("lengthscales", self.lengthscales, A_DIM)
        if min(self.lengthscales) <= 0 or self.signal_std <= 0 or self.noise_std <= 0:
            raise ValueError("hyperparameters must be > 0")


@dataclass(frozen=True, kw_only=True)
class HyperMsg(Message):
    """Versioned GP hyperparameters of one route, one entry per output dimension of g."""
    SCHEMA_VERSION = 2    # v2: note
    stamp_s: float
    path_id: str
    version: int
    n_used: int
    n_total: int
    fit_s: float
    lml: list[float]
    dims: list[HyperDim]
    # the nominal model of the experiences they were fitted on (Experience.model): a controller uses
    # only its own model's
    model: str = ""
    # what the store changed after the likelihood's fit, and why (services/gp_store/authority.py); "": nothing
    note: str = ""

    def __post_init__(self):
        _check_vector("dims", self.dims, G_DIM)
        if self.model:
            check_name("model", self.model)


@dataclass(frozen=True, kw_only=True)
class PathStats(Message):
    path_id: str
    retained: int
    ingested: int
    bins: int
    hyper_version: int


@dataclass(frozen=True, kw_only=True)
class StoreStats(Message):
    stamp_s: float
    store: str
    db_path: str
    paths: list[PathStats]


# --- speed schedules (thesis chapter 4) -------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class SpeedSchedule(Message):
    """Scheduled speed at every vertex of a route. Version 1 is the first trial's (v_init); each later
    one was computed from one robot's trial (`based_on_robot`, `based_on_trial`)."""
    MAX_BYTES: ClassVar[int] = 8 * 1024 * 1024
    stamp_s: float
    path_id: str
    version: int
    based_on_robot: str
    based_on_trial: int
    v_mps: list[float]
    decisions: list[int]            # eq. 4.2 per vertex: +1 increase, 0 keep, -1 decrease
    notes: list[str]

    def __post_init__(self):
        check_name("path_id", self.path_id)
        if len(self.decisions) != len(self.v_mps) or not self.v_mps:
            raise ValueError("v_mps and decisions must be non-empty and of equal length")
        if min(self.v_mps) <= 0:
            raise ValueError("scheduled speeds must be > 0")


@dataclass(frozen=True, kw_only=True)
class ScheduleUpdate(Message):
    """Ask the scheduler for the next schedule from a finished trial of `robot` on `path_id`."""
    stamp_s: float
    path_id: str
    robot: str
    trial: int

    def __post_init__(self):
        check_name("path_id", self.path_id)
        check_name("robot", self.robot)


@dataclass(frozen=True, kw_only=True)
class CorridorUpdate(Message):
    """Narrow or widen the safety corridor of a route over [from_m, to_m] (a guidance module or an
    operator); the constrained laws (C-/RC-LB-NMPC) respect it from their next step on."""
    stamp_s: float
    path_id: str
    from_m: float
    to_m: float
    left_m: float                   # largest lateral error allowed to the left of the route (+)
    right_m: float                  # ... and to the right (negative, or positive if the corridor is offset)
    heading_rad: float

    def __post_init__(self):
        check_name("path_id", self.path_id)
        if not (self.left_m > self.right_m and self.heading_rad > 0 and self.to_m >= self.from_m):
            raise ValueError("a corridor needs left_m > right_m, heading_rad > 0 and to_m >= from_m")


ALL_MESSAGES: tuple[type[Message], ...] = (
    Clock, Odometry, TruthPose, LocState, VelocityCommand, ControllerStatus, BridgeStatus,
    TrialEvent, ControlRequest, ControlReply, RouteMsg, AliveEvent, Experience, ExperienceBatch, ExperienceAck,
    ExperienceWindow, HyperDim, HyperMsg, PathStats, StoreStats, SpeedSchedule, ScheduleUpdate,
    CorridorUpdate,
)

# Zenoh reassembles a fragmented message up to this size and drops larger ones before they take memory
# (transport/link/rx/max_message_size): the largest message the codec would accept, plus framing
LARGEST_MESSAGE_BYTES = max(cls.MAX_BYTES for cls in (*ALL_MESSAGES, StereoFrame, NominalModel)) + 64 * 1024
