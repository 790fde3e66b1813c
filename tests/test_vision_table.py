"""Table hypotheses: one junction of two image lines gives a block's whole resting pose."""

from __future__ import annotations

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import invert_pose, make_pose
from work_site.vision.model import project, transform, vision_model
from work_site.vision.table import (
    back_project_to_plane,
    batch_support,
    rest_corners,
    table_hypotheses,
)


@pytest.fixture(scope="module")
def setup():
    scene = load_scene()
    objs = {o.name: o.model for o in scene.movable}
    names = ["cube", "plank", "wedge", "hex_prism"]
    models = [vision_model(objs[n]) for n in names]
    corners = rest_corners(models, [objs[n].com_O for n in names])
    return scene.camera, models, corners


def _rotation_error_at(poses: np.ndarray, X_WO: np.ndarray, model) -> float:
    """The least rotation error (Frobenius, up to ``model``'s symmetries) of those ``poses``
    at ``X_WO``'s position; inf when none is there."""
    best = np.inf
    for X in poses:
        if np.linalg.norm(X[:3, 3] - X_WO[:3, 3]) > 1e-6:
            continue
        R = X[:3, :3].T @ X_WO[:3, :3]
        best = min(best, min(np.linalg.norm(R @ S - np.eye(3)) for S in model.symmetries))
    return best


def _drawn_edges(camera, model, X_CO: np.ndarray):
    """Every edge of ``model`` at ``X_CO`` projected (e, 2, 2) px, drawn one pixel wide into
    a black image, and that image's gradients (gx, gy)."""
    import cv2

    img = np.zeros((camera.height, camera.width), np.uint8)
    uv = project(transform(X_CO, model.edges_O), camera.K)
    for a, b in uv:
        cv2.line(img, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), 255, 1)
    f = img.astype(np.float32)
    return uv, cv2.Scharr(f, cv2.CV_32F, 1, 0), cv2.Scharr(f, cv2.CV_32F, 0, 1)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_rest_corners_are_right_angles_of_boxes_on_the_table(setup) -> None:
    _, models, corners = setup
    cube = (corners.model == 0) & corners.level
    # A cube rests on any of its 6 faces with 8 corners on top and bottom, 2 orders each: up
    # to its 24 symmetries only a top and a bottom corner are left, in both orders.
    assert np.count_nonzero(cube) == 6 * 8 * 2 // 24
    np.testing.assert_allclose(np.abs(corners.turn[cube]), np.pi / 2, atol=1e-9)
    assert set(np.round(corners.corner[cube, 2], 9)) == {0.0, 0.05}
    # With its vertical edge: each of the two horizontal edges of a top and a bottom corner,
    # the vertical edge going down and up.
    mixed = (corners.model == 0) & ~corners.level
    assert np.count_nonzero(mixed) == 4 and np.isnan(corners.turn[mixed]).all()
    top = corners.corner[mixed, 2] > 0.01
    np.testing.assert_allclose(corners.second[mixed, 2], np.where(top, -1.0, 1.0))
    hexp = (corners.model == 3) & corners.level
    # The hexagon's corners turn by 120° when it stands on its end.
    assert np.any(np.isclose(np.abs(corners.turn[hexp]), 2 * np.pi / 3, atol=1e-9))
    # Every resting rotation puts the model's lowest point on the table.
    for k in np.flatnonzero(corners.model >= 0)[::7]:
        m = models[corners.model[k]]
        z = (m.vertices_O @ corners.R_WO0[k].T)[:, 2] + corners.lift_m[k]
        assert abs(z.min()) < 1e-12


def test_back_projection_lands_on_the_plane(setup) -> None:
    camera = setup[0]
    p_W = np.array([[0.4, 0.05, 0.025], [0.5, -0.1, 0.025]])
    uv = project(transform(invert_pose(camera.X_WC), p_W), camera.K)
    P, ok = back_project_to_plane(uv, camera.K, camera.X_WC, 0.025)
    assert ok.all()
    np.testing.assert_allclose(P, p_W, atol=1e-12)


@pytest.mark.parametrize("mi", [0, 1, 2, 3])
def test_a_junction_of_two_exact_top_edges_gives_the_pose(setup, mi) -> None:
    camera, models, corners = setup
    m = models[mi]
    k = np.flatnonzero((corners.model == mi) & corners.level & (corners.corner[:, 2] > 0.01))[0]
    R_WO = _rot_z(0.7) @ corners.R_WO0[k]
    X_WO = make_pose(R_WO, [0.45, 0.03, corners.lift_m[k]])
    X_CW = invert_pose(camera.X_WC)
    # The two horizontal edges at that corner, projected exactly.
    c_W = transform(X_WO, (corners.R_WO0[k].T @ (corners.corner[k] - [0, 0, corners.lift_m[k]])))
    E_W = transform(X_WO, m.edges_O)
    at = np.linalg.norm(E_W - c_W, axis=2).min(axis=1) < 1e-9
    horiz = np.abs(E_W[:, 0, 2] - E_W[:, 1, 2]) < 1e-9
    two = np.flatnonzero(at & horiz)[:2]
    segs = project(transform(X_CW, E_W[two]), camera.K).reshape(-1, 4)
    uv_c = project(transform(X_CW, c_W[None]), camera.K)[0]
    ends = [int(np.argmin(np.linalg.norm(s.reshape(2, 2) - uv_c, axis=1))) for s in segs]
    junctions = [(0, ends[0], 1, ends[1], uv_c)]
    mod, poses, pairs = table_hypotheses(corners, junctions, segs, camera.K, camera.X_WC, 0.0)
    assert len(mod) > 0 and np.all(pairs == [0, 1])
    assert _rotation_error_at(poses[mod == mi], X_WO, m) < 1e-6


@pytest.mark.parametrize("mi", [0, 1, 2, 3])
def test_a_junction_of_a_top_edge_and_a_sloping_or_upright_edge_gives_the_pose(setup, mi):
    """Only one edge horizontal: it gives the yaw, the other's image direction is checked."""
    camera, models, corners = setup
    m = models[mi]
    X_CW = invert_pose(camera.X_WC)
    for k in np.flatnonzero((corners.model == mi) & ~corners.level):
        R_WO = _rot_z(0.7) @ corners.R_WO0[k]
        X_WO = make_pose(R_WO, [0.45, 0.03, corners.lift_m[k]])
        c_O = corners.R_WO0[k].T @ (corners.corner[k] - [0, 0, corners.lift_m[k]])
        c_W = transform(X_WO, c_O[None])[0]
        first = _rot_z(0.7) @ [np.cos(corners.heading[k]), np.sin(corners.heading[k]), 0.0]
        second = _rot_z(0.7) @ corners.second[k]
        # The model's two edges leaving that corner those ways, projected exactly.
        E_W = transform(X_WO, m.edges_O)
        two = []
        for want in (first, second):
            for e in E_W:
                for end in (0, 1):
                    d = e[1 - end] - e[end]
                    if np.linalg.norm(e[end] - c_W) < 1e-9 and d @ want > 0.999 * np.linalg.norm(d):
                        two.append(e if end == 0 else e[::-1])
        segs = project(transform(X_CW, np.array(two)), camera.K).reshape(-1, 4)
        uv_c = project(transform(X_CW, c_W[None]), camera.K)[0]
        # The junction's lines in either order: either may be the horizontal one.
        for order in ((0, 1), (1, 0)):
            s2 = segs[list(order)]
            junctions = [(0, 0, 1, 0, uv_c)]
            mod, poses, _ = table_hypotheses(corners, junctions, s2, camera.K, camera.X_WC, 0.0)
            assert _rotation_error_at(poses[mod == mi], X_WO, m) < 1e-6, (k, order)


def test_batch_support_prefers_the_true_pose(setup) -> None:
    camera, models, _ = setup

    m = models[0]
    X_WO = make_pose(_rot_z(0.3), [0.45, 0.0, 0.025])
    X_CO = invert_pose(camera.X_WC) @ X_WO
    # Draw the cube's visible outline and inner edges into an image, then take gradients.
    _, gx, gy = _drawn_edges(camera, m, X_CO)
    shifted = X_CO.copy()
    shifted[0, 3] += 0.02
    s = batch_support(m, m.edge_faces, np.array([X_CO, shifted]), camera.K, gx, gy, 60.0, 0.35)
    assert s[0] > 0.8 and s[1] < 0.3


def test_coarse_to_fine_support_is_exact_where_it_samples_in_full(setup) -> None:
    """With ``coarse_min``, poses whose support at 2 of 6 points per edge reaches it get exactly
    the full support; the others get that coarse support, below ``coarse_min``."""
    camera, models, _ = setup

    m = models[1]
    rng = np.random.default_rng(21)
    X_WO = make_pose(_rot_z(0.7), [0.40, 0.05, 0.0125])
    X_CO = invert_pose(camera.X_WC) @ X_WO
    _, gx, gy = _drawn_edges(camera, m, X_CO)
    poses = []
    for _ in range(300):  # from the true pose to far off, so both branches are taken
        X = X_CO.copy()
        X[:3, 3] += rng.normal(0.0, 0.006, 3)
        X[:3, :3] = X[:3, :3] @ _rot_z(rng.normal(0.0, 0.1))
        poses.append(X)
    poses = np.array(poses)
    full = batch_support(m, m.edge_faces, poses, camera.K, gx, gy, 60.0, 0.35)
    staged = batch_support(m, m.edge_faces, poses, camera.K, gx, gy, 60.0, 0.35, coarse_min=0.3)
    in_full = staged >= 0.3
    assert 10 < in_full.sum() < len(poses) - 10
    np.testing.assert_array_equal(staged[in_full], full[in_full])
    assert np.all(staged[~in_full] < 0.3)


def test_the_table_stream_counts_each_pose_once_against_its_cap(setup) -> None:
    """Every corner of a cube seen gives its pose again: with a cap of 3, the stream holds 3
    different poses, the cube's true one first."""

    from work_site.vision.hypotheses import table_stream
    from work_site.vision.index import GroupParams
    from work_site.vision.params import RecognizerParams
    from work_site.vision.pose_sets import PoseSet

    camera, models, corners = setup
    m = models[0]
    X_CO = invert_pose(camera.X_WC) @ make_pose(_rot_z(0.3), [0.45, 0.0, 0.025])
    segs, gx, gy = _drawn_edges(camera, m, X_CO)
    p = RecognizerParams(max_table_hypotheses=3)
    items = table_stream(
        corners, models, GroupParams(), 0.0, segs.reshape(-1, 4), camera.K, camera.X_WC,
        gx, gy, p,
    )  # fmt: skip
    assert len(items) == 3
    same = PoseSet(p.same_pose_m, p.same_pose_rad)
    for model, _, X in items:
        assert not same.seen(model, X)
        same.add(model, X)
    model, _, X = items[0]
    assert model is m
    R = X[:3, :3].T @ X_CO[:3, :3]
    assert np.linalg.norm(X[:3, 3] - X_CO[:3, 3]) < 1e-3
    assert min(np.linalg.norm(R @ S - np.eye(3)) for S in m.symmetries) < 1e-2
