"""The steering laws by name: one table for the node, the experiment runner and the bench. The names
are the scenario file's (`common.scenario.ALGORITHMS`); every one has an entry here."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

from common.scenario import ALGORITHMS
from services.controller.actuator import ActuatorLag
from services.controller.fl import FLGains
from services.controller.ilc import ILCLaw, ILCMemory
from services.controller.laws import FLLaw, StepContext, SteeringLaw
from services.controller.nmpc import LBNMPCLaw
from services.controller.robust_nmpc import MMLBNMPCLaw, RCLBNMPCLaw
from services.controller.settings import NMPCSettings

# the laws that choose their own speed draw the local window's speed bin with this hysteresis (0.5 s at
# 10 Hz): their commanded speed moves every step, and a window rebuilt at each bin crossing costs a step
WINDOW_HOLD_STEPS = 5


@dataclass(frozen=True)
class LawInputs:
    """What building a law for one trial may take."""
    gains: FLGains
    nmpc: NMPCSettings
    period_s: float
    model_for: Callable[[StepContext], object] = lambda ctx: None   # the local window's GP, or None
    model_at: Callable[[StepContext, float], object] = lambda ctx, v: None   # ... drawn at speed v
    ilc: ILCMemory | None = None                                      # the route's learned feedforward

    @property
    def lag(self) -> ActuatorLag:
        """The drive the commands go through (actuator.py), for the laws that do not plan with it."""
        return self.nmpc.lag(self.period_s)


@dataclass(frozen=True)
class LawEntry:
    name: str
    thesis: str                           # where the method is described
    build: Callable[[LawInputs], SteeringLaw]
    learns: Literal["", "ilc", "gp"]      # from nothing, its own feedforward per route, or the GP windows
    needs_corridor: bool = False          # the constrained laws read [constraints]
    window_hold_steps: int = 0
    uses_variance: bool = False           # plans with the GP's variance (uncertainty.py), not its mean alone
    # chooses its speed under its own speed ladder (speed_ladder.py), which keeps the plan's turn rates under
    # the drive's limit: the tracker's cap from the robot's turn (turn_speed.py) is for the others
    chooses_speed: bool = False


STEERING_LAWS: dict[str, LawEntry] = {e.name: e for e in (
    LawEntry("fl", "3.5, eq. 3.1-3.5", lambda i: FLLaw(i.gains, i.lag), ""),
    LawEntry("ilc", "ch. 3, eq. 3.12-3.16", lambda i: ILCLaw(i.gains, i.ilc, i.lag), "ilc"),
    LawEntry("lb-nmpc", "ch. 5, eq. 5.2-5.16", lambda i: LBNMPCLaw(i.nmpc, i.period_s, i.model_for), "gp"),
    LawEntry("mm-lb-nmpc", "ch. 6, eq. 6.2-6.14", lambda i: MMLBNMPCLaw(i.nmpc, i.period_s, i.model_for), "gp",
             uses_variance=True),
    LawEntry("c-lb-nmpc", "ch. 7, eq. 7.2-7.6, alpha = 0",
             lambda i: RCLBNMPCLaw(i.nmpc, i.period_s, i.model_for, alpha=0.0, model_at=i.model_at), "gp", True,
             WINDOW_HOLD_STEPS,
             uses_variance=True, chooses_speed=True),
    LawEntry("rc-lb-nmpc", "ch. 7, eq. 7.2-7.12",
             lambda i: RCLBNMPCLaw(i.nmpc, i.period_s, i.model_for, model_at=i.model_at), "gp", True,
             WINDOW_HOLD_STEPS,
             uses_variance=True, chooses_speed=True),
)}

if set(STEERING_LAWS) != set(ALGORITHMS):
    raise ImportError(f"steering laws {sorted(STEERING_LAWS)} do not match the scenario's {sorted(ALGORITHMS)}")


def law_entry(name: str) -> LawEntry:
    try:
        return STEERING_LAWS[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r} (available: {', '.join(STEERING_LAWS)})") from None
