"""What every `lbc bench` shares: SIGTERM unwinds like Ctrl-C (so child processes are stopped in the
benchmark's own finally blocks), and the result is one JSON object on the last stdout line."""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
from contextlib import AbstractContextManager, nullcontext
from typing import Callable

import zenoh

log = logging.getLogger("bench")


def _interrupt(_signum, _frame):
    raise KeyboardInterrupt


def run_and_print(run: Callable[[], dict], failures: tuple[type[BaseException], ...] = ()) -> int:
    in_main = threading.current_thread() is threading.main_thread()
    prev = signal.signal(signal.SIGTERM, _interrupt) if in_main else None
    try:
        result = run()
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except (RuntimeError, TimeoutError, ConnectionError, LookupError, zenoh.ZError, *failures) as exc:
        log.error("bench failed: %s", exc)
        return 1
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, prev)
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    return 0


def single_core() -> tuple[str, AbstractContextManager]:
    """Pin the process to one CPU and OpenCV to one thread now; the returned context limits BLAS to
    one thread (threadpoolctl, when installed). Returns (where it is pinned, that context)."""
    try:
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        pinned = f"cpu {cpu}"
    except (AttributeError, OSError):
        pinned = "not pinned"
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(1)
    try:
        from threadpoolctl import threadpool_limits
        return pinned, threadpool_limits(limits=1, user_api="blas")
    except ImportError:
        log.warning("threadpoolctl not installed: BLAS keeps its default threads")
        return pinned, nullcontext()
