"""Exact polytope distance against an independent reference: the origin's distance to the
Minkowski difference's hull (Qhull), on every pair of the scene's parts at random poses and gaps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from models.geometry import ConvexPart
from models.scene import load_scene
from models.transforms import so3_exp
from operator_site.simulator.polytope import Polytope, polytope_distance

ROUNDING_M = 1e-12
"""How far two float64 computations of one distance between parts within a metre of the origin
may differ (thousands of ulps of their coordinates)."""


def _point_triangle_m(T: np.ndarray) -> float:
    """Distance from the origin to triangle T (3, 3)."""
    a, b, c = T
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    p = (a @ n) * n  # the origin projected onto the triangle's plane
    inside = all(np.cross(v1 - v0, p - v0) @ n >= 0.0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return abs(float(a @ n))
    best = np.inf
    for v0, v1 in ((a, b), (b, c), (c, a)):
        d = v1 - v0
        s = np.clip(-(v0 @ d) / (d @ d), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(v0 + s * d)))
    return best


def reference_distance_m(V_A: np.ndarray, V_B: np.ndarray) -> float:
    """Signed distance between the hulls of V_A and V_B: from the origin to the hull of
    {a − b}, outside by its nearest triangle, inside by minus its nearest facet plane."""
    M = (V_A[:, None, :] - V_B[None, :, :]).reshape(-1, 3)
    hull = ConvexHull(M)
    planes = hull.equations  # n·x + c ≤ 0 inside, n outward
    if np.all(planes[:, 3] < 0.0):
        return float(np.max(planes[:, 3]))
    return min(_point_triangle_m(M[s]) for s in hull.simplices)


def _pairs() -> list[tuple[str, ConvexPart, str, ConvexPart]]:
    scene = load_scene()
    parts = [(o.name, p) for o in scene.objects for p in o.model.parts]
    return [(na, a, nb, b) for na, a in parts for nb, b in parts if na != "frame"]


def _placed(rng: np.random.Generator, part: ConvexPart) -> tuple[np.ndarray, np.ndarray]:
    """A random rotation, near a face-aligned one or anywhere, and a centre near the origin."""
    spread = rng.choice([0.0, 1e-9, 1e-6, 1e-3, 0.3, 3.0])
    axes = [np.eye(3), so3_exp(np.array([0.0, 0.0, np.pi / 2]))][rng.integers(2)]
    R = axes @ so3_exp(rng.normal(size=3) * spread)
    return R, rng.normal(size=3) * 0.02 - R @ part.vertices_O.mean(axis=0)


def _case(rng: np.random.Generator, a: ConvexPart, b: ConvexPart, gap_m: float):
    """A and B posed so that their distance is ``gap_m`` (B moved along the reference's nearest
    direction: a translation along it changes the distance by exactly its length)."""
    RA, tA = _placed(rng, a)
    RB, tB = _placed(rng, b)
    A, B = Polytope.of(a).moved(RA, tA), Polytope.of(b).moved(RB, tB)
    d0 = reference_distance_m(A.vertices, B.vertices)
    if d0 <= 0.0:  # overlapping: move B off along the line between centres by both diameters
        u = B.vertices.mean(axis=0) - A.vertices.mean(axis=0)
        span = np.ptp(A.vertices, axis=0) + np.ptp(B.vertices, axis=0)
        tB = tB + u / np.linalg.norm(u) * float(np.linalg.norm(span))
        B = Polytope.of(b).moved(RB, tB)
        d0 = reference_distance_m(A.vertices, B.vertices)
    _, pA, pB = polytope_distance(A, B)
    n = (pB - pA) / np.linalg.norm(pB - pA)
    return A, Polytope.of(b).moved(RB, tB - (d0 - gap_m) * n), n


@pytest.mark.parametrize("seed", range(4))
def test_distance_matches_the_minkowski_reference_to_rounding(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pairs = _pairs()
    for _ in range(60):
        na, a, nb, b = pairs[rng.integers(len(pairs))]
        gap = 10 ** rng.uniform(-9, -2)
        A, B, _ = _case(rng, a, b, gap)
        ref = reference_distance_m(A.vertices, B.vertices)
        d, pA, pB = polytope_distance(A, B)
        where = f"{na} to {nb}, gap {gap:.3g} m: exact {d!r}, reference {ref!r}"
        assert abs(d - ref) <= ROUNDING_M, where
        assert abs(ref - gap) <= ROUNDING_M, where
        # The nearest points lie on the bodies' surfaces and are d apart.
        assert abs(np.linalg.norm(pB - pA) - d) <= ROUNDING_M, where
        assert np.max(pA @ A.normals.T - A.offsets) == pytest.approx(0.0, abs=ROUNDING_M), where
        assert np.max(pB @ B.normals.T - B.offsets) == pytest.approx(0.0, abs=ROUNDING_M), where


def test_overlap_gives_the_exact_penetration_depth() -> None:
    rng = np.random.default_rng(11)
    pairs = _pairs()
    for _ in range(60):
        na, a, nb, b = pairs[rng.integers(len(pairs))]
        depth = 10 ** rng.uniform(-9, -3)
        A, B, n = _case(rng, a, b, 0.0)
        B = B.moved(np.eye(3), -depth * n)
        d, pA, pB = polytope_distance(A, B)
        ref = reference_distance_m(A.vertices, B.vertices)
        assert d < 0.0 and abs(d - ref) <= ROUNDING_M, f"{na} into {nb}: {d!r} vs {ref!r}"
        # Moving A by the depth along its escape separates the bodies (to rounding).
        assert polytope_distance(A.moved(np.eye(3), pB - pA), B)[0] >= -ROUNDING_M
