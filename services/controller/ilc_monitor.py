"""What keeps the lifted ILC update from learning what its linear model cannot explain.

Two guards, both about the model of ilc_lifted.py being linear and exact only where the steering can
do what the feedforward asks:

- **Saturation.** Where the trial's command reached the turn-rate (or curvature) limit, the loop was
  not the linear one the update models: a feedforward change there has no effect in the saturated
  direction, and the errors while saturated and while the loop recovers from it answer to no linear
  map. Those errors are left out of the update (the feedforward before them still answers to every
  error it can reach).
- **A trial that got worse.** The feedforward is applied only provisionally: the trial that drives it
  is compared with the one that drove the last accepted feedforward (the baseline), at the same speed.
  If its error cost grew by more than `revert_margin`, the feedforward returns to the baseline's and
  the next change is computed again from the baseline's errors with half the step (a trust region
  on the trial axis); an accepted trial becomes the baseline and lets the step grow back. A trial at
  another speed is a new baseline: its errors are not comparable.
- **A route that got harder.** Ruts deepen with every pass, so a trial can be worse than the baseline
  whatever its feedforward, and every later trial is reverted until the step is nil: learning stops
  where it is most needed. A feedforward that made things worse does so less with half the step; the
  route's change does not shrink with it. So a worse trial whose excess cost over the baseline is not
  below WORLD_SHARE of the excess of the trial reverted just before it (driven with twice its step) is
  accepted as the new baseline: the route changed, not the feedforward. Unless that excess is smaller
  than the cost the estimates' own variance gives a trial: the localizer's wandering offset moves a
  trial's cost by about that much from trial to trial, and a change within it says nothing of the route
  (at such a noise floor the rule would only learn noise).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from common.codec import Message
from common.messages import check_name
from services.controller.ilc_lifted import ILCPlant, LiftedWeights

SAME_SPEED = 0.05          # trials whose mean speeds differ by less than this share are comparable
MIN_STEP_SCALE = 1.0 / 64.0
WORLD_SHARE = 0.75         # halving the step leaves at most ~1/2 (linear) to 1/4 (quadratic) of its harm


@dataclass(frozen=True, kw_only=True)
class ILCBaseline(Message):
    """The last accepted feedforward of a route with the errors of the trial that drove it."""
    SCHEMA_VERSION = 2              # v2: reverted_cost
    MAX_BYTES: ClassVar[int] = 64 * 1024 * 1024
    path_id: str
    w_ff_radps: list[float]
    e_lat_m: list[float]
    e_head_rad: list[float]
    learn_from: list[bool]          # vertices whose errors the update answers (seen and not saturated)
    speeds_mps: list[float]
    cost: float                     # trial_cost of that trial
    speed_mps: float                # its mean speed
    step_scale: float = 1.0         # on the lifted update's step: halved by every reverted trial
    reverted_cost: float = 0.0      # the cost of the last trial reverted since this one (0: none yet)

    def __post_init__(self):
        check_name("path_id", self.path_id)
        n = len(self.w_ff_radps)
        if not all(len(x) == n for x in (self.e_lat_m, self.e_head_rad, self.learn_from, self.speeds_mps)):
            raise ValueError("ILCBaseline arrays differ in length")

    def comparable(self, speed_mps: float) -> bool:
        return abs(speed_mps - self.speed_mps) <= SAME_SPEED * max(self.speed_mps, 1e-3)

    def route_changed(self, cost: float, noise_cost: float = 0.0) -> bool:
        """A worse trial, driven with half the step of the trial reverted before it, whose excess over
        this baseline did not shrink with the step and is larger than `noise_cost`, what the estimates'
        own error contributes to a trial's cost (module docstring)."""
        excess = cost - self.cost
        return (self.reverted_cost > self.cost and excess > WORLD_SHARE * (self.reverted_cost - self.cost)
                and excess > noise_cost)


def trial_cost(e_lat: np.ndarray, e_head: np.ndarray, seen: np.ndarray, wt: LiftedWeights) -> float:
    """The mean over the seen vertices of the error the lifted update minimizes."""
    if not np.any(seen):
        return 0.0
    return float(np.mean(wt.q_lat * e_lat[seen] ** 2 + wt.q_head * e_head[seen] ** 2))


def recovery_s(plant: ILCPlant) -> float:
    """How long the feedback loop takes to forget a saturation: ~4 time constants of its slower pole
    (s^2 + gamma2 s + gamma1: decay rate gamma2 / 2 when damped), after the drive lag and the delay."""
    return 8.0 / plant.fl.gamma2 + plant.tau_w_s + plant.delay_s


def after_saturation(saturated: np.ndarray, distances_m: np.ndarray, speeds_mps: np.ndarray,
                     window_s: float) -> np.ndarray:
    """The vertices from each saturated one until `window_s` of travel later (at the trial's speeds)."""
    n = len(saturated)
    dt = np.asarray(distances_m, dtype=float) / np.maximum(np.asarray(speeds_mps[:-1], dtype=float), 0.05)
    t = np.concatenate([[0.0], np.cumsum(dt)])         # time of reaching each vertex
    out = np.zeros(n, dtype=bool)
    for i in np.flatnonzero(saturated):
        j = int(np.searchsorted(t, t[i] + window_s, side="right"))
        out[i:j] = True
    return out
