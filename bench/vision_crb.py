"""The physical limit of one view: the Cramér–Rao bound of an object's pose from its visible
edges, at a camera's noise, blur and the edges' contrast.

Model: every pixel of length along a visible edge measures the edge's position across it, with
independent Gaussian noise. For a blurred step edge of contrast ``h`` (grey levels) under white
noise ``σ_n`` the bound on that position, per pixel of length, is
``σ⊥² = σ_n² · 2√π σ_b / h²`` (the Fisher information of the edge's offset in the profile
``h·Φ(x/σ_b)`` is ``h² ∫ φ(x/σ_b)²/σ_b² dx = h² / (2√π σ_b)``), ``σ_b`` the total blur: the
lens's and a pixel's width (variance 1/12). The pose's Fisher information sums, over those
pixels, the squared derivative of the edge's projected position across it by the six pose
parameters; its inverse bounds the covariance of any unbiased estimate. The bound is reported
in the benchmark's own terms: the median error across the ray, along it and in rotation that
a Gaussian of that covariance gives (``median_errors``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from work_site.vision.model import VisionModel, occluded, planes_in, project, transform

PIXEL_BLUR_VAR_PX2 = 1.0 / 12.0
"""A pixel integrates light over its width: a box of 1 px, variance 1/12 px²."""
CONTRAST_OFFSET_PX = 2.5
"""An edge's contrast is read this far to either side of it, past the blur of the edge itself."""
MEDIAN_SAMPLES = 4000
"""Draws from the bound's Gaussian for its median errors (their median to about 2 %)."""


@dataclass(frozen=True)
class PoseBound:
    """The bound's covariance (6, 6) of the pose update ``(ω, v)`` in C (rad, m), as
    :func:`work_site.vision.pose.apply_update` moves a pose: rotation about O's origin, then a
    shift; and how many edge pixels carried it."""

    covariance: np.ndarray
    edge_px: float

    def median_errors(self, X_CO: np.ndarray, rng: np.random.Generator) -> tuple[float, ...]:
        """Median position error across the ray and along it (m) and rotation (rad) of
        estimates drawn from the bound, the ray through O's origin."""
        draws = rng.multivariate_normal(np.zeros(6), self.covariance, MEDIAN_SAMPLES)
        ray = X_CO[:3, 3] / np.linalg.norm(X_CO[:3, 3])
        v = draws[:, 3:]
        along = v @ ray
        across = np.linalg.norm(v - along[:, None] * ray, axis=1)
        turn = np.linalg.norm(draws[:, :3], axis=1)
        return float(np.median(across)), float(np.median(np.abs(along))), float(np.median(turn))


def edge_sigma_px(contrast_grey: np.ndarray, noise_grey: float, blur_sigma_px: float) -> np.ndarray:
    """σ⊥ (px) of an edge's position, per pixel of its length: see the module's formula."""
    sigma_b = math.sqrt(blur_sigma_px**2 + PIXEL_BLUR_VAR_PX2)
    h = np.maximum(np.abs(contrast_grey), 1e-9)
    return noise_grey * np.sqrt(2 * math.sqrt(math.pi) * sigma_b) / h


def visible_edge_points(
    model: VisionModel, X_CO: np.ndarray, K: np.ndarray, occluders_C: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) in O along the model's edges about a pixel apart in the image, those the
    camera sees (not behind the model's own faces nor ``occluders_C``), and each one's edge."""
    pts, which = [], []
    for e, (a, b) in enumerate(model.edges_O):
        ab_px = project(transform(X_CO, np.array([a, b])), K)
        n = max(2, math.ceil(float(np.linalg.norm(ab_px[1] - ab_px[0]))))
        t = (np.arange(n) + 0.5) / n
        pts.append(a + t[:, None] * (b - a))
        which.append(np.full(n, e))
    P_O, edge = np.vstack(pts), np.concatenate(which)
    P_C = transform(X_CO, P_O)
    own = [planes_in(X_CO, P) for P in model.planes_O]
    seen = (P_C[:, 2] > 1e-3) & ~occluded(P_C, own + list(occluders_C))
    return P_O[seen], edge[seen]


def pose_bound(
    model: VisionModel,
    X_CO: np.ndarray,
    K: np.ndarray,
    points_O: np.ndarray,
    edge: np.ndarray,
    sigma_px: np.ndarray,
) -> PoseBound | None:
    """The bound from edge points ``points_O`` (n, 3) of edges ``edge`` (n,) with position
    noise ``sigma_px`` (n,) across the projected edge; None if they do not fix all six
    parameters."""
    if len(points_O) < 6:
        return None
    R, t = X_CO[:3, :3], X_CO[:3, 3]
    Q = points_O @ R.T  # the points turned into C, about O's origin
    p = Q + t
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    # d(u, v)/dp at each point (2, 3), the pinhole with skew
    du = np.stack([fx / z, s / z, -(fx * x + s * y) / z**2], axis=1)
    dv = np.stack([np.zeros_like(z), fy / z, -fy * y / z**2], axis=1)
    # The unit normal of each point's projected edge in the image
    ends = project(transform(X_CO, model.edges_O[edge]), K)  # (n, 2, 2)
    d = ends[:, 1] - ends[:, 0]
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1, keepdims=True)
    g = nrm[:, :1] * du + nrm[:, 1:] * dv  # d(offset across)/dp (n, 3)
    # dp = ω × Q + v: d/dω = g · [−Q]× = Q × g, d/dv = g
    J = np.hstack([np.cross(Q, g), g]) / np.asarray(sigma_px)[:, None]
    info = J.T @ J
    if np.linalg.cond(info) > 1e12:
        return None
    return PoseBound(np.linalg.inv(info), float(len(points_O)))


def contrast_along(
    image: np.ndarray, points_px: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Grey-level difference across an edge at each point (n, 2), and the mean of the two
    sides, read ``CONTRAST_OFFSET_PX`` to either side along the unit normals (n, 2),
    bilinearly."""
    import cv2

    img = image.astype(np.float32)
    a = (points_px + CONTRAST_OFFSET_PX * normals).astype(np.float32)
    b = (points_px - CONTRAST_OFFSET_PX * normals).astype(np.float32)
    ia = cv2.remap(img, a[:, :1], a[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ib = cv2.remap(img, b[:, :1], b[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ia, ib = ia.ravel().astype(np.float64), ib.ravel().astype(np.float64)
    return ia - ib, 0.5 * (ia + ib)


def scene_bound(
    model: VisionModel,
    X_CO: np.ndarray,
    K: np.ndarray,
    occluders_C: list[np.ndarray],
    image_undistorted: np.ndarray,
    noise_grey: Callable[[float], float],
    blur_sigma_px: float,
) -> PoseBound | None:
    """The bound for one object in one image (undistorted, with ``K``): its visible edge
    points, each edge's contrast and grey level read from the image (medians along it), the
    camera's noise at that level (``noise_grey``) and its blur."""
    P_O, edge = visible_edge_points(model, X_CO, K, occluders_C)
    if len(P_O) < 6:
        return None
    uv = project(transform(X_CO, P_O), K)
    ends = project(transform(X_CO, model.edges_O[edge]), K)
    d = ends[:, 1] - ends[:, 0]
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1, keepdims=True)
    c, level = contrast_along(image_undistorted, uv, nrm)
    sigma = np.zeros(len(c))
    for e in np.unique(edge):
        on = edge == e
        h = np.median(np.abs(c[on]))
        sigma[on] = edge_sigma_px(np.array([h]), noise_grey(float(np.median(level[on]))),
                                  blur_sigma_px)[0]  # fmt: skip
    return pose_bound(model, X_CO, K, P_O, edge, sigma)
