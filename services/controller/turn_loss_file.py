"""The learned turn loss (turn_speed.TurnLoss) on disk, one file per nominal model in the controller's
data_dir: a controller restarted between trials goes on from what the robot's corners showed, as ILC goes
on from its feedforward."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path as FsPath

from common.codec import Message
from services.controller import per_model_file
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
    return per_model_file.file_of(directory, model_tag, SUFFIX)


def save(directory: str | FsPath, model_tag: str, loss: TurnLoss) -> FsPath:
    rec = TurnLossRecord(model_tag=model_tag, turn_gain=loss.turn_gain, sxx=loss.sxx, sxy=loss.sxy,
                         samples=loss.samples)
    return per_model_file.save(directory, rec, SUFFIX)


def load(directory: str | FsPath, model_tag: str, turn_gain: float) -> TurnLoss:
    """The stored loss of this model, or a fresh one: none stored, an unreadable file, or one learned
    over another turn gain (each logged)."""
    rec = per_model_file.load(directory, model_tag, TurnLossRecord, SUFFIX, "the turn loss is learned afresh")
    if rec is None:
        return TurnLoss(turn_gain)
    if not math.isclose(rec.turn_gain, turn_gain, rel_tol=1e-6):
        log.warning("%s was learned over turn gain %.3f, not %.3f: the turn loss is learned afresh",
                    file_of(directory, model_tag), rec.turn_gain, turn_gain)
        return TurnLoss(turn_gain)
    return TurnLoss(turn_gain, rec.sxx, rec.sxy, rec.samples)
