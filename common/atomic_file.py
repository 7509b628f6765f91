"""A file replaced whole or not at all: a crash leaves the old contents or the new, never a mix."""
from __future__ import annotations

import os
from pathlib import Path as FsPath


def write_atomically(target: str | FsPath, data: bytes) -> FsPath:
    """Write `data` to a temporary file beside `target`, fsync it, rename it over `target` and fsync the
    directory (so the rename itself survives a power cut). Creates the directory if needed."""
    target = FsPath(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    try:
        dir_fd = os.open(target.parent, os.O_RDONLY)
    except OSError:
        return target               # platforms without directory handles
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return target
