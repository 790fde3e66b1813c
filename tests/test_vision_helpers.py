"""The recogniser's vectorised helpers against plain reference implementations."""

from __future__ import annotations

import cv2
import numpy as np

from models.scene import load_scene
from models.transforms import make_pose, so3_exp
from work_site.vision.model import vision_model
from work_site.vision.pose_sets import PoseSet
from work_site.vision.verification import (
    _clip_segments,
    _covered_length,
    _distance_to_polygon,
    _outside_convex,
)


def _union_reference(intervals: list[tuple[float, float]]) -> float:
    total, cur = 0.0, None
    for lo, hi in sorted(intervals):
        if cur is None or lo > cur[1]:
            total += 0.0 if cur is None else cur[1] - cur[0]
            cur = [lo, hi]
        else:
            cur[1] = max(cur[1], hi)
    return total + (0.0 if cur is None else cur[1] - cur[0])


def test_covered_length_is_the_union_per_edge() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        L = rng.uniform(5.0, 80.0, rng.integers(1, 6))
        m = int(rng.integers(1, 15))
        edge = rng.integers(0, len(L), m)
        a, b = rng.uniform(0, 1, (2, m)) * L[edge]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        expected = sum(
            _union_reference([(x, y) for x, y, k in zip(lo, hi, edge, strict=True) if k == e])
            for e in range(len(L))
        )
        assert abs(_covered_length(edge, lo, hi, L) - expected) < 1e-9


def _clip_reference(seg, w, h):
    x0, y0, x1, y1 = seg
    dx, dy = x1 - x0, y1 - y0
    t0, t1 = 0.0, 1.0
    for pp, qq in ((-dx, x0), (dx, w - 1 - x0), (-dy, y0), (dy, h - 1 - y0)):
        if pp == 0:
            if qq < 0:
                t0, t1 = 1.0, 0.0
            continue
        r = qq / pp
        t0, t1 = (max(t0, r), t1) if pp < 0 else (t0, min(t1, r))
    if t0 >= t1:
        return [x0, y0, x0, y0]
    return [x0 + t0 * dx, y0 + t0 * dy, x0 + t1 * dx, y0 + t1 * dy]


def test_clip_segments_matches_liang_barsky_one_by_one() -> None:
    rng = np.random.default_rng(2)
    segs = rng.uniform(-100, 740, (400, 4))
    segs[:40, 2] = segs[:40, 0]  # vertical, some outside
    segs[40:80, 3] = segs[40:80, 1]  # horizontal
    clipped = _clip_segments(segs, 640, 480)
    expected = np.array([_clip_reference(s, 640, 480) for s in segs])
    np.testing.assert_allclose(clipped, expected, atol=1e-9)
    inside = np.linalg.norm(clipped[:, 2:] - clipped[:, :2], axis=1) > 0
    assert 0 < inside.sum() < len(segs)
    assert np.all(clipped[inside][:, [0, 2]] >= -1e-9) and np.all(
        clipped[inside][:, [0, 2]] <= 639 + 1e-9
    )
    within = rng.uniform(0, 479, (50, 4))  # all inside: returned as they are
    expected = np.array([_clip_reference(s, 640, 480) for s in within])
    np.testing.assert_allclose(_clip_segments(within, 640, 480), expected, atol=1e-9)
    assert _clip_segments(np.zeros((0, 4)), 640, 480).shape == (0, 4)


def test_distance_to_polygon_matches_opencv() -> None:
    rng = np.random.default_rng(3)
    hull = cv2.convexHull(rng.uniform(100, 300, (12, 2)).astype(np.float32))
    poly = hull.reshape(-1, 2).astype(np.float64)
    P = rng.uniform(50, 350, (500, 2)).astype(np.float32)
    expected = [abs(cv2.pointPolygonTest(hull, (float(x), float(y)), True)) for x, y in P]
    np.testing.assert_allclose(
        _distance_to_polygon(P.astype(np.float64), poly), expected, atol=1e-3
    )


def test_outside_convex_is_beyond_some_edge_line_by_the_margin() -> None:
    rng = np.random.default_rng(4)
    hull = cv2.convexHull(rng.uniform(100, 300, (12, 2)).astype(np.float32))
    poly = hull.reshape(-1, 2).astype(np.float64)
    P = rng.uniform(50, 350, (500, 2))
    expected = []
    for p in P:  # the farthest any edge's line has the point on its outer side
        beyond = -np.inf
        for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            d = b - a
            side = (d[0] * (p - a)[1] - d[1] * (p - a)[0]) / np.linalg.norm(d)
            inner = (d[0] * (poly.mean(0) - a)[1] - d[1] * (poly.mean(0) - a)[0]) > 0
            beyond = max(beyond, -side if inner else side)
        expected.append(beyond > 1.5)
    for polygon in (poly, poly[::-1]):
        np.testing.assert_array_equal(_outside_convex(P, polygon, 1.5), expected)
    inside = [cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in P]
    assert not _outside_convex(P, poly, 1.5)[inside].any()


def test_pose_set_sees_poses_equal_up_to_symmetry_only() -> None:
    models = {o.name: vision_model(o.model) for o in load_scene().movable}
    cube, wedge = models["cube"], models["wedge"]
    rng = np.random.default_rng(4)
    tested = PoseSet(same_pose_m=0.004, same_pose_rad=np.deg2rad(4.0))
    X = make_pose(so3_exp(rng.normal(0, 1, 3)), [0.1, 0.0, 0.8])
    assert not tested.seen(cube, X)
    for _ in range(40):  # enough to make the arrays grow
        tested.add(wedge, make_pose(so3_exp(rng.normal(0, 1, 3)), rng.uniform(-0.2, 0.2, 3)))
    tested.add(cube, X)
    # The same cube turned by one of its symmetries, nudged within the tolerances.
    S = cube.symmetries[5]
    near = make_pose(
        X[:3, :3] @ S.T @ so3_exp([0.0, 0.0, np.deg2rad(3.0)]), X[:3, 3] + [0.002, 0.002, 0.0]
    )
    assert tested.seen(cube, near)
    assert not tested.seen(wedge, near)  # other models' poses do not count
    far = make_pose(near[:3, :3], X[:3, 3] + [0.005, 0.0, 0.0])
    assert not tested.seen(cube, far)
    turned = make_pose(X[:3, :3] @ so3_exp([0.0, 0.0, np.deg2rad(6.0)]), X[:3, 3])
    assert not tested.seen(cube, turned)


def test_initial_poses_undo_a_known_image_similarity() -> None:
    """A group seen on the optical axis, turned by θ and at half the canonical scale, gives
    the indexed view turned by θ about the axis at twice the view distance; many at once."""
    from work_site.vision.hypotheses import initial_pose, initial_poses
    from work_site.vision.index import IndexParams

    params = IndexParams()
    f = params.canonical_f_px
    K = np.array([[f, 0.0, 320.0], [0.0, f, 240.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(6)
    n = 8
    R_view = np.array([so3_exp(rng.normal(0, 1, 3)) for _ in range(n)])
    canonical = rng.normal(0.0, 50.0, (n, 3, 2))
    canonical -= canonical.mean(axis=1, keepdims=True)
    theta = rng.uniform(-np.pi, np.pi, n)
    z = 0.5 * np.exp(1j * theta)[:, None] * (canonical[..., 0] + 1j * canonical[..., 1])
    image = np.stack([z.real + 320.0, z.imag + 240.0], axis=-1)
    X = initial_poses(R_view, canonical, image, K, params)
    for k in range(n):
        c, s = np.cos(theta[k]), np.sin(theta[k])
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(X[k, :3, :3], Rz @ R_view[k], atol=1e-12)
        np.testing.assert_allclose(X[k, :3, 3], [0.0, 0.0, 2 * params.view_distance_m], atol=1e-12)
        np.testing.assert_array_equal(
            initial_pose(R_view[k], canonical[k], image[k], K, params), X[k]
        )


def test_match_segments_pairs_each_image_line_with_its_own_edge() -> None:
    """Parts of edges, shifted less than the tolerance, match their own edge; lines turned
    beyond the angle, shifted beyond the tolerance or mostly off the edge do not."""
    from work_site.vision.verification import match_segments

    rng = np.random.default_rng(7)
    model = np.column_stack([rng.uniform(50, 550, (12, 2)), rng.uniform(50, 550, (12, 2))])
    a, b = model[:, :2], model[:, 2:]
    u = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    n = np.column_stack([-u[:, 1], u[:, 0]])
    t0, t1 = rng.uniform(0.05, 0.3, (2, 12, 1))
    shift = rng.uniform(-1.0, 1.0, (12, 1)) * n
    image = np.column_stack([a + t0 * (b - a) + shift, b - t1 * (b - a) + shift])
    mi, mj = match_segments(model, image, 1.5, np.deg2rad(5.0))
    np.testing.assert_array_equal(mj, np.arange(12))
    np.testing.assert_array_equal(mi, np.arange(12))
    far = image + np.column_stack([3.0 * n, 3.0 * n])  # 2–4 px off
    assert len(match_segments(model, far, 1.5, np.deg2rad(5.0))[0]) == 0
    beyond = np.column_stack([b + 0.2 * (b - a), b + 1.2 * (b - a)])  # overlap < half
    assert len(match_segments(model, beyond, 1.5, np.deg2rad(5.0))[0]) == 0
    c, s = np.cos(np.deg2rad(8.0)), np.sin(np.deg2rad(8.0))
    mid = 0.5 * (image[:, :2] + image[:, 2:])
    half = 0.5 * (image[:, 2:] - image[:, :2]) @ np.array([[c, s], [-s, c]])
    turned = np.column_stack([mid - 0.2 * half, mid + 0.2 * half])
    assert len(match_segments(model, turned, 1.5, np.deg2rad(5.0))[0]) == 0


def test_pose_set_adds_many_as_one_by_one() -> None:
    """``add_new`` records and reports the same poses as ``seen`` then ``add`` in turn,
    with poses equal to recorded ones, to earlier ones of the batch, and up to symmetry."""
    scene = load_scene()
    cube = vision_model(next(o.model for o in scene.movable if o.name == "cube"))
    rng = np.random.default_rng(4)
    base = [make_pose(so3_exp(rng.normal(size=3)), rng.uniform(-0.05, 0.05, 3)) for _ in range(6)]
    for trial in range(20):
        batch = []
        for _ in range(30):
            X = base[int(rng.integers(len(base)))].copy()
            X[:3, :3] = X[:3, :3] @ cube.symmetries[int(rng.integers(len(cube.symmetries)))]
            X[:3, :3] = so3_exp(rng.normal(scale=0.025, size=3)) @ X[:3, :3]
            X[:3, 3] += rng.normal(scale=0.0015, size=3)
            batch.append(X)
        batch = np.array(batch)
        one, many = PoseSet(0.004, np.deg2rad(4.0)), PoseSet(0.004, np.deg2rad(4.0))
        for X in base[: trial % 4]:
            one.add(cube, X)
            many.add(cube, X)
        expected = []
        for X in batch:
            fresh = not one.seen(cube, X)
            if fresh:
                one.add(cube, X)
            expected.append(fresh)
        got = many.add_new(cube, batch)
        np.testing.assert_array_equal(got, expected)
        assert 0 < sum(expected) < len(batch)


def test_turned_poses_keep_the_centre_and_differ_up_to_symmetry() -> None:
    """The turns tried for a pose fitted to few edges: about the bounding-box centre, none
    equal to the model's own pose or to each other up to its symmetries (a cube has none)."""
    from work_site.vision.hypotheses import turned_poses

    scene = load_scene()
    for name, expected in (("cube", 0), ("wedge", 11), ("tall_block", 2)):
        m = vision_model(next(o.model for o in scene.movable if o.name == name))
        T = turned_poses(m)
        assert len(T) == expected == 24 // len(m.symmetries) - 1
        c = 0.5 * (m.vertices_O.min(0) + m.vertices_O.max(0))
        for X in T:
            np.testing.assert_allclose(X[:3, :3] @ c + X[:3, 3], c, atol=1e-12)


def test_support_is_what_lies_under_a_block_not_beside_it() -> None:
    """A block is held up by the table or by what is under it; beside another, or in the air,
    it is not."""
    from work_site.vision.params import RecognizerParams
    from work_site.vision.verification import Surroundings

    def box(centre, half=0.025):
        c = np.array(centre, dtype=np.float64)
        V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half + c
        return [(V, np.vstack([np.eye(3), -np.eye(3)]))]

    p = RecognizerParams()
    s = Surroundings(0.0, (np.array([-1.0, -1.0]), np.array([1.0, 1.0])), [])
    lower = box((0.0, 0.0, 0.025))
    assert s.supported_by(lower, [], p)  # on the table
    assert s.supported_by(box((0.01, 0.0, 0.0751)), [lower], p)  # on the lower block
    assert s.supported_by(box((0.045, 0.0, 0.0752)), [lower], p)  # overhanging its edge
    assert not s.supported_by(box((0.0, 0.0, 0.10)), [lower], p)  # 2.5 cm above it
    assert not s.supported_by(box((0.0501, 0.0, 0.04)), [lower], p)  # beside it, in the air
    assert not s.supported_by(box((0.0, 0.0, 0.0752)), [], p)  # nothing under it


def test_a_block_sunk_into_what_is_under_it_is_settled_along_its_line_of_sight() -> None:
    """A cube fitted 4 mm too far along its ray sinks into the slab under it: settled, it
    moves back along that ray (translation scaled, rotation kept) to where it overlaps by at
    most the allowed depth, its image a fraction of a pixel from where it was. Sunk by 5 cm, or
    by 4 mm where its fit's residual is 0.05 px, it is not: its lines would tell."""
    from models.transforms import look_at
    from work_site.vision.model import convex_overlap_depth, parts_in
    from work_site.vision.params import RecognizerParams
    from work_site.vision.pose_sets import Candidate, _settled
    from work_site.vision.verification import Surroundings, Verification

    cube = vision_model(load_scene().object("cube").model)
    p = RecognizerParams()
    K = np.array([[900.0, 0.0, 320.0], [0.0, 900.0, 240.0], [0.0, 0.0, 1.0]])
    X_WC = look_at(np.array([0.0, -0.55, 0.55]), np.array([0.0, 0.0, 0.0]))
    X_CW = np.linalg.inv(X_WC)
    s = Surroundings(0.0, (np.array([-1.0, -1.0]), np.array([1.0, 1.0])), [])
    size = float(np.ptp(cube.vertices_O[:, 2]))
    # Under it a slab wider than anything within reach along the ray: no way round it.
    half = np.array([0.1, 0.1, size / 2])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    lower = [(corners * half + [0.0, 0.0, size / 2], np.vstack([np.eye(3), -np.eye(3)]))]
    on_top = make_pose(p_AB=np.array([0.005, 0.0, size - cube.vertices_O[:, 2].min()]))

    def candidate(sunk_m: float, rms_px: float = 0.3) -> Candidate:
        """The cube on top moved ``sunk_m`` further along its line of sight, fitted to its
        lines with an rms residual of ``rms_px``."""
        X_CO = X_CW @ on_top
        t = X_CO[:3, 3]
        X_CO[:3, 3] = t * (1.0 + sunk_m / np.linalg.norm(t))
        X_WO = X_WC @ X_CO
        v = Verification(1.0, 1.0, 1.0, [], 0.0)
        return Candidate(cube, X_CO, X_WO, rms_px, v, parts_in(X_WO, cube), resting=False)

    def overlap(c: Candidate) -> float:
        return max(convex_overlap_depth(a, b, na, nb) for a, na in c.parts_W for b, nb in lower)

    c = candidate(0.004)
    assert overlap(c) > p.max_penetration_m  # what the selection refuses as it is
    settled = _settled(c, [lower], s, p, K, 1.0)
    assert settled is not None and settled.settled_from is c and settled.origin is c
    assert overlap(settled) <= p.max_penetration_m
    np.testing.assert_allclose(settled.X_CO[:3, :3], c.X_CO[:3, :3])
    t0, t1 = c.X_CO[:3, 3], settled.X_CO[:3, 3]
    assert np.linalg.norm(np.cross(t0, t1)) <= 1e-12 * np.linalg.norm(t0) ** 2  # same ray
    assert np.linalg.norm(t1) < np.linalg.norm(t0)  # towards the camera: up, off the slab
    # Moved by less than the lines can tell: the cube's image by a fraction of a pixel.
    uv0 = project_px(c.X_CO, cube, K)
    assert np.max(np.linalg.norm(project_px(settled.X_CO, cube, K) - uv0, axis=1)) < 0.5
    np.testing.assert_allclose(settled.X_WO, X_WC @ settled.X_CO, atol=1e-12)
    assert _settled(candidate(0.05), [lower], s, p, K, 1.0) is None
    assert _settled(candidate(0.004, rms_px=0.05), [lower], s, p, K, 1.0) is None


def project_px(X_CO: np.ndarray, model, K: np.ndarray) -> np.ndarray:
    """The model's vertices' images (n, 2) px at ``X_CO``."""
    from work_site.vision.model import project, transform

    return project(transform(X_CO, model.vertices_O), K)
