"""Exact polytope distance against an independent reference (the origin's distance to the
Minkowski difference's hull, :func:`reference_distance_m`), on every pair of the scene's parts
at random poses and gaps."""

from __future__ import annotations

import numpy as np
import pytest

from models.geometry import ConvexPart
from models.scene import load_scene
from models.transforms import so3_exp
from operator_site.simulator.polytope import Polytope, polytope_distance, reference_distance_m

ROUNDING_M = 1e-12
"""How far two float64 computations of one distance between parts within a metre of the origin
may differ (thousands of ulps of their coordinates)."""


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
