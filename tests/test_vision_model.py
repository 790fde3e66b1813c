"""Interpenetration depth of convex parts: the same with given facet normals as without."""

from __future__ import annotations

import numpy as np

from work_site.vision.model import convex_overlap_depth, hull_facets


def _box(lo, hi) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])], dtype=np.float64)  # fmt: skip


def test_overlap_depth_with_given_normals_matches_the_hull_computation() -> None:
    rng = np.random.default_rng(5)
    a = _box([0, 0, 0], [0.05, 0.05, 0.05])
    na = np.array([n for n, _ in hull_facets(a)])
    for _ in range(20):
        c, s = np.cos(rng.uniform(-np.pi, np.pi)), np.sin(rng.uniform(-np.pi, np.pi))
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        b = _box([0, 0, 0], [0.1, 0.05, 0.025]) @ R.T + rng.uniform(-0.08, 0.08, 3)
        nb = np.array([n for n, _ in hull_facets(b)])
        assert convex_overlap_depth(a, b, na, nb) == convex_overlap_depth(a, b)
    # Two cubes overlapping by 5 mm along x.
    b = a + np.array([0.045, 0.0, 0.0])
    assert abs(convex_overlap_depth(a, b, na, na) - 0.005) < 1e-12
    assert convex_overlap_depth(a, a + np.array([0.06, 0, 0]), na, na) == 0.0


def test_occlusion_by_several_parts_is_the_union_of_each_part() -> None:
    """All parts tested at once (stacked planes) equals testing them one by one."""
    from work_site.vision.model import occluded

    rng = np.random.default_rng(9)
    parts = []
    for _ in range(4):
        V = _box([0, 0, 0], rng.uniform(0.02, 0.08, 3)) + rng.uniform(
            [-0.1, -0.1, 0.3], [0.1, 0.1, 0.6]
        )
        parts.append(np.array([[*n, d] for n, d in hull_facets(V)]))
    points = rng.uniform([-0.2, -0.2, 0.2], [0.2, 0.2, 0.9], (2000, 3))
    each = [occluded(points, [P]) for P in parts]
    together = occluded(points, parts)
    np.testing.assert_array_equal(together, np.any(each, axis=0))
    assert 0 < together.sum() < len(points)  # the test exercises both outcomes
    assert not occluded(points, []).any()
