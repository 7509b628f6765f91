"""A small record kept per nominal model in the controller's data_dir (the turn loss, the turn drive's
acceleration limit): one file per model tag, written atomically, so a controller restarted between trials
goes on from what the robot showed under that model."""
from __future__ import annotations

import logging
from pathlib import Path as FsPath
from typing import TypeVar

from common.atomic_file import write_atomically
from common.codec import DecodeError, Message, decode, encode

log = logging.getLogger(__name__)
R = TypeVar("R", bound=Message)


def file_of(directory: str | FsPath, model_tag: str, suffix: str) -> FsPath:
    return FsPath(directory) / f"{model_tag}{suffix}"


def save(directory: str | FsPath, record: Message, suffix: str) -> FsPath:
    """Store `record` (a message with a `model_tag`) under its model."""
    return write_atomically(file_of(directory, record.model_tag, suffix), encode(record))


def load(directory: str | FsPath, model_tag: str, kind: type[R], suffix: str, otherwise: str) -> R | None:
    """The stored record of this model, or None: none stored, an unreadable file or one of another model
    (both logged with `otherwise`, what the controller does instead)."""
    f = file_of(directory, model_tag, suffix)
    if not f.exists():
        return None
    try:
        rec = decode(kind, f.read_bytes())
    except (DecodeError, OSError) as exc:
        log.warning("%s not used (%s): %s", f, exc, otherwise)
        return None
    if rec.model_tag != model_tag:
        log.warning("%s is of model %s: %s", f, rec.model_tag, otherwise)
        return None
    return rec
