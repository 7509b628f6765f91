"""Typed configuration of the localizer service."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from common.path import DEFAULT_SPACING_M
from services.localizer.vision.settings import VisionSettings


@dataclass(frozen=True, kw_only=True)
class PoseSourceConfig:
    """The `pose` source's errors (the scenario's [localization] keys of the same names)."""
    noise_m: float = 0.01           # std of the slowly wandering position error
    noise_heading_deg: float = 0.3
    noise_tau_s: float = 1.0        # its correlation time
    jitter_m: float = 0.002         # independent frame-to-frame position error
    delay_s: float = 0.0
    dropout_prob: float = 0.0       # chance per tick that a dropout starts
    dropout_s: float = 0.3          # length of each dropout
    jumps: list[tuple[float, float, float]] = field(default_factory=list)   # [at_m, length_m, lateral_m]


@dataclass(frozen=True, kw_only=True)
class LocalizerConfig:
    robot_name: str
    source: Literal["pose", "vision"] = "pose"
    seed: int = 0
    data_dir: str                    # taught routes live in <data_dir>/routes/<path_id>.route
    period_s: float = 0.1            # sensor period, to turn delays into ticks
    vertex_spacing_m: float = DEFAULT_SPACING_M
    pose: PoseSourceConfig = field(default_factory=PoseSourceConfig)
    vision: VisionSettings = field(default_factory=VisionSettings)
