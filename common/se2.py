"""SE(2) poses as (x, y, theta) triples. `compose(T_a_b, T_b_c) = T_a_c`; `inverse(T_a_b) = T_b_a`.

All functions accept a single pose of shape (3,) or a stack of shape (N, 3) and broadcast.
"""
from __future__ import annotations

import numpy as np


def wrap(angle):
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def compose(T_ab, T_bc) -> np.ndarray:
    a = np.asarray(T_ab, dtype=float)
    b = np.asarray(T_bc, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap(a[..., 2] + b[..., 2])], axis=-1)


def inverse(T_ab) -> np.ndarray:
    a = np.asarray(T_ab, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap(-a[..., 2])], axis=-1)


def between(T_wa, T_wb) -> np.ndarray:
    """T_ab: pose of b expressed in frame a, given both in a common frame w."""
    return compose(inverse(T_wa), T_wb)


def transform_points(T_ab, p_b) -> np.ndarray:
    """Points given in frame b (shape (..., 2)) expressed in frame a."""
    a = np.asarray(T_ab, dtype=float)
    p = np.asarray(p_b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * p[..., 0] - s * p[..., 1],
                     a[..., 1] + s * p[..., 0] + c * p[..., 1]], axis=-1)


def to_matrix(T) -> np.ndarray:
    x, y, th = np.asarray(T, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def from_matrix(M) -> np.ndarray:
    M = np.asarray(M, dtype=float)
    return np.array([M[0, 2], M[1, 2], np.arctan2(M[1, 0], M[0, 0])])


def adjoint(T) -> np.ndarray:
    """Adjoint of T for (x, y, theta) tangent vectors: maps a perturbation in frame b to frame a.

    Used to move a pose covariance between frames: Sigma_a = Ad(T_ab) Sigma_b Ad(T_ab)^T.
    """
    x, y, th = np.asarray(T, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])
