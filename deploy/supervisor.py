"""Keeps a deployment's children running: a child that exits is started again, after a back-off that
grows while it keeps failing, so one crash (or a restarted router) does not take the host down.
A child that exits with a configuration error is not restarted: that needs a person."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

from deploy.launcher import Child, Launcher

log = logging.getLogger(__name__)

CONFIG_ERROR_EXIT = 2              # what service_main returns for a bad configuration
BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
HEALTHY_AFTER_S = 60.0             # a child that ran this long starts again with the shortest back-off


@dataclass
class Supervisor:
    launcher: Launcher
    say: Callable[[str], None]
    clock: Callable[[], float] = time.monotonic
    failures: dict[str, int] = field(default_factory=dict)
    pending: dict[str, tuple[float, Child]] = field(default_factory=dict)   # name -> (restart at, child)
    restarts: int = 0

    def poll(self) -> str | None:
        """Restart what is due; returns why supervision must give up (a configuration error), else None."""
        now = self.clock()
        for child in self.launcher.exited():
            if child.name in self.pending:
                continue
            code = child.proc.returncode
            if code == CONFIG_ERROR_EXIT:
                return f"{child.name} exited with a configuration error:\n{child.tail()}"
            lived = now - child.started_s
            n = 0 if lived >= HEALTHY_AFTER_S else self.failures.get(child.name, 0)
            self.failures[child.name] = n + 1
            delay = BACKOFF_S[min(n, len(BACKOFF_S) - 1)]
            self.say(f"{child.name} exited ({code}) after {lived:.0f} s; restarting in {delay:.0f} s "
                     f"(log {child.log_path})")
            self.pending[child.name] = (now + delay, child)
        for name, (due, child) in list(self.pending.items()):
            if now >= due:
                del self.pending[name]
                self.launcher.restart(child)
                self.restarts += 1
                log.info("restarted %s", name)
        return None
