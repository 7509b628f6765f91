"""Tie a child process's life to its launcher: no orphan services when the launcher dies."""
from __future__ import annotations

import ctypes
import os
import signal
import sys

PARENT_ENV = "LBC_PARENT_PID"
_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None = None) -> None:
    """If started by the launcher (LBC_PARENT_PID set) or given a parent, ask Linux to SIGTERM us when
    that parent exits.

    Set from inside the child, after exec, which is thread-safe (unlike a preexec_fn); the getppid
    check closes the race where the launcher died before the request was made.
    """
    parent = parent_pid if parent_pid is not None else os.environ.get(PARENT_ENV)
    if not parent or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except OSError:
        return
    if os.getppid() != int(parent):
        os.kill(os.getpid(), signal.SIGTERM)
