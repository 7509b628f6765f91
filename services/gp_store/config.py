"""Typed configuration of the experience store service."""
from __future__ import annotations

from dataclasses import dataclass, field

from common.bins import BinPolicy


# How fast a disturbance can physically change with each input of a (experience.py A_NAMES): terrain
# varies over metres along and across the route, wheel-ground effects over radians of heading error
# and tenths of m/s or rad/s of motion. Closed-loop data are narrow, and without these floors the
# likelihood picks lengthscales of centimetres that a controller, querying off the data, exploits.
DEFAULT_MIN_LENGTHSCALES = [0.5, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]


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

    def __post_init__(self):
        if len(self.min_lengthscales) != 9 or min(self.min_lengthscales) < 0:
            raise ValueError("min_lengthscales needs 9 values >= 0, one per input of a")
        if self.teach_min_lengthscale_other < 0:
            raise ValueError("teach_min_lengthscale_other must be >= 0")

    def floors(self, teach_only: bool) -> list[float]:
        """The lengthscale floors of a fit; `teach_only`: on the teach pass's experiences alone."""
        if not teach_only:
            return list(self.min_lengthscales)
        return self.min_lengthscales[:1] + [max(x, self.teach_min_lengthscale_other) for x in self.min_lengthscales[1:]]


@dataclass(frozen=True, kw_only=True)
class StoreConfig:
    name: str = "store1"
    db_path: str
    paths: list[str] = field(default_factory=lambda: ["*"])   # routes served here; split across machines
    bins: BinPolicy = field(default_factory=BinPolicy)   # thesis 5.3.2 / 5.4.2 (common/bins.py)
    fit: FitConfig = field(default_factory=FitConfig)
