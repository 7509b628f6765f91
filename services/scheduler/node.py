"""Speed scheduler service (thesis chapter 4): collects every robot's per-vertex experience from the
bus, proposes the next speed schedule of a route after a trial, keeps the schedules and the experience
in its database, and serves them:

- `lbc/sched/<path>/schedule` (query): the latest schedule (the first one, v_init, made on demand);
  new schedules are also published on this key;
- `lbc/sched/<path>/update` (query, payload ScheduleUpdate): the next schedule from a robot's trial,
  made once per (robot, trial) and then served again (so the runner and the automatic update after a
  trial event agree).
"""
from __future__ import annotations

import time

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
from services.scheduler.core import PassCollector, failure_speeds, initial_schedule, next_schedule
from services.scheduler.db import ScheduleDB


def schedule_msg(body: dict) -> SpeedSchedule:
    return SpeedSchedule(stamp_s=body["stamp_s"], path_id=body["path_id"], version=body["version"],
                         based_on_robot=body["based_on_robot"], based_on_trial=body["based_on_trial"],
                         v_mps=body["v_mps"], decisions=body["decisions"], notes=body["notes"])


class SchedulerService(Service):
    name = "scheduler"

    def __init__(self, cfg: SchedulerConfig, node: Node):
        super().__init__(node)
        self.cfg = cfg
        self.params = cfg.params
        self.db = ScheduleDB(cfg.db_path)
        self.routes: dict[str, Path] = {}
        # (robot, path, trial) -> (collector, schedule version the trial ran at)
        self.collecting: dict[tuple[str, str, int], tuple[PassCollector, int]] = {}
        for pattern, cls, kind in ((f"{keys.ROOT}/*/ctrl/status", ControllerStatus, "status"),
                                   (f"{keys.ROOT}/*/loc/state", LocState, "loc"),
                                   (f"{keys.ROOT}/*/trial/event", TrialEvent, "event")):
            node.subscribe(pattern, cls, lambda m, k, kind=kind: self.inbox.put((kind, (k.split("/")[1], m))))
        node.queryable(keys.sched_schedule("*"), lambda q: self.inbox.put(("q_schedule", q)))
        node.queryable(keys.sched_update("*"), lambda q: self.inbox.put(("q_update", q)))

    # --- experience from the bus -----------------------------------------------------------------
    def _collector(self, robot: str, path_id: str, trial: int) -> PassCollector | None:
        key = (robot, path_id, trial)
        entry = self.collecting.get(key)
        if entry is None:
            route = self._route(path_id)
            latest = self.db.latest(path_id)
            if route is None or latest is None:
                return None   # not a scheduled route (no schedule was ever asked for)
            entry = self.collecting[key] = (PassCollector(len(route)), latest["version"])
        return entry[0]

    def on_message(self, kind: str, item) -> None:
        if kind == "q_schedule":
            return self._answer(item, self._on_schedule_query)
        if kind == "q_update":
            return self._answer(item, self._on_update_query)
        robot, msg = item
        if kind == "status" and msg.state in ("tracking", "holding") and msg.path_id:
            c = self._collector(robot, msg.path_id, msg.trial)
            if c is not None:
                c.add(msg.vertex, msg.lateral_m, msg.heading_rad, msg.w_cmd_radps)
        elif kind == "loc" and msg.status == "ok" and msg.matched_features is not None and msg.path_id:
            c = self._collector(robot, msg.path_id, msg.trial)
            if c is not None:
                c.add_features(msg.vertex, float(msg.matched_features))
        elif (kind == "event" and msg.event == "ended" and msg.mode == "repeat" and self.cfg.auto_after_trial
              and (robot, msg.path_id, msg.trial) in self.collecting):
            try:
                self._update(msg.path_id, robot, msg.trial)
            except (LookupError, ValueError) as exc:
                self.log.warning("no schedule from %s trial %d: %s", robot, msg.trial, exc)

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

    def _store(self, path_id: str, proposal, robot: str, trial: int) -> dict:
        body = self.db.add_schedule({
            "stamp_s": time.time(), "path_id": path_id, "based_on_robot": robot, "based_on_trial": trial,
            "v_mps": [float(v) for v in proposal.schedule], "decisions": [int(d) for d in proposal.decisions],
            "notes": list(proposal.notes)})
        self.node.publish(keys.sched_schedule(path_id), schedule_msg(body))
        v = np.asarray(body["v_mps"])
        self.log.info("%s schedule v%d (from %s trial %d): %.2f-%.2f m/s; %s", path_id, body["version"], robot or "-",
                      trial, v.min(), v.max(), "; ".join(body["notes"]) or "")
        return body

    def latest(self, path_id: str) -> dict:
        body = self.db.latest(path_id)
        if body is None:
            route = self._route(path_id)
            if route is None:
                raise LookupError(f"no taught route {path_id!r} to schedule")
            body = self._store(path_id, initial_schedule(route.s, route.poses[:, :2], self.params), "", 0)
        return body

    def _update(self, path_id: str, robot: str, trial: int) -> dict:
        done = self.db.based_on(path_id, robot, trial)
        if done is not None:
            return done
        entry = self.collecting.pop((robot, path_id, trial), None)
        if entry is None:
            raise LookupError(f"no experience collected from {robot} trial {trial} on {path_id}")
        collector, version = entry
        route = self._route(path_id)
        prev = self.latest(path_id)
        self.db.save_passes(path_id, robot, trial, version, collector.passes)
        failed = failure_speeds(self.db.history(path_id), self.params) if self.params.use_all_trials else None
        proposal = next_schedule(np.asarray(prev["v_mps"]), collector.passes, route.s, route.poses[:, :2],
                                 self.params, failed)
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
        return schedule_msg(self.latest(check_name("path_id", str(query.key_expr).split("/")[2])))

    def _on_update_query(self, query: zenoh.Query) -> SpeedSchedule:
        if query.payload is None:
            raise ValueError("an update needs a ScheduleUpdate payload")
        req = decode(ScheduleUpdate, query.payload.to_bytes())
        return schedule_msg(self._update(req.path_id, req.robot, req.trial))

    def on_control(self, ctl: Control) -> None:
        return self.reply(ctl, True, "the scheduler is shared; trial control does not apply")

    def close(self) -> None:
        self.db.close()


def main(argv: list[str] | None = None) -> int:
    return service_main("scheduler", SchedulerConfig, SchedulerService, lambda c: keys.STORE_ROBOT, argv)
