"""Rigid transforms in Drake's monogram notation: ``X_AB`` is frame B's pose in frame A (4×4).

Quaternion conventions differ between our libraries (pybullet ``xyzw``, viser ``wxyz``); every
conversion lives here, named after its order, and nowhere else.
"""

from __future__ import annotations

import math

import numpy as np

ROTATION_ORTHONORMAL_TOL = 1e-6
"""Largest ``|RᵀR − I|`` entry accepted as a rotation read from a file or the wire."""

GIMBAL_LOCK_TOL = 1e-9
"""|cos(pitch)| below which roll and yaw are one rotation and :func:`R_to_rpy` sets roll to 0."""


def make_pose(R_AB: np.ndarray | None = None, p_AB: np.ndarray | None = None) -> np.ndarray:
    """The 4×4 pose ``X_AB`` from a rotation ``R_AB`` (3×3) and a translation ``p_AB`` (m)."""
    X = np.eye(4)
    if R_AB is not None:
        X[:3, :3] = R_AB
    if p_AB is not None:
        X[:3, 3] = p_AB
    return X


def invert_pose(X_AB: np.ndarray) -> np.ndarray:
    """``X_BA`` from ``X_AB`` using the rotation's transpose (exact for rigid transforms)."""
    R = X_AB[:3, :3]
    X = np.eye(4)
    X[:3, :3] = R.T
    X[:3, 3] = -R.T @ X_AB[:3, 3]
    return X


def rpy_to_R(rpy_rad: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed axes x, y, z) to a rotation matrix: ``Rz(y) Ry(p) Rx(r)``."""
    r, p, y = (float(a) for a in rpy_rad)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def R_to_rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw (rad) of a rotation matrix, the inverse of :func:`rpy_to_R`; at
    pitch ±π/2, where roll and yaw turn about one axis, roll is 0."""
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    if math.hypot(R[2, 1], R[2, 2]) < GIMBAL_LOCK_TOL:
        return np.array([0.0, pitch, math.atan2(-R[0, 1], R[1, 1])])
    return np.array([math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])])


def rotation_error(R: np.ndarray) -> float:
    """Largest entry of ``|RᵀR − I|`` plus ``|det R − 1|``: zero for an exact rotation."""
    return float(np.max(np.abs(R.T @ R - np.eye(3))) + abs(np.linalg.det(R) - 1.0))


def is_rigid_transform(X: np.ndarray, tol: float = ROTATION_ORTHONORMAL_TOL) -> bool:
    """True when X is a finite 4×4 homogeneous transform with a proper rotation."""
    X = np.asarray(X)
    return (
        X.shape == (4, 4)
        and bool(np.all(np.isfinite(X)))
        and np.array_equal(X[3], [0.0, 0.0, 0.0, 1.0])
        and rotation_error(X[:3, :3]) <= tol
    )


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to a unit quaternion ``(w, x, y, z)`` with ``w ≥ 0`` (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_wxyz_to_R(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` to a rotation matrix (normalised first)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64) / np.linalg.norm(q_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """pybullet's ``(x, y, z, w)`` to viser's ``(w, x, y, z)``."""
    x, y, z, w = q_xyzw
    return np.array([w, x, y, z], dtype=np.float64)


def quat_wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """viser's ``(w, x, y, z)`` to pybullet's ``(x, y, z, w)``."""
    w, x, y, z = q_wxyz
    return np.array([x, y, z, w], dtype=np.float64)


def look_at(
    p_WEye: np.ndarray, p_WTarget: np.ndarray, up_W: np.ndarray | None = None
) -> np.ndarray:
    """Camera pose ``X_WC`` (OpenCV: x right, y down, z forward) looking from eye to target."""
    up_W = np.array([0.0, 0.0, 1.0]) if up_W is None else np.asarray(up_W, dtype=np.float64)
    z = np.asarray(p_WTarget, dtype=np.float64) - np.asarray(p_WEye, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, up_W)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.column_stack([x, y, z]), p_WEye)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad), by Rodrigues' formula."""
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-8:  # second-order series: exact to rounding at this size
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + (math.sin(theta) / theta) * K + ((1 - math.cos(theta)) / theta**2) * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of rotation matrix ``R``, robust near 0 and π."""
    # The cosine as np.clip(np.trace …) computes it, without their per-call overhead.
    cos = min(max((float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0, -1.0), 1.0)
    theta = math.acos(cos)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return 0.5 * v
    if theta > math.pi - 1e-6:
        # Near π: the axis is the column of R + I with the largest norm.
        M = R + np.eye(3)
        axis = M[:, np.argmax(np.linalg.norm(M, axis=0))]
        axis /= np.linalg.norm(axis)
        return theta * axis
    return theta / (2.0 * math.sin(theta)) * v


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """One Newton step towards the nearest rotation: keeps ``RᵀR = I`` to rounding forever."""
    return R @ (1.5 * np.eye(3) - 0.5 * R.T @ R)
