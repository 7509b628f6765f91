"""Taught routes on disk: one file per route, the RouteMsg codec (versioned) as the file format,
written atomically (temp file, fsync, rename) so a crash never leaves half a route."""
from __future__ import annotations

import threading
from pathlib import Path as FsPath

from common.atomic_file import write_atomically
from common.codec import DecodeError, decode, encode
from common.messages import RouteMsg, check_name
from common.path import Path


class RouteStore:
    SUFFIX = ".route"

    def __init__(self, directory: str | FsPath):
        self.dir = FsPath(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._cache: dict[str, RouteMsg] = {}
        self._lock = threading.Lock()

    def file_of(self, path_id: str) -> FsPath:
        return self.dir / f"{check_name('path_id', path_id)}{self.SUFFIX}"

    def save(self, path: Path, stamp_s: float) -> FsPath:
        msg = path.to_msg(stamp_s)
        target = write_atomically(self.file_of(path.path_id), encode(msg))
        with self._lock:
            self._cache[path.path_id] = msg
        return target

    def load_msg(self, path_id: str) -> RouteMsg:
        """The stored route; KeyError if there is none, ValueError if the file is corrupt."""
        with self._lock:
            if path_id in self._cache:
                return self._cache[path_id]
        target = self.file_of(path_id)
        if not target.exists():
            raise KeyError(f"no taught route {path_id!r} in {self.dir}")
        try:
            msg = decode(RouteMsg, target.read_bytes())
        except DecodeError as exc:
            raise ValueError(f"route file {target} is unreadable: {exc}") from None
        with self._lock:
            self._cache[path_id] = msg
        return msg

    def load(self, path_id: str) -> Path:
        return Path.from_msg(self.load_msg(path_id))

    def ids(self) -> list[str]:
        return sorted(p.stem for p in self.dir.glob(f"*{self.SUFFIX}"))
