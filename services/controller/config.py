"""Typed configuration of the controller service."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True, kw_only=True)
class LimitsConfig:
    v_max_mps: float
    w_max_radps: float
    max_curvature_per_m: float = 0.0   # 0 = no curvature limit (skid-steer); Ackermann: tan(steer_max)/L


@dataclass(frozen=True, kw_only=True)
class FLConfig:
    gamma1: float = 1.0
    gamma2: float = 1.8
    curvature_feedforward: bool = True


@dataclass(frozen=True, kw_only=True)
class ILCConfig:
    """Eq. 3.14-3.16; see ilc.py."""
    gamma_L: float = 0.8
    gamma_H: float = 0.4
    gamma_u: float = 1.0
    lookahead: int = 4
    ic_vertices: int = 8


@dataclass(frozen=True, kw_only=True)
class NMPCConfig:
    """Eq. 5.3-5.16 weights and solver settings; see nmpc.py."""
    horizon: int = 10
    q_along: float = 1.0
    q_lat: float = 40.0
    q_head: float = 10.0
    r_w: float = 0.2
    r_dw: float = 1.0
    q_terminal: float = 100.0
    lookahead_m: float = 1.5
    max_iter: int = 10
    tol: float = 1e-3

    def __post_init__(self):
        if self.horizon < 1 or self.max_iter < 1 or min(self.q_along, self.q_lat, self.q_head, self.r_w, self.r_dw,
                                                         self.q_terminal, self.lookahead_m) < 0:
            raise ValueError("horizon and max_iter must be >= 1 and the weights >= 0")
        if self.r_w + self.r_dw <= 0:
            raise ValueError("r_w or r_dw must be > 0 (eq. 5.3 needs R positive definite)")


@dataclass(frozen=True, kw_only=True)
class StoreClientConfig:
    """Experiences out, local windows and hyperparameters in (thesis 5.3.2 window sizes)."""
    enabled: bool = True
    v_bin_mps: float = 0.25
    c_vertex: int = 5
    c_velocity: int = 1
    lookahead_vertices: int = 20
    resend_after_s: float = 2.0
    ack_timeout_s: float = 10.0   # at the end of a trial, wait this long for the store's acknowledgements


@dataclass(frozen=True, kw_only=True)
class ControllerConfig:
    robot_name: str
    algorithm: str = "fl"
    clock_mode: Literal["lockstep", "realtime"] = "lockstep"
    period_s: float = 0.1
    loc_timeout_s: float = 0.5
    stop_decel_mps2: float = 0.4
    route_timeout_s: float = 5.0
    limits: LimitsConfig
    fl: FLConfig = field(default_factory=FLConfig)
    ilc: ILCConfig = field(default_factory=ILCConfig)
    nmpc: NMPCConfig = field(default_factory=NMPCConfig)
    store: StoreClientConfig = field(default_factory=StoreClientConfig)
    data_dir: str = ""   # where learned feedforwards (ILC) are kept, one file per route
