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
from scipy.stats import f as f_distribution

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
    a residual ``r = n·(q − a)`` changes by ``dr = −(1 − s) n·da − s n·db``. For an end point
    ``P`` of the edge in C, ``n·d(uv) = g·dP`` with ``g = (∂uv/∂P)ᵀ n``, and the update moves
    ``P`` by ``ω × Q + v`` (``Q = R·p_O``), so ``n·d(uv) = (Q × g)·ω + g·v``. Written with
    elementwise arithmetic only: this runs ~10 times per fit, thousands of times a frame.
    """
    R, t = X_CO[:3, :3], X_CO[:3, 3]
    Q = edges_O @ R.T  # (n, 2, 3) rotated about O's origin
    P = Q + t
    z = P[..., 2]
    n_res = 2 * len(edges_O)
    if z.min() <= 1e-6:
        return np.full(n_res, 1e6), np.zeros((n_res, 6))
    fx, fy, skew = K[0, 0], K[1, 1], K[0, 1]
    iz = 1.0 / z
    x, y = P[..., 0] * iz, P[..., 1] * iz
    ux = fx * x + skew * y if skew else fx * x  # the skew's terms are 0 (the usual case)
    u_px = ux + K[0, 2]  # (n, 2)
    v_px = fy * y + K[1, 2]
    dx, dy = u_px[:, 1] - u_px[:, 0], v_px[:, 1] - v_px[:, 0]
    L = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12)
    ex, ey = dx / L, dy / L  # u, the edge's direction
    nx, ny = -ey, ex  # its normal
    # g = (∂uv/∂P)ᵀ n at both ends, (n, 2) per component
    gx = (fx * iz) * nx[:, None]
    gy = (fy * iz) * ny[:, None]
    if skew:
        gy = (skew * iz) * nx[:, None] + gy
    gz = -(ux * iz) * nx[:, None] - (fy * y * iz) * ny[:, None]
    Qx, Qy, Qz = Q[..., 0], Q[..., 1], Q[..., 2]
    Je = np.empty((len(edges_O), 2, 6))  # n·d(uv) per update parameter, at end a and b
    Je[..., 0] = Qy * gz - Qz * gy
    Je[..., 1] = Qz * gx - Qx * gz
    Je[..., 2] = Qx * gy - Qy * gx
    Je[..., 3], Je[..., 4], Je[..., 5] = gx, gy, gz
    wx = segs_px[:, 0::2] - u_px[:, :1]  # (n, 2): both image end points relative to a
    wy = segs_px[:, 1::2] - v_px[:, :1]
    r = (wx * nx[:, None] + wy * ny[:, None]).ravel()
    s = (wx * ex[:, None] + wy * ey[:, None]) / L[:, None]  # (n, 2)
    J = -(1 - s)[..., None] * Je[:, None, 0] - s[..., None] * Je[:, None, 1]
    return r, J.reshape(n_res, 6)


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
    w2 = None if weights is None else np.repeat(np.sqrt(np.asarray(weights, np.float64)), 2)
    n_lines = 2 * len(edges_O)

    def evaluate(X_CO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = residuals_and_jacobian(X_CO, edges_O, segs_px, K)
        if w2 is not None:
            r, J = r * w2, J * w2[:, None]
        if prior is None:
            return r, J
        r_p, J_p = prior(X_CO)
        return np.concatenate([r, r_p]), np.concatenate([J, J_p])

    r, J = evaluate(X)
    cost = float(r @ r)
    lam = 1e-4
    converged = False
    it = 0
    diag = np.diag_indices(6)
    for it in range(1, iterations + 1):  # noqa: B007 (the count is reported)
        JtJ = J.T @ J
        g = J.T @ r
        step_ok = False
        delta = np.zeros(6)
        small = True  # as long as no step is solved for
        for _ in range(6):
            A = JtJ.copy()  # JtJ + λ·(diag(JtJ) + 1e-12·I)
            d = JtJ[diag]
            A[diag] = d + lam * (d + 1e-12)
            try:
                delta = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            small = np.abs(delta).max() < tol
            if small:
                break  # at the minimum: a step this small cannot be worth evaluating
            X_new = apply_update(X, delta)
            r_new, J_new = evaluate(X_new)
            cost_new = float(r_new @ r_new)
            if cost_new <= cost:
                X, r, J, cost = X_new, r_new, J_new, cost_new
                lam = max(lam / 10, 1e-9)
                step_ok = True
                break
            lam *= 10
        if not step_ok or small:
            converged = True
            break
    raw = r[:n_lines] if w2 is None else r[:n_lines] / w2
    rms = float(np.sqrt(np.mean(raw**2))) if len(raw) else 0.0
    return PoseFit(X, rms, raw, it, converged)


def constraint_p_value(
    X_free_CO: np.ndarray,
    X_held_CO: np.ndarray,
    edges_O: np.ndarray,
    segs_px: np.ndarray,
    K: np.ndarray,
    prior: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    iterations: int,
    tol: float,
) -> float:
    """How likely the lines are if the pose meets ``prior``'s constraints (such as "rests on
    the table"): the p-value of the F-test of nested least-squares models. Both fits are
    refined on the same correspondences, free from ``X_free_CO`` and with the prior from
    ``X_held_CO``; with ``m`` line residuals and ``k`` prior residuals,
    ``((SSR_held − SSR_free) / k) / (SSR_free / (m − 6))`` follows F(k, m − 6) when the
    constraints hold, the free fit's residuals being the noise's measure. 1.0 when the lines
    leave no degree of freedom to measure it (fewer than 7 residuals)."""
    m = 2 * len(edges_O)
    if m <= 6:
        return 1.0
    free = fit_pose(X_free_CO, edges_O, segs_px, K, iterations=iterations, tol=tol)
    held = fit_pose(X_held_CO, edges_O, segs_px, K, iterations=iterations, tol=tol, prior=prior)
    k = len(prior(held.X_CO)[0])
    ssr_free = float(free.residuals_px @ free.residuals_px)
    ssr_held = float(held.residuals_px @ held.residuals_px)
    if ssr_free <= 0.0:
        return 0.0 if ssr_held > 0.0 else 1.0
    statistic = (max(ssr_held - ssr_free, 0.0) / k) / (ssr_free / (m - 6))
    return float(f_distribution.sf(statistic, k, m - 6))
