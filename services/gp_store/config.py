"""Typed configuration of the experience store service."""
from __future__ import annotations

from dataclasses import dataclass, field

from common.bins import BinPolicy


# How fast a disturbance can physically change with each input of a (experience.py A_NAMES): terrain
# varies over metres along and across the route, wheel-ground effects over radians of heading error
# and tenths of m/s or rad/s of motion. Closed-loop data are narrow, and without these floors the
# likelihood picks lengthscales of centimetres that a controller, querying off the data, exploits.
DEFAULT_MIN_LENGTHSCALES = [0.5, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
MOTION_INPUTS = 3    # a's inputs from here on are speeds and commands (experience.A_NAMES)


@dataclass(frozen=True, kw_only=True)
class FitConfig:
    restarts: int = 3
    max_points: int = 1000        # fit on a random subsample beyond this many experiences
    seed: int = 0
    auto_after_trial: bool = True # fit when a robot ends a repeat on a route with new experiences
    min_new: int = 50             # ... and at least this many are new since the last fit
    local_windows: bool = True    # likelihood of the local windows the controller uses (5.3.2)
    min_lengthscales: list[float] = field(default_factory=lambda: list(DEFAULT_MIN_LENGTHSCALES))
    # the teach pass alone drove one command per place, so it cannot tell the place's disturbance from the
    # commands' (fitted, its heading residual followed the counter-steer at 0.3 rad/s and the NMPC chattered
    # against it): fitted on it alone, the motion inputs' lengthscales are at least this (m/s, rad/s)
    teach_min_lengthscale_motion: float = 2.0

    def __post_init__(self):
        if len(self.min_lengthscales) != 9 or min(self.min_lengthscales) < 0:
            raise ValueError("min_lengthscales needs 9 values >= 0, one per input of a")
        if self.teach_min_lengthscale_motion < 0:
            raise ValueError("teach_min_lengthscale_motion must be >= 0")

    def floors(self, teach_only: bool) -> list[float]:
        """The lengthscale floors of a fit; `teach_only`: on the teach pass's experiences alone."""
        if not teach_only:
            return list(self.min_lengthscales)
        motion = [max(x, self.teach_min_lengthscale_motion) for x in self.min_lengthscales[MOTION_INPUTS:]]
        return list(self.min_lengthscales[:MOTION_INPUTS]) + motion


@dataclass(frozen=True, kw_only=True)
class StoreConfig:
    name: str = "store1"
    db_path: str
    paths: list[str] = field(default_factory=lambda: ["*"])   # routes served here; split across machines
    bins: BinPolicy = field(default_factory=BinPolicy)   # thesis 5.3.2 / 5.4.2 (common/bins.py)
    fit: FitConfig = field(default_factory=FitConfig)
