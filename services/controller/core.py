"""The controller's pure core: the tracking law plus the experiences each step yields."""
from __future__ import annotations

from common.messages import LocState
from common.path import Path
from services.controller.experience import ExperienceBuilder, Observation
from services.controller.tracker import Decision, PathTracker


class ControllerCore:
    def __init__(self, path: Path, tracker: PathTracker, period_s: float):
        self.path = path
        self.tracker = tracker
        self.builder = ExperienceBuilder(path, period_s, lag=tracker.lag)

    def step(self, now_s: float, tick: int, loc: LocState | None) -> tuple[Decision, Observation | None]:
        """One control step at robot tick `tick`: the command to apply now, and the disturbance
        observation completed by this estimate (eq. 5.17), if any."""
        obs = None
        # experiences only from map-refined estimates: a VO-only pose drifts, and the model would learn it
        if loc is not None and loc.status == "ok":
            obs = self.builder.add_estimate(loc.capture_tick, loc.capture_stamp_s, loc.vertex, loc.T_vertex_robot)
        decision = self.tracker.step(now_s, loc, tick, self.builder.command_at)
        self.builder.add_command(tick, decision.v_mps, decision.w_radps)
        return decision, obs
