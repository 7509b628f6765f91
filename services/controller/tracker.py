"""The controller's tracking core: one call per control step, localization in, command and status out.

It owns everything that is not the steering law itself: waiting for the first estimate, holding the
last command through a short dropout, stopping when localization is stale or lost, the speed profile
(scheduled speed, robot limits, the turn the robot makes, a gentle stop into the end of the route),
angular-rate limits (actuator and, for an Ackermann robot, the steering limit), the initial-condition smoothing of
eq. 3.16, and the end of the route. The law (laws.py) chooses w. Every stop it makes while the robot
still rolls, a law's safety stop and the end of the route alike, brakes while steering along the route
(_brake).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from common import se2
from common.messages import LocState
from common.path import Path
from services.controller.actuator import ActuatorLag
from services.controller.brake import balanced_offset, roll_out_m
from services.controller.corridor import Corridor
from services.controller.fl import FLGains, fl_angular_rate
from services.controller.laws import FLLaw, LawResult, StepContext, SteeringLaw
from services.controller.calibration import PlaceCap
from services.controller.missed_variance import FloorsBySpeed
from services.controller.turn_speed import TURN_SHARE, TurnLoss, turn_cap, turn_speed_caps

LOC_TIMEOUT_S = 0.5      # stop when the newest estimate is older than this
STOP_DECEL_MPS2 = 0.4    # the gentle deceleration into the end of the route
REST_MPS = 0.03          # a braking robot whose drive the lag model puts below this has stopped
REST_RADPS = 0.02        # ... and, a skid-steer, has stopped turning below this
CREEP_MPS = 0.01         # what a braking Ackermann is commanded while it rolls: its steering needs a speed
BRAKE_CURVATURE_PER_M = 0.5   # the most a stop steers beyond the route's own curvature
END_OF_ROUTE = "end of route reached"
RECOVERY_ROOM_M = 0.02   # the least room a heading error is given to be turned away in (_recovery_cap)
RECOVERY_MIN_MPS = 0.2   # ... and the least speed it holds the robot to
RECOVERED_SHARE = 0.5    # a recovery ends once the errors are back within this share of the corridor

# what a law may fail with numerically (ArithmeticError: FloatingPointError, OverflowError, ZeroDivisionError)
NUMERICAL_FAILURES = (ArithmeticError, np.linalg.LinAlgError)


@dataclass(frozen=True)
class TrackerLimits:
    v_max_mps: float
    w_max_radps: float
    max_curvature: float = math.inf   # Ackermann: tan(steer_max) / L
    decel_mps2: float = math.inf      # the hardest braking a safety stop uses (inf: at once)

    def w_limit(self, v: float) -> float:
        return min(self.w_max_radps, abs(v) * self.max_curvature)


@dataclass(frozen=True)
class Decision:
    v_mps: float
    w_radps: float
    state: str           # ControllerState
    reason: str
    vertex: int
    distance_m: float
    lateral_m: float
    heading_rad: float
    loc_age_s: float
    law: LawResult | None = None     # what the steering law reported, when it ran this step
    held_by: str = ""                # what held v_mps below the asked speed (messages.SpeedCause; "": nothing)

    @property
    def iterations(self) -> int:
        return self.law.solve.iterations if self.law is not None and self.law.solve is not None else 0


class PathTracker:
    def __init__(self, path: Path, law: SteeringLaw, limits: TrackerLimits, *, speed_mps: float,
                 loc_timeout_s: float = LOC_TIMEOUT_S, stop_decel_mps2: float = STOP_DECEL_MPS2, ic_vertices: int = 0,
                 schedule: np.ndarray | None = None, corridor: Corridor | None = None,
                 lag: ActuatorLag = ActuatorLag(), period_s: float = 0.1, turn_share: float = TURN_SHARE,
                 turn_loss: TurnLoss | None = None):
        self.path = path
        self.period_s = period_s
        self.lag = lag
        self.law = law
        self.limits = limits
        self.asked_mps = speed_mps            # the trial's speed as asked (the robot's limit may hold it)
        self.speed_mps = min(speed_mps, limits.v_max_mps)
        if schedule is not None and len(schedule) != len(path):
            raise ValueError(f"a schedule of {len(schedule)} speeds for a route of {len(path)} vertices")
        self.schedule = None if schedule is None else np.asarray(schedule, dtype=float)
        self.loc_timeout_s = loc_timeout_s
        self.stop_decel = stop_decel_mps2
        self.ic_vertices = ic_vertices
        self.finished = False
        self.corridor = corridor
        self.halted = ""        # a law's safety stop (C-/RC-LB-NMPC): latched until the next trial
        self._last_ok: LocState | None = None
        self._prev_pose: tuple[int, np.ndarray] | None = None   # (capture tick, pose) one estimate back
        self._initial_error: tuple[float, float] | None = None
        self._last_cmd = (0.0, 0.0)
        self._fallback = FLLaw(FLGains(), lag)
        self.turn_share = turn_share
        # a skid-steer's turn loss with its drive's load, learned as it drives (an Ackermann's: not modelled)
        self.turn_loss = turn_loss if turn_loss is not None else TurnLoss(lag.turn_gain)
        self._caps_loss = self._loss_now()
        self.turn_caps = self._turn_caps()
        self._recovery_hold = math.inf  # the speed the recovery cap last held, until the errors are back
        self._prev_head: tuple[int, float] | None = None   # (capture tick, heading error) one estimate back

    def _loss_now(self) -> float:
        return self.turn_loss.per_mps2 if math.isinf(self.limits.max_curvature) else 0.0

    def learn_turn(self, v_mps: float, w_drive_radps: float, w_radps: float, s_m: float) -> None:
        """One period's turn at `s_m` along the route (turn_speed.TurnLoss); the caps follow once the loss
        moved by a tenth."""
        kappa = float(np.interp(s_m, self.path.s, self.path.curvature))
        self.turn_loss.add(v_mps, w_drive_radps, w_radps, kappa * v_mps)
        c = self._loss_now()
        if abs(c - self._caps_loss) > 0.1 * self._caps_loss + 1e-3:
            self._caps_loss = c
            self.turn_caps = self._turn_caps()

    def _turn_caps(self) -> np.ndarray:
        """(N,) the speed the robot can turn along the route at, per vertex (turn_speed.py), for the
        fastest speed this trial asks; a turn share of 0: the asked speeds."""
        share = self.turn_share
        top = self.speed_mps if self.schedule is None else float(np.max(self.schedule, initial=self.speed_mps))
        top = min(top, self.limits.v_max_mps)
        if share <= 0.0:
            return np.full(len(self.path), max(top, 0.0))
        lim = self.limits
        caps = turn_speed_caps(self.path, share * self.lag.turn_gain, lim.w_max_radps, lim.max_curvature,
                               settle_m=top * self.lag.tau_w_s, decel_mps2=self.stop_decel,
                               lead_m=top * (self.lag.tau_v_s + self.period_s), loss_per_mps2=self._caps_loss)
        return np.minimum(caps, max(top, 0.0))

    def turn_cap_at(self, distance_m: float) -> float:
        """The turn's cap at a place where it holds the robot below the asked speed, else 0."""
        cap = float(np.interp(distance_m, self.path.s, self.turn_caps))
        return cap if cap < min(self.scheduled_speed(distance_m), self.limits.v_max_mps) - 1e-6 else 0.0

    def turn_capped(self) -> tuple[float, float]:
        """(metres of route, lowest speed) where the turn cap holds the robot below its asked speed."""
        asked = np.array([self.scheduled_speed(s) for s in self.path.s.tolist()])
        below = self.turn_caps < np.minimum(asked, self.limits.v_max_mps) - 1e-6
        if not below.any():
            return 0.0, math.inf
        ds = np.diff(self.path.s, append=self.path.s[-1])
        return float(ds[below].sum()), float(self.turn_caps[below].min())

    def scheduled_speed(self, distance_m: float) -> float:
        """Speed at a place on the route: the schedule's speed at the nearest vertex (thesis 5.3.1:
        v_cmd = v_sched,i), or the one fixed speed of the trial, as asked (speed_at holds it to the robot's
        limit)."""
        if self.schedule is None:
            return self.asked_mps
        i = int(np.clip(np.searchsorted(self.path.s, distance_m), 0, len(self.path) - 1))
        if i > 0 and distance_m - self.path.s[i - 1] < self.path.s[i] - distance_m:
            i -= 1
        return float(self.schedule[i])

    def speed_at(self, distance_m: float) -> float:
        """What the robot is commanded at a distance along the route: the schedule, the robot's limit,
        the speed it can turn along the route at (turn_speed.py), and a constant deceleration into the
        end of the route."""
        return min(v for v, _ in self._speed_limits(distance_m))

    def _speed_limits(self, distance_m: float) -> tuple[tuple[float, str], ...]:
        """speed_at's terms, each with its SpeedCause (the asked speed's: "")."""
        remaining = max(self.path.length_m - distance_m, 0.0)
        return ((self.scheduled_speed(distance_m), ""),
                (math.sqrt(2.0 * self.stop_decel * remaining) + 0.02, "route-end"),
                (self.limits.v_max_mps, "robot-limit"),
                (float(np.interp(distance_m, self.path.s, self.turn_caps)), "turn-cap"))

    def _recovery_cap(self, distance_m: float, lateral_m: float, heading_rad: float) -> float:
        """The fastest speed at which a skid-steer heading towards its corridor's edge can still turn its
        heading error away before it gets there (inf: any): turning it away at curvature c moves the robot
        e_H^2 / 2c further, so c = e_H^2 / 2 room on top of the route's own, which turn_cap turns into a
        speed with the learned turn loss (turn_speed.py). A skid-steer's turn per metre falls with speed
        (a Grizzly with a turn loss of 0.6 per m/s^2 turned 0.18 /m at 1.8 m/s and 0.6 /m at 0.8 m/s): at
        the asked speed after a corner it took 37 deg over, a fixed-speed law swung +-3.6 m and 60 deg
        in a 0.35 m corridor (bench seed 1931, s197186723). Only for laws that keep the asked speed (the
        turn cap's share > 0; RC-LB-NMPC chooses its own) and a turn that slowing gives more of (not an
        Ackermann's curvature)."""
        if self.corridor is None or self.turn_share <= 0.0 or math.isfinite(self.limits.max_curvature):
            return math.inf
        right, left, _ = (float(x) for x in self.corridor.at(distance_m))
        room = max((left - lateral_m) if heading_rad > 0.0 else (lateral_m - right), RECOVERY_ROOM_M)
        kappa = abs(float(np.interp(distance_m, self.path.s, self.path.curvature)))
        cap = turn_cap(kappa + heading_rad * heading_rad / (2.0 * room), self.turn_share * self.lag.turn_gain,
                       self.limits.w_max_radps, self.limits.max_curvature, self._loss_now())
        return max(cap, RECOVERY_MIN_MPS)

    def _recovery_limit(self, distance_m: float, lateral_m: float, heading_rad: float, heading_ahead_rad: float,
                        profile_mps: float) -> float:
        """_recovery_cap, and no speeding up once it held the speed until the errors, with the heading
        where its present rate takes it (`heading_ahead_rad`), are back within RECOVERED_SHARE of the
        corridor: the cap looks at the heading error alone, and lets go as the robot turns back through the
        route's heading while still far out, its turn towards the route still to be reversed. A Grizzly (turn
        drive limited to 1 rad/s^2) let go at 0.84 m/s 0.30 m out, was back at 1.83 m/s in 0.6 s, and swung
        24 deg and 0.41 m to the other side (bench seed 1931, s197186723)."""
        cap = self._recovery_cap(distance_m, lateral_m, heading_rad)
        if cap < profile_mps:
            self._recovery_hold = min(self._recovery_hold, cap)
        elif math.isfinite(self._recovery_hold) and self.corridor is not None and max(
                self.corridor.share(distance_m, lateral_m, heading_rad),
                self.corridor.share(distance_m, 0.0, heading_ahead_rad)) <= RECOVERED_SHARE:
            self._recovery_hold = math.inf
        return min(cap, self._recovery_hold)

    def _heading_ahead(self, capture_tick: int, heading_rad: float, age_s: float) -> float:
        """The heading error its rate between the last two estimates carries it to by the time a command
        sent now has turned the drive (the estimate's age, a period, the turn lag)."""
        prev, self._prev_head = self._prev_head, (capture_tick, heading_rad)
        if prev is None or prev[0] != capture_tick - 1:
            return heading_rad
        rate = (heading_rad - prev[1]) / self.period_s
        return heading_rad + rate * (age_s + self.period_s + self.lag.tau_w_s)

    def _held_by(self, distance_m: float, profile_mps: float, res: LawResult) -> str:
        """What held the command below the asked speed: the law where it chose a slower speed than the
        profile, else the profile's lowest term."""
        if res.v_mps is not None and math.isfinite(res.v_mps) and res.v_mps < profile_mps - 1e-9:
            return res.held_by
        return min(self._speed_limits(distance_m), key=lambda t: (t[0], t[1] != ""))[1]

    def route_errors(self, loc: LocState) -> tuple[np.ndarray, float, float, float]:
        """Pose in the route frame and its (distance, lateral, heading) errors, continuous along the route.

        The vertex frame's axis is the robot's heading when it was taught, which on a slope differs
        from the route's direction (the robot crabbed). Taking y in the nearest vertex frame would make
        the lateral error jump at every vertex change, so the lateral error is measured against the
        route polyline next to that vertex, the heading error against the interpolated taught heading.
        """
        pose = se2.compose(self.path.poses[loc.vertex], loc.T_vertex_robot)
        pr = self.path.project(pose, hint=loc.vertex)
        return pose, pr.distance_m, pr.lateral_m, pr.heading_rad

    def step(self, now_s: float, loc: LocState | None, tick: int | None = None,
             command_at: Callable[[int], tuple[float, float] | None] | None = None,
             spread_factors: tuple[float, ...] = (),
             spread_beyond: tuple[float, tuple[float, ...]] = (float("inf"), ()),
             spread_floors: FloorsBySpeed | None = None, place_cap: PlaceCap | None = None) -> Decision:
        """`tick`: the robot tick this command will be applied at; `command_at(t)`: the command applied
        at tick t. With both, the law learns which commands were applied since the estimate's capture.
        `spread_factors`: the online calibration's factors on the predicted spread per step (calibration.py);
        `spread_beyond`: from which speed a plan outruns the place's passes, and the factors then;
        `spread_floors`: its floors per step under the model's share of the variance (lateral, heading),
        by the plan's speed; `place_cap`: the speed the latest pass's errors here allow a law that chooses
        its speed."""
        if loc is not None and loc.has_pose:
            self._last_ok = loc
        last = self._last_ok
        age = now_s - last.capture_stamp_s if last is not None else math.inf

        def stop(state: str, reason: str) -> Decision:
            self._last_cmd = (0.0, 0.0)
            if last is None:
                return Decision(0.0, 0.0, state, reason, 0, 0.0, 0.0, 0.0, age)
            _, dist, lat, head = self.route_errors(last)
            return Decision(0.0, 0.0, state, reason, last.vertex, dist, lat, head, age)

        if self.finished:
            return self._finish(last, age, loc, tick, command_at) or stop("finished", END_OF_ROUTE)
        if self.halted:
            return self._halt(last, age, loc, tick, command_at) or stop("stopped", self.halted)
        if last is None:
            return stop("waiting", f"no localization yet ({loc.status if loc else 'nothing received'})")
        if loc is not None and loc.status == "lost":
            return stop("stopped", f"localization lost: {loc.reason}")
        if age > self.loc_timeout_s:
            return stop("stopped", f"localization stale: newest estimate is {age:.2f} s old")

        vertex = last.vertex
        pose, dist, lat, head = self.route_errors(last)
        if loc is not last:
            # short dropout: keep the last command, the robot is still within the timeout
            v, w = self._last_cmd
            return Decision(v, w, "holding", f"no fresh estimate ({loc.status if loc else 'none'}), "
                            f"holding last command", vertex, dist, lat, head, age)

        if dist >= self.path.length_m or (vertex == len(self.path) - 1 and last.T_vertex_robot[0] >= 0.0):
            self.finished = True
            return self._finish(last, age, loc, tick, command_at) or stop("finished", END_OF_ROUTE)

        prev_pose = None
        if self._prev_pose is not None and self._prev_pose[0] == last.capture_tick - 1:
            prev_pose = self._prev_pose[1]
        self._prev_pose = (last.capture_tick, pose)
        law_lat, law_head = self._smoothed(vertex, lat, head)
        v = self.speed_at(dist)
        recovery = self._recovery_limit(dist, lat, head, self._heading_ahead(last.capture_tick, head, age), v)
        v = min(v, recovery)
        delayed, before = (), None
        xi_now = xi_capture = self.lag.settled(self._last_cmd)   # without a command history: settled
        if tick is not None and command_at is not None:
            if tick > last.capture_tick:
                cmds = [command_at(t) for t in range(last.capture_tick, tick)]
                if all(c is not None for c in cmds):
                    delayed, before = tuple(cmds), command_at(last.capture_tick - 1)
            if self.lag.active:
                xi_now = self.lag.state_before(tick, command_at)
                xi_capture = self.lag.state_before(last.capture_tick, command_at) if delayed else xi_now
        ctx = StepContext(now_s=now_s, path=self.path, vertex=vertex, pose=pose, s_m=dist, e_lat_m=law_lat,
                          e_head_rad=law_head, v_mps=v, speed_at=self.speed_at, prev_cmd=self._last_cmd,
                          prev_pose=prev_pose, w_limit=self.limits.w_limit(v), w_limit_at=self.limits.w_limit,
                          delayed_cmds=delayed, cmd_before_capture=before, xi_capture=xi_capture, xi_now=xi_now,
                          pose_cov=self.route_cov(last), corridor=self.corridor, v_max_mps=self.limits.v_max_mps,
                          spread_factors=spread_factors, spread_beyond_mps=spread_beyond[0],
                          spread_factors_beyond=spread_beyond[1], spread_floors=spread_floors, loc_age_s=age,
                          place_cap=place_cap)
        res, reason = self._run_law(ctx)
        if res.stop_reason:
            self.halted = res.stop_reason
            return self._halt(last, age, loc, tick, command_at) or stop("stopped", res.stop_reason)
        held_by = "recovery" if recovery <= v else self._held_by(dist, v, res)
        if res.v_mps is not None and math.isfinite(res.v_mps):
            v = max(0.0, min(res.v_mps, self.limits.v_max_mps))
        w_limit = self.limits.w_limit(v)
        w = max(-w_limit, min(w_limit, res.w_radps))
        self._last_cmd = (v, w)
        return Decision(v, w, "tracking", reason or res.note, vertex, dist, lat, head, age, res, held_by)

    def _drive_state(self, tick: int | None,
                     command_at: Callable[[int], tuple[float, float] | None] | None) -> tuple[float, float] | None:
        """The drive's state by the lag model (its speed, and its turn rate or the steering's curvature);
        None without a lag or a command history: the drive then follows the command within the period."""
        if self.lag.active and tick is not None and command_at is not None:
            return self.lag.state_before(tick, command_at)
        return None

    def _finish(self, last: LocState | None, age: float, loc: LocState | None, tick: int | None,
                command_at: Callable[[int], tuple[float, float] | None] | None) -> Decision | None:
        """The end of the route as the same manoeuvre as a safety stop: a heavy robot's drive still rolls
        when the estimate passes the last vertex (its lag), and v = w = 0 would let it coast off turning
        as its last commands left it."""
        return self._brake(last, age, loc, self._drive_state(tick, command_at), "finished",
                           f"{END_OF_ROUTE}: braking along the route")

    def _halt(self, last: LocState | None, age: float, loc: LocState | None, tick: int | None,
              command_at: Callable[[int], tuple[float, float] | None] | None) -> Decision | None:
        """A law's safety stop (`halted`), braking along the route."""
        return self._brake(last, age, loc, self._drive_state(tick, command_at), "stopping",
                           f"{self.halted}: braking along the route")

    def _brake(self, last: LocState | None, age: float, loc: LocState | None, drive: tuple[float, float] | None,
               state: str, reason: str) -> Decision | None:
        """A stop as a manoeuvre that keeps the robot inside: brake at the robot's limit while steering
        along the route, not v = w = 0, which drops the counter-steer and lets the robot coast off. The
        steering holds until the drive has stopped (`drive`, by the lag model), not the command: a
        heavy robot's drive lags its command by a second. It steers a curvature within
        BRAKE_CURVATURE_PER_M of the route's: with a corridor, the one that weighs its lateral and heading
        limits over the distance still to roll (brake.py); without, feedback linearization's at the
        rolling speed. A curvature, not a turn rate: FL's turn rate grows like 1 / v and would spin a
        slow skid-steer in place. An Ackermann robot steers by the ratio w / v of its command (eq. 5.27),
        so while it rolls it is commanded a creep with that curvature; a skid-steer's turn drive is
        brought to that curvature at its speed (_turn_held). None once at rest, or without a usable
        estimate (then there is nothing to steer by: plain stop)."""
        v = max(0.0, self._last_cmd[0] - self.limits.decel_mps2 * self.period_s)
        rolling = max(v, drive[0]) if drive else v
        turning = abs(drive[1]) if drive and not self.lag.rate_limited else 0.0
        if (rolling <= REST_MPS and turning <= REST_RADPS) or last is None or age > self.loc_timeout_s \
                or (loc is not None and loc.status == "lost"):
            return None
        _, dist, lat, head = self.route_errors(last)
        kappa = float(np.interp(dist, self.path.s, self.path.curvature))
        if self.corridor is not None:
            c = self.lag.command_for(kappa + self._balanced(dist, lat, head, v, drive))
        else:
            at = max(rolling, REST_MPS)
            c = fl_angular_rate(at, lat, head, kappa, self._fallback.gains, turn_gain=self.lag.turn_gain) / at
        kappa = self.lag.command_for(kappa)      # the curvature commanded for the robot's to be the route's
        c = max(kappa - BRAKE_CURVATURE_PER_M, min(kappa + BRAKE_CURVATURE_PER_M, c))
        c = max(-self.limits.max_curvature, min(self.limits.max_curvature, c))
        if math.isfinite(self.limits.max_curvature):
            v = max(v, CREEP_MPS)
            w = c * v
        else:
            w = c * rolling if drive is None else self._turn_held(c, v, drive)
            w = max(-self.limits.w_max_radps, min(self.limits.w_max_radps, w))
        self._last_cmd = (v, w)
        return Decision(v, w, state, reason, last.vertex, dist, lat, head, age)

    def _balanced(self, dist: float, lat: float, head: float, v: float, drive: tuple[float, float] | None) -> float:
        """The brake's curvature offset from the route's that weighs the corridor's lateral and heading
        limits over the distance the robot still rolls (brake.py)."""
        right, left, limit = (float(x) for x in self.corridor.at(dist))
        d = roll_out_m(self.lag, drive or self.lag.settled(self._last_cmd), v, self.limits.decel_mps2,
                       self.period_s, REST_MPS)
        return balanced_offset(lat, head, d, right, left, limit, BRAKE_CURVATURE_PER_M)

    def _turn_held(self, c: float, v: float, drive: tuple[float, float]) -> float:
        """The turn-rate command that brings a braking skid-steer's turn drive to curvature c at the speed
        its drive will have at the period's end. A lagging turn drive keeps its last rate while the speed
        falls: commanding c times the speed alone turned a Grizzly 15-25 deg off the route as it stopped
        from 1.5-2 m/s in a corner (docs/results.md, stop 61)."""
        v_next = self.lag.step(drive, (v, 0.0))[1][0]
        return self.lag.turn_command_reaching(drive[1], c * v_next)

    def _run_law(self, ctx: StepContext) -> tuple[LawResult, str]:
        """The law's result, or feedback linearization for this step when the law failed numerically (a
        singular matrix, an overflow, a non-finite command); any other error is a bug and propagates."""
        try:
            res = self.law.angular(ctx)
            if not math.isfinite(res.w_radps):
                raise FloatingPointError(f"{self.law.name} returned w = {res.w_radps}")
            return res, ""
        except NUMERICAL_FAILURES as exc:
            return (self._fallback.angular(ctx),
                    f"{self.law.name} failed ({type(exc).__name__}: {exc}); feedback linearization this step")

    def route_cov(self, loc: LocState) -> np.ndarray:
        """The estimate's covariance turned from the vertex frame into the route's frame."""
        cov = np.asarray(loc.cov_T_vertex_robot, dtype=float).reshape(3, 3)
        th = float(self.path.poses[loc.vertex, 2])
        R = np.array([[math.cos(th), -math.sin(th), 0.0], [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
        return R @ cov @ R.T

    def _smoothed(self, vertex: int, lat: float, head: float) -> tuple[float, float]:
        """Eq. 3.16: over the first m_ic vertices the desired path blends from where the robot started
        into the taught one, so a trial does not begin by fighting its initial offset."""
        if self.ic_vertices <= 0:
            return lat, head
        if self._initial_error is None:
            self._initial_error = (lat, head)
        if vertex >= self.ic_vertices:
            return lat, head
        share = (self.ic_vertices - vertex) / self.ic_vertices
        return lat - share * self._initial_error[0], head - share * self._initial_error[1]


def fl_tracker(path: Path, gains, limits: TrackerLimits, **kw) -> PathTracker:
    """The feedback-linearized tracker of eq. 3.5."""
    return PathTracker(path, FLLaw(gains), limits, **kw)
