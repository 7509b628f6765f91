"""A learned heading model that would take the steering away where the controller plans, held at the command.

The store checks each fit at its own data and refits the heading without the turn-rate inputs where more
than 1 % of them keep less than `min_share` of the nominal turn (services/gp_store/authority.py). A fit
that passes can still cancel the steering between those points, with the command's lengthscale at its
0.3 rad/s floor. Measured: a perturbed ROC6 (bench seed 8461, s538851852) entering a slip patch on a side
slope in trial 2: at the plan's inputs the heading model kept -6 % of the nominal turn; the SQP found no
step that lowered its merit ("stalled") and held -0.28 rad/s while the heading error grew from 4 to 16.5
deg, and the robot stopped outside its corridor.

So every step the NMPC laws ask the same of the model at the inputs of the reference's rollout. Where
any keeps less than `min_share`, the step plans with the heading output's mean held at the turn rate
commanded last period: its value there (what the place does to the heading now), without a slope in
the command, so the nominal model's turn authority is whole. The other outputs and every variance stay
the model's own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.turn_share import HEADING, W_CMD, kept_turn_share
from services.controller.horizon import DisturbanceModel, HorizonProblem


@dataclass(frozen=True)
class HeldTurn:
    """`model` with its heading mean taken at the commanded turn rate `w_cmd_radps`."""
    model: DisturbanceModel
    w_cmd_radps: float
    kept_share: float          # the least share of the nominal turn the model kept at the plan's inputs

    @property
    def hypers(self):
        return self.model.hypers

    def _held(self, A: np.ndarray) -> np.ndarray:
        held = np.array(A, dtype=float)
        held[..., W_CMD] = self.w_cmd_radps
        return held

    def mean_and_grad(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, dg = self.model.mean_and_grad(a)
        gh, dgh = self.model.mean_and_grad(self._held(a))
        g, dg = g.copy(), dg.copy()
        g[HEADING], dg[HEADING] = gh[HEADING], dgh[HEADING]
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
            f"held at the command {model.w_cmd_radps:+.2f} rad/s")


def least_kept_share(gradients: np.ndarray, turn_gain: float, dt: float) -> float:
    """The least share of the nominal turn a heading model keeps, from its gradients dg/da (n, 3, 9)."""
    return min(kept_turn_share(dg[HEADING] / dt, turn_gain) for dg in gradients)


def hold_turn_where_cancelled(problem: HorizonProblem, w_cmd_radps: float, min_share: float) -> DisturbanceModel | None:
    """The problem's model, held at `w_cmd_radps` (HeldTurn) where it keeps less than `min_share` of the
    nominal turn at the inputs of the reference's rollout; itself otherwise (and with no model or check)."""
    model = problem.model
    if model is None or min_share <= 0.0:
        return model
    share = least_kept_share(problem.model_gradients(problem.w_ref), problem.turn_gain, problem.dt)
    return model if share >= min_share else HeldTurn(model, float(w_cmd_radps), share)
