"""Does a fitted disturbance model leave the controller its steering?

The disturbance g(a) of a repeat is learned from closed-loop data, where the controller turns hardest
exactly where the terrain turns the robot the other way. The inputs of a (experience.py A_NAMES) include
the commanded turn rates (w_cmd, w_cmd_prev) and the measured one (w_act), so a fit can explain a rut's
yaw by them instead of by the place: the heading residual becomes "the last period's turn rate persists,
whatever is commanded", g_head ~ (w_act - w_cmd) dt. That predicts one period well and takes the
steering away from the NMPC, which then commands either sign at the limit (measured: a MATS in a
deepening rut corner, 0.2 m corridor, left the route by 1.0-1.8 m in three of eight trials).

The check: per fitted point, the share of the nominal turn the model keeps (common/turn_share.py; for a
command held one period and one held until the turn rate settles, r = k w + (G_wcmd + G_wprev) w + G_wact r).
Terrain scales the turn (slip lowers it, a skid-steer at speed keeps a fraction of
it) but does not cancel or reverse it; a model that keeps less than `min_share` (default 0.1) at more than
MAX_FRACTION_BELOW of its points has learned the controller's own commands,
and the store refits its heading dimension with the turn-rate inputs switched off (lengthscales >= the
fit's off-lengthscale): the place and the speed explain the yaw. Gradients come from each local window's
GP, as the controller predicts (thesis 5.3.2). By default the store fits the heading without w_act and
w_cmd_prev already (config.py `heading_from_turn_history`), which removes the persistence; the check
then guards the command's own term. A fit that passes can still cancel the steering between its points;
the controller checks its own plans the same way (services/controller/held_turn.py).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from common.gp import GaussianProcess, SEHyper
from common.turn_share import W_ACT, W_CMD, W_CMD_PREV, kept_turn_share

TURN_INPUTS = (W_ACT, W_CMD, W_CMD_PREV)
MAX_FRACTION_BELOW = 0.01              # of the fitted points, the share allowed below min_share (outliers)

_TAG = re.compile(r"^unicycle-dt(\d+)ms-.*?(?:-gw(\d+))?$")


@dataclass(frozen=True, kw_only=True)
class AuthorityRule:
    """What the check needs: the nominal model's period and turn gain, and the bounds."""
    period_s: float
    turn_gain: float = 1.0
    min_share: float = 0.1
    off_lengthscale: float = 100.0     # a turn-rate input switched off in the refit

    @classmethod
    def for_model(cls, tag: str, min_share: float, off_lengthscale: float) -> "AuthorityRule | None":
        """From a nominal model tag (services/controller/actuator.py ActuatorLag.model_tag); None where the
        tag does not say the period (untagged experiences) or the check is off (min_share <= 0)."""
        m = _TAG.match(tag or "")
        if m is None or min_share <= 0:
            return None
        gain = int(m.group(2)) / 1000.0 if m.group(2) else 1.0
        return cls(period_s=int(m.group(1)) / 1000.0, turn_gain=gain, min_share=min_share,
                   off_lengthscale=off_lengthscale)


@dataclass(frozen=True)
class AuthorityCheck:
    shares: np.ndarray     # per checked point, the nominal turn authority the model keeps (-inf: none)
    min_share: float

    @property
    def fraction_below(self) -> float:
        return float(np.mean(self.shares < self.min_share)) if len(self.shares) else 0.0

    @property
    def passed(self) -> bool:
        return self.fraction_below <= MAX_FRACTION_BELOW

    def describe(self) -> str:
        p5 = float(np.percentile(self.shares, 5)) if len(self.shares) else 1.0
        return (f"the heading model kept < {self.min_share:.0%} of the steering at {self.fraction_below:.1%} of "
                f"{len(self.shares)} points (5th percentile {max(p5, -9.99):.2f})")


def turn_authority(A: np.ndarray, g_head: np.ndarray, groups: np.ndarray | None, hyper: SEHyper,
                   rule: AuthorityRule) -> AuthorityCheck:
    """The share of the nominal turn authority the heading model `hyper` keeps at every row of A (module
    doc), each row's gradient from the GP of its group (all rows one GP without groups)."""
    labels = np.zeros(len(A), dtype=int) if groups is None else np.asarray(groups)
    shares = np.empty(len(A))
    for label in np.unique(labels):
        rows = np.flatnonzero(labels == label)
        gp = GaussianProcess(A[rows], g_head[rows, None], [hyper])
        for i in rows:
            shares[i] = kept_turn_share(gp.mean_and_grad(A[i])[1][0] / rule.period_s, rule.turn_gain)
    return AuthorityCheck(shares, rule.min_share)


def turn_free(hyper: SEHyper, off_lengthscale: float) -> tuple[np.ndarray, SEHyper]:
    """The lengthscale floors that switch the turn-rate inputs off, and `hyper` moved onto them (a start)."""
    floors = np.zeros(len(hyper.lengthscales))
    floors[list(TURN_INPUTS)] = off_lengthscale
    ell = np.maximum(np.asarray(hyper.lengthscales, dtype=float), floors)
    return floors, SEHyper(ell, hyper.signal_std, hyper.noise_std)
