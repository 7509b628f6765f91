"""SE(3) poses as 4x4 homogeneous matrices. `T_a_b` maps coordinates in frame b into frame a, so
`T_a_b @ T_b_c = T_a_c`, as in `common.se2`."""
from __future__ import annotations

import math

import numpy as np


def inverse(T_ab: np.ndarray) -> np.ndarray:
    T = np.asarray(T_ab, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp(xi: np.ndarray) -> np.ndarray:
    """exp of the twist xi = (rho, phi) (translation first), via Rodrigues with the SE(3) V matrix."""
    xi = np.asarray(xi, dtype=float)
    rho, phi = xi[:3], xi[3:]
    th = float(np.linalg.norm(phi))
    P = hat(phi)
    if th < 1e-9:
        R, V = np.eye(3) + P, np.eye(3) + 0.5 * P
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th ** 2
        R = np.eye(3) + a * P + b * P @ P
        V = np.eye(3) + b * P + (th - math.sin(th)) / th ** 3 * P @ P
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ rho
    return T


def to_se2(T: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of a pose in a frame with z up (yaw of the x axis projected on the x-y plane)."""
    T = np.asarray(T, dtype=float)
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])
