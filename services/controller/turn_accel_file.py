"""The turn drive's acceleration limit read off the repeats (turn_accel.py) on disk, one file per nominal
model in the controller's data_dir: a controller restarted between trials keeps what the robot's drive
showed, as it keeps its turn loss (turn_loss_file.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path as FsPath

from common.codec import Message
from services.controller import per_model_file

SUFFIX = ".turnaccel"


@dataclass(frozen=True, kw_only=True)
class TurnAccelRecord(Message):
    """The limit under one nominal model, as stored."""
    model_tag: str
    limit_radps2: float

    def __post_init__(self):
        if not (self.limit_radps2 > 0 and math.isfinite(self.limit_radps2)) or "/" in self.model_tag:
            raise ValueError("a turn acceleration record needs a finite limit > 0 and a plain model tag")


def file_of(directory: str | FsPath, model_tag: str) -> FsPath:
    return per_model_file.file_of(directory, model_tag, SUFFIX)


def save(directory: str | FsPath, model_tag: str, limit_radps2: float) -> FsPath:
    return per_model_file.save(directory, TurnAccelRecord(model_tag=model_tag, limit_radps2=limit_radps2), SUFFIX)


def load(directory: str | FsPath, model_tag: str) -> float | None:
    """The stored limit of this model, or None: none stored, or an unreadable file (logged)."""
    rec = per_model_file.load(directory, model_tag, TurnAccelRecord, SUFFIX,
                              "the turn drive's limit is read again from the next repeat")
    return None if rec is None else rec.limit_radps2
