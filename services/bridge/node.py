"""Bridge service, `sim` backend: owns the robot clock, steps the simulator, applies commands.

Lockstep (default): after publishing tick k the bridge waits until the tick has been answered (the
controller's command and its status during a repeat, the localizer's state during teach) or
`lockstep_timeout_s` passes or the answering service's liveliness token disappears, then steps (each tick
stepped so is counted and reported with the trial's end: that run depended on the wall clock). The
status too, because whoever watches the run (the experiment runner, the scheduler) learns from it:
once it is out, whatever follows from the next tick or the trial's end reaches them after it. So that a
seed gives one run, a lockstep repeat ends at the first tick at which the controller has reported the
end of the route and the robot is at rest, or has reported itself stopped for STOPPED_ENDS_TRIAL_S (the
runner's rule, which it would otherwise carry out with a stop request that arrives a tick or two late),
and a stop request takes effect once the current tick has been answered, not wherever it happens to
arrive. Realtime: it steps at
wall-clock pace and applies whatever command arrived last. Either way the watchdog (robot time)
brakes the robot when commands go stale.
"""
from __future__ import annotations

import math
import queue
import threading
import time

from common import keys, se2
from common.bus import Node
from common.messages import (CONTROLLER_STOPPED, ENDED_AT_ROUTE_END, STOPPED_ENDS_TRIAL_S, BridgeStatus, Clock,
                             ControllerStatus, LocState, Odometry, TrialEvent, TruthPose, VelocityCommand)
from common.service import Control, Service, service_main
from services.bridge.config import BridgeConfig
from services.bridge.render import StereoRenderer
from services.bridge.simulator import SimSample, Simulator
from services.bridge.teach_driver import PurePursuitDriver, smooth_waypoints

# below these ground speeds a robot that has finished its route is at rest (the runner's rule too)
AT_REST_MPS = 0.01
AT_REST_RADPS = 0.01


class BridgeService(Service):
    name = "bridge"

    def __init__(self, cfg: BridgeConfig, node: Node):
        super().__init__(node)
        self.cfg = cfg
        self.robot = cfg.robot_name
        c = cfg.clock
        self.sim = Simulator(cfg.robot, cfg.terrain, cfg.seed, c.period_s, c.physics_substeps, c.watchdog_s)
        self.reference = smooth_waypoints(cfg.teach.waypoints, cfg.teach.corner_radius_m, cfg.teach.loop)
        self.mode = "idle"
        self.running = False
        self.trial = 0
        self.path_id = ""
        self.deadline_s = math.inf
        self.driver: PurePursuitDriver | None = None
        self.sample: SimSample = self.sim.sample()
        self.latest_cmd: VelocityCommand | None = None
        self._applied_cmd: VelocityCommand | None = None
        self.latest_loc_tick = -1
        self.latest_status_tick = -1     # of the controller's statuses of this trial (lockstep)
        self.route_finished = False      # the controller has reported the end of the route (lockstep)
        self.stopped: tuple[float, float, str] | None = None   # since, last status stamp, reason (lockstep)
        self._stop_requested = False     # a stop request waits for the end of the tick (lockstep)
        self.alive: set[str] = set()
        self.unanswered_ticks = 0        # of this trial: stepped without their answer (lockstep)
        r = self.robot
        self.k_clock, self.k_truth, self.k_odom = keys.clock(r), keys.truth(r), keys.odom(r)
        self.k_status, self.k_event = keys.bridge_status(r), keys.trial_event(r)
        self.k_stereo = keys.stereo(r)
        # the textured world is built once, up front (a few seconds), so no tick waits for it
        self.renderer = StereoRenderer.from_bridge_config(cfg) if cfg.stereo is not None else None
        node.subscribe_queue(keys.cmd_vel(r), VelocityCommand, self.inbox)
        node.subscribe_queue(keys.loc_state(r), LocState, self.inbox)
        if c.mode == "lockstep":
            node.subscribe_queue(keys.ctrl_status(r), ControllerStatus, self.inbox)
        node.liveliness_subscriber(keys.alive_all(r), lambda k, up: self.inbox.put(("__alive__", (k, up))))

    # --- inputs ------------------------------------------------------------------------------
    def on_message(self, key: str, msg) -> None:
        if key == "__alive__":
            k, up = msg
            (self.alive.add if up else self.alive.discard)(k)
        elif isinstance(msg, VelocityCommand):
            if self.mode == "repeat" and msg.trial == self.trial:
                self.latest_cmd = msg
        elif isinstance(msg, LocState):
            if msg.trial == self.trial:
                self.latest_loc_tick = max(self.latest_loc_tick, msg.tick)
        elif isinstance(msg, ControllerStatus):
            if self.mode == "repeat" and msg.trial == self.trial and msg.tick > self.latest_status_tick:
                self.latest_status_tick = msg.tick
                self.route_finished = self.route_finished or msg.state == "finished"
                since = msg.stamp_s if self.stopped is None else self.stopped[0]
                self.stopped = (since, msg.stamp_s, msg.reason) if msg.state == "stopped" else None

    def on_control(self, ctl: Control) -> None:
        req = ctl.request
        if req.action == "ping":
            return self.reply(ctl, True, f"mode={self.mode} running={self.running} t={self.sim.t:.2f}")
        if req.action == "prepare":
            if self.running:
                return self.reply(ctl, False, f"trial {self.trial} is still running; stop it first")
            if req.mode == "idle":
                return self.reply(ctl, False, "prepare needs mode teach or repeat")
            start = self.reference[0].copy()
            driver = None
            if req.mode == "teach":
                driver = PurePursuitDriver(self.reference, self.cfg.teach.speed_mps,
                                           self.cfg.robot.max_curvature, self.cfg.robot.w_max_radps)
            else:
                start = se2.compose(start, [0.0, self.cfg.start_offset_m, math.radians(self.cfg.start_offset_deg)])
            self.sim.reset(start, req.trial)
            # all checks passed and the world is reset: only now take on the new trial
            self.mode, self.trial, self.path_id, self.driver = req.mode, req.trial, req.path_id, driver
            self.sample = self.sim.sample()
            self.latest_cmd = self._applied_cmd = None
            self.latest_loc_tick = self.latest_status_tick = -1
            self.route_finished, self.stopped = False, None
            self.deadline_s = self.sim.t + req.max_duration_s if req.max_duration_s > 0 else math.inf
            return self.reply(ctl, True, f"{req.mode} trial {req.trial} ready at "
                              f"({start[0]:.2f}, {start[1]:.2f}, {math.degrees(start[2]):.1f} deg)")
        if req.action == "start":
            if self.mode == "idle":
                return self.reply(ctl, False, "nothing prepared")
            if self.running:
                return self.reply(ctl, False, "already running")
            self.running = True
            self.unanswered_ticks = 0
            self.node.publish(self.k_event, TrialEvent(stamp_s=self.sim.t, trial=self.trial, mode=self.mode,
                                                       event="started", reason="", path_id=self.path_id))
            return self.reply(ctl, True, f"{self.mode} trial {self.trial} started at t={self.sim.t:.2f} s")
        if req.action == "stop":
            if self.running and self.cfg.clock.mode == "lockstep":
                # between ticks, once this one is answered: its answer reaches everyone before the end
                self._stop_requested = True
                return self.reply(ctl, True, f"stopping after tick {self.sample.tick}")
            if self.running:
                self._end_trial("stopped on request")
            return self.reply(ctl, True, "stopped")
        return self.reply(ctl, False, f"unsupported action {req.action}")

    # --- loop --------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        period = self.cfg.clock.period_s
        next_wall = time.monotonic()
        while not stop.is_set():
            if not self.running:
                self._drain(timeout=0.1)
                next_wall = time.monotonic()
                continue
            self._publish_tick()
            if self.cfg.clock.mode == "lockstep":
                self._wait_for_answer(stop)
            else:
                next_wall += period
                while not stop.is_set() and (left := next_wall - time.monotonic()) > 0:
                    self._drain(timeout=left)
                if time.monotonic() - next_wall > 5 * period:
                    next_wall = time.monotonic()  # fell far behind (debugger, suspend): do not sprint
            if not self.running:
                continue
            self._apply_inputs()
            if self._trial_over():
                continue
            self.sample = self.sim.step()

    def _drain(self, timeout: float) -> bool:
        try:
            key, item = self.inbox.get(timeout=timeout)
        except queue.Empty:
            return False
        self.dispatch(key, item)
        while True:  # take whatever else is already there
            try:
                key, item = self.inbox.get_nowait()
            except queue.Empty:
                return True
            self.dispatch(key, item)

    def _answerer(self) -> str:
        return keys.alive(self.robot, "controller" if self.mode == "repeat" else "localizer")

    def _answered(self) -> bool:
        tick = self.sample.tick
        if self.mode == "repeat":
            return self.latest_cmd is not None and self.latest_cmd.tick >= tick and self.latest_status_tick >= tick
        return self.latest_loc_tick >= tick

    def _wait_for_answer(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + self.cfg.clock.lockstep_timeout_s
        while self.running and not stop.is_set() and not self._answered():
            if self._answerer() not in self.alive:
                self.unanswered_ticks += 1
                return  # nobody to wait for: the robot's own watchdog takes over
            left = deadline - time.monotonic()
            if left <= 0:
                if not self.unanswered_ticks:
                    self.log.warning("tick %d not answered within %.1f s; stepping without it (this run is "
                                     "no longer reproducible)", self.sample.tick, self.cfg.clock.lockstep_timeout_s)
                self.unanswered_ticks += 1
                return
            self._drain(timeout=left)

    def _apply_inputs(self) -> None:
        s = self.sample
        if self.mode == "teach" and self.driver is not None:
            self.sim.command(*self.driver.command((s.x, s.y, s.theta)))
        elif self.latest_cmd is not None and self.latest_cmd is not self._applied_cmd:
            self.sim.command(self.latest_cmd.v_mps, self.latest_cmd.w_radps)
            self._applied_cmd = self.latest_cmd

    def _trial_over(self) -> bool:
        """Ends the trial where it is over: the robot-time rules first, so that where one holds at the tick
        a stop request also arrived for, the trial ends with its reason whatever the timing."""
        reason = self._ended_by_rule()
        if reason is None and self._stop_requested:
            reason = "stopped on request"
        if reason is None:
            return False
        self._end_trial(reason)
        return True

    def _ended_by_rule(self) -> str | None:
        s = self.sample
        if self.mode == "teach" and self.driver is not None and self.driver.done and abs(s.v_ground) < 1e-3:
            return "teach complete"
        if s.stamp_s >= self.deadline_s:
            return "time limit reached"
        if self.mode != "repeat" or self.cfg.clock.mode != "lockstep":
            return None
        if self.route_finished and abs(s.v_ground) < AT_REST_MPS and abs(s.w_ground) < AT_REST_RADPS:
            return ENDED_AT_ROUTE_END
        if self.stopped is not None and self.stopped[1] - self.stopped[0] >= STOPPED_ENDS_TRIAL_S:
            return f"{CONTROLLER_STOPPED}: {self.stopped[2]}"
        return None

    def _end_trial(self, reason: str) -> None:
        mode, self.mode, self.running = self.mode, "idle", False   # a new trial needs a new prepare
        self._stop_requested = False
        self.sim.end_trial()
        self.sample = self.sim.sample()
        self.latest_cmd = self._applied_cmd = None
        self.node.publish(self.k_event, TrialEvent(stamp_s=self.sim.t, trial=self.trial, mode=mode,
                                                   event="ended", reason=reason, path_id=self.path_id,
                                                   unanswered_ticks=self.unanswered_ticks))
        self.log.info("%s trial %d ended at t=%.2f s: %s", mode, self.trial, self.sim.t, reason)
        if self.unanswered_ticks:
            self.log.warning("%s trial %d: %d ticks stepped without their answer", mode, self.trial,
                             self.unanswered_ticks)

    def _publish_tick(self) -> None:
        s, r, trial = self.sample, self.node, self.trial
        r.publish(self.k_clock, Clock(stamp_s=s.stamp_s, tick=s.tick, period_s=self.cfg.clock.period_s,
                                      mode=self.cfg.clock.mode, trial=trial))
        r.publish(self.k_odom, Odometry(stamp_s=s.stamp_s, tick=s.tick, v_mps=s.odom_v, w_radps=s.odom_w,
                                        x_odom_m=s.odom_x, y_odom_m=s.odom_y, theta_odom_rad=s.odom_theta))
        r.publish(self.k_status, BridgeStatus(stamp_s=s.stamp_s, tick=s.tick, trial=trial, mode=self.mode,
                                              running=self.running, watchdog_tripped=s.watchdog_tripped,
                                              cmd_age_s=s.cmd_age_s, v_cmd_applied_mps=s.v_cmd,
                                              w_cmd_applied_radps=s.w_cmd,
                                              rejected_msgs=self.node.decoder.rejected_total))
        if self.renderer is not None:
            # realtime: a newer frame supersedes a dropped one; lockstep: the localizer answers the tick from it
            r.publish(self.k_stereo, self.renderer.frame_for_sample(s, trial),
                      droppable=self.cfg.clock.mode != "lockstep")
        # truth last: the localizer reacts to it, so everything else of this tick is already out
        r.publish(self.k_truth, TruthPose(stamp_s=s.stamp_s, tick=s.tick, trial=trial, x_world_m=s.x,
                                          y_world_m=s.y, theta_world_rad=s.theta, v_mps=s.v_ground,
                                          w_radps=s.w_ground, lateral_slip_mps=s.v_lateral))


def main(argv: list[str] | None = None) -> int:
    return service_main("bridge", BridgeConfig, BridgeService, lambda c: c.robot_name, argv)
