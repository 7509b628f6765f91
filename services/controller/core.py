"""The controller's pure core: the tracking law, the experiences each step yields, and the online check
of the predicted spread (calibration.py)."""
from __future__ import annotations

import math

import numpy as np

from common.messages import LocState
from common.path import Path
from services.controller.calibration import Prediction, SpreadCalibration
from services.controller.estimate_jumps import EstimateJumps
from services.controller.experience import ExperienceBuilder, Observation
from services.controller.tracker import Decision, PathTracker
from services.controller.turn_share import TurnShare


class ControllerCore:
    def __init__(self, path: Path, tracker: PathTracker, period_s: float,
                 calibration: SpreadCalibration | None = None):
        self.path = path
        self.tracker = tracker
        self.builder = ExperienceBuilder(path, period_s, lag=tracker.lag)
        self.calibration = calibration or SpreadCalibration(horizon=0)
        self.period_s = period_s
        self.s_m: float | None = None         # route distance of the newest estimate
        self.v_mps = 0.0                      # the speed last commanded
        self.kappa = self.calibration.factors_at(None)   # the calibration's factors of the latest step
        self.floors = self.calibration.floors_by_speed()  # ... and its floors on the model's share
        self.jumps = EstimateJumps()
        self.turns = TurnShare(period_s, tracker.limits.w_limit)
        self._from_tick = -1                  # capture tick of the newest estimate
        self._deferred: tuple | None = None   # a candidate jump's check, until its verdict
        self._held: tuple[int, Observation | None] | None = None   # ... and its experience

    def step(self, now_s: float, tick: int, loc: LocState | None) -> tuple[Decision, list[Observation]]:
        """One control step at robot tick `tick`: the command to apply now, and the disturbance
        observations (eq. 5.17) this estimate completed or released."""
        obs = None
        # experiences only from map-refined estimates: a VO-only pose drifts, and the model would learn it
        if loc is not None and loc.status == "ok":
            obs = self.builder.add_estimate(loc.capture_tick, loc.capture_stamp_s, loc.vertex, loc.T_vertex_robot)
            if obs is not None:
                self._learn_turn(obs)
        observed = [obs] if obs is not None else []
        if loc is not None and loc.has_pose:
            candidate = self._realize(loc)
            observed = self._experiences(obs, loc.capture_tick, candidate)
            self._from_tick = loc.capture_tick
        self.kappa = self.calibration.factors_at(self.s_m, self.v_mps)
        self.floors = self.calibration.floors_by_speed(self.s_m, self.v_mps)
        beyond = self.calibration.beyond_at(self.s_m, self.v_mps)
        factors = () if beyond.factors is None else tuple(float(f) for f in np.sqrt(beyond.factors))
        cap = self.calibration.speed_cap_at(self.s_m, self.v_mps) if self.tracker.corridor is not None else None
        decision = self.tracker.step(now_s, loc, tick, self.builder.command_at, self.spread_factors,
                                     (beyond.speed_mps, factors), self.floors if self.floors.any() else None, cap)
        self.builder.add_command(tick, decision.v_mps, decision.w_radps)
        self.v_mps = decision.v_mps
        self._observe_turn(decision)
        if decision.state == "stopped":
            # a robot held at rest after a safety stop shows nothing of how it moves, and how many such steps
            # a trial has depends on when the runner ends it
            observed = []
        return decision, observed

    def _learn_turn(self, obs: Observation) -> None:
        """The period's turn for the tracker's turn loss (turn_speed.py): the drive's turn rate by the lag
        model and the ground's, the model's plus the residual."""
        v, w_model = self.builder.model_speeds
        self.tracker.learn_turn(v, w_model / self.tracker.lag.turn_gain, w_model + obs.g[2] / self.period_s, obs.a[0])

    def _observe_turn(self, d: Decision) -> None:
        """The share of the steering margin the tracking commands take here, for the place cap."""
        if self.tracker.corridor is None or d.state != "tracking":
            self.turns.reset()
            return
        kappa = float(np.interp(d.distance_m, self.path.s, self.path.curvature))
        w_route = kappa * d.v_mps / self.tracker.lag.turn_gain
        self.calibration.observe(d.distance_m, self.turns.add(d.v_mps, d.w_radps, w_route), "steering margin")

    def _experiences(self, obs: Observation | None, capture_tick: int, candidate: bool) -> list[Observation]:
        """The experiences to send now: a candidate jump's waits for its verdict, and a jump's is dropped
        with the next one (whose measured velocity spans the step): the model must not learn a disturbance
        that was the localizer's (thesis 5.4.5)."""
        out = []
        if self._held is not None:
            tick, held = self._held
            self._held = None
            if self.jumps.jumps and self.jumps.jumps[-1].capture_tick == tick:
                obs = None
            elif held is not None:
                out.append(held)
        if candidate:
            self._held = (capture_tick, obs)
        elif obs is not None:
            out.append(obs)
        return out

    @property
    def spread_factors(self) -> tuple[float, ...]:
        """sqrt(kappa_j) of the latest step: what its predicted standard deviations were multiplied by."""
        return tuple(float(f) for f in np.sqrt(self.kappa))

    def _realize(self, loc: LocState) -> bool:
        """Check the predictions made for this estimate's capture tick against it; a candidate jump's
        (estimate_jumps.py) once the next estimate has told whether it was one. True: this is one."""
        pose, dist, lateral, heading = self.tracker.route_errors(loc)
        self.s_m = dist
        cov = self.tracker.route_cov(loc)
        th = float(self.path.tangent_at(dist))
        n = np.array([-math.sin(th), math.cos(th)])
        check = (loc.capture_tick, lateral, heading, float(n @ cov[:2, :2] @ n), float(cov[2, 2]))
        if self.tracker.corridor is not None:
            self.calibration.observe(dist, self.tracker.corridor.share(dist, lateral, heading))
        kappa = float(np.interp(dist, self.path.s, self.path.curvature))
        candidate = self.jumps.add(loc.capture_tick, dist, lateral, heading, kappa)
        if self._deferred is not None:
            self._check(*self._deferred)
        self._deferred = check if candidate else None
        if not candidate:
            self._check(*check)
        return candidate

    def _check(self, tick: int, lateral: float, heading: float, var_lat: float, var_head: float) -> None:
        self.calibration.realize(tick, lateral, heading, var_lat, var_head,
                                 lambda from_tick: self.jumps.offset_between(from_tick, tick))

    def keep_prediction(self, tick: int, d: Decision) -> None:
        """After the command is out: the law's predicted poses x_1..x_K (of ticks tick + 1..K) with their
        spread, for the online check, as errors against the route each at its own place."""
        law = d.law
        unc = law.uncertainty if law is not None else None
        if unc is None or not unc.horizon_sigma_lat_m or law.predicted is None or d.state != "tracking":
            return
        scales = np.asarray(unc.spread_kappa) if unc.spread_kappa else self.kappa
        hint, predictions = d.vertex, []
        for j, x in enumerate(np.asarray(law.predicted)):
            pr = self.path.project(x, hint=hint)
            hint = pr.vertex
            loc = (unc.horizon_loc_sigma_lat_m[j], unc.horizon_loc_sigma_head_rad[j]) \
                if j < len(unc.horizon_loc_sigma_lat_m) else (0.0, 0.0)
            model = (unc.horizon_model_sigma_lat_m[j], unc.horizon_model_sigma_head_rad[j]) \
                if j < len(unc.horizon_model_sigma_lat_m) else (math.nan, math.nan)
            predictions.append(Prediction(j + 1, pr.lateral_m, pr.heading_rad, unc.horizon_sigma_lat_m[j],
                                          unc.horizon_sigma_head_rad[j], float(scales[j]) if j < len(scales) else 1.0,
                                          *loc, s_m=d.distance_m, v_mps=d.v_mps, model_sigma_lat_m=model[0],
                                          model_sigma_head_rad=model[1], from_tick=self._from_tick))
        self.calibration.predict(tick, predictions)
