"""The turn drive's acceleration limit read off the repeats (turn_accel.py) on disk, one file per nominal
model in the controller's data_dir: a controller restarted between trials keeps what the robot's drive
showed, as it keeps its turn loss (turn_loss_file.py)."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path as FsPath

from common.atomic_file import write_atomically
from common.codec import DecodeError, Message, decode, encode

log = logging.getLogger(__name__)
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
    return FsPath(directory) / f"{model_tag}{SUFFIX}"


def save(directory: str | FsPath, model_tag: str, limit_radps2: float) -> FsPath:
    return write_atomically(file_of(directory, model_tag),
                            encode(TurnAccelRecord(model_tag=model_tag, limit_radps2=limit_radps2)))


def load(directory: str | FsPath, model_tag: str) -> float | None:
    """The stored limit of this model, or None: none stored, or an unreadable file (logged)."""
    f = file_of(directory, model_tag)
    if not f.exists():
        return None
    try:
        rec = decode(TurnAccelRecord, f.read_bytes())
    except (DecodeError, OSError) as exc:
        log.warning("%s not used (%s): the turn drive's limit is read again from the next repeat", f, exc)
        return None
    if rec.model_tag != model_tag:
        log.warning("%s is of model %s: the turn drive's limit is read again from the next repeat", f, rec.model_tag)
        return None
    return rec.limit_radps2
