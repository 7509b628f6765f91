"""A learned heading model that would take the steering away where the controller plans, held at the
route's turn rate.

The store checks each fit at its own data and refits the heading without the turn-rate inputs where more
than 1 % of them keep less than `min_share` of the nominal turn (services/gp_store/authority.py). A fit
that passes can still cancel the steering between those points, with the command's lengthscale at its
0.3 rad/s floor. Measured: a perturbed ROC6 (bench seed 8461, s538851852) entering a slip patch on a side
slope in trial 2: at the plan's inputs the heading model kept -6 % of the nominal turn; the SQP found no
step that lowered its merit ("stalled") and held -0.28 rad/s while the heading error grew from 4 to 16.5
deg, and the robot stopped outside its corridor.

So every step the NMPC laws ask the same of the model at the inputs of the reference's rollout and of
the warm start's (the previous plan shifted: where the solver starts and usually ends, often at the turn
limit, where closed-loop data confound the command with the terrain most). Where any keeps less than
`min_share`, the step plans with the heading output's mean held at the route's own turn rate (its
curvature times the commanded speed, through the drive's turn gain): the model's value there (what the
place does to a robot that follows the route), without a slope in the command, so the nominal model's
turn authority is whole. The other outputs and every variance stay the model's own. LB-NMPC also checks
the solution it found and, where that went where the model cancels the turn, solves again held.

Held at the last command instead, the mean there is what the data saw whenever the controller was last
saturated: the terrain turning the robot the other way. The plan then needs the same saturated command
to hold its heading, and keeps it while the real turn swings past (bench seed 7583, LB-NMPC MATS
s270925663, a rough patch on a straight: +0.32 rad/s held 2 s into a +36 deg heading error, 2.5 m off).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.turn_share import HEADING, S, V_CMD, W_CMD, kept_turn_share
from services.controller.horizon import DisturbanceModel, HorizonProblem


@dataclass(frozen=True)
class HeldTurn:
    """`model` with its heading mean taken at the route's turn rate kappa(s) v_cmd / turn_gain, kappa
    interpolated over the knots (s_m, kappa) of the problem's reference."""
    model: DisturbanceModel
    s_m: np.ndarray
    kappa: np.ndarray
    turn_gain: float
    kept_share: float          # the least share of the nominal turn the model kept at the plan's inputs

    @property
    def hypers(self):
        return self.model.hypers

    def _held(self, A: np.ndarray) -> np.ndarray:
        held = np.array(A, dtype=float)
        held[..., W_CMD] = np.interp(held[..., S], self.s_m, self.kappa) * held[..., V_CMD] / self.turn_gain
        return held

    def _kappa_slope(self, s: float) -> float:
        i = int(np.searchsorted(self.s_m, s, side="right"))
        if i == 0 or i == len(self.s_m):
            return 0.0
        return float((self.kappa[i] - self.kappa[i - 1]) / (self.s_m[i] - self.s_m[i - 1]))

    def mean_and_grad(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, dg = self.model.mean_and_grad(a)
        a_h = self._held(a)
        gh, dgh = self.model.mean_and_grad(a_h)
        g, dg = g.copy(), dg.copy()
        g[HEADING], dg[HEADING] = gh[HEADING], dgh[HEADING]
        dw = dgh[HEADING, W_CMD] / self.turn_gain   # the held turn rate moves with the place and the speed
        dg[HEADING, S] += dw * self._kappa_slope(float(a[S])) * a[V_CMD]
        dg[HEADING, V_CMD] += dw * float(np.interp(a[S], self.s_m, self.kappa))
        dg[HEADING, W_CMD] = 0.0
        return g, dg

    def mean(self, A: np.ndarray) -> np.ndarray:
        A = np.atleast_2d(np.asarray(A, dtype=float))
        g = np.array(self.model.mean(A), dtype=float)
        g[:, HEADING] = self.model.mean(self._held(A))[:, HEADING]
        return g

    def predict(self, A: np.ndarray, coverage: bool = False):
        A = np.atleast_2d(np.asarray(A, dtype=float))
        _, *rest = self.model.predict(A, coverage)
        return (self.mean(A), *rest)

    def capped(self, dims: tuple[int, ...], caps: tuple[float, ...]):
        """The variance's GP (uncertainty.variance_gp): the model's; this one where that is the model itself,
        so that the variance and the mean still come from one object."""
        capped = self.model.capped(dims, caps)
        return self if capped is self.model else capped


def held_note(model: DisturbanceModel | None) -> str:
    """What a step planned on a held model says in the controller's status ("" otherwise)."""
    if not isinstance(model, HeldTurn):
        return ""
    return (f"learned heading model kept {model.kept_share:+.0%} of the turn at the plan: "
            f"held at the route's turn rate")


def least_kept_share(gradients: np.ndarray, turn_gain: float, dt: float) -> float:
    """The least share of the nominal turn a heading model keeps, from its gradients dg/da (n, 3, 9)."""
    return min(kept_turn_share(dg[HEADING] / dt, turn_gain) for dg in gradients)


def least_share_along(problem: HorizonProblem, rollouts: Sequence[np.ndarray]) -> float:
    """The least share of the nominal turn the problem's model keeps along the rollouts of these turn
    rates (each (K,), at the profile's speeds; others are skipped)."""
    shares = [least_kept_share(problem.model_gradients(w), problem.turn_gain, problem.dt)
              for w in rollouts if len(w) == problem.K]
    return min(shares, default=np.inf)


def held_along(problem: HorizonProblem, share: float) -> HeldTurn:
    """The problem's model held at the route's turn rate, `share` being the least it kept."""
    ref = problem.ref
    return HeldTurn(problem.model, np.asarray(ref.s_m[:-1], dtype=float), np.asarray(ref.kappa, dtype=float),
                    problem.turn_gain, share)


def hold_turn_where_cancelled(problem: HorizonProblem, min_share: float,
                              rollouts: Sequence[np.ndarray]) -> DisturbanceModel | None:
    """The problem's model, held at the route's turn rate (HeldTurn) where it keeps less than `min_share`
    of the nominal turn at the inputs of any of the rollouts (turn rates (K,) at the profile's speeds);
    itself otherwise (and with no model, no check or a model held already)."""
    model = problem.model
    if model is None or min_share <= 0.0 or isinstance(model, HeldTurn):
        return model
    share = least_share_along(problem, rollouts)
    return model if share >= min_share else held_along(problem, share)
