"""`lbc bench stops`: how far a safety stop from speed in a corner turns a robot and carries it off its route.

A stop is a manoeuvre (tracker._brake): it brakes at the robot's limit while steering along the route
until the drive, by its identified lag, neither rolls nor turns. This bench measures that manoeuvre on
every preset, in the closed-loop simulator (bench/closed_loop.py: the services' pure cores without the
bus). Each route is a 15 m straight into a 110 deg arc of radius R, taught at half the preset's top
speed (0.8 m/s at most); the controller's drive model is identified from that teach pass, as the node
does. FL tracks at a share of the preset's top speed, and at a share of the arc the law asks for a
safety stop. From the stop until the robot is at rest (or 25 s): the largest change of the heading
error (deg), how much the lateral error grows beyond its value at the stop (m, 0 if it only shrinks),
the distance rolled (m), and how much of the corridor the errors take (the larger of |lateral| over the
half-width and |heading| over its limit: 1 on an edge) at the stop and at most afterwards.
`left_after_stop` counts the stops inside the corridor at the stop and outside it afterwards: what a
stop must not do. The grid is --speeds x --radii x --at. With `--slope DEG`, the corner lies on a side
slope falling towards `--downhill` (world frame; the default, -90 deg, falls to the right of the
straight, out of the left corner): its slide and its yaw act on the robot while it rolls. The
controller has the corridor the services give it (`--corridor`, the scenario's default); the brake
weighs its two limits (brake.py).
Deterministic; prints, per preset, the stops with their medians, maxima and worst cases, and over all
presets the largest turn and the stops that left, on its last line.
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass

import numpy as np

from bench.closed_loop import ClosedLoop
from bench.report import run_and_print
from common.robot import PRESETS
from common.scenario import ConstraintsSection, TerrainPatch
from services.controller.actuator import ActuatorLag
from services.controller.corridor import Corridor
from services.controller.fl import FLGains
from services.controller.laws import FLLaw, LawResult

log = logging.getLogger("bench.stops")

STRAIGHT_M = 15.0
ARC_RAD = math.radians(110.0)
SLOPE_MARGIN_M = 4.0       # the slope's patch reaches this far beyond the arc (its edge fades over 30 %)
SETTLE_STEPS = 250          # 25 s at 10 Hz: every preset is at rest well before


class StopsAt:
    """FL until `stop_m` along the route, then a safety stop; remembers the step it stopped at."""
    name = "stops-at"

    def __init__(self, stop_m: float):
        self.stop_m, self.fl, self.steps, self.stop_step = stop_m, FLLaw(FLGains()), 0, None

    def angular(self, ctx):
        self.steps += 1
        if ctx.s_m < self.stop_m:
            return self.fl.angular(ctx)
        self.stop_step = self.stop_step or self.steps
        return LawResult(0.0, v_mps=0.0, stop_reason="bench stop")


@dataclass(frozen=True)
class StopOutcome:
    preset: str
    speed_mps: float
    radius_m: float
    stop_m: float
    heading_turned_deg: float
    lateral_growth_m: float
    rolled_m: float
    share_at_stop: float = math.nan     # of the corridor (NaN without one)
    share_max: float = math.nan         # its largest from the stop to rest


def corner_route(radius_m: float) -> list[list[float]]:
    arc = [[STRAIGHT_M + radius_m * math.sin(a), radius_m - radius_m * math.cos(a)]
           for a in np.linspace(0.0, ARC_RAD, 12)[1:]]
    return [[0.0, 0.0], [STRAIGHT_M, 0.0]] + arc


def corner_slope(radius_m: float, slope_deg: float, downhill_deg: float) -> list[TerrainPatch]:
    """A side slope under the whole arc of corner_route and the straight's last metres (none at 0 deg)."""
    if slope_deg <= 0.0:
        return []
    return [TerrainPatch(kind="side_slope", center=(STRAIGHT_M, radius_m), radius_m=radius_m + SLOPE_MARGIN_M,
                         slope_deg=slope_deg, downhill_deg=downhill_deg)]


def stops_on(preset: str, radius_m: float, speeds: list[float], at: list[float], seed: int,
             corridor: tuple[float, float] | None = None,
             slope: tuple[float, float] = (0.0, -90.0)) -> list[StopOutcome]:
    """One teach pass of the corner route, then one repeat per (speed share, arc share); `corridor`:
    (lateral m, heading deg), None for none; `slope`: (deg, downhill deg) of a side slope under the corner."""
    robot = PRESETS[preset]
    sim = ClosedLoop(corner_route(radius_m), terrain=corner_slope(radius_m, *slope), preset=preset, seed=seed,
                     teach_speed=min(0.8, 0.5 * robot.v_max_mps))
    path = sim.teach()
    limits = None if corridor is None else Corridor(path.s, corridor[0], math.radians(corridor[1]))
    m = sim.identified()
    lag = ActuatorLag(m.tau_v_s, m.tau_w_s, sim.period_s, curvature_rate_max_per_ms=m.curvature_rate_max_per_ms,
                      turn_gain=m.turn_gain)
    out = []
    for share in speeds:
        for frac in at:
            law = StopsAt(STRAIGHT_M + frac * ARC_RAD * radius_m)
            v = share * robot.v_max_mps
            r = sim.repeat(1, v, law=law, lag=lag, max_steps=SETTLE_STEPS + int(60 / sim.period_s), corridor=limits)
            k = law.stop_step
            if k is None:
                raise RuntimeError(f"{preset} at {v:.2f} m/s never reached its stop at {law.stop_m:.1f} m")
            head, lat = r.heading_rad[k:], r.lateral_m[k:]
            growth = float(np.max(np.abs(lat)) - abs(lat[0]))
            taken = (np.maximum(np.abs(lat) / corridor[0], np.abs(head) / math.radians(corridor[1]))
                     if corridor else np.full(len(lat), math.nan))
            out.append(StopOutcome(preset, v, radius_m, law.stop_m, math.degrees(float(np.max(np.abs(head - head[0])))),
                                   max(0.0, growth), r.rolled_m(k), float(taken[0]), float(np.max(taken))))
            o = out[-1]
            log.info("%s R=%.0f m v=%.2f m/s stop at %.1f m: turned %.1f deg, lateral +%.3f m, rolled %.2f m, "
                     "corridor share %.2f -> at most %.2f", preset, radius_m, v, law.stop_m, o.heading_turned_deg,
                     o.lateral_growth_m, o.rolled_m, o.share_at_stop, o.share_max)
    return out


def _case(o: StopOutcome) -> dict:
    return {"speed_mps": round(o.speed_mps, 3), "radius_m": o.radius_m, "stop_m": round(o.stop_m, 2),
            "heading_turned_deg": round(o.heading_turned_deg, 2), "lateral_growth_m": round(o.lateral_growth_m, 4),
            "rolled_m": round(o.rolled_m, 3), "share_at_stop": _num(o.share_at_stop), "share_max": _num(o.share_max)}


def _num(x: float, digits: int = 3) -> float | None:
    return None if math.isnan(x) else round(x, digits)


def summary(outcomes: list[StopOutcome]) -> dict:
    turned = [o.heading_turned_deg for o in outcomes]
    growth = [o.share_max - o.share_at_stop for o in outcomes]
    return {"stops": len(outcomes),
            "heading_turned_deg_median": round(float(np.median(turned)), 2),
            "heading_turned_deg_max": round(float(np.max(turned)), 2),
            "lateral_growth_m_max": round(max(o.lateral_growth_m for o in outcomes), 4),
            "rolled_m_median": round(float(np.median([o.rolled_m for o in outcomes])), 3),
            "worst_turn": _case(max(outcomes, key=lambda o: o.heading_turned_deg)),
            "worst_lateral": _case(max(outcomes, key=lambda o: o.lateral_growth_m)),
            "share_growth_median": _num(float(np.median(growth))),
            "share_growth_max": _num(float(np.max(growth))),
            "left_after_stop": sum(1 for o in outcomes if o.share_at_stop <= 1.0 < o.share_max)}


def run_bench(args) -> dict:
    result: dict = {"presets": {}}
    everything = []
    for preset in args.robots:
        outcomes = [o for radius in args.radii
                    for o in stops_on(preset, radius, args.speeds, args.at, args.seed, args.corridor,
                                      (args.slope, args.downhill))]
        result["presets"][preset] = summary(outcomes)
        everything += outcomes
    result["heading_turned_deg_max"] = round(max(o.heading_turned_deg for o in everything), 2)
    result["stops"] = len(everything)
    result["left_after_stop"] = sum(p["left_after_stop"] for p in result["presets"].values())
    result["corridor"] = list(args.corridor) if args.corridor else None
    result["slope_deg"], result["downhill_deg"] = args.slope, args.downhill
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench stops", description=__doc__.splitlines()[0])
    parser.add_argument("--robots", nargs="+", default=sorted(PRESETS), choices=sorted(PRESETS))
    parser.add_argument("--speeds", nargs="+", type=float, default=[0.5, 0.75, 0.95],
                        help="shares of the preset's top speed")
    parser.add_argument("--radii", nargs="+", type=float, default=[5.0, 8.0], help="corner radii, m")
    parser.add_argument("--at", nargs="+", type=float, default=[0.25, 0.5, 0.75],
                        help="where in the arc the stop comes, as shares of its length")
    parser.add_argument("--seed", type=int, default=3)
    default = ConstraintsSection()
    parser.add_argument("--corridor", nargs=2, type=float, default=[default.lateral_m, default.heading_deg],
                        metavar=("LATERAL_M", "HEADING_DEG"), help="the controller's corridor; 0 0: none")
    parser.add_argument("--slope", type=float, default=0.0, metavar="DEG",
                        help="a side slope of this many degrees under the corner (0: flat)")
    parser.add_argument("--downhill", type=float, default=-90.0, metavar="DEG",
                        help="where the slope falls to, world frame (-90: out of the left corner at its start)")
    args = parser.parse_args(argv)
    if not all(0.0 < s <= 1.0 for s in args.speeds) or not all(0.0 <= a <= 1.0 for a in args.at) \
            or not all(r > 0.0 for r in args.radii) or min(args.corridor) < 0.0 or not 0.0 <= args.slope < 45.0:
        parser.error("speeds in (0, 1], --at in [0, 1], radii > 0, a corridor >= 0, a slope in [0, 45) deg")
    args.corridor = tuple(args.corridor) if min(args.corridor) > 0.0 else None
    logging.basicConfig(level=logging.INFO, format="[bench.stops] %(message)s", stream=sys.stderr)
    log.setLevel(logging.INFO)      # progress, also under lbc's root logger at WARNING
    return run_and_print(lambda: run_bench(args))


if __name__ == "__main__":
    raise SystemExit(main())
