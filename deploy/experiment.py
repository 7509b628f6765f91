"""`lbc experiment run`: teach, then every repeat trial, through the real services over a router.

The runner is only an orchestrator and an observer: it sends trial-control queries, watches the bus
(truth, controller status, localization, trial events, liveliness), records everything to MCAP and
computes the summary from simulator truth. It never computes a command.
"""
from __future__ import annotations

import json
import logging
import math
import os
import queue
import sys
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Any, Callable, TextIO

import numpy as np
import zenoh

from common import keys
from common.bus import open_session, query, query_one
from common.codec import Decoder, decode, encode
from common.config import ConfigError
from common.messages import (CONTROLLER_STOPPED, ENDED_AT_ROUTE_END, STOPPED_ENDS_TRIAL_S, ControllerStatus,
                             ControlReply, ControlRequest, Experience, ExperienceBatch, HyperMsg, LocState,
                             NominalModel, RouteMsg, ScheduleUpdate, SpeedSchedule, StoreStats, TrialEvent,
                             TruthPose)
from common.path import Path, RouteRecorder
from common.typecheck import to_dict
from common.scenario import Scenario, load_scenario
from deploy.configs import service_configs, write_service_configs
from deploy.launcher import LaunchError, Launcher
from deploy.learned import predict_trial
from deploy.metrics import TrialRecord, loop_figures, outside_3sigma_fraction, time_lost, trial_metrics, truth_series
from deploy.recorder import McapRecorder
from deploy.ros2_export import Ros2Export
from deploy.router import free_port
from services.bridge.teach_driver import smooth_waypoints
from services.controller.registry import law_entry

log = logging.getLogger(__name__)
ROBOT_SERVICES = ("localizer", "controller", "bridge")
FLEET_SERVICES = ("gp_store", "scheduler")   # shared by every robot: liveliness under lbc/alive/fleet/


def services_of(sc: Scenario) -> tuple[str, ...]:
    """The processes a scenario needs, in start order."""
    return ROBOT_SERVICES + ("gp_store",) + (("scheduler",) if sc.scheduler.enabled else ())


READY_TIMEOUT_S = 60.0         # how long the runner waits for the services to be up
LATE_STATUS_LOCKSTEP_S = 30.0  # wall time the runner waits for the last stepped tick's status (lockstep never drops it)


class ExperimentError(RuntimeError):
    pass


def check_supported(sc: Scenario) -> None:
    """Refuse, with a clear reason, what this version cannot run yet (rather than run something else).
    The algorithm's name is checked where the scenario is loaded (every name there has a steering law)."""
    if sc.scheduler.enabled and sc.trials.speeds:
        raise ConfigError("trials.speeds and scheduler.enabled both set the speed: choose one")


class Progress:
    """One live status line on a terminal; periodic plain lines otherwise (CI logs)."""

    def __init__(self, stream: TextIO):
        self.stream = stream
        self.tty = stream.isatty()
        self._last = 0.0

    def update(self, text: str) -> None:
        now = time.monotonic()
        if self.tty:
            self.stream.write("\r\033[K" + text)
            self.stream.flush()
        elif now - self._last >= 10.0:
            self._last = now
            self.stream.write(text + "\n")
            self.stream.flush()

    def line(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        self.stream.write(text + "\n")
        self.stream.flush()
        self._last = time.monotonic()


def _missed_ticks(ticks: list[int]) -> list[tuple[int, int]]:
    """Gaps (last tick before, first tick after) in a stream of ticks that should be contiguous."""
    return [(a, b) for a, b in zip(ticks, ticks[1:]) if b != a + 1]


def _bar(frac: float, width: int = 24) -> str:
    n = int(round(max(0.0, min(1.0, frac)) * width))
    return "[" + "#" * n + "." * (width - n) + "]"


def write_json_atomic(path: FsPath, data: Any) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


REJOIN_S = 30.0     # how long a service may be gone mid-trial (a restart, a link down) before the run gives up


class Experiment:
    def __init__(self, sc: Scenario, session, recorder: McapRecorder | None, progress: Progress,
                 launcher: Launcher | None = None, ready_timeout_s: float = READY_TIMEOUT_S):
        self.sc = sc
        self.session = session
        self.recorder = recorder
        self.progress = progress
        self.launcher = launcher
        self.robot = sc.robot.name
        self.path_id = sc.path_id
        self.path: Path | None = None          # the localizer's route: what the services track
        self.truth_path: Path | None = None    # the teach pass from simulator truth: what errors are measured on
        self.events: queue.Queue = queue.Queue()
        self.alive: set[str] = set()
        self.ready_timeout_s = ready_timeout_s
        self.teach_sim_s = self.teach_wall_s = 0.0
        self.teach_unanswered_ticks = 0
        self.scheduled = False        # the trial being prepared follows the scheduler's schedule
        self.learns_feedforward = law_entry(sc.controller.algorithm).learns == "ilc"   # the controller's own
        # the controller stores the teach pass's observations as the first experiences (GP laws)
        self.learns_from_teach = law_entry(sc.controller.algorithm).learns == "gp" and sc.trials.learn_from_teach
        self.nominal_model: NominalModel | None = None
        self.teach_learning: TrialLearning | None = None   # what was fitted on the teach pass, if anything
        self.decoder = Decoder(log)
        r = self.robot
        self._decls = [session.declare_subscriber(key, self._enqueue(kind, cls, key)) for kind, cls, key in (
            ("truth", TruthPose, keys.truth(r)), ("status", ControllerStatus, keys.ctrl_status(r)),
            ("loc", LocState, keys.loc_state(r)), ("event", TrialEvent, keys.trial_event(r)))]
        self.experiences: dict[int, dict[tuple[str, int], Experience]] = {}
        self._decls.append(session.declare_subscriber(keys.experience(r), self._on_experiences))
        self.services = services_of(sc)
        self.schedules: dict[int, SpeedSchedule] = {}
        for pattern in (keys.alive_all(r), *(keys.alive(keys.STORE_ROBOT, f) for f in FLEET_SERVICES)):
            self._decls.append(session.liveliness().declare_subscriber(pattern, self._on_alive, history=True))

    def _on_experiences(self, sample) -> None:
        batch = self.decoder(ExperienceBatch, sample.payload.to_bytes(), str(sample.key_expr))
        if batch is not None:
            for e in batch.experiences:   # re-sends arrive twice: keep one per (source, seq)
                self.experiences.setdefault(e.trial, {})[(batch.source, e.seq)] = e

    def trial_experiences(self, trial: int) -> list[Experience]:
        return list(self.experiences.get(trial, {}).values())

    def retained(self) -> list[Experience]:
        """Every experience the store keeps for this route (what the next trial's model learns from)."""
        out = []
        for rep in query(self.session, keys.store_dump(self.path_id), timeout_s=60.0):
            if rep.error is None:
                out.extend(decode(ExperienceBatch, rep.payload).experiences)
        return out

    def _enqueue(self, kind: str, cls: type, key: str):
        def on_sample(sample) -> None:
            msg = self.decoder(cls, sample.payload.to_bytes(), key)  # bad payloads: logged, counted, dropped
            if msg is not None:
                self.events.put((kind, msg))
        return on_sample

    def close(self) -> None:
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:
                pass

    def _on_alive(self, sample) -> None:
        self.events.put(("alive", (str(sample.key_expr).rsplit("/", 1)[-1],
                                   sample.kind == zenoh.SampleKind.PUT)))

    # --- plumbing ----------------------------------------------------------------------------
    def _check_children(self) -> None:
        if self.launcher is None:
            return
        dead = self.launcher.exited()
        if dead:
            c = dead[0]
            raise ExperimentError(f"{c.name} exited with code {c.proc.returncode}; last lines of {c.log_path}:\n"
                                  f"{c.tail()}")

    def _next_event(self, timeout: float):
        try:
            kind, data = self.events.get(timeout=timeout)
        except queue.Empty:
            self._check_children()
            return None, None
        if kind == "alive":
            name, up = data
            (self.alive.add if up else self.alive.discard)(name)
        return kind, data

    def wait_ready(self) -> None:
        """Every service up, or, against a deployment started elsewhere, at least the robot's: with the
        learning host unreachable the robot can still teach and repeat on its nominal model."""
        deadline = time.monotonic() + self.ready_timeout_s
        self.progress.update("waiting for services: " + ", ".join(self.services))
        while not all(s in self.alive for s in self.services):
            if time.monotonic() > deadline:
                missing = [s for s in self.services if s not in self.alive]
                if self.launcher is not None or any(s in ROBOT_SERVICES for s in missing):
                    raise ExperimentError(f"services not up within {self.ready_timeout_s:.0f} s: {missing}")
                self.progress.line(f"warning {', '.join(missing)} not reachable (learning host down?): teaching "
                                   "and repeating without; the controller drives on its nominal model, experiences "
                                   "queue on the robot until a store answers")
                break
            self._next_event(0.2)
        up = [s for s in self.services if s in self.alive]
        self.progress.line(f"services up: {', '.join(up)} (robot {self.robot})")

    def control(self, service: str, action: str, mode: str, trial: int, speed: float = 0.0,
                max_duration_s: float = 0.0) -> ControlReply:
        req = ControlRequest(stamp_s=time.time(), action=action, mode=mode, trial=trial, path_id=self.path_id,
                             speed_mps=speed, max_duration_s=max_duration_s, learning=self.sc.trials.learning,
                             loop=self.sc.path.loop, schedule=self.scheduled and mode == "repeat")
        key = keys.control(self.robot, service)
        payload = encode(req)
        if self.recorder:
            self.recorder.record(key, payload)
        try:
            rep = query_one(self.session, key, ControlReply, payload=payload, timeout_s=30.0)
        except LookupError as exc:
            self._check_children()
            raise ExperimentError(f"{service} did not answer {action}: {exc}") from None
        if self.recorder:
            self.recorder.record(key + "/reply", encode(rep))
        if not rep.ok:
            raise ExperimentError(f"{service} refused {action} {mode} trial {trial}: {rep.detail}")
        log.info("%s %s: %s", service, action, rep.detail)
        return rep

    # --- phases ------------------------------------------------------------------------------
    def teach(self) -> Path:
        sc = self.sc
        ref = smooth_waypoints(sc.path.waypoints, sc.path.corner_radius_m, sc.path.loop)
        ref_len = float(sum(math.hypot(*d) for d in (ref[1:, :2] - ref[:-1, :2])))
        limit_s = self.sc.trials.time_limit_factor * ref_len / sc.path.teach_speed_mps + 30.0
        for s in ROBOT_SERVICES:
            self.control(s, "prepare", "teach", 0, max_duration_s=limit_s)
        t_wall = time.monotonic()
        self.control("bridge", "start", "teach", 0)
        driven, last, last_progress = 0.0, None, time.monotonic()
        truth_route = RouteRecorder(sc.path.vertex_spacing_m)
        ticks: list[int] = []
        while True:
            kind, msg = self._next_event(1.0)
            if kind is None and time.monotonic() - last_progress > 60.0:
                raise ExperimentError("teach: no truth from the bridge for 60 s")
            if kind == "truth" and msg.trial == 0:
                last_progress = time.monotonic()
                if last is not None:
                    driven += math.hypot(msg.x_world_m - last.x_world_m, msg.y_world_m - last.y_world_m)
                last = msg
                ticks.append(msg.tick)
                truth_route.add((msg.x_world_m, msg.y_world_m, msg.theta_world_rad))
                self.progress.update(f"teach   {_bar(driven / ref_len)} {driven:6.1f}/{ref_len:.1f} m  "
                                     f"t={msg.stamp_s:7.1f} s")
            elif kind == "event" and msg.event == "ended" and msg.mode == "teach":
                self.teach_sim_s, self.teach_unanswered_ticks = msg.stamp_s, msg.unanswered_ticks
                if msg.unanswered_ticks:
                    self.progress.line(f"warning teach: the bridge stepped {msg.unanswered_ticks} ticks without the "
                                       f"localizer's answer (sim.lockstep_timeout_s): another run can differ")
                break
            elif kind == "alive" and not msg[1] and msg[0] in ROBOT_SERVICES:
                raise ExperimentError(f"{msg[0]} disappeared during teach")
        # the last ticks' truth may reach the runner after the end event (each key has its own subscriber):
        # the taught route must not depend on which arrived first
        late: list[TruthPose] = []
        self._await_late(0, "truth", late, lambda: (late or [last])[-1] is not None
                         and (late or [last])[-1].stamp_s >= self.teach_sim_s - 1e-6)
        for msg in late:
            ticks.append(msg.tick)
            truth_route.add((msg.x_world_m, msg.y_world_m, msg.theta_world_rad))
        if missed := _missed_ticks(ticks):
            # every later error figure is measured against this route: say it is short of samples
            log.warning("teach: %d truth samples did not reach the runner (%s); the truth route is built "
                        "without them", sum(b - a - 1 for a, b in missed), ", ".join(f"{a}-{b}" for a, b in missed[:5]))
        rep = self.control("localizer", "stop", "teach", 0)
        try:
            route = query_one(self.session, keys.route(self.path_id), RouteMsg, timeout_s=10.0)
        except LookupError as exc:
            raise ExperimentError(f"taught route not available: {exc}") from None
        if self.recorder:
            self.recorder.record(keys.route(self.path_id), encode(route))
        self.path = Path.from_msg(route)
        try:
            self.truth_path = truth_route.finish(self.path_id, loop=sc.path.loop)
        except ValueError as exc:
            raise ExperimentError(f"teach: no usable truth for the taught route: {exc}") from None
        self.teach_wall_s = time.monotonic() - t_wall
        self.progress.line(f"teach   done in {self.teach_wall_s:.1f} s wall: {rep.detail}")
        self.nominal_model = self._identify()
        return self.path

    def _identify(self) -> NominalModel:
        """The controller identifies its nominal model on the teach pass just driven (and stores the pass's
        experiences, if it learns from them: they are fitted on before trial 1)."""
        rep = self.control("controller", "stop", "teach", 0)
        try:
            model = query_one(self.session, keys.ctrl_model(self.robot, self.path_id), NominalModel, timeout_s=10.0)
        except LookupError as exc:
            raise ExperimentError(f"the controller's identified model is not available: {exc}") from None
        if self.recorder:
            self.recorder.record(keys.ctrl_model(self.robot, self.path_id), encode(model))
        self.progress.line(f"model   {rep.detail}")
        if self.learns_from_teach:
            self.teach_learning = self._fit("the teach pass", "")
        return model

    def schedule(self, trial: int) -> SpeedSchedule | None:
        """The schedule the scheduler has for the route now (trial 1: v_init, made on demand); None if no
        scheduler is reachable (the trial then runs at the scenario's speed)."""
        if "scheduler" not in self.alive:
            self.progress.line(f"warning no scheduler reachable: trial {trial} at the scenario's fixed speed")
            return None
        try:
            sched = query_one(self.session, keys.sched_schedule(self.path_id), SpeedSchedule, timeout_s=30.0)
        except LookupError as exc:
            self._check_children()
            raise ExperimentError(f"no speed schedule for trial {trial}: {exc}") from None
        self.schedules[trial] = sched
        return sched

    def reschedule(self, trial: int) -> SpeedSchedule | None:
        """After a trial: the next schedule, from what this robot experienced (thesis 4.2.3-4.2.4)."""
        if "scheduler" not in self.alive:
            return None
        req = ScheduleUpdate(stamp_s=time.time(), path_id=self.path_id, robot=self.robot, trial=trial)
        try:
            sched = query_one(self.session, keys.sched_update(self.path_id), SpeedSchedule, payload=encode(req),
                              timeout_s=30.0)
        except LookupError as exc:
            # e.g. a scheduler that joined mid-trial saw too little of it: the next trial keeps the schedule
            # it has (thesis 4.2.4 updates from a traversal it has watched)
            self._check_children()
            self.progress.line(f"warning the schedule was not updated after trial {trial}: {exc}")
            return None
        v = np.asarray(sched.v_mps)
        self.progress.line(f"sched   v{sched.version} for trial {trial + 1}: {v.min():.2f}-{v.max():.2f} m/s, "
                           f"{int(np.sum(np.asarray(sched.decisions) > 0))} vertices faster, "
                           f"{int(np.sum(np.asarray(sched.decisions) < 0))} slower" +
                           (f" ({'; '.join(sched.notes)})" if sched.notes else ""))
        return sched

    def repeat(self, trial: int, speed: float) -> TrialRecord:
        path = self.path
        # the nominal time is at no more than the teach speed: a controller that slows down while its
        # model is uncertain (RC-LB-NMPC's first trial) is not stuck while it moves faster than a third of it
        v_teach = self.sc.path.teach_speed_mps
        nominal_s = path.length_m / max(min(speed, v_teach), 1e-3)
        sched = self.schedule(trial) if self.sc.scheduler.enabled else None
        self.scheduled = sched is not None
        if sched is not None:
            v = np.minimum(np.asarray(sched.v_mps), v_teach)
            speed = float(np.mean(sched.v_mps))
            nominal_s = float(np.sum(path.segment_lengths / np.maximum(v[:-1], 1e-3)))
        limit_s = self.sc.trials.time_limit_factor * nominal_s + 10.0
        rec = TrialRecord(trial=trial, speed_mps=speed)
        for s in ROBOT_SERVICES:
            self.control(s, "prepare", "repeat", trial, speed, limit_s)
        t_wall = time.monotonic()
        self.control("bridge", "start", "repeat", trial, speed, limit_s)
        finished, stopping, hint = False, False, 0
        stopped_since, halt_reason, cut_s = None, "", None
        count = self.sc.trials.count
        last_progress = None
        gone: dict[str, float] = {}     # service -> when its liveliness token went (a blip, until REJOIN_S)
        while True:
            kind, msg = self._next_event(1.0)
            if kind is None and last_progress is not None and time.monotonic() - last_progress > 60.0:
                raise ExperimentError(f"trial {trial}: no truth from the bridge for 60 s")
            if kind == "alive":
                self._note_presence(gone, *msg)
            gone_for = self._gone_too_long(gone)
            if gone_for is not None:
                rec.end_reason = f"{gone_for} disappeared"
                if gone_for != "bridge":
                    try:
                        self.control("bridge", "stop", "repeat", trial)
                    except ExperimentError:
                        pass
                raise ExperimentError(f"trial {trial}: {gone_for} disappeared mid-trial and did not come back "
                                      f"within {REJOIN_S:.0f} s")
            if kind in (None, "alive"):
                continue
            if getattr(msg, "trial", trial) != trial:
                continue
            if kind == "truth":
                rec.truth.append(msg)
                last_progress = time.monotonic()
                pr = path.project((msg.x_world_m, msg.y_world_m, msg.theta_world_rad), hint)
                hint = pr.vertex
                self.progress.update(f"trial {trial:>2}/{count} {_bar(pr.distance_m / path.length_m)} "
                                     f"{pr.distance_m:6.1f}/{path.length_m:.1f} m  lat {pr.lateral_m:+.3f} m  "
                                     f"v {msg.v_mps:.2f} m/s  t={msg.stamp_s:7.1f} s")
                if finished and not stopping and abs(msg.v_mps) < 0.01 and abs(msg.w_radps) < 0.01:
                    stopping = True
                    self.control("bridge", "stop", "repeat", trial)
            elif kind == "status":
                rec.status.append(msg)
                finished = finished or msg.state == "finished"
                # a controller that stays stopped (a safety stop: outside the corridor, too uncertain,
                # localization lost) ends the trial with its reason rather than at the time limit
                stopped_since = (stopped_since if stopped_since is not None else msg.stamp_s) \
                    if msg.state == "stopped" else None
                if stopped_since is not None and msg.stamp_s - stopped_since >= STOPPED_ENDS_TRIAL_S and not stopping:
                    stopping, cut_s = True, msg.stamp_s
                    halt_reason = f"{CONTROLLER_STOPPED}: {msg.reason}"
                    self.control("bridge", "stop", "repeat", trial)
            elif kind == "loc":
                rec.loc.append(msg)
            elif kind == "event" and msg.event == "ended" and msg.mode == "repeat":
                finished = finished or msg.reason == ENDED_AT_ROUTE_END
                rec.completed = finished
                rec.end_reason = "end of route" if finished else (halt_reason or msg.reason)
                rec.unanswered_ticks = msg.unanswered_ticks
                if msg.unanswered_ticks:
                    self.progress.line(f"warning trial {trial}: the bridge stepped {msg.unanswered_ticks} ticks "
                                       f"without their answer (sim.lockstep_timeout_s): another run of this "
                                       f"seed can differ")
                end_stamp_s = msg.stamp_s
                break
        self._late_truth(rec, end_stamp_s if cut_s is None else min(end_stamp_s, cut_s))
        self._late_statuses(rec)
        if cut_s is not None:   # the trial ended at the deciding status, not when the stop reached the bridge
            rec.cut_after(cut_s)
        rec.wall_s = time.monotonic() - t_wall
        return rec

    def _note_presence(self, gone: dict[str, float], name: str, up: bool) -> None:
        """A service's liveliness token went or came back: a restarted service or router, or a link
        that dropped, comes back on its own, so a blip is noted, not fatal."""
        if name not in self.services:
            return
        if not up and name not in gone:
            gone[name] = time.monotonic()
            self.progress.line(f"warning {name} disappeared; waiting up to {REJOIN_S:.0f} s for it to rejoin")
        elif up and name in gone:
            self.progress.line(f"warning {name} rejoined after {time.monotonic() - gone.pop(name):.1f} s")

    @staticmethod
    def _gone_too_long(gone: dict[str, float]) -> str | None:
        """A robot service that has not come back: the trial cannot go on. The learning host's services
        may stay away: the controller drives on what it has, the experiences queue on the robot."""
        now = time.monotonic()
        return next((name for name, t in gone.items() if name in ROBOT_SERVICES and now - t > REJOIN_S), None)

    def _late_truth(self, rec: TrialRecord, end_stamp_s: float) -> None:
        """The bridge's truth of its last tick may reach the runner after its end event (each key has its
        own subscriber): wait for it (the event carries its stamp), so the window a summary counts
        (TrialRecord.stepped_status) does not depend on the wall clock."""
        self._await_late(rec.trial, "truth", rec.truth, lambda: bool(rec.truth) and rec.truth[-1].stamp_s >= end_stamp_s - 1e-6)

    def _late_statuses(self, rec: TrialRecord) -> None:
        """The controller's answers to the last stepped ticks may reach the runner after the bridge's end
        event (another publisher): wait for the one before the last stepped tick, as for the truth."""
        if not rec.truth:
            return
        last = rec.truth[-1].tick
        self._await_late(rec.trial, "status", rec.status, lambda: any(s.tick >= last - 1 for s in rec.status[-3:]))

    def _await_late(self, trial: int, kind_wanted: str, into: list, arrived: Callable[[], bool]) -> None:
        """Take trial `trial`'s `kind_wanted` messages from the events into `into` until `arrived()`. In
        lockstep they are never dropped, so the wait is bounded only against a service that died (a
        loaded machine can hold them back more than a second); in realtime they may have been: 1 s."""
        wait_s = LATE_STATUS_LOCKSTEP_S if self.sc.sim.clock == "lockstep" else 1.0
        deadline, others = time.monotonic() + wait_s, []
        while not arrived() and time.monotonic() < deadline:
            try:
                kind, msg = self.events.get(timeout=0.1)
            except queue.Empty:
                continue
            if kind == kind_wanted and msg.trial == trial:
                into.append(msg)
            else:
                others.append((kind, msg))
        for event in others:            # for whoever reads next (statuses, fits, liveliness)
            self.events.put(event)

    def learn(self, trial: int) -> "TrialLearning":
        """Between trials: make sure the trial's experiences are stored (the controller learns its own
        feedforward, if its law has one, as it stops), then fit the GP hyperparameters offline (thesis
        5.2.3) and wait for them."""
        rep = self.control("controller", "stop", "repeat", trial)
        note = rep.detail.removeprefix("idle; ").removeprefix("idle")
        if self.learns_feedforward:
            self.progress.line(f"learn   controller after trial {trial}: {note}")
        return self._fit(f"trial {trial}", note, rep.detail)

    def _fit(self, after: str, note: str, detail: str = "") -> "TrialLearning":
        """Fit the GP hyperparameters on what the store keeps for the route now (thesis 5.2.3) and wait."""
        if "gp_store" not in self.alive:
            self.progress.line(f"learn   no store reachable after {after}{f' ({detail})' if detail else ''}: nothing fitted")
            return TrialLearning(None, 0, note)
        self.progress.update(f"learn   {detail + '; ' if detail else ''}fitting GP hyperparameters ...")
        t0 = time.monotonic()
        try:
            hyper = query_one(self.session, keys.store_fit(self.path_id), HyperMsg, timeout_s=1800.0)
        except LookupError as exc:
            self._check_children()
            self.progress.line(f"learn   no fit after {after}: {exc}")
            hyper = None
        ingested = self.ingested()
        if hyper is not None:
            self.progress.line(fit_line(hyper, ingested, time.monotonic() - t0))
        return TrialLearning(hyper, ingested, note)

    def ingested(self) -> int:
        total = 0
        for rep in query(self.session, keys.store_stats(), timeout_s=5.0):
            if rep.error is None:
                stats = decode(StoreStats, rep.payload)
                total += sum(p.ingested for p in stats.paths if p.path_id == self.path_id)
        return total


@dataclass(frozen=True)
class TrialLearning:
    """What was learned after a trial: the GP fit (None: none), the experiences ingested on the route
    so far, and the controller's account of its stop (its feedforward update, the acknowledgements)."""
    hyper: HyperMsg | None
    ingested: int
    controller_note: str


def fit_line(hyper: HyperMsg, ingested: int, wall_s: float) -> str:
    """The console's account of a fit. Two different counts: the fit's (the experiences the store
    retains for the route's nominal model after per-bin eviction, and how many of those the fit used)
    and every experience ever ingested on the route (summary.json `experiences_total`)."""
    model = f" of model {hyper.model}" if hyper.model else ""
    return (f"learn   hyperparameters v{hyper.version} fitted on {hyper.n_used} of the {hyper.n_total} experiences "
            f"retained{model}; {ingested} ingested on this route in all (experiences_total); "
            f"fit {hyper.fit_s:.1f} s ({wall_s:.1f} s wall)" + (f"; {hyper.note}" if hyper.note else ""))


def trial_line(count: int, rec: TrialRecord, m: dict) -> str:
    """The console's line for a finished trial; one that did not complete says why."""
    outcome = "done" if rec.completed else f"NOT COMPLETED ({rec.end_reason or 'no reason given'})"
    return (f"trial {rec.trial:>2}/{count} {outcome}: "
            f"max lat {m['max_lateral_m']:.3f} m, rms {m['rms_lateral_m']:.3f} m, "
            f"max head {math.degrees(m['max_heading_rad']):.1f} deg, "
            f"{m['travel_time_s']:.1f} s, violations {m['constraint_violations']}, wall {rec.wall_s:.1f} s")


OUTPUTS = ("summary.json", "report.html", "run.mcap", "config", "logs", "data")


def prepare_out_dir(out: FsPath, overwrite: bool) -> None:
    """A run started by the runner begins from nothing learned: an output directory holding an earlier
    run (whose store, routes and ILC feedforwards would silently carry its learning over) is refused
    unless `overwrite` clears it. With --connect, the deployment's own store and controller data are
    used as they are: learning carries over between runs against the same deployment, by design."""
    import shutil
    earlier = [n for n in OUTPUTS if (out / n).exists()]
    if earlier and not overwrite:
        raise ExperimentError(f"{out} already holds a run ({', '.join(earlier)}); choose another directory "
                              "or pass --overwrite to replace it")
    for n in earlier:
        target = out / n
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _start_deployment(sc: Scenario, out: FsPath, log_level: str, progress: Progress) -> tuple[Launcher, str]:
    """Router and services of a run on a private port; the router must listen before services start."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # a private data dir per run: the taught route belongs to this experiment
    paths = write_service_configs(service_configs(sc, (out / "data").resolve()), out / "config")
    launcher = Launcher(endpoint, out / "logs")
    try:
        launcher.start_router(port)
        launcher.wait_router()
        for s in services_of(sc):
            launcher.start_service(s, paths[s], log_level)
    except LaunchError as exc:
        launcher.stop()
        raise ExperimentError(str(exc)) from None
    except BaseException:
        launcher.stop()
        raise
    progress.line(f"started router on {endpoint} and {', '.join(services_of(sc))} (logs in {out / 'logs'})")
    return launcher, endpoint


def _connect(endpoint: str, launcher: Launcher | None, timeout_s: float,
             zenoh_conf: str | dict | None = None) -> zenoh.Session:
    try:
        return open_session(endpoint, timeout_s=timeout_s, zenoh_conf=zenoh_conf)
    except ValueError as exc:
        raise ExperimentError(f"--connect: {exc}") from None
    except ConnectionError as exc:
        dead = launcher.exited() if launcher else []
        if dead:
            raise ExperimentError(f"{exc}; {dead[0].name} exited:\n{dead[0].tail()}") from None
        hint = "" if launcher else "; is a deployment running there (lbc launch SCENARIO --port PORT)?"
        raise ExperimentError(f"{exc}{hint}") from None


def _trial_summary(sc: Scenario, exp: Experiment, rec: TrialRecord, series, d, hyper: HyperMsg | None,
                   ingested: int) -> dict:
    """One entry of summary.json `trials`."""
    limits = (sc.constraints.lateral_m, math.radians(sc.constraints.heading_deg))
    # experiences_total: every experience the store ever ingested on the route (evicted ones and
    # other nominal models' included), not what the fit used: that is experiences_fit_*
    m = trial_metrics(exp.truth_path, rec, series, *limits, experiences_total=ingested)
    m["outside_3sigma_fraction"] = outside_3sigma_fraction(exp.path, exp.truth_path, rec)
    m.update(loop_figures(rec, sc.sim.period_s, realtime=sc.sim.clock == "realtime"))
    # the online calibration's factor on the 1 s prediction's spread when the trial ended (calibration.py)
    stepped = rec.stepped_status()
    m["spread_factor_1s"] = stepped[-1].spread_factors[-1] if stepped and stepped[-1].spread_factors else None
    m.update(turn_cap_figures(stepped))
    nominal, learned = d.rmse()
    schedule = np.asarray(exp.schedules[rec.trial].v_mps) if rec.trial in exp.schedules else None
    m.update(time_lost(rec, (lambda i: float(schedule[min(i, len(schedule) - 1)])) if schedule is not None
                       else (lambda i: rec.speed_mps)))
    if rec.trial in exp.schedules:
        v = np.asarray(exp.schedules[rec.trial].v_mps)
        m.update({"schedule_version": exp.schedules[rec.trial].version, "scheduled_speed_mean_mps": float(v.mean()),
                  "scheduled_speed_max_mps": float(v.max())})
    m.update({"experiences_trial": len(d.observed),
              "experiences_fit_retained": hyper.n_total if hyper else None,
              "experiences_fit_used": hyper.n_used if hyper else None,
              "fit_note": hyper.note if hyper else None,
              "heading_rate_residual_rmse_nominal_radps": float(nominal[2] / sc.sim.period_s),
              "heading_rate_residual_rmse_learned_radps": float(learned[2] / sc.sim.period_s),
              "lateral_residual_rmse_nominal_mps": float(nominal[1] / sc.sim.period_s),
              "lateral_residual_rmse_learned_mps": float(learned[1] / sc.sim.period_s)})
    return m


def turn_cap_figures(stepped: list[ControllerStatus]) -> dict:
    """The speed cap from the robot's turn over a trial (services/controller/turn_speed.py): the tracking
    steps it held below the asked speed, the lowest cap among them (None: none), and the turn loss the
    controller had learned by the end."""
    caps = [s.turn_cap_mps for s in stepped if s.state == "tracking" and s.turn_cap_mps > 0.0]
    return {"turn_capped_steps": len(caps), "turn_cap_min_mps": min(caps) if caps else None,
            "turn_loss_per_mps2": stepped[-1].turn_loss_per_mps2 if stepped else None}


def _run_trials(sc: Scenario, exp: Experiment, out: FsPath, summary: dict, records: list, series: list,
                disturbance: list) -> None:
    # what the store knew before the trial: after the teach pass, its experiences if they were learned from
    teach = exp.teach_learning
    model_train, model_hyper = (exp.retained(), teach.hyper) if teach is not None else ([], None)
    for trial in range(1, sc.trials.count + 1):
        rec = exp.repeat(trial, sc.trials.speed_of(trial))
        records.append(rec)
        learned = exp.learn(trial)
        hyper, ingested = learned.hyper, learned.ingested
        if sc.scheduler.enabled and trial < sc.trials.count:
            exp.reschedule(trial)
        d = predict_trial(trial, exp.trial_experiences(trial), model_train, model_hyper, sc.store.v_bin_mps,
                          sc.store.c_vertex, sc.store.c_velocity)
        disturbance.append(d)
        model_train, model_hyper = exp.retained(), hyper
        s = truth_series(exp.truth_path, rec)
        series.append(s)
        m = _trial_summary(sc, exp, rec, s, d, hyper, ingested)
        m["controller_note"] = learned.controller_note
        summary["trials"].append(m)
        write_json_atomic(out / "summary.json", summary)  # nothing lost if a later trial fails
        exp.progress.line(trial_line(sc.trials.count, rec, m))


def run_experiment(scenario_path: str | FsPath, out_dir: str | FsPath, connect: str | None = None,
                   progress_stream: TextIO = sys.stderr, log_level: str = "INFO", overwrite: bool = False,
                   connect_timeout_s: float = 30.0, zenoh_conf: str | dict | None = None,
                   ready_timeout_s: float = READY_TIMEOUT_S) -> dict:
    """Run a whole experiment; returns the summary (also written to out_dir/summary.json). With
    `connect`, against a running deployment; `zenoh_conf` then holds the runner's certificate."""
    t_start = time.monotonic()
    sc = load_scenario(scenario_path)
    check_supported(sc)
    out = FsPath(out_dir)
    prepare_out_dir(out, overwrite)
    progress = Progress(progress_stream)
    launcher, endpoint = _start_deployment(sc, out, log_level, progress) if connect is None else (None, connect)
    summary: dict[str, Any] = {"scenario": sc.name, "algorithm": sc.controller.algorithm, "trials": []}
    session = recorder = exp = None
    series, records, disturbance = [], [], []
    try:
        session = _connect(endpoint, launcher, connect_timeout_s, zenoh_conf)
        recorder = McapRecorder(out / "run.mcap", session, stereo_every=sc.localization.record_stereo_every,
                                ros2=Ros2Export(sc.robot.name, sc.constraints.lateral_m))
        exp = Experiment(sc, session, recorder, progress, launcher, ready_timeout_s=ready_timeout_s)
        exp.wait_ready()
        exp.teach()
        summary["identified_model"] = to_dict(exp.nominal_model)
        summary["teach_unanswered_ticks"] = exp.teach_unanswered_ticks
        if exp.teach_learning is not None:   # the teach pass's experiences, fitted on before trial 1
            hyper = exp.teach_learning.hyper
            summary["teach_learning"] = {"experiences_stored": exp.teach_learning.ingested,
                                         "hyper_version": hyper.version if hyper else None}
        _run_trials(sc, exp, out, summary, records, series, disturbance)
    finally:
        if exp is not None:
            exp.close()
        if recorder is not None:
            recorder.close()
        if session is not None:
            session.close()
        if launcher is not None:
            launcher.stop()
        if exp is not None and "teach_learning" in summary:   # published by the end, acknowledged or not
            summary["teach_learning"]["experiences_trial"] = len(exp.trial_experiences(0))
        if summary["trials"]:   # an empty summary would only make the folder look used
            write_json_atomic(out / "summary.json", summary)
    wall = time.monotonic() - t_start
    # simulated phases only (teach and repeats), so start-up, fits and the report do not blur the figure
    sim_s = exp.teach_sim_s + sum(r.truth[-1].stamp_s - r.truth[0].stamp_s for r in records if r.truth)
    sim_wall = exp.teach_wall_s + sum(r.wall_s for r in records)
    run_info = {"scenario file": str(scenario_path), "endpoint": endpoint, "robot": f"{sc.robot.name} ({sc.robot.preset})",
                "wall time (s)": round(wall, 1), "simulated time, teach + repeats (s)": round(sim_s, 1),
                "wall s per simulated minute (teach + repeats)": round(sim_wall / (sim_s / 60.0), 2) if sim_s else None,
                "wall s per simulated minute (whole run)": round(wall / (sim_s / 60.0), 2) if sim_s else None,
                "messages recorded": recorder.count if recorder else 0,
                "stereo frames not recorded (record_stereo_every)": recorder.stereo_skipped if recorder else 0,
                "messages no service would accept (recorded up to a budget)":
                    f"{recorder.rejected} ({recorder.rejected_skipped} not recorded)" if recorder else "0",
                "messages not recorded, writer behind": recorder.backlog_skipped if recorder else 0}
    from deploy.report import write_report  # matplotlib only when a report is written
    write_report(out / "report.html", sc, exp.truth_path, series, summary, run_info, disturbance,
                 {t: np.asarray(v.v_mps) for t, v in exp.schedules.items()}, route=exp.path)
    progress.line(f"wrote {out / 'summary.json'}, {out / 'report.html'}, {out / 'run.mcap'} in {wall:.1f} s")
    return summary
