"""Exact polytope distance against an independent reference (the origin's distance to the
Minkowski difference's hull, :func:`reference_distance_m`), on every pair of the scene's parts
at random poses and gaps."""

from __future__ import annotations

import numpy as np
import pytest

from models.geometry import ConvexPart
from models.scene import load_scene
from models.transforms import so3_exp
from operator_site.simulator.polytope import (
    Polytope,
    PolytopeGroup,
    distances_over_faces,
    polytope_distance,
    posed_distances_and_faces,
    reference_distance_m,
)

ROUNDING_M = 1e-12
"""How far two float64 computations of one distance between parts within a metre of the origin
may differ (thousands of ulps of their coordinates)."""


def _pairs() -> list[tuple[str, ConvexPart, str, ConvexPart]]:
    scene = load_scene()
    parts = [(o.name, p) for o in scene.objects for p in o.model.parts]
    return [(na, a, nb, b) for na, a in parts for nb, b in parts if na != "frame"]


SPREADS_RAD = (0.0, 1e-9, 1e-6, 1e-3, 0.3, 3.0)
"""How far a random rotation strays from a face-aligned one: not at all to anywhere."""


def _placed(
    rng: np.random.Generator, part: ConvexPart, spreads: tuple[float, ...] = SPREADS_RAD
) -> tuple[np.ndarray, np.ndarray]:
    """A random rotation, near a face-aligned one (within one of ``spreads``), and a centre
    near the origin."""
    spread = rng.choice(spreads)
    axes = [np.eye(3), so3_exp(np.array([0.0, 0.0, np.pi / 2]))][rng.integers(2)]
    R = axes @ so3_exp(rng.normal(size=3) * spread)
    return R, rng.normal(size=3) * 0.02 - R @ part.vertices_O.mean(axis=0)


def _case(
    rng: np.random.Generator,
    a: ConvexPart,
    b: ConvexPart,
    gap_m: float,
    spreads: tuple[float, ...] = SPREADS_RAD,
):
    """A and B posed so that their distance is ``gap_m`` (B moved along the reference's nearest
    direction: a translation along it changes the distance by exactly its length)."""
    RA, tA = _placed(rng, a, spreads)
    RB, tB = _placed(rng, b, spreads)
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


@pytest.mark.parametrize("seed", range(2))
def test_the_last_query_s_faces_give_the_exact_distance_or_decline(seed: int) -> None:
    """A line search's next pose is near its last: the faces that held the nearest pairs there
    answer the exact distance (the reference's) or decline, never a wrong one; for a block
    just above the table among the scene's other objects, the simulator's common case, they
    mostly answer."""
    rng = np.random.default_rng(100 + seed)
    scene = load_scene()
    answered = tried = 0
    for _ in range(20):
        moving = scene.objects[rng.integers(2, len(scene.objects))]  # not the table or frame
        others = [
            Polytope.of(p).moved(o.X_WO[:3, :3], o.X_WO[:3, 3])
            for o in scene.objects
            if o.name != moving.name
            for p in o.model.parts
        ]
        table_top_m = float(others[0].vertices[:, 2].max())
        R0 = so3_exp(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])) @ so3_exp(
            rng.normal(size=3) * rng.choice([0.0, 1e-6, 1e-3])
        )
        p0 = np.array([*rng.uniform([0.1, -0.2], [0.6, 0.3]), 0.0])
        for part in moving.model.parts:
            A_O = Polytope.of(part)
            p0[2] = table_top_m - float((A_O.vertices @ R0.T)[:, 2].min())
            p0[2] += 10 ** rng.uniform(-7, -4)
            # The simulator's broad phase: the obstacles within a centimetre's box.
            V0 = A_O.vertices @ R0.T + p0
            near = tuple(
                o
                for o in others
                if np.all(o.vertices.min(axis=0) <= V0.max(axis=0) + 0.01)
                and np.all(o.vertices.max(axis=0) >= V0.min(axis=0) - 0.01)
            )
            group = PolytopeGroup.of(near)
            pairs, faces = posed_distances_and_faces(A_O, R0, p0, group)
            if min(d for d, _, _ in pairs) <= 0.0:
                continue  # dropped into another block: no pose a simulator would reach
            for _ in range(5):
                step = 10 ** rng.uniform(-9, -5)
                R = so3_exp(rng.normal(size=3) * step / 0.05) @ R0
                p = p0 + rng.normal(size=3) * step
                V = A_O.vertices @ R.T + p
                refs = [reference_distance_m(V, member.vertices) for member in near]
                d = distances_over_faces(A_O, R, p, group, faces)
                tried += min(refs) > 0.0
                if d is None:
                    continue
                answered += 1
                for got, ref in zip(d, refs, strict=True):
                    assert abs(got - ref) <= ROUNDING_M, (moving.name, got, ref, step)
    assert answered >= 0.5 * tried, (answered, tried)


def test_a_part_s_features_are_found_once_and_cannot_be_changed() -> None:
    """Every simulator world is built from the same parts: their features are found once,
    read-only, and the part's own arrays stay writable."""
    part = load_scene().object("cube").model.parts[0]
    first, again = Polytope.of(part), Polytope.of(part)
    assert first is again
    fresh = Polytope._features(part)
    for name in ("vertices", "edges", "normals", "planes", "face_sides", "face_side_offsets"):
        np.testing.assert_array_equal(getattr(first, name), getattr(fresh, name))
        with pytest.raises(ValueError, match="read-only"):
            getattr(first, name)[...] = 0
    assert part.vertices_O.flags.writeable
