"""Batched rotation maths for paths of many poses (vectorised over nodes: no Python loops).

Rotation vectors are in rad; arrays carry a leading node axis: ``R`` (n, 3, 3), ``w`` (n, 3).
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE_RAD = 1e-6
"""Below this angle the series forms of exp and log are exact to rounding."""


def hat(w: np.ndarray) -> np.ndarray:
    """Skew matrices (n, 3, 3) of vectors ``w`` (n, 3)."""
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def exp_batch(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors ``w`` (n, 3) (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat(w)
    small = theta < SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def log_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of rotation matrices ``R`` (n, 3, 3); angles up to π − 1e-6
    (a path's neighbouring nodes never turn half a turn apart)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    small = theta < SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)
    scale = np.where(small, 0.5 + theta**2 / 12.0, safe / (2.0 * np.sin(safe)))
    return scale[..., None] * v


def interpolate(X0: np.ndarray, X1: np.ndarray, t: np.ndarray, c_O: np.ndarray) -> np.ndarray:
    """Poses (n, 4, 4) a fraction ``t`` (n,) of the way from ``X0`` to ``X1`` (each (4, 4) or
    (n, 4, 4)): the point ``c_O`` (the centre of mass) moves on a straight line and the rotation
    turns about a fixed axis (the robot's spatially-linear move)."""
    t = np.asarray(t, dtype=np.float64)
    X0 = np.broadcast_to(X0, (*t.shape, 4, 4))
    X1 = np.broadcast_to(X1, (*t.shape, 4, 4))
    R0, R1 = X0[..., :3, :3], X1[..., :3, :3]
    c0 = R0 @ c_O + X0[..., :3, 3]
    c1 = R1 @ c_O + X1[..., :3, 3]
    w = log_batch(R1 @ np.swapaxes(R0, -1, -2))
    R = exp_batch(w * t[..., None]) @ R0
    X = np.zeros((*t.shape, 4, 4))
    X[..., :3, :3] = R
    X[..., :3, 3] = c0 + (c1 - c0) * t[..., None] - R @ c_O
    X[..., 3, 3] = 1.0
    return X


def centres(X: np.ndarray, c_O: np.ndarray) -> np.ndarray:
    """Where the point ``c_O`` of O is (n, 3) at each pose ``X`` (n, 4, 4)."""
    return X[:, :3, :3] @ c_O + X[:, :3, 3]
