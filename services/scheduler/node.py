"""Speed scheduler service (thesis chapter 4): collects every robot's per-vertex experience from the
bus, proposes the next speed schedule of a route after a trial, keeps the schedules and the experience
in its database, and serves them:

- `lbc/sched/<path>/schedule` (query): the latest schedule (the first one, v_init, made on demand);
  new schedules are also published on this key;
- `lbc/sched/<path>/update` (query, payload ScheduleUpdate): the next schedule from a robot's trial,
  made once per (robot, trial) and then served again (so the runner and the automatic update after a
  trial event agree).

The trial's end reaches the scheduler from other publishers (the bridge's event, the runner's query)
than its passes (the controller's status), so it may overtake the last of them. An update therefore
waits until the controller's own end of the trial ("finished" status) has arrived, or until its
status has been quiet for `settle_s`, and only then proposes and replies.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import zenoh

from common import keys
from common.bus import Node, query_one
from common.codec import DecodeError, decode, encode
from common.messages import (ControllerStatus, LocState, RouteMsg, ScheduleUpdate, SpeedSchedule, TrialEvent,
                             check_name)
from common.path import Path
from common.service import Control, Service, service_main
from services.scheduler.config import SchedulerConfig
from services.scheduler.core import PassCollector, Proposal, initial_schedule, plan
from services.scheduler.db import ScheduleDB


@dataclass
class Collecting:
    """A trial's passes while it runs: the collector, the schedule version it ran at, and whether
    (and when) the controller's status said the trial is over."""
    collector: PassCollector
    version: int
    finished: bool = False
    last_status_wall_s: float = 0.0


@dataclass
class PendingUpdate:
    robot: str
    path_id: str
    trial: int
    query: zenoh.Query | None
    asked_wall_s: float


class SchedulerService(Service):
    name = "scheduler"

    def __init__(self, cfg: SchedulerConfig, node: Node):
        super().__init__(node)
        self.cfg = cfg
        self.params = cfg.params
        self.db = ScheduleDB(cfg.db_path)
        self.routes: dict[str, Path] = {}
        self.collecting: dict[tuple[str, str, int], Collecting] = {}    # by (robot, path, trial)
        self.pending: list[PendingUpdate] = []
        for pattern, cls, kind in ((f"{keys.ROOT}/*/ctrl/status", ControllerStatus, "status"),
                                   (f"{keys.ROOT}/*/loc/state", LocState, "loc"),
                                   (f"{keys.ROOT}/*/trial/event", TrialEvent, "event")):
            node.subscribe(pattern, cls, lambda m, k, kind=kind: self.inbox.put((kind, (k.split("/")[1], m))))
        node.queryable(keys.sched_schedule("*"), lambda q: self.inbox.put(("q_schedule", q)))
        node.queryable(keys.sched_update("*"), lambda q: self.inbox.put(("q_update", q)))

    # --- experience from the bus -----------------------------------------------------------------
    def _collecting(self, robot: str, path_id: str, trial: int) -> Collecting | None:
        key = (robot, path_id, trial)
        entry = self.collecting.get(key)
        if entry is None:
            if self.db.based_on(path_id, robot, trial) is not None:
                return None   # already scheduled from this trial (late or repeated messages)
            route = self._route(path_id)
            latest = self.db.latest(path_id)
            if route is None or latest is None:
                return None   # not a scheduled route (no schedule was ever asked for)
            entry = self.collecting[key] = Collecting(PassCollector(len(route)), latest.version)
        return entry

    def on_message(self, kind: str, item) -> None:
        if kind == "q_schedule":
            self._answer(item, self._on_schedule_query)
        elif kind == "q_update":
            self._on_update_query(item)
        else:
            self._on_bus(kind, *item)
        self._serve_pending()

    def on_idle(self) -> None:
        self._serve_pending()

    def _on_bus(self, kind: str, robot: str, msg) -> None:
        if kind == "status" and msg.path_id:
            c = self._collecting(robot, msg.path_id, msg.trial)
            if c is None:
                return
            c.last_status_wall_s = time.monotonic()
            if msg.state in ("tracking", "holding"):
                c.collector.add(msg.vertex, msg.lateral_m, msg.heading_rad, msg.w_cmd_radps, v_cmd=msg.v_cmd_mps)
            elif msg.state == "finished":
                c.finished = True
        elif kind == "loc" and msg.has_pose and msg.matched_features is not None and msg.path_id:
            c = self._collecting(robot, msg.path_id, msg.trial)
            if c is not None:
                c.collector.add_features(msg.vertex, float(msg.matched_features))
        elif (kind == "event" and msg.event == "ended" and msg.mode == "repeat" and self.cfg.auto_after_trial
              and msg.path_id and self.db.latest(msg.path_id) is not None):
            self.pending.append(PendingUpdate(robot, msg.path_id, msg.trial, None, time.monotonic()))

    def _serve_pending(self) -> None:
        """Make the updates whose trial's passes are all in (see the module doc), and reply."""
        now = time.monotonic()
        for p in list(self.pending):
            c = self.collecting.get((p.robot, p.path_id, p.trial))
            done = self.db.based_on(p.path_id, p.robot, p.trial) is not None
            quiet_s = now - (p.asked_wall_s if c is None else max(c.last_status_wall_s, p.asked_wall_s))
            if not (done or (c is not None and c.finished) or quiet_s > self.cfg.settle_s):
                continue
            self.pending.remove(p)
            if c is None and not done and p.query is None:
                self.log.debug("%s trial %d on %s ended without passes to schedule from", p.robot, p.trial, p.path_id)
                continue
            if c is not None and not c.finished:
                self.log.warning("%s trial %d on %s: no end-of-route status; scheduling from what arrived",
                                 p.robot, p.trial, p.path_id)
            if p.query is not None:
                self._answer(p.query, lambda _q, p=p: self._update(p.path_id, p.robot, p.trial))
            else:
                try:
                    self._update(p.path_id, p.robot, p.trial)
                except (LookupError, ValueError) as exc:
                    self.log.warning("no schedule from %s trial %d: %s", p.robot, p.trial, exc)

    # --- schedules --------------------------------------------------------------------------------
    def _route(self, path_id: str) -> Path | None:
        if path_id not in self.routes:
            try:
                self.routes[path_id] = Path.from_msg(query_one(self.node.session, keys.route(path_id), RouteMsg,
                                                               timeout_s=3.0))
            except (LookupError, DecodeError, ValueError) as exc:
                self.log.warning("route %s unavailable: %s", path_id, exc)
                return None
        return self.routes[path_id]

    def _store(self, path_id: str, proposal: Proposal, robot: str, trial: int) -> SpeedSchedule:
        msg = self.db.add_schedule(path_id, proposal, robot, trial, time.time())
        self.node.publish(keys.sched_schedule(path_id), msg)
        v = np.asarray(msg.v_mps)
        self.log.info("%s schedule v%d (from %s trial %d): %.2f-%.2f m/s; %s", path_id, msg.version, robot or "-",
                      trial, v.min(), v.max(), "; ".join(msg.notes) or "")
        return msg

    def latest(self, path_id: str) -> SpeedSchedule:
        schedule = self.db.latest(path_id)
        if schedule is None:
            route = self._route(path_id)
            if route is None:
                raise LookupError(f"no taught route {path_id!r} to schedule")
            schedule = self._store(path_id, initial_schedule(route.s, route.poses[:, :2], self.params), "", 0)
        return schedule

    def _update(self, path_id: str, robot: str, trial: int) -> SpeedSchedule:
        done = self.db.based_on(path_id, robot, trial)
        if done is not None:
            return done
        entry = self.collecting.pop((robot, path_id, trial), None)
        if entry is None:
            raise LookupError(f"no experience collected from {robot} trial {trial} on {path_id}")
        collector, version = entry.collector, entry.version
        route = self._route(path_id)
        prev = self.latest(path_id)
        self.db.save_passes(path_id, robot, trial, version, collector.passes)
        history = self.db.history(path_id) if self.params.use_all_trials or self.params.guard else []
        proposal = plan(np.asarray(prev.v_mps), collector.passes, history, route.s, route.poses[:, :2], self.params,
                        route.curvature)
        return self._store(path_id, proposal, robot, trial)

    def _answer(self, query: zenoh.Query, fn) -> None:
        try:
            msg = fn(query)
            # reply on the key that was asked (schedule or update) of this route
            query.reply(f"{keys.ROOT}/sched/{msg.path_id}/{str(query.key_expr).rsplit('/', 1)[-1]}", encode(msg))
        except (LookupError, ValueError, DecodeError) as exc:
            query.reply_err(str(exc).encode())
        except Exception as exc:
            self.log.exception("schedule query failed")
            query.reply_err(f"scheduler error: {exc}".encode())
        finally:
            query.drop()

    def _on_schedule_query(self, query: zenoh.Query) -> SpeedSchedule:
        return self.latest(check_name("path_id", str(query.key_expr).split("/")[2]))

    def _on_update_query(self, query: zenoh.Query) -> None:
        """Answered once the trial's passes are in (or it was scheduled already)."""
        try:
            if query.payload is None:
                raise ValueError("an update needs a ScheduleUpdate payload")
            req = decode(ScheduleUpdate, query.payload.to_bytes())
        except (ValueError, DecodeError) as exc:
            query.reply_err(f"bad ScheduleUpdate: {exc}".encode())
            return query.drop()
        self.pending.append(PendingUpdate(req.robot, req.path_id, req.trial, query, time.monotonic()))

    def on_control(self, ctl: Control) -> None:
        return self.reply(ctl, True, "the scheduler is shared; trial control does not apply")

    def close(self) -> None:
        self.db.close()


def main(argv: list[str] | None = None) -> int:
    return service_main("scheduler", SchedulerConfig, SchedulerService, lambda c: keys.STORE_ROBOT, argv)
