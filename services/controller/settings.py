"""Settings of the NMPC laws: the controller config's [nmpc] table and the scenario's [controller.nmpc]."""
from __future__ import annotations

from dataclasses import dataclass, replace

from common.messages import NominalModel
from services.controller.actuator import MAX_TURN_GAIN, MIN_TURN_GAIN, ActuatorLag
from services.controller.uncertainty import VOUCH_SCALES, PriorStd

_PRIOR = PriorStd()
# the settings a teach pass identifies unless they are set by hand (NominalModel has the same names)
PRIOR = ("prior_std_base", "prior_std_per_mps", "prior_std_per_radps")
IDENTIFIED = ("actuator_tau_s", "curvature_rate_max_per_ms", "turn_gain") + PRIOR


@dataclass(frozen=True, kw_only=True)
class NMPCSettings:
    """Weights (eq. 5.16, 7.2) and solver settings of LB-, MM-, C- and RC-LB-NMPC; one set of defaults."""
    horizon: int = 10
    q_along: float = 1.0      # 1/m^2, on the along-route error
    q_lat: float = 40.0       # 1/m^2, on the lateral error
    q_head: float = 10.0      # 1/rad^2, on the heading error
    r_w: float = 0.2          # s^2/rad^2, on w - v kappa (the route's own turn rate keeps curves unbiased)
    r_dw: float = 1.0         # s^2/rad^2, on w_j - w_{j-1}
    q_terminal: float = 100.0 # 1/m^2, on the lateral error lookahead_m ahead of the last predicted pose
    lookahead_m: float = 1.5  # a one-second horizon is too short to see a lateral correction pay off
    max_iter: int = 10        # solver iterations per step at most
    max_evals: int = 6        # residual evaluations per step at most: bounds the solve time
    tol: float = 1e-3         # rad/s: stop when no angular rate moves more than this
    delay_compensation: bool = True   # eq. 7.12: start from the estimate carried forward to now
    # --- MM-, C- and RC-LB-NMPC (chapters 6, 7) ---
    sp_gamma: float = 2.0     # sigma-point scaling (eq. 6.10-6.14; thesis 6.4.2)
    mm_sigmas: float = 3.0    # MM: boundary sequences at +-mm_sigmas sigma (eq. 6.5)
    alpha: float = 3.0        # RC: corridor tightened by alpha * sigma (eq. 7.4); C-LB-NMPC uses 0
    r_v: float = 4.0          # s^2/m^2, on v - v_desired (eq. 7.2's u_d: the scheduled speed)
    r_dv: float = 2.0         # s^2/m^2, on v_j - v_{j-1}
    v_min_mps: float = 0.05   # C/RC: the slowest the law may choose while moving
    slack_weight: float = 2000.0    # C/RC: L1 price of violating a (tightened) corridor limit
    sqp_iter: int = 4         # C/RC: SQP iterations per step at most
    # the a-priori std of the unicycle model's error per period (body frame: along, lateral, heading),
    # base + per_mps |v| + per_radps |w|: slip and lag grow with speed and with turning. None: identified
    # from the route's teach pass (identification.py), or uncertainty.PriorStd's without one
    prior_std_base: tuple[float, float, float] | None = None
    prior_std_per_mps: tuple[float, float, float] | None = None
    prior_std_per_radps: tuple[float, float, float] | None = None
    # C/RC beyond the first step: the tightened band keeps at least this fraction of the corridor (the
    # open-loop covariance ignores the localization updates still to come)
    min_band_fraction: float = 0.2
    # where the learned heading model keeps less than this share of the nominal turn at a step's planned
    # inputs, that step plans with its heading mean held at the route's turn rate (held_turn.py); 0: never
    min_turn_share: float = 0.1
    process_std: tuple[float, float, float] = (0.0005, 0.001, 0.002)   # floor for what never repeats
    # MM/C/RC: how far an experience vouches at most, as the GP variance's lengthscale caps along the route
    # (m), in commanded speed (m/s) and in commanded turn rate (rad/s); the mean keeps the fitted ones
    # (uncertainty.py). A robot much faster than 2.5 m/s may want a wider speed cap (its speed bins too)
    vouch_lengthscales: tuple[float, float, float] = VOUCH_SCALES
    # the drive's first-order lag (v, w) in seconds (actuator.py); 0: eq. 5.26 as is. None: identified from
    # the route's teach pass (identification.py), or none without one
    actuator_tau_s: tuple[float, float] | None = None
    # Ackermann: the steering's rate limit as curvature per second, 1/(m s) (actuator.py); 0: no limit.
    # None: the robot's, as the teach pass's model carries it (identification.py), or none without one
    curvature_rate_max_per_ms: float | None = None
    # the robot's turn rate over the drive's: what ground slip (a skid-steer's) or understeer leave of a
    # turn (actuator.py); 1: none. None: identified from the route's teach pass against the localizer's
    # heading (identification.py), or 1 without one
    turn_gain: float | None = None
    # a skid-steer's turn drive: its acceleration limit, rad/s^2 (turn_accel.py); C-/RC-LB-NMPC keep each turn
    # command's lead over the drive within what it lets the drive follow. None: read off the earlier
    # repeats' commands and wheel odometry under the same nominal model (no limit until one met it)
    turn_accel_max_radps2: float | None = None
    # with a learned model, weigh the heading error against the crab angle the model needs to hold the
    # route at the planned speed (nmpc.crab_offsets), not the taught heading, which holds the teach
    # speed's crab: for repeats well above the teach speed on ground that slides the robot sideways
    crab_reference: bool = False

    def __post_init__(self):
        for name in ("prior_std_base", "prior_std_per_mps", "prior_std_per_radps", "process_std"):   # TOML gives lists
            if getattr(self, name) is None:
                continue
            value = tuple(float(x) for x in getattr(self, name))
            if len(value) != 3 or min(value) < 0:
                raise ValueError(f"{name}: three non-negative values (along, lateral, heading)")
            object.__setattr__(self, name, value)
        caps = tuple(float(x) for x in self.vouch_lengthscales)
        if len(caps) != 3 or not min(caps) > 0:
            raise ValueError("vouch_lengthscales: three positive lengthscales (along m, speed m/s, turn rate rad/s)")
        object.__setattr__(self, "vouch_lengthscales", caps)
        if self.actuator_tau_s is not None:
            tau = tuple(float(x) for x in self.actuator_tau_s)
            if len(tau) != 2 or min(tau) < 0:
                raise ValueError("actuator_tau_s: two non-negative time constants (v, w) in seconds")
            object.__setattr__(self, "actuator_tau_s", tau)
        if self.curvature_rate_max_per_ms is not None and self.curvature_rate_max_per_ms < 0:
            raise ValueError("curvature_rate_max_per_ms must be >= 0 (0: no limit)")
        if self.turn_accel_max_radps2 is not None and not self.turn_accel_max_radps2 > 0:
            raise ValueError("turn_accel_max_radps2 must be > 0 (leave it out to learn it from the repeats)")
        if self.turn_gain is not None and not MIN_TURN_GAIN <= self.turn_gain <= MAX_TURN_GAIN:
            raise ValueError(f"turn_gain must be in [{MIN_TURN_GAIN}, {MAX_TURN_GAIN}] (1: the robot turns as its drive)")
        if self.horizon < 1 or self.max_iter < 1 or self.max_evals < 2 or min(
                self.q_along, self.q_lat, self.q_head, self.r_w, self.r_dw, self.q_terminal, self.lookahead_m) < 0:
            raise ValueError("horizon, max_iter >= 1, max_evals >= 2 and non-negative weights required")
        if self.r_w + self.r_dw <= 0:
            raise ValueError("r_w or r_dw must be > 0 (eq. 5.3 needs R positive definite)")
        if not 0.0 <= self.min_band_fraction < 1.0:
            raise ValueError("min_band_fraction must be in [0, 1)")
        if not 0.0 <= self.min_turn_share < 1.0:
            raise ValueError("min_turn_share must be in [0, 1)")

    def lag(self, dt: float) -> ActuatorLag:
        tau = self.actuator_tau_s or (0.0, 0.0)
        return ActuatorLag(tau[0], tau[1], dt, self.curvature_rate_max_per_ms or 0.0,
                           1.0 if self.turn_gain is None else self.turn_gain)

    @property
    def prior_is_identified(self) -> bool:
        """No part of the a-priori uncertainty was set by hand."""
        return all(getattr(self, name) is None for name in PRIOR)

    def prior_std(self) -> PriorStd:
        return PriorStd(base=self.prior_std_base or _PRIOR.base, per_mps=self.prior_std_per_mps or _PRIOR.per_mps,
                        per_radps=self.prior_std_per_radps or _PRIOR.per_radps)

    def with_identified(self, model: NominalModel | None) -> NMPCSettings:
        """These settings with what was left to identification (None) taken from `model`; hand-set
        values stay as they are."""
        if model is None:
            return self
        fill = {name: getattr(model, name) for name in IDENTIFIED if getattr(self, name) is None}
        return replace(self, **fill)
