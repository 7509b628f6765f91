"""Controller service: the real-time path tracker.

Lockstep: one control step per localization tick, answered with a command carrying that tick.
Realtime: one step per period on a wall-clock timer with the newest estimate. Either way the step
works only from what is already in memory (the route is fetched once, when a trial is prepared),
so the loop never waits on the network.
"""
from __future__ import annotations

import dataclasses
import math
import queue
import threading
import time
from pathlib import Path as FsPath

import numpy as np

from common import keys
from common.bus import Node, query_one, reply
from common.config import ConfigError
from common.messages import (NAME_RE, BridgeStatus, Clock, ControllerStatus, CorridorUpdate, LocState, NominalModel,
                             Odometry, RouteMsg, SpeedSchedule, VelocityCommand)
from common.path import Path
from common.service import Control, Service, service_main
from common.outbox_journal import OutboxJournal
from common.store_client import ExperienceOutbox, WindowCache
from services.controller.actuator import ActuatorLag
from services.controller.calibration import SpreadCalibration, teach_places, teach_shares, teach_speeds
from services.controller.config import ControllerConfig, StoreClientConfig
from services.controller.core import ControllerCore
from services.controller.corridor import Corridor
from services.controller.ilc import ILCMemory
from services.controller.identification import TeachRecorder, teach_observations
from services.controller.ilc_lifted import ILCPlant
from services.controller.laws import SteeringLaw
from services.controller.local_model import LocalModels
from services.controller.nominal_models import NominalModels
from services.controller.registry import LawInputs, law_entry
from services.controller.settings import NMPCSettings
from services.controller.tracker import Decision, PathTracker, TrackerLimits
from services.controller import turn_accel_file, turn_loss_file
from services.controller.turn_accel import fit_turn_accel
from services.controller.turn_speed import TurnLoss

class ControllerService(Service):
    name = "controller"

    def __init__(self, cfg: ControllerConfig, node: Node):
        try:
            law_entry(cfg.algorithm)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        super().__init__(node)
        self.cfg = cfg
        r = cfg.robot_name
        self.k_cmd, self.k_status = keys.cmd_vel(r), keys.ctrl_status(r)
        self.core: ControllerCore | None = None
        self.ilc: ILCMemory | None = None
        self.models: LocalModels | None = None
        self.learning = True
        self.speed_mps = 0.0
        self.trial = 0
        self.path_id = ""
        self.latest_loc: LocState | None = None
        self._stepped_capture = -1
        # the robot's turn lost to skidding, learned in every trial under a nominal model (turn_speed.py)
        self.turn_losses: dict[str, TurnLoss] = {}
        self.clock = node.subscribe_latest(keys.clock(r), Clock)
        node.subscribe_queue(keys.loc_state(r), LocState, self.inbox)
        # corridor changes at run time, kept per route for this and later trials
        self.k_corridor = keys.ctrl_corridor(r)
        self.corridor_updates: dict[str, list[CorridorUpdate]] = {}
        node.subscribe_queue(self.k_corridor, CorridorUpdate, self.inbox)
        lim = cfg.limits
        self.limits = TrackerLimits(lim.v_max_mps, lim.w_max_radps,
                                    lim.max_curvature_per_m if lim.max_curvature_per_m > 0 else math.inf,
                                    lim.decel_max_mps2 if lim.decel_max_mps2 > 0 else math.inf)
        self.gains = cfg.fl
        # the nominal model per route, identified on its teach pass (nominal_models.py)
        self.nominal = NominalModels(r, cfg.period_s, FsPath(cfg.data_dir) / "models" if cfg.data_dir else None,
                                     lim.curvature_rate_max_per_ms, self.limits.w_limit)
        self.calibrations: dict[tuple[str, str], SpreadCalibration] = {}   # (route, model) -> the last trial's
        # the turn drive's acceleration limit per nominal model, read off the repeats (turn_accel.py), and
        # what the current repeat records for it
        self.turn_accel: dict[str, float] = {}
        self.drive_record: TeachRecorder | None = None
        node.subscribe_queue(keys.bridge_status(r), BridgeStatus, self.inbox)
        node.subscribe_queue(keys.odom(r), Odometry, self.inbox)
        node.queryable(keys.ctrl_model(r, "*"), lambda q: self.inbox.put(("q_model", q)))
        st = cfg.store
        # experiences are residuals of the trial's nominal model, and only its own are learned from
        self.model_tag = cfg.nmpc.lag(cfg.period_s).model_tag
        self.outbox = self._outbox(node, r, st) if st.enabled else None
        # one snapshot of the store per trial (store_client.py): the whole route's windows are in memory
        # before the robot moves, so a link to the learning host that drops mid-trial costs nothing, and
        # in lockstep a seed gives one run
        self.cache = WindowCache(node.session, bins=st.bins(), lookahead_vertices=st.lookahead_vertices,
                                 model=self.model_tag, snapshot=True) if st.enabled else None
        self.learning_off_since_s = -1.0    # robot time since which the store's data is missing here
        self.learning_note = ""
        self.step_late_ms = 0.0             # realtime: how late the current step started

    # --- control -----------------------------------------------------------------------------
    def on_control(self, ctl: Control) -> None:
        req = ctl.request
        if req.action == "ping":
            return self.reply(ctl, True, f"algorithm={self.cfg.algorithm} trial={self.trial}")
        if req.action == "prepare":
            self.core = None
            if req.mode == "teach":
                self.nominal.start_teach()
                return self.reply(ctl, True, "recording the teach pass to identify the nominal model")
            return self._prepare_repeat(ctl)
        if req.action == "stop":
            return self._finish_teach(ctl) if req.mode == "teach" else self._stop_repeat(ctl)
        if req.action == "start":
            return self.reply(ctl, True, "")
        return self.reply(ctl, False, f"unsupported action {req.action}")

    def _load_route(self, path_id: str) -> Path:
        msg = query_one(self.node.session, keys.route(path_id), RouteMsg, timeout_s=self.cfg.route_timeout_s)
        window = self.cfg.heading_window_m(law_entry(self.cfg.algorithm).needs_corridor)
        return Path.from_msg(msg, heading_window_m=window)

    def _prepare_repeat(self, ctl: Control) -> None:
        req = ctl.request
        try:
            path = self._load_route(req.path_id)
        except (LookupError, ValueError) as exc:
            return self.reply(ctl, False, f"cannot load route {req.path_id}: {exc}")
        self.learning = req.learning
        schedule, note = None, f"at {req.speed_mps:.2f} m/s"
        if req.schedule:
            try:
                sched = query_one(self.node.session, keys.sched_schedule(req.path_id), SpeedSchedule,
                                  timeout_s=self.cfg.route_timeout_s)
            except (LookupError, ValueError) as exc:
                return self.reply(ctl, False, f"no speed schedule for {req.path_id}: {exc}")
            schedule = np.asarray(sched.v_mps)
            note = f"on schedule v{sched.version} ({schedule.min():.2f}-{schedule.max():.2f} m/s)"
        # the route's identified model, where the configuration leaves it to identification
        settings = self._with_turn_accel(self.cfg.nmpc.with_identified(self.nominal.of(req.path_id)))
        try:
            law, ic_vertices = self._make_law(req.path_id, path, settings)
            lag = settings.lag(self.cfg.period_s)
            turn_share = 0.0 if law_entry(self.cfg.algorithm).chooses_speed else self.cfg.turn_share
            tracker = PathTracker(path, law, self.limits, speed_mps=req.speed_mps,
                                  loc_timeout_s=self.cfg.loc_timeout_s, stop_decel_mps2=self.cfg.stop_decel_mps2,
                                  turn_share=turn_share,
                                  ic_vertices=ic_vertices, schedule=schedule,
                                  corridor=self._corridor(req.path_id, path), lag=lag, period_s=self.cfg.period_s,
                                  turn_loss=self._turn_loss(lag))
        except (OSError, ValueError) as exc:
            return self.reply(ctl, False, f"cannot prepare {self.cfg.algorithm}: {exc}")
        self.core = ControllerCore(path, tracker, self.cfg.period_s,
                                   self._calibration(req.path_id, tracker.lag.model_tag, settings.horizon))
        self.trial, self.path_id, self.latest_loc, self.speed_mps = req.trial, req.path_id, None, req.speed_mps
        self.drive_record = None if tracker.lag.rate_limited else TeachRecorder(self.cfg.period_s)
        self.learning_off_since_s, self.learning_note = -1.0, ""
        self._use_model(tracker.lag.model_tag)
        if self.cache is not None:
            snapshot = self.cache.set_route(req.path_id, len(path))
            self.cache.set_position(0, req.speed_mps)
            if snapshot is not None:
                self.log.info("trial %d: %s", req.trial, snapshot.describe())
        window = f", the route's heading averaged over {path.heading_window_m:.1f} m" if path.heading_window_m else ""
        if settings.turn_accel_max_radps2 is not None:
            window += f", the turn drive's acceleration limit {settings.turn_accel_max_radps2:.2f} rad/s^2"
        capped_m, lowest = tracker.turn_capped()
        if capped_m > 0.0:
            loss = tracker.turn_loss.per_mps2
            window += (f", slower over {capped_m:.1f} m where the route turns beyond {tracker.turn_share:.0%} of "
                       f"the robot's turn at its limit (down to {lowest:.2f} m/s"
                       + (f"; turn lost to skidding {loss:.2f} per m/s^2" if loss > 0 else "") + ")")
        return self.reply(ctl, True, f"tracking {req.path_id} ({len(path)} vertices) {note} "
                          f"with {self.cfg.algorithm}, nominal model {tracker.lag.model_tag}{window}")

    def _with_turn_accel(self, settings: NMPCSettings) -> NMPCSettings:
        """The settings with the turn drive's acceleration limit the earlier repeats under the same model
        met, where none is set by hand; with learning off, none."""
        if settings.turn_accel_max_radps2 is not None or not self.learning:
            return settings
        tag = settings.lag(self.cfg.period_s).model_tag
        if tag not in self.turn_accel and self.cfg.data_dir:
            limit = turn_accel_file.load(self._turn_accel_dir, tag)
            if limit is not None:
                self.turn_accel[tag] = limit
        limit = self.turn_accel.get(tag)
        return settings if limit is None else dataclasses.replace(settings, turn_accel_max_radps2=limit)

    @property
    def _turn_accel_dir(self) -> FsPath:
        return FsPath(self.cfg.data_dir) / "turn_accel"

    def _learn_turn_accel(self, core: ControllerCore) -> str:
        """The limit this repeat's commands and odometry show (turn_accel.py), kept for the next repeats
        under its model (and on disk, for a restarted controller). The last second is left out: its
        messages may still be on their way, and a seed must give one run."""
        rec, self.drive_record = self.drive_record, None
        if rec is None or not rec.u:
            return ""
        u, y = rec.arrays(until_tick=max(rec.u) - round(1.0 / self.cfg.period_s))
        lag = core.tracker.lag
        fit = fit_turn_accel(u[:, 1], y[:, 1], self.cfg.period_s, lag.tau_w_s)
        if fit is None:
            return ""
        if self.learning and math.isfinite(fit.limit_radps2):
            self.turn_accel[lag.model_tag] = fit.limit_radps2
            if self.cfg.data_dir:
                try:
                    turn_accel_file.save(self._turn_accel_dir, lag.model_tag, fit.limit_radps2)
                except OSError as exc:
                    self.log.warning("turn drive's limit not saved (%s): a restarted controller reads it again", exc)
        return fit.describe()

    def _turn_loss(self, lag: ActuatorLag) -> TurnLoss:
        """The turn loss the trial starts from (turn_speed.py): the one the earlier trials under this
        nominal model learned; with learning off, none (it learns its own within the trial)."""
        if not self.learning:
            return TurnLoss(lag.turn_gain)
        tag = lag.model_tag
        if tag not in self.turn_losses:
            self.turn_losses[tag] = turn_loss_file.load(self._turn_loss_dir, tag, lag.turn_gain) \
                if self.cfg.data_dir else TurnLoss(lag.turn_gain)
        return self.turn_losses[tag]

    @property
    def _turn_loss_dir(self) -> FsPath:
        return FsPath(self.cfg.data_dir) / "turn_loss"

    def _save_turn_loss(self, core: ControllerCore) -> None:
        """The turn loss learned so far under the trial's nominal model, for a controller started again."""
        loss = core.tracker.turn_loss
        if not (self.learning and self.cfg.data_dir and loss.samples):
            return
        try:
            turn_loss_file.save(self._turn_loss_dir, core.tracker.lag.model_tag, loss)
        except OSError as exc:
            self.log.warning("turn loss not saved (%s): a restarted controller learns it again", exc)

    def _calibration(self, path_id: str, model_tag: str, horizon: int) -> SpreadCalibration:
        """Where the online check of the predicted spread starts: where the last trial on this route under
        this model left it, else the teach pass's factors (identification.py), else nothing widened. The
        teach factors (overall, and by place as the memory of places) measure the teach residuals against
        the identified prior: a hand-set prior starts unwidened. The drive's acceleration limit seen on the
        teach pass is the robot's, whichever model it drives with, and so are the pass's speeds and the
        share of the steering margin it took by place (the place cap's memory for trial 1)."""
        if (path_id, model_tag) in self.calibrations:
            return self.calibrations[(path_id, model_tag)].continued()
        model = self.nominal.of(path_id)
        if model is None:
            return SpreadCalibration(horizon)
        brake = model.rate_limit_v_mps2 or math.inf
        speeds = teach_speeds(model.place_bin_m, model.place_speed_mps)
        shares = teach_shares(model.place_bin_m, model.place_turn_share)
        if model.model_tag != model_tag or not self.cfg.nmpc.prior_is_identified:
            return SpreadCalibration(horizon, brake_mps2=brake, speeds=speeds, shares=shares)
        return SpreadCalibration(horizon, np.square(model.spread_factors[:horizon]),
                                 places=teach_places(model.place_bin_m, model.place_spread_factors, horizon),
                                 speeds=speeds, brake_mps2=brake, shares=shares)

    def _use_model(self, tag: str) -> None:
        """The trial's nominal model names its experiences and selects the windows and fits learned from."""
        self.model_tag = tag
        if self.outbox is not None:
            self.outbox.set_model(tag)
        if self.cache is not None:
            self.cache.set_model(tag)

    def _stop_repeat(self, ctl: Control) -> None:
        core, self.core = self.core, None
        if core is not None:
            self.calibrations[(self.path_id, self.model_tag)] = core.calibration
        notes = [self._learn_ilc(core)] if self.ilc is not None and core is not None else []
        if core is not None:
            notes.append(self._learn_turn_accel(core))
        if core is not None and core.tracker.turn_loss.samples:
            self._save_turn_loss(core)
            loss = core.tracker.turn_loss
            notes.append(f"turn lost to skidding {loss.per_mps2:.3f} per m/s^2 of drive load "
                         f"({loss.samples} loaded periods)")
        self.ilc = None
        if self.outbox is not None:
            # a sync point for the runner: everything this trial produced is stored once we answer
            ok = self.outbox.wait_acked(self.cfg.store.ack_timeout_s)
            notes.append(f"{self.outbox.acked} experiences acknowledged" if ok else
                         f"{self.outbox.pending} experiences not yet acknowledged by any store")
        return self.reply(ctl, True, "; ".join(["idle"] + [n for n in notes if n]))

    def _finish_teach(self, ctl: Control) -> None:
        """Identify the nominal model on the teach pass just driven (identification.py), keep it for the
        route, and store the pass's disturbance observations as the route's first experiences."""
        req = ctl.request
        rec = self.nominal.teach
        if rec is None:
            return self.reply(ctl, True, "idle (no teach pass recorded)")
        try:
            path = self._load_route(req.path_id)
            model = self.nominal.finish_teach(path, req.stamp_s)
        except (LookupError, ValueError) as exc:
            return self.reply(ctl, False, f"cannot identify the nominal model on {req.path_id}: {exc}")
        self.node.publish(keys.ctrl_model(self.cfg.robot_name, model.path_id), model)
        tau = model.actuator_tau_s
        notes = [*model.notes, self._learn_from_teach(rec, path, model)]
        return self.reply(ctl, True, f"nominal model {model.model_tag}: drive lags {tau[0]:.2f} / {tau[1]:.2f} s, "
                          f"turns at {model.turn_gain:.2f} of its drive, "
                          f"prior x{model.prior_scale[0]:.2f} / {model.prior_scale[1]:.2f} / {model.prior_scale[2]:.2f} "
                          f"of the default" + "".join(f"; {n}" for n in notes if n))

    def _learn_from_teach(self, rec: TeachRecorder, path: Path, model: NominalModel) -> str:
        """The teach pass met the route's slopes and slip before any repeat: its observations, as residuals
        of the model the repeats will use, become trial 0's experiences (GP laws only)."""
        if self.outbox is None or not self.cfg.store.learn_from_teach or law_entry(self.cfg.algorithm).learns != "gp":
            return ""
        lag = self.cfg.nmpc.with_identified(model).lag(self.cfg.period_s)
        self._use_model(lag.model_tag)
        n = 0
        for _, obs in teach_observations(rec, path, lag):
            self.outbox.add(stamp_s=obs.stamp_s, trial=0, path_id=path.path_id, vertex=obs.vertex,
                            v_cmd_mps=obs.v_cmd_mps, a=obs.a, g=obs.g)
            n += 1
        ok = self.outbox.wait_acked(self.cfg.store.ack_timeout_s)
        return f"{n} teach experiences " + ("stored" if ok else "not yet acknowledged by any store")

    def _serve_model(self, q) -> None:
        """lbc/<robot>/ctrl/model/<path_id>: the route's identified nominal model."""
        path_id = str(q.key_expr).rsplit("/", 1)[-1]
        try:
            model = self.nominal.of(path_id) if NAME_RE.match(path_id) else None
            if model is None:
                q.reply_err(f"no nominal model identified on route {path_id!r} here".encode())
            else:
                reply(q, keys.ctrl_model(self.cfg.robot_name, path_id), model)
        finally:
            q.drop()       # the querier waits for the end of the replies until the query is dropped

    def _make_law(self, path_id: str, path: Path, settings: NMPCSettings) -> tuple[SteeringLaw, int]:
        """The steering law of the configured algorithm for a trial on `path`, and its eq. 3.16 m_ic."""
        entry = law_entry(self.cfg.algorithm)
        self.ilc, self.models = None, None
        if entry.learns == "ilc":
            if not self.cfg.data_dir:
                raise ValueError("ILC keeps its feedforward per route on disk: set data_dir")
            self.ilc = ILCMemory.load(FsPath(self.cfg.data_dir) / "ilc", path_id, len(path))
        if entry.learns == "gp" and self.cache is not None:
            cache = self.cache

            def window(vertex: int, speed: float):
                data = cache.local(vertex, speed)
                return data.A, data.G
            # learning off: the same controller on its nominal model only
            self.models = LocalModels(window, lambda: cache.hyper if self.learning else None,
                                      settings.horizon * self.cfg.period_s, self.cfg.store.v_bin_mps,
                                      hold_steps=entry.window_hold_steps,
                                      variance_caps=settings.vouch_lengthscales if entry.uses_variance else None)
        law = entry.build(LawInputs(self.gains, settings, self.cfg.period_s,
                                    self.models.model_for if self.models else (lambda ctx: None),
                                    self.models.model_at if self.models else (lambda ctx, v: None), self.ilc))
        return law, self.cfg.ilc.ic_vertices if entry.learns == "ilc" else 0

    def _corridor(self, path_id: str, path: Path) -> Corridor:
        c = self.cfg.corridor
        corridor = Corridor(path.s, c.lateral_m, math.radians(c.heading_deg))
        for f, t, left, right, head_deg in c.segments:
            corridor.update(f, t, left, right, math.radians(head_deg))
        for u in self.corridor_updates.get(path_id, []):
            corridor.update(u.from_m, u.to_m, u.left_m, u.right_m, u.heading_rad)
        return corridor

    def _on_corridor(self, msg: CorridorUpdate) -> None:
        self.corridor_updates.setdefault(msg.path_id, []).append(msg)
        tracker = self.core.tracker if self.core is not None else None
        changed = 0
        if tracker is not None and msg.path_id == self.path_id and tracker.corridor is not None:
            changed = tracker.corridor.update(msg.from_m, msg.to_m, msg.left_m, msg.right_m, msg.heading_rad)
        self.log.info("corridor of %s over %.1f-%.1f m: [%+.2f, %+.2f] m, +-%.1f deg (%d vertices of the active "
                      "route)", msg.path_id, msg.from_m, msg.to_m, msg.right_m, msg.left_m,
                      math.degrees(msg.heading_rad), changed)

    def _learn_ilc(self, core: ControllerCore) -> str:
        """The feedforward for the next trial (ilc.py), saved per route; nothing is learned when learning is
        off. The lifted update's model of the loop: the FL gains, the drive lag the trial ran with (the
        identified one unless set by hand) and the estimates' mean age."""
        if not self.learning:
            return "ILC learning off: feedforward unchanged"
        lag, age = core.tracker.lag, self.ilc.mean_age_s
        plant = ILCPlant(self.gains, tau_w_s=lag.tau_w_s, delay_s=age, turn_gain=lag.turn_gain,
                         lead_s=age + lag.tau_w_s if self.gains.lead else 0.0)
        update = self.ilc.update(self.cfg.ilc, plant, np.diff(core.path.s))
        where = self.ilc.save(FsPath(self.cfg.data_dir) / "ilc")
        return f"ILC feedforward updated (trial {self.ilc.trials}, {update.describe()}), saved as {where.name}"

    # --- control loop ------------------------------------------------------------------------
    def on_message(self, key: str, msg) -> None:
        if key == self.k_corridor:
            return self._on_corridor(msg)
        if key == "q_model":
            return self._serve_model(msg)
        if self.nominal.teach is not None:
            return self.nominal.record(msg)
        if self.drive_record is not None and isinstance(msg, BridgeStatus):
            if msg.trial == self.trial and msg.mode == "repeat" and msg.running:
                self.drive_record.add_applied(msg.tick, msg.v_cmd_applied_mps, msg.w_cmd_applied_radps)
            return
        if self.drive_record is not None and isinstance(msg, Odometry):
            self.drive_record.add_odometry(msg.tick, msg.v_mps, msg.w_radps)
            return
        if not isinstance(msg, LocState) or self.core is None or msg.trial != self.trial:
            return
        if msg.path_id != self.path_id or msg.vertex >= len(self.core.path):
            self.node.decoder.reject(key, f"an estimate for route {msg.path_id} vertex {msg.vertex} while tracking "
                                          f"{self.path_id} ({len(self.core.path)} vertices)")
            return
        self.latest_loc = msg
        if self.cfg.clock_mode == "lockstep":
            self._step(now_s=msg.stamp_s, tick=msg.tick, loc=msg)

    def run(self, stop: threading.Event) -> None:
        if self.cfg.clock_mode == "lockstep":
            return super().run(stop)
        next_wall = time.monotonic()
        while not stop.is_set():
            next_wall += self.cfg.period_s
            resync = False
            while (left := next_wall - time.monotonic()) > 0:
                try:
                    key, item = self.inbox.get(timeout=left)
                except queue.Empty:
                    break
                self.dispatch(key, item)
                # a control request (prepare: the route, the law, the store's snapshot) is a change of
                # phase, not a step: the period starts afresh after it rather than counting as late
                resync = resync or key == "__control__"
            late_s = 0.0 if resync else time.monotonic() - next_wall
            self.step_late_ms = max(0.0, late_s) * 1e3
            if resync or late_s > self.cfg.period_s:
                # a step that missed its period is taken now and the grid restarts from it: the missed
                # ones are not made up back to back (each would act on the same robot time)
                next_wall = time.monotonic()
            clock, _ = self.clock.get()
            if self.core is None:
                self.on_idle()
            if self.core is not None and clock is not None:
                # robot time now: the newest clock tick from the bridge; an estimate is used once, after
                # that the tracker holds (or stops) as it does through any gap in localization
                loc = self.latest_loc
                if loc is not None and loc.capture_tick == self._stepped_capture:
                    loc = None
                elif loc is not None:
                    self._stepped_capture = loc.capture_tick
                self._step(now_s=clock.stamp_s, tick=clock.tick, loc=loc)

    def _step(self, now_s: float, tick: int, loc: LocState | None) -> None:
        t0 = time.perf_counter()
        d, obs = self.core.step(now_s, tick, loc)
        solve_ms = (time.perf_counter() - t0) * 1e3
        # the command first: everything below is bookkeeping that must not delay it
        self.node.publish(self.k_cmd, VelocityCommand(stamp_s=now_s, tick=tick, trial=self.trial,
                                                      v_mps=d.v_mps, w_radps=d.w_radps, source=self.cfg.algorithm))
        if self.outbox is not None:
            for o in obs:
                self.outbox.add(stamp_s=o.stamp_s, trial=self.trial, path_id=self.path_id, vertex=o.vertex,
                                v_cmd_mps=o.v_cmd_mps, a=o.a, g=o.g)
            self.outbox.flush()
        window_n, hyper_version = self._follow_window(d, now_s)
        # the command must arrive; in realtime a status may be dropped under congestion rather than stall
        # the loop, in lockstep it is part of the tick's answer (the bridge waits for it, the runner counts it)
        self.node.publish(self.k_status, self._status(d, now_s, tick, solve_ms, window_n, hyper_version),
                          droppable=self.cfg.clock_mode != "lockstep")
        self.core.keep_prediction(tick, d)
        if self.models is not None and d.v_mps > 0:
            # the next window's GP now, while the robot drives on this command (local_model.py)
            self.models.prepare(self.core.path, d.distance_m + d.v_mps * self.cfg.period_s, d.v_mps)

    def _follow_window(self, d: Decision, now_s: float) -> tuple[int, int]:
        """Moves the prefetch to where the robot is and notes whether learning is off here (the store's
        data for this place is missing); returns the size of the window the law predicted with and the
        hyperparameters' version."""
        if self.cache is None:
            return 0, 0
        speed = d.v_mps if d.v_mps > 0 else self.speed_mps   # the commanded speed here, when moving
        self.cache.set_position(d.vertex, speed, self.core.tracker.speed_at(d.distance_m))
        local = self.cache.local(d.vertex, speed)
        self._note_learning(local.missing_bins, now_s)
        if self.models is not None:
            return self.models.last_n, self.models.last_version
        hyper = self.cache.hyper
        return len(local.A), hyper.version if hyper is not None else 0

    def _note_learning(self, missing_bins: int, now_s: float) -> None:
        if missing_bins == 0:
            if self.learning_off_since_s >= 0:
                self.log.info("learning on again at %.1f s (off since %.1f s)", now_s, self.learning_off_since_s)
            self.learning_off_since_s, self.learning_note = -1.0, ""
            return
        if self.learning_off_since_s < 0:
            self.learning_off_since_s = now_s
            self.log.warning("learning off at %.1f s: the store's data for vertex here is missing (%s); "
                             "tracking with the nominal model", now_s, self.cache.last_error or "not fetched yet")
        self.learning_note = f"store data missing: {self.cache.last_error or 'not fetched yet'}"

    def _status(self, d: Decision, now_s: float, tick: int, solve_ms: float, window_n: int,
                hyper_version: int) -> ControllerStatus:
        law = d.law
        pred = law.predicted if law is not None and law.predicted is not None else np.zeros((0, 3))
        unc = law.uncertainty if law is not None else None
        return ControllerStatus(
            stamp_s=now_s, tick=tick, trial=self.trial, algorithm=self.cfg.algorithm, state=d.state,
            reason=d.reason, path_id=self.path_id, vertex=d.vertex, distance_m=d.distance_m,
            lateral_m=d.lateral_m, heading_rad=d.heading_rad, v_cmd_mps=d.v_mps, w_cmd_radps=d.w_radps,
            solve_ms=solve_ms, iterations=d.iterations, loc_age_s=min(d.loc_age_s, 1e6),
            rejected_msgs=self.node.decoder.rejected_total,
            experiences_sent=self.outbox.acked + self.outbox.pending if self.outbox else 0,
            experiences_pending=self.outbox.pending if self.outbox else 0,
            window_experiences=window_n, hyper_version=hyper_version,
            w_ff_radps=law.feedforward_radps if law is not None else 0.0, pred_x_m=pred[:, 0].tolist(),
            pred_y_m=pred[:, 1].tolist(), pred_theta_rad=pred[:, 2].tolist(),
            sigma_lat_m=unc.sigma_lat_max_m if unc else 0.0, sigma_head_rad=unc.sigma_head_max_rad if unc else 0.0,
            solver_status=law.solve.status if law is not None and law.solve is not None else "",
            spread_factors=[math.sqrt(k) for k in unc.spread_kappa] if unc and unc.spread_kappa else
            list(self.core.spread_factors) if self.core is not None else [],
            pred_sigma_lat_m=list(unc.horizon_sigma_lat_m) if unc else [],
            pred_sigma_head_rad=list(unc.horizon_sigma_head_rad) if unc else [],
            learning_off_since_s=self.learning_off_since_s, learning_note=self.learning_note,
            step_late_ms=self.step_late_ms,
            turn_cap_mps=self.core.tracker.turn_cap_at(d.distance_m) if self.core is not None else 0.0,
            turn_loss_per_mps2=self.core.tracker.turn_loss.per_mps2 if self.core is not None else 0.0,
            speed_held_by=d.held_by)

    def _outbox(self, node: Node, robot: str, st: StoreClientConfig) -> ExperienceOutbox:
        """Pending experiences are kept on disk too (with a data_dir): a controller that dies while the
        learning host is unreachable sends them when it is back."""
        journal = None
        if self.cfg.data_dir:
            journal = OutboxJournal(FsPath(self.cfg.data_dir) / "outbox.db", robot)
        else:
            self.log.warning("no data_dir: experiences not yet acknowledged by a store are kept in memory only")
        outbox = ExperienceOutbox(node, robot, resend_after_s=st.resend_after_s, model=self.model_tag,
                                  journal=journal)
        if outbox.recovered:
            self.log.info("%d experiences not acknowledged before the last stop: sending them again (source %s)",
                          outbox.recovered, outbox.source)
        return outbox

    def on_idle(self) -> None:
        if self.outbox is not None and self.core is None:
            self.outbox.flush()        # between trials: re-send what no store has acknowledged yet

    def close(self) -> None:
        if self.cache is not None:
            self.cache.close()
        if self.outbox is not None and self.outbox.journal is not None:
            self.outbox.journal.close()


def main(argv: list[str] | None = None) -> int:
    return service_main("controller", ControllerConfig, ControllerService, lambda c: c.robot_name, argv)
