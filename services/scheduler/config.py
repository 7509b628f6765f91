"""Typed configuration of the speed scheduler service."""
from __future__ import annotations

from dataclasses import dataclass, field

from services.scheduler.core import SchedulerParams


@dataclass(frozen=True, kw_only=True)
class SchedulerConfig:
    name: str = "scheduler1"
    db_path: str                      # schedules and collected per-vertex experience (SQLite)
    params: SchedulerParams = field(default_factory=SchedulerParams)
    auto_after_trial: bool = True     # propose the next schedule when a robot ends a repeat
    settle_s: float = 2.0             # without the controller's end-of-route status, wait this long
                                      # after its last status before scheduling from a trial
