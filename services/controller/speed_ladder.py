"""RC-LB-NMPC's speed cap (thesis 7.3: "slows down while uncertain"): the fastest of a ladder of
slowed-down speed profiles whose 3-sigma region, with the band left to the mean, fits the corridor over
the whole horizon. Uncertainty grows with speed, so slowing down is what makes an uncertain plan fit.

A rung fits when alpha * sigma of its own plan stays inside the band cap, and the turn rates that follow
the route at its speeds (with last step's corrections, scaled) keep some headroom below the drive's
turn-rate limit: a plan pinned at the limit cannot correct anything. Only the rate limit counts, the one
slowing down relieves; an Ackermann's curvature limit binds at every speed alike (the SQP keeps to it).
The ladder climbs one rung per step at most and descends as far as needed (where no rung fits, to the
one that misses by least); the SQP then fine-tunes below the cap. Without it the band is infeasible at
the scheduled speed, the slack price dominates the cost and the plan flips between steps. Between a rung
that fits and the one above it that does not, the ladder drives at the speed where the fit ends, if that
fits (_between). A rung faster than the passes over the place vouch for is widened by the teach pass's
needs there (calibration.beyond_at): its covariance model is the rung's own.

The learned model is the local window drawn at the speed the law drives (thesis 5.3.2), whose speed bins
end a bin or two above it. Once the law has slowed below the speeds its earlier trials drove at a place,
every faster rung lies beyond its window's experience and is tested on the prior's variance; none fits,
and the robot stays slow until the route leaves the place (bench seed 8371: a MATS whose rut surprise at
2.1 m/s held it at 1.2-1.5 m/s for the next 30 m of a straight it had driven at 2.1 in four trials, and a
ROC6 slower every trial, 110 s to 181 s). So where the climb by one rung fails, the asked speed's rung is
also tested on the window drawn at its own speed (AskedModel), and taken where it fits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from services.controller.horizon import HorizonProblem
from services.controller.horizon_covariance import HorizonCovariance
from services.controller.missed_variance import FloorsBySpeed

SPEED_LADDER = (1.0, 0.85, 0.7, 0.58, 0.48, 0.4, 0.32, 0.25, 0.18, 0.12)   # shares of the scheduled speeds
TURN_HEADROOM = 0.9      # a rung's turn rates stay below this share of the drive's turn-rate limit
BETWEEN_FIT = 0.98       # the overflow aimed at between a rung that fits and the one above (_between)


@dataclass(frozen=True)
class Rung:
    """A rung's plan: speeds, turn rates, their covariance, and the problem following those speeds
    (whose rollout with sensitivities is memoized: the SQP's first iterate)."""
    index: int
    problem: HorizonProblem
    v: np.ndarray
    w: np.ndarray
    Sigma: np.ndarray       # (K+1, 3, 3)
    sig_model: np.ndarray   # (K, 3) route-frame standard deviations of x_1..x_K, as the model gives them
    sig: np.ndarray         # (K, 3) the same widened by the online calibration (what the corridor must hold)
    sig_loc: np.ndarray     # (K, 3) the localizer's share of them (never widened)
    cov: HorizonCovariance  # the covariance model it was tested with
    scale: float            # the share of the scheduled speeds it drives: its rung's, or one between two
    asked_model: bool = False   # tested on the asked speed's own window (AskedModel), not the driven speed's
    held_by: str = ""           # what kept the ladder from a faster rung (Misses.describe; "": nothing)
    cause: str = ""             # ... as a name: "lateral", "heading", "turn" or "no-fit" (Misses.cause)


@dataclass(frozen=True)
class Misses:
    """The shares of its room a rung's plan takes (`overflow`: the largest; <= 1 fits): the lateral and
    heading alpha-sigma regions of their bands, its turn rates of the turn-rate headroom."""
    lateral: float
    heading: float
    turn: float
    alpha: float = 3.0

    @property
    def worst(self) -> float:
        return max(self.lateral, self.heading, self.turn)

    @property
    def cause(self) -> str:
        """The check that took the largest share: "lateral", "heading" or "turn"."""
        return max((("lateral", self.lateral), ("heading", self.heading), ("turn", self.turn)), key=lambda x: x[1])[0]

    def describe(self, scale: float) -> str:
        """What held the ladder below a rung at `scale` of the asked speed that took these shares."""
        cause = self.cause
        what = "turn rate" if cause == "turn" else f"{cause} {self.alpha:g}-sigma region"
        room = "turn-rate headroom" if cause == "turn" else "band"
        share = {"lateral": self.lateral, "heading": self.heading, "turn": self.turn}[cause]
        return f"at {scale:.2f} x the asked speed its {what} would take {share:.2f} of its {room}"


@dataclass(frozen=True)
class AskedModel:
    """The learned model of the local window drawn at the asked speed, for testing the top rung when the
    law drives slower (module docstring): the window's GP, the step's problem with it (following the warm
    start's speeds, as the ladder's own), its covariance model, and its widening beyond the places' passes."""
    model: object
    problem: HorizonProblem
    cov: HorizonCovariance
    beyond: tuple[float, HorizonCovariance] | None = None


def _try_rung(k: int, base: HorizonProblem, v: np.ndarray, w: np.ndarray, cov: HorizonCovariance,
              a_out: np.ndarray, v_min: float, beyond: tuple[float, HorizonCovariance] | None = None,
              floors: FloorsBySpeed | None = None, scale: float | None = None) -> Rung:
    """The rung's own profile (at `scale` of the scheduled speeds instead of rung k's, if given), tested
    at its own speeds (and the calibration's floors at them): a rung "fitted" at the warm start's slower
    speeds would be driven at the rung's and fall back next step (two-step chatter)."""
    scale = SPEED_LADDER[k] if scale is None else scale
    vk = np.clip(scale * base.v, v_min, None)
    if beyond is not None and float(vk.max()) > beyond[0]:
        cov = beyond[1]
    if floors is not None:
        cov = cov.with_floors(floors.at(float(vk.max())))
    p = base.following(vk)
    # same path: corrections scaled down with speed, never up (a correction made at a crawl is a turn on
    # the spot, which no faster rung could drive)
    wk = (vk * p.ref.kappa + (w * base.turn_gain - v * base.ref.kappa) * np.minimum(1.0, vk / np.maximum(v, 1e-3))
          ) / base.turn_gain
    X = p.rollout(wk, with_jac=True, v=vk, with_v_jac=True, a_out=a_out)[0]
    Sig, sig = cov.along(p, X, a_out, vk, wk)
    loc = cov.localizer_part(X, p.ref.direction_rad[1:])
    return Rung(k, p, vk, wk, Sig, sig, cov.widened(sig, loc), loc, cov, scale)


def misses(rung: Rung, cap: np.ndarray, alpha: float, w_rate_cap: float) -> Misses:
    """The shares of its band that alpha * sigma takes beyond the first step, lateral and heading, and of
    the turn-rate headroom its turn rates take."""
    t = alpha * rung.sig[1:]
    room = np.maximum(cap[1:, 1:3], 1e-12)
    spread = np.max(t[:, 1:3] / room, axis=0)
    turn = float(np.max(np.abs(rung.w))) / max(TURN_HEADROOM * w_rate_cap, 1e-12)
    return Misses(float(spread[0]), float(spread[1]), turn, alpha)


def overflow(rung: Rung, cap: np.ndarray, alpha: float, w_rate_cap: float) -> float:
    """How far the rung misses fitting: the largest share of its room it takes (`misses`; <= 1: it fits)."""
    return misses(rung, cap, alpha, w_rate_cap).worst


def fastest_fitting_rung(base: HorizonProblem, v: np.ndarray, w: np.ndarray, cov: HorizonCovariance,
                         cap: np.ndarray, alpha: float, w_rate_cap: float, last_index: int | None,
                         a_out: np.ndarray, beyond: tuple[float, HorizonCovariance] | None = None,
                         floors: FloorsBySpeed | None = None,
                         asked: Callable[[], AskedModel | None] | None = None) -> Rung:
    """From one rung faster than last step's (`last_index`; None: the top) down to the first that fits;
    where none does, the one that misses by least (`overflow`; the faster of equals). `cap` (K, 3): the
    most alpha * sigma may take of the corridor; `w_rate_cap`: the drive's turn-rate limit at any speed.
    `a_out` (K, 9) receives the chosen rung's GP inputs. `beyond`: the speed above which a rung is tested
    with the other covariance model; `floors`: the calibration's, taken at each rung's speed; `asked`: the
    asked speed's own model (built on demand; None where it is the driven speed's), for a climb that fails.

    Slower is not always narrower: the prior's speed-independent terms, a place's remembered widening and
    what a crawl itself missed do not fade at a crawl, and a side slope whose slide acts per second needs
    a crab angle that grows as the robot slows. Where no rung fits, the bottom one is then not always the
    least unsafe."""
    first = 0 if last_index is None else max(last_index - 1, 0)
    best, best_miss, best_a = None, Misses(math.inf, math.inf, math.inf), np.empty_like(a_out)
    faster: tuple[float, float] | None = None      # (scale, overflow) of the rung above, which did not fit
    held: Misses | None = None                     # ... and the shares of its room it took
    for k in range(first, len(SPEED_LADDER)):
        rung = _try_rung(k, base, v, w, cov, a_out, base.s.v_min_mps, beyond, floors)
        m = misses(rung, cap, alpha, w_rate_cap)
        if m.worst <= 1.0:
            chosen = rung if faster is None else _between(rung, m.worst, faster, base, v, w, cov, cap, alpha,
                                                          w_rate_cap, a_out, beyond, floors)
            return replace(chosen, held_by=held.describe(faster[0]) if held is not None else "",
                           cause=held.cause if held is not None else "")
        if k == first > 0 and asked is not None and (top := _asked_top(asked, v, w, cap, alpha, w_rate_cap, a_out,
                                                                       base.s.v_min_mps, floors)) is not None:
            return top
        faster, held = (rung.scale, m.worst), m
        if m.worst < best_miss.worst:
            best, best_miss = rung, m
            best_a[:] = a_out
    a_out[:] = best_a
    return replace(best, held_by="no rung fits; " + best_miss.describe(best.scale), cause="no-fit")


def _asked_top(asked: Callable[[], AskedModel | None], v: np.ndarray, w: np.ndarray, cap: np.ndarray,
               alpha: float, w_rate_cap: float, a_out: np.ndarray, v_min: float,
               floors: FloorsBySpeed | None) -> Rung | None:
    """The top rung tested on the asked speed's own window, if there is one and it fits there (a_out then
    holds its GP inputs; else a_out is left as it was)."""
    model = asked()
    if model is None:
        return None
    a_then = a_out.copy()
    top = _try_rung(0, model.problem, v, w, model.cov, a_out, v_min, model.beyond, floors)
    if overflow(top, cap, alpha, w_rate_cap) <= 1.0:
        return replace(top, asked_model=True)
    a_out[:] = a_then
    return None


def _between(fits: Rung, miss: float, faster: tuple[float, float], base: HorizonProblem, v: np.ndarray,
             w: np.ndarray, cov: HorizonCovariance, cap: np.ndarray, alpha: float, w_rate_cap: float,
             a_out: np.ndarray, beyond: tuple[float, HorizonCovariance] | None,
             floors: FloorsBySpeed | None) -> Rung:
    """Between a rung that fits and the one above that does not, the speed where the overflow, taken as
    linear between them, reaches BETWEEN_FIT, if it fits there (else the rung). Without it a rung above
    that misses by a hair at its own speed fits when tested from the slower one (the drive's lag starts
    its plan slower), and the command flipped between the two every period (a MATS between 1.47 and
    1.78 m/s for 20 s, overflows 0.985 / 1.006: bench seed 4409, s1021326272)."""
    s_fast, m_fast = faster
    share = (BETWEEN_FIT - miss) / max(m_fast - miss, 1e-9)
    if share <= 0.05:
        return fits
    a_fits = a_out.copy()
    mid = _try_rung(fits.index, base, v, w, cov, a_out, base.s.v_min_mps, beyond, floors,
                    fits.scale + min(share, 0.95) * (s_fast - fits.scale))
    if overflow(mid, cap, alpha, w_rate_cap) <= 1.0:
        return mid
    a_out[:] = a_fits
    return fits
