"""Typed configuration of the controller service."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from common.bins import BinPolicy
from services.controller.fl import FLGains
from services.controller.ilc import ILCGains
from services.controller.settings import NMPCSettings
from services.controller.tracker import LOC_TIMEOUT_S, STOP_DECEL_MPS2
from services.controller.turn_speed import TURN_SHARE


_BINS = BinPolicy()


@dataclass(frozen=True, kw_only=True)
class LimitsConfig:
    v_max_mps: float
    w_max_radps: float
    max_curvature_per_m: float = 0.0   # 0 = no curvature limit (skid-steer); Ackermann: tan(steer_max)/L
    curvature_rate_max_per_ms: float = 0.0   # Ackermann: steering rate / L, 1/(m s); 0 = none (skid-steer)
    decel_max_mps2: float = 0.0        # hardest braking of a safety stop, which steers along the route; 0: at once


@dataclass(frozen=True, kw_only=True)
class StoreClientConfig:
    """Experiences out, local windows and hyperparameters in (thesis 5.3.2 window sizes, common/bins.py)."""
    enabled: bool = True
    v_bin_mps: float = _BINS.v_bin_mps
    c_vertex: int = _BINS.c_vertex
    c_velocity: int = _BINS.c_velocity
    lookahead_vertices: int = 20
    resend_after_s: float = 2.0
    ack_timeout_s: float = 10.0   # at the end of a trial, wait this long for the store's acknowledgements
    learn_from_teach: bool = True  # store the teach pass's disturbance observations as trial 0's experiences

    def bins(self) -> BinPolicy:
        """The window geometry (c_bin is the store's business)."""
        return BinPolicy(v_bin_mps=self.v_bin_mps, c_vertex=self.c_vertex, c_velocity=self.c_velocity)


@dataclass(frozen=True, kw_only=True)
class CorridorConfig:
    """Thesis 7.2's tracking limits: the scenario's [constraints]."""
    lateral_m: float = 0.3
    heading_deg: float = 15.0
    segments: list[list[float]] = field(default_factory=list)   # [from_m, to_m, left_m, right_m, heading_deg]


@dataclass(frozen=True, kw_only=True)
class ControllerConfig:
    robot_name: str
    algorithm: str = "fl"
    clock_mode: Literal["lockstep", "realtime"] = "lockstep"
    period_s: float = 0.1
    loc_timeout_s: float = LOC_TIMEOUT_S
    stop_decel_mps2: float = STOP_DECEL_MPS2
    # laws at a fixed speed: the share of the robot's turn the route's may take (turn_speed.py); 0: no cap
    turn_share: float = TURN_SHARE
    route_timeout_s: float = 5.0
    limits: LimitsConfig
    fl: FLGains = field(default_factory=FLGains)
    ilc: ILCGains = field(default_factory=ILCGains)
    nmpc: NMPCSettings = field(default_factory=NMPCSettings)
    store: StoreClientConfig = field(default_factory=StoreClientConfig)
    corridor: CorridorConfig = field(default_factory=CorridorConfig)
    data_dir: str = ""   # where learned feedforwards (ILC) are kept, one file per route
    # the taught heading is averaged over this much route into the reference the controller follows
    # (common/path.py); None: a corridor law's on a car-like robot, its turning radius; else none
    route_heading_window_m: float | None = None

    def __post_init__(self):
        if self.route_heading_window_m is not None and not self.route_heading_window_m >= 0:
            raise ValueError("route_heading_window_m must be >= 0 (0: the taught heading as it is)")
        if not 0.0 <= self.turn_share <= 1.0:
            raise ValueError("turn_share must be in [0, 1] (0: no cap on the speed from the robot's turn)")

    def heading_window_m(self, corridor_law: bool) -> float:
        """The route heading window in use. A car-like robot turns its heading by at most a radian within
        its turning radius: the teach pass's wiggles shorter than that (its yaw on rough ground) hold its
        steering at the limit both ways. A corridor law (C-, RC-LB-NMPC) is asked to stay inside the
        corridor, not on those few centimetres, so by default it follows their mean; the other laws track
        the taught route as it is."""
        if self.route_heading_window_m is not None:
            return self.route_heading_window_m
        k = self.limits.max_curvature_per_m
        return 1.0 / k if corridor_law and k > 0 else 0.0
