"""Typed configuration of the experience store service."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from common.bins import BinPolicy
from common.turn_share import HEADING, V_CMD, W_ACT, W_CMD_PREV


# How fast a disturbance can physically change with each input of a (experience.py A_NAMES): terrain
# varies over metres along and across the route, wheel-ground effects over radians of heading error
# and tenths of m/s or rad/s of motion. Closed-loop data are narrow, and without these floors the
# likelihood picks lengthscales of centimetres that a controller, querying off the data, exploits.
DEFAULT_MIN_LENGTHSCALES = [0.5, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
TURN_HISTORY = (W_ACT, W_CMD_PREV)


@dataclass(frozen=True, kw_only=True)
class FitConfig:
    restarts: int = 3
    max_points: int = 1000        # fit on a random subsample beyond this many experiences
    seed: int = 0
    auto_after_trial: bool = True # fit when a robot ends a repeat on a route with new experiences
    min_new: int = 50             # ... and at least this many are new since the last fit
    local_windows: bool = True    # likelihood of the local windows the controller uses (5.3.2)
    min_lengthscales: list[float] = field(default_factory=lambda: list(DEFAULT_MIN_LENGTHSCALES))
    # one teach pass is a function of the place: its tracking errors, speeds and commands vary with s
    # alone, so a fit on it cannot tell their effect from the place's (fitted freely, the heading residual
    # followed the counter-steer, or a trend in w and e_head, and the NMPC steered against it). Fitted on
    # the teach pass alone, every input but s has at least this lengthscale (its own units): the place
    # explains the disturbance
    teach_min_lengthscale_other: float = 100.0
    # ... except the commanded speed, whose lengthscale (m/s) this holds, if above 0: the pass saw one speed,
    # and a terrain's push per period is the same at any speed on a slope but grows with speed over rough
    # ground and ruts. Held, the pass's disturbance is believed near its speed and fades to the prior (zero
    # mean, the prior's spread) away from it. 0: believed at any speed, the speed's lengthscale as the other
    # inputs' (docs/results.md, stop 48)
    teach_speed_lengthscale_mps: float = 0.0
    # a repeat's heading model must leave the controller at least this share of its nominal turn authority
    # (services/gp_store/authority.py); one that does not is refitted with the turn-rate inputs switched off
    # (lengthscales >= teach_min_lengthscale_other). Low on purpose: a skid-steer at speed really turns at a
    # fraction of its teach-speed gain (a Grizzly at 1.95 m/s kept 0.45-0.66, 5th percentile, and lost
    # accuracy when refitted at 0.5); what no terrain does is cancel or reverse the steering. 0: no check
    min_turn_authority: float = 0.1
    # the thesis's a includes the measured turn rate and the previous command (5.3.1) for dynamics the
    # unicycle lacks; the identified drive lag now models those, and in closed loop the two let a fit explain
    # a place's yaw as "the last period's turn rate persists, whatever is commanded": one period predicted
    # well, no yaw foreseen ahead, and a controller that alternates its steering at the limit because the
    # model credits that with more turn (a MATS in a rut corner left a 0.19 m corridor by 1.8 m). False: the
    # heading residual's lengthscales of w_act and w_cmd_prev are at least teach_min_lengthscale_other
    heading_from_turn_history: bool = False

    def __post_init__(self):
        if len(self.min_lengthscales) != 9 or min(self.min_lengthscales) < 0:
            raise ValueError("min_lengthscales needs 9 values >= 0, one per input of a")
        if self.teach_min_lengthscale_other < 0:
            raise ValueError("teach_min_lengthscale_other must be >= 0")
        if self.teach_speed_lengthscale_mps < 0:
            raise ValueError("teach_speed_lengthscale_mps must be >= 0 (0: the teach pass holds at any speed)")
        if not 0 <= self.min_turn_authority < 1:
            raise ValueError("min_turn_authority must be in [0, 1)")

    def floors(self, teach_only: bool) -> list[list[float]]:
        """The lengthscale floors of a fit, one row per output dimension of g (G_NAMES); `teach_only`: on the
        teach pass's experiences alone."""
        off = self.teach_min_lengthscale_other
        if teach_only:
            row = self.min_lengthscales[:1] + [max(x, off) for x in self.min_lengthscales[1:]]
            if self.teach_speed_lengthscale_mps > 0:
                row[V_CMD] = min(self.teach_speed_lengthscale_mps, off)
            return [list(row) for _ in range(3)]
        rows = [list(self.min_lengthscales) for _ in range(3)]
        if not self.heading_from_turn_history:
            for i in TURN_HISTORY:
                rows[HEADING][i] = max(rows[HEADING][i], off)
        return rows

    def ceilings(self, teach_only: bool) -> list[list[float]] | None:
        """The lengthscale ceilings of a fit (None: none): on the teach pass alone, the commanded speed's
        lengthscale is held at `teach_speed_lengthscale_mps` (one speed seen, the likelihood cannot set it)."""
        if not teach_only or self.teach_speed_lengthscale_mps <= 0:
            return None
        row = [math.inf] * len(self.min_lengthscales)
        row[V_CMD] = min(self.teach_speed_lengthscale_mps, self.teach_min_lengthscale_other)
        return [list(row) for _ in range(3)]


@dataclass(frozen=True, kw_only=True)
class StoreConfig:
    name: str = "store1"
    db_path: str
    paths: list[str] = field(default_factory=lambda: ["*"])   # routes served here; split across machines
    bins: BinPolicy = field(default_factory=BinPolicy)   # thesis 5.3.2 / 5.4.2 (common/bins.py)
    fit: FitConfig = field(default_factory=FitConfig)
