"""The learned turn loss (turn_speed.TurnLoss) on disk, one file per nominal model in the controller's
data_dir: a controller restarted between trials goes on from what the robot's corners showed, as ILC goes
on from its feedforward."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path as FsPath

from common.atomic_file import write_atomically
from common.codec import DecodeError, Message, decode, encode
from services.controller.turn_speed import TurnLoss

log = logging.getLogger(__name__)
SUFFIX = ".turnloss"


@dataclass(frozen=True, kw_only=True)
class TurnLossRecord(Message):
    """TurnLoss's sums under one nominal model, as stored."""
    model_tag: str
    turn_gain: float
    sxx: float
    sxy: float
    samples: int

    def __post_init__(self):
        if not (self.turn_gain > 0 and self.sxx >= 0 and self.samples >= 0) or "/" in self.model_tag:
            raise ValueError("a turn loss record needs turn_gain > 0, sxx >= 0, samples >= 0 and a plain model tag")


def file_of(directory: str | FsPath, model_tag: str) -> FsPath:
    return FsPath(directory) / f"{model_tag}{SUFFIX}"


def save(directory: str | FsPath, model_tag: str, loss: TurnLoss) -> FsPath:
    rec = TurnLossRecord(model_tag=model_tag, turn_gain=loss.turn_gain, sxx=loss.sxx, sxy=loss.sxy,
                         samples=loss.samples)
    return write_atomically(file_of(directory, model_tag), encode(rec))


def load(directory: str | FsPath, model_tag: str, turn_gain: float) -> TurnLoss:
    """The stored loss of this model, or a fresh one: none stored, an unreadable file, or one learned
    over another turn gain (each logged)."""
    f = file_of(directory, model_tag)
    if not f.exists():
        return TurnLoss(turn_gain)
    try:
        rec = decode(TurnLossRecord, f.read_bytes())
    except (DecodeError, OSError) as exc:
        log.warning("%s not used (%s): the turn loss is learned afresh", f, exc)
        return TurnLoss(turn_gain)
    if rec.model_tag != model_tag or not math.isclose(rec.turn_gain, turn_gain, rel_tol=1e-6):
        log.warning("%s is of model %s, turn gain %.3f: the turn loss is learned afresh", f, rec.model_tag,
                    rec.turn_gain)
        return TurnLoss(turn_gain)
    return TurnLoss(turn_gain, rec.sxx, rec.sxy, rec.samples)
