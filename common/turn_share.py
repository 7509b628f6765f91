"""How much of the nominal turn a learned heading model leaves the controller.

The disturbance g(a) is learned from closed-loop data, where the controller turns hardest exactly where
the terrain turns the robot the other way, so a fit can explain the terrain's yaw by the commanded turn
rate. With G_i = dg_head/da_i / dt (dimensionless) and the nominal turn gain k, the model keeps the share
(k + G_wcmd) / k of the nominal turn for a command held one period, and

    (k + G_wcmd + G_wprev) / (k (1 - G_wact))        (G_wact < 1; otherwise it has no steady turn)

for one held until the turn rate settles; whichever is smaller. Terrain scales a turn (slip lowers it, a
skid-steer at speed keeps a fraction of it) but does not cancel or reverse it. The store checks its fits
with this at their data (services/gp_store/authority.py), the controller its plans at their inputs
(services/controller/held_turn.py).
"""
from __future__ import annotations

import math

import numpy as np

HEADING = 2                                      # output dimension of g (G_NAMES dtheta_rad)
S, W_ACT, V_CMD, W_CMD, W_CMD_PREV = 0, 4, 5, 6, 8     # inputs of a (services/controller/experience.py A_NAMES)


def kept_turn_share(dg_head_per_s: np.ndarray, turn_gain: float) -> float:
    """The share of the nominal turn kept, from the heading output's gradient by a (9,) over the period."""
    k, g = turn_gain, dg_head_per_s
    persist = float(g[W_ACT])
    steady = (k + g[W_CMD] + g[W_CMD_PREV]) / (k * (1.0 - persist)) if persist < 1.0 else -math.inf
    return float(min((k + g[W_CMD]) / k, steady))
