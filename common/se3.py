"""SE(3) poses as 4x4 homogeneous matrices. `T_a_b` maps coordinates in frame b into frame a, so
`T_a_b @ T_b_c = T_a_c`, as in `common.se2`. Perturbations xi = (rho, phi): translation first."""
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


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula."""
    a = float(np.linalg.norm(phi))
    if a < 1e-12:
        return np.eye(3) + hat(phi)
    k = hat(np.asarray(phi, dtype=float) / a)
    return np.eye(3) + math.sin(a) * k + (1.0 - math.cos(a)) * (k @ k)


def exp(xi: np.ndarray) -> np.ndarray:
    """exp((rho, phi)^) as a 4x4 matrix (translation V rho, with SE(3)'s left Jacobian V)."""
    xi = np.asarray(xi, dtype=float)
    rho, phi = xi[:3], xi[3:]
    a = float(np.linalg.norm(phi))
    K = hat(phi)
    if a < 1e-9:
        V = np.eye(3) + 0.5 * K
    else:
        V = np.eye(3) + (1.0 - math.cos(a)) / a ** 2 * K + (a - math.sin(a)) / a ** 3 * (K @ K)
    T = np.eye(4)
    T[:3, :3] = so3_exp(phi)
    T[:3, 3] = V @ rho
    return T


def adjoint(T: np.ndarray) -> np.ndarray:
    """Ad(T) for xi = (rho, phi): exp((Ad(T) xi)^) = T exp(xi^) T^-1."""
    C, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = C
    A[:3, 3:] = hat(t) @ C
    return A


def rotation_angle_deg(C: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(C[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def transform(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(N, 3) points given in frame b expressed in frame a, for T = T_a_b."""
    return P @ T[:3, :3].T + T[:3, 3]


def to_se2(T: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of a pose in a frame with z up (yaw of the x axis projected on the x-y plane)."""
    T = np.asarray(T, dtype=float)
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])
