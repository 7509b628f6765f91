"""Typed configuration of the localizer service."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from common.path import DEFAULT_SPACING_M
from services.localizer.vision.settings import VisionSettings


@dataclass(frozen=True, kw_only=True)
class PoseSourceConfig:
    noise_m: float = 0.01
    noise_heading_deg: float = 0.3
    noise_tau_s: float = 1.0
    jitter_m: float = 0.002
    delay_s: float = 0.0
    dropout_prob: float = 0.0
    dropout_s: float = 0.3
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
