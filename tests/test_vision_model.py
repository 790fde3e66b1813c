"""Interpenetration depth of convex parts: the same with given facet normals as without."""

from __future__ import annotations

import numpy as np

from work_site.vision.model import convex_overlap_depth, hull_facets, overlap_exceeds


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


def test_overlap_exceeds_decides_as_the_full_depth() -> None:
    """The facet-normal shortcut gives the full test's answer, tilted boxes included (whose
    separating axis may be an edge cross product), over and under the limit."""
    rng = np.random.default_rng(11)
    a = _box([0, 0, 0], [0.05, 0.05, 0.05])
    na = np.array([n for n, _ in hull_facets(a)])
    depths = []
    for _ in range(300):
        w = rng.normal(size=3)
        w *= rng.uniform(0, np.pi) / np.linalg.norm(w)
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        t = np.linalg.norm(w)
        R = np.eye(3) + np.sin(t) / t * K + (1 - np.cos(t)) / t**2 * K @ K
        b = _box([0, 0, 0], [0.1, 0.05, 0.025]) @ R.T + rng.uniform(-0.1, 0.1, 3)
        nb = np.array([n for n, _ in hull_facets(b)])
        depth = convex_overlap_depth(a, b, na, nb)
        depths.append(depth)
        for limit in (0.0, 0.002, 0.01):
            assert overlap_exceeds(a, b, na, nb, limit) == (depth > limit)
    assert min(depths) == 0.0 and max(depths) > 0.01  # both answers were asked for


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


def test_occluders_set_aside_only_parts_that_hide_nothing() -> None:
    """Visible edges with the culled occluders equal those with every part, over random
    poses of a block among boxes, some of which hide part of it (and some reach behind the
    camera, so their images are unknown)."""
    from models.scene import load_scene
    from models.transforms import make_pose, so3_exp
    from work_site.vision.model import (
        Occluders,
        planes_in,
        transform,
        visible_edges,
        vision_model,
    )

    scene = load_scene()
    model = vision_model(next(o.model for o in scene.movable if o.name == "l_block"))
    K = np.array([[580.0, 0.0, 320.0], [0.0, 580.0, 240.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    culled = hidden = 0
    for trial in range(60):
        verts, planes = [], []
        for _ in range(6):
            V = _box([0, 0, 0], rng.uniform(0.01, 0.06, 3))
            lo = [-0.15, -0.15, -0.2 if trial % 3 == 0 else 0.2]
            X = make_pose(so3_exp(rng.normal(size=3)), rng.uniform(lo, [0.15, 0.15, 0.7]))
            verts.append(V @ X[:3, :3].T + X[:3, 3])
            planes.append(planes_in(X, np.array([[*n, d] for n, d in hull_facets(V)])))
        occ = Occluders.of_parts(verts, planes, K)
        t = rng.uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.8])
        X_CO = make_pose(so3_exp(rng.normal(size=3)), t)
        ref = visible_edges(model, X_CO, K, planes)
        got = visible_edges(model, X_CO, K, occ)
        for a, b in zip(ref, got, strict=True):
            np.testing.assert_array_equal(a, b)
        culled += len(planes) - len(occ.relevant(transform(X_CO, model.edges_O).reshape(-1, 3), K))
        hidden += not np.array_equal(ref[2], visible_edges(model, X_CO, K)[2])
    assert culled > 0 and hidden > 0  # the test exercises culling and occlusion


def test_a_convex_model_hides_its_edges_as_ray_casting_does() -> None:
    """Self-occlusion of a one-part model from its faces' orientation gives the edges, end
    points and fractions that ray casting against the part gives (the part listed twice makes
    the model take the ray-casting path), with and without other parts in front."""
    import dataclasses

    from models.scene import load_scene
    from models.transforms import make_pose, so3_exp
    from work_site.vision.model import planes_in, visible_edges, vision_model

    scene = load_scene()
    K = np.array([[580.0, 0.0, 320.0], [0.0, 580.0, 240.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(11)
    for obj in scene.movable:
        model = vision_model(obj.model)
        if len(model.planes_O) != 1:
            continue
        cast = dataclasses.replace(model, planes_O=model.planes_O * 2)
        for trial in range(30):
            X_CO = make_pose(
                so3_exp(rng.normal(size=3)), rng.uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.8])
            )
            others = []
            if trial % 2:
                V = _box([0, 0, 0], [0.03, 0.03, 0.03])
                X = make_pose(so3_exp(rng.normal(size=3)), X_CO[:3, 3] * rng.uniform(0.6, 0.9))
                others.append(planes_in(X, np.array([[*n, d] for n, d in hull_facets(V)])))
            fast = visible_edges(model, X_CO, K, others)
            ref = visible_edges(cast, X_CO, K, others)
            np.testing.assert_array_equal(fast[0], ref[0])
            np.testing.assert_allclose(fast[1], ref[1], atol=1e-9)
            np.testing.assert_allclose(fast[2], ref[2], atol=1e-12)
