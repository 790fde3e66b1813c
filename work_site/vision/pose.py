"""Lowe's iterative least-squares pose fit of projected model edges to image lines (§IV-A).

The unknown is the object's pose in the camera, ``X_CO``. Each correspondence pairs a model
edge (two points in O) with an image segment (two end points, px); its two residuals are the
perpendicular distances (px) of the image segment's end points from the projected model edge's
line. Measuring from the image end points means an image segment that covers only part of an
edge (occlusion, a missed corner) still fits exactly.

The update rotates about the object's own origin (``R ← exp(ω)·R``, ``t ← t + v``, both in C),
which keeps rotation and translation far better separated than rotating about the camera.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.transforms import so3_exp
from work_site.vision.model import project, transform


@dataclass(frozen=True)
class PoseFit:
    """Result of a fit: pose, RMS residual (px), residuals (2n,), iterations, converged."""

    X_CO: np.ndarray
    rms_px: float
    residuals_px: np.ndarray
    iterations: int
    converged: bool


def apply_update(X_CO: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``X_CO`` moved by ``delta = (ω (3), v (3))``: rotation about O's origin, then shift."""
    X = X_CO.copy()
    X[:3, :3] = so3_exp(delta[:3]) @ X_CO[:3, :3]
    X[:3, 3] = X_CO[:3, 3] + delta[3:]
    return X


def line_residuals(
    X_CO: np.ndarray, edges_O: np.ndarray, segs_px: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """Signed distances (px) of image segment end points from projected model edge lines.

    ``edges_O``: (n, 2, 3) m; ``segs_px``: (n, 4). Returns (2n,): both end points of segment 0,
    then of segment 1, … Points behind the camera give a large residual instead of NaN.
    """
    p_C = transform(X_CO, edges_O)
    z = p_C[..., 2]
    if np.any(z <= 1e-6):
        return np.full(2 * len(edges_O), 1e6)
    uv = project(p_C, K)
    a, b = uv[:, 0], uv[:, 1]
    d = b - a
    L = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    n = np.column_stack([-d[:, 1], d[:, 0]]) / L[:, None]
    r0 = np.sum((segs_px[:, :2] - a) * n, axis=1)
    r1 = np.sum((segs_px[:, 2:] - a) * n, axis=1)
    return np.column_stack([r0, r1]).ravel()


def residuals_and_jacobian(
    X_CO: np.ndarray, edges_O: np.ndarray, segs_px: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`line_residuals` and their analytic Jacobian (2n, 6) for :func:`apply_update`.

    With ``d = b − a`` the projected edge, ``u = d/|d|``, ``n ⟂ u`` and ``s = u·(q − a)/|d|``,
    a residual ``r = n·(q − a)`` changes by ``dr = −(1 − s) n·da − s n·db``.
    """
    R, t = X_CO[:3, :3], X_CO[:3, 3]
    Q = edges_O @ R.T  # (n, 2, 3) rotated about O's origin
    P = Q + t
    z = P[..., 2]
    if np.any(z <= 1e-6):
        return np.full(2 * len(edges_O), 1e6), np.zeros((2 * len(edges_O), 6))
    fx, fy = K[0, 0], K[1, 1]
    x, y = P[..., 0] / z, P[..., 1] / z
    uv = np.stack([fx * x + K[0, 1] * y + K[0, 2], fy * y + K[1, 2]], axis=-1)
    # d(uv)/dP, (n, 2, 2, 3)
    Jp = np.zeros((*P.shape[:2], 2, 3))
    Jp[..., 0, 0] = fx / z
    Jp[..., 0, 1] = K[0, 1] / z
    Jp[..., 0, 2] = -(fx * x + K[0, 1] * y) / z
    Jp[..., 1, 1] = fy / z
    Jp[..., 1, 2] = -fy * y / z
    # dP/dθ = [−[Q]×, I]: rotation about O's origin, then translation.
    Jq = np.zeros((*P.shape[:2], 3, 6))
    Jq[..., 0, 1], Jq[..., 0, 2] = Q[..., 2], -Q[..., 1]
    Jq[..., 1, 0], Jq[..., 1, 2] = -Q[..., 2], Q[..., 0]
    Jq[..., 2, 0], Jq[..., 2, 1] = Q[..., 1], -Q[..., 0]
    Jq[..., 0, 3] = Jq[..., 1, 4] = Jq[..., 2, 5] = 1.0
    Juv = Jp @ Jq  # (n, 2 ends, 2, 6)
    a, b = uv[:, 0], uv[:, 1]
    d = b - a
    L = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    u = d / L[:, None]
    nrm = np.column_stack([-u[:, 1], u[:, 0]])
    na = np.einsum("nk,nkj->nj", nrm, Juv[:, 0])
    nb = np.einsum("nk,nkj->nj", nrm, Juv[:, 1])
    r = np.empty(2 * len(edges_O))
    J = np.empty((2 * len(edges_O), 6))
    for k, q in enumerate((segs_px[:, :2], segs_px[:, 2:])):
        w = q - a
        r[k::2] = np.sum(w * nrm, axis=1)
        s = np.sum(w * u, axis=1) / L
        J[k::2] = -(1 - s)[:, None] * na - s[:, None] * nb
    return r, J


def fit_pose(
    X_CO_init: np.ndarray,
    edges_O: np.ndarray,
    segs_px: np.ndarray,
    K: np.ndarray,
    iterations: int = 20,
    tol: float = 1e-10,
    weights: np.ndarray | None = None,
    prior: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> PoseFit:
    """Levenberg–Marquardt on the 6 pose parameters (Gauss–Newton near the solution).

    ``weights``: optional (n,) per correspondence (applied to both of its residuals).
    ``prior``: optional extra residuals of the pose and their Jacobian (k,), (k, 6) for
    :func:`apply_update` (weighted, in px-equivalents), e.g. "rests on the table".
    ``rms_px`` covers the lines only.
    Stops when the step is below ``tol`` (rad and m) or after ``iterations``.
    """
    X = np.asarray(X_CO_init, dtype=np.float64).copy()
    w = np.ones(len(edges_O)) if weights is None else np.asarray(weights, dtype=np.float64)
    w2 = np.repeat(np.sqrt(w), 2)
    n_lines = 2 * len(edges_O)

    def evaluate(X_CO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = residuals_and_jacobian(X_CO, edges_O, segs_px, K)
        r, J = r * w2, J * w2[:, None]
        if prior is None:
            return r, J
        r_p, J_p = prior(X_CO)
        return np.concatenate([r, r_p]), np.vstack([J, J_p])

    r, J = evaluate(X)
    cost = float(r @ r)
    lam = 1e-4
    converged = False
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (the count is reported)
        JtJ = J.T @ J
        g = J.T @ r
        step_ok = False
        delta = np.zeros(6)
        for _ in range(6):
            A = JtJ + lam * (np.diag(np.diag(JtJ)) + 1e-12 * np.eye(6))
            try:
                delta = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            X_new = apply_update(X, delta)
            r_new, J_new = evaluate(X_new)
            cost_new = float(r_new @ r_new)
            if cost_new <= cost:
                X, r, J, cost = X_new, r_new, J_new, cost_new
                lam = max(lam / 10, 1e-9)
                step_ok = True
                break
            lam *= 10
        if not step_ok or np.max(np.abs(delta)) < tol:
            converged = True
            break
    raw = r[:n_lines] / w2
    rms = float(np.sqrt(np.mean(raw**2))) if len(raw) else 0.0
    return PoseFit(X, rms, raw, it, converged)
