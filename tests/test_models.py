"""Object models, the scene and the camera: dimensions from DESIGN.md, checks, clear errors."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import models
from models.errors import ModelError
from models.generate import generate
from models.geometry import make_convex_part, write_obj
from models.scene import (
    DEFAULT_SCENE,
    frame_bar_height_m,
    frame_opening_W,
    frame_outer_W,
    load_camera,
    load_object,
    load_scene,
)
from models.transforms import rpy_to_R

DIMENSION_TOL_M = 1e-4  # the 0.1 mm
MODELS_DIR = Path(models.__file__).parent
HEX_CIRCUMRADIUS_M = 0.025 / np.cos(np.pi / 6)

# name: (volume m³, bounding-box size m (x, y, z), feature edges)
EXPECTED = {
    "cube": (0.05**3, (0.05, 0.05, 0.05), 12),
    "tall_block": (0.05 * 0.05 * 0.10, (0.05, 0.05, 0.10), 12),
    "plank": (0.10 * 0.05 * 0.025, (0.10, 0.05, 0.025), 12),
    "wedge": (0.5 * 0.05 * 0.05 * 0.05, (0.05, 0.05, 0.05), 9),
    "l_block": (0.10 * 0.05 * 0.05 + 0.05**3, (0.10, 0.05, 0.10), 18),
    "hex_prism": (
        1.5 * np.sqrt(3) * HEX_CIRCUMRADIUS_M**2 * 0.05,
        (2 * HEX_CIRCUMRADIUS_M, 0.05, 0.05),
        18,
    ),
    # Four bars 0.02 wide and 0.03 tall round a 0.20 m square opening.
    "frame": (0.03 * (0.24**2 - 0.20**2), (0.24, 0.24, 0.03), 24),
}


@pytest.fixture(scope="module")
def scene() -> models.Scene:
    return load_scene()


def test_exported_names_exist() -> None:
    assert sorted(models.__all__) == sorted(set(models.__all__))
    for name in models.__all__:
        assert hasattr(models, name), name


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_object_dimensions_match_design(scene: models.Scene, name: str) -> None:
    volume, size, n_edges = EXPECTED[name]
    model = scene.object(name).model
    assert model.volume_m3 == pytest.approx(volume, rel=1e-9)
    np.testing.assert_allclose(model.bbox_O[1] - model.bbox_O[0], size, atol=DIMENSION_TOL_M)
    assert len(model.feature_edges_O) == n_edges
    assert model.mass_kg > 0


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_parts_are_closed_and_convex(scene: models.Scene, name: str) -> None:
    for part in scene.object(name).model.parts:
        V = part.vertices_O
        # Every vertex on or inside every face plane: convex.
        assert np.max(V @ part.normals_O.T - part.offsets_m) < 1e-9
        # Each undirected edge used by exactly two faces, once in each direction: closed.
        directed = [(a, b) for f in part.faces for a, b in zip(f, f[1:] + f[:1], strict=True)]
        assert len(set(directed)) == len(directed)
        assert all((b, a) in set(directed) for a, b in directed)
        # Euler's formula for a genus-0 polyhedron.
        assert len(V) - len(directed) // 2 + len(part.faces) == 2


def test_feature_edges_of_cube_are_its_twelve_edges(scene: models.Scene) -> None:
    edges = scene.object("cube").model.feature_edges_O
    lengths = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    np.testing.assert_allclose(lengths, 0.05, atol=1e-12)
    np.testing.assert_allclose(
        np.abs(edges), 0.025 * np.ones_like(edges) * (np.abs(edges) > 0), atol=1e-12
    )


def test_l_block_concave_crease_and_merged_outer_edges(scene: models.Scene) -> None:
    edges = scene.object("l_block").model.feature_edges_O
    lengths = np.sort(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1))
    # 6 extrusion edges (0.05), profile edges on both sides: 0.10 ×2 (bottom, outer side merged
    # across the two parts), 0.05 ×4 per side.
    assert np.sum(np.isclose(lengths, 0.10)) == 4
    assert np.sum(np.isclose(lengths, 0.05)) == 14
    # The inner corner of the L (x = 0, z = 0, along y) is a (concave) feature edge.
    mid = edges.mean(axis=1)
    assert np.any(np.all(np.isclose(mid, [0.0, 0.0, 0.0], atol=1e-12), axis=1))


def test_scene_layout(scene: models.Scene) -> None:
    assert [o.name for o in scene.objects if o.fixed] == ["table", "frame"]
    assert sorted(o.name for o in scene.movable) == sorted(
        ["cube", "tall_block", "plank", "wedge", "l_block", "hex_prism"]
    )
    table = scene.object("table")
    assert table.X_WO[2, 3] + table.model.bbox_O[1, 2] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(scene.object("frame").X_WO[:3, 3], [0.45, 0.0, 0.015])
    inner_half = 0.10
    for obj in scene.movable:
        # Resting on the table and entirely outside the frame's outer square.
        corners_W = (
            np.vstack([p.vertices_O for p in obj.model.parts]) @ obj.X_WO[:3, :3].T
            + obj.X_WO[:3, 3]
        )
        assert corners_W[:, 2].min() == pytest.approx(0.0, abs=1e-12)
        outside = np.abs(corners_W[:, 1]).min() > inner_half + 0.02
        assert outside, obj.name
    with pytest.raises(KeyError, match="known: table"):
        scene.object("teapot")


def test_camera_matches_design(scene: models.Scene) -> None:
    cam = scene.camera
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose(cam.X_WC[:3, 3], [0.45, -0.55, 0.65])
    # The optical axis (z of C) points at the frame's centre.
    target = np.array([0.45, 0.0, 0.0]) - cam.X_WC[:3, 3]
    np.testing.assert_allclose(cam.X_WC[:3, 2], target / np.linalg.norm(target), atol=1e-12)
    assert cam.to_json()["K"] == cam.K.tolist()


def test_generated_files_are_up_to_date(tmp_path: Path) -> None:
    generate(tmp_path)
    for path in sorted(tmp_path.rglob("*")):
        if path.is_file():
            committed = MODELS_DIR / path.relative_to(tmp_path)
            assert committed.read_text() == path.read_text(), (
                f"{committed} differs from what models/generate.py writes: run "
                "`python -m models.generate`"
            )


# ----------------------------------------------------------------------------- bad input

CUBE_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
CUBE_F = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def test_a_unit_cube_part_is_accepted() -> None:
    part = make_convex_part(CUBE_V, CUBE_F, "cube")
    assert len(part.faces) == 6


@pytest.mark.parametrize(
    ("vertices", "faces", "problem"),
    [
        (CUBE_V, CUBE_F[:-1], "not closed"),
        (np.where(np.arange(24).reshape(8, 3) == 5, np.nan, CUBE_V), CUBE_F, "NaN"),
        (CUBE_V, [f[::-1] for f in CUBE_F], "inwards"),
        (CUBE_V, [CUBE_F[0][::-1], *CUBE_F[1:]], "same direction"),
        (CUBE_V + np.array([[0, 0, 0]] * 7 + [[0.3, 0, 0]]), CUBE_F, "not planar"),
        (CUBE_V, [[0, 1, 1, 2], *CUBE_F[1:]], "degenerate"),
    ],
)
def test_malformed_parts_are_refused(vertices, faces, problem: str) -> None:
    with pytest.raises(ModelError, match=problem) as e:
        make_convex_part(vertices, faces, "bad.obj")
    assert "bad.obj" in str(e.value)


def test_non_convex_part_is_refused() -> None:
    # A tetrahedron whose slanted face is pushed in to an interior point: closed, not convex.
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.2]], dtype=float)
    F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 4], [2, 3, 4], [3, 1, 4]]
    with pytest.raises(ModelError, match=r"dent\.obj: part is not convex"):
        make_convex_part(V, F, "dent.obj")


def _copy_objects(tmp_path: Path) -> Path:
    shutil.copytree(MODELS_DIR / "objects", tmp_path / "objects")
    return tmp_path / "objects"


def test_missing_mesh_file_names_the_file(tmp_path: Path) -> None:
    objects = _copy_objects(tmp_path)
    (objects / "meshes" / "cube_0.obj").unlink()
    with pytest.raises(ModelError, match=r"cube_0\.obj does not exist"):
        load_object(objects / "cube.urdf")
    with pytest.raises(ModelError, match=r"nothing\.urdf: object model file does not exist"):
        load_object(objects / "nothing.urdf")


def test_nan_in_mesh_names_the_file(tmp_path: Path) -> None:
    objects = _copy_objects(tmp_path)
    mesh = objects / "meshes" / "wedge_0.obj"
    mesh.write_text(mesh.read_text().replace("v -0.025", "v nan", 1))
    with pytest.raises(ModelError, match=r"wedge_0\.obj: vertex coordinates contain NaN"):
        load_object(objects / "wedge.urdf")


def test_open_mesh_names_the_file(tmp_path: Path) -> None:
    objects = _copy_objects(tmp_path)
    mesh = objects / "meshes" / "hex_prism_0.obj"
    lines = mesh.read_text().splitlines()
    mesh.write_text("\n".join(lines[:-1]) + "\n")  # drop one face
    with pytest.raises(ModelError, match=r"hex_prism_0\.obj: mesh is not closed"):
        load_object(objects / "hex_prism.urdf")


def test_interpenetrating_parts_are_refused(tmp_path: Path) -> None:
    objects = _copy_objects(tmp_path)
    V = CUBE_V * 0.05
    write_obj(objects / "meshes" / "a.obj", V, CUBE_F, "a")
    write_obj(objects / "meshes" / "b.obj", V + 0.02, CUBE_F, "b")
    (objects / "two.urdf").write_text(
        '<robot name="two"><link name="base">'
        '<collision><geometry><mesh filename="meshes/a.obj"/></geometry></collision>'
        '<collision><geometry><mesh filename="meshes/b.obj"/></geometry></collision>'
        "</link></robot>"
    )
    with pytest.raises(ModelError, match=r"two\.urdf: convex parts 0 and 1 interpenetrate"):
        load_object(objects / "two.urdf")


def test_bad_scene_and_camera_files_name_the_problem(tmp_path: Path) -> None:
    scene = json.loads(DEFAULT_SCENE.read_text())
    bad = tmp_path / "scenes"
    shutil.copytree(MODELS_DIR / "scenes", bad)
    shutil.copytree(MODELS_DIR / "objects", tmp_path / "objects")
    shutil.copytree(MODELS_DIR / "cameras", tmp_path / "cameras")
    shutil.copytree(MODELS_DIR / "robots", tmp_path / "robots")
    path = bad / "puzzle.json"
    assert load_scene(path).name == "puzzle"

    scene["objects"][2]["X_WO"][0][0] = float("nan")
    path.write_text(json.dumps(scene))
    with pytest.raises(ModelError, match=r"puzzle\.json: objects\[2\]: NaN"):
        load_scene(path)

    scene["objects"][2]["X_WO"][0][0] = 2.0
    path.write_text(json.dumps(scene))
    with pytest.raises(ModelError, match=r"objects\[2\]: not a rigid transform"):
        load_scene(path)

    path.write_text("{ not json")
    with pytest.raises(ModelError, match=r"puzzle\.json: not valid JSON"):
        load_scene(path)
    with pytest.raises(ModelError, match="scene file does not exist"):
        load_scene(tmp_path / "none.json")

    cam = json.loads((MODELS_DIR / "cameras" / "default.json").read_text())
    cam["K"][0][0] = 0.0
    cam_path = tmp_path / "cam.json"
    cam_path.write_text(json.dumps(cam))
    with pytest.raises(ModelError, match=r"cam\.json: K must be"):
        load_camera(cam_path)
    cam["K"][0][0] = 580.0
    cam["width"] = 0
    cam_path.write_text(json.dumps(cam))
    with pytest.raises(ModelError, match=r"cam\.json: width must be"):
        load_camera(cam_path)


def test_random_layouts_put_every_block_on_the_table_outside_the_frame_apart() -> None:
    from models.layout import (
        FRAME_OUTLINE_W,
        LANE_M,
        MAX_REACH_XY_M,
        MIN_REACH_XY_M,
        perturbed_camera_pose,
        random_layout,
    )

    scene = load_scene()
    for seed in range(50):
        layout = random_layout(scene, seed)
        assert set(layout) == {o.name for o in scene.movable}
        centres = {n: X[:3, 3] for n, X in layout.items()}
        (fx0, fx1), (fy0, fy1) = FRAME_OUTLINE_W
        for name, c in centres.items():
            gap = np.maximum([fx0 - c[0], fy0 - c[1]], [c[0] - fx1, c[1] - fy1])
            assert np.linalg.norm(np.maximum(gap, 0.0)) >= LANE_M, (seed, name)
            assert MIN_REACH_XY_M <= np.linalg.norm(c[:2]) <= MAX_REACH_XY_M
            assert c[2] == scene.object(name).X_WO[2, 3]  # resting as in the scene file
        assert random_layout(scene, seed).keys() == layout.keys()
        np.testing.assert_array_equal(random_layout(scene, seed)["cube"], layout["cube"])
    X = perturbed_camera_pose(scene.camera.X_WC, 3)
    assert np.linalg.norm(X[:3, 3] - scene.camera.X_WC[:3, 3]) == pytest.approx(0.002)


def test_a_scaled_camera_keeps_pixel_centres_consistent() -> None:
    camera = load_scene().camera
    half = camera.scaled(0.5)
    assert (half.width, half.height) == (camera.width // 2, camera.height // 2)
    p_C = np.array([0.03, -0.02, 0.8])  # a point in front of the camera (m)
    u = camera.K @ p_C / p_C[2]
    u_half = half.K @ p_C / p_C[2]
    # Pixel (0, 0) covers [-0.5, 0.5]: a point at u lands at (u + 0.5) f - 0.5 after resizing.
    np.testing.assert_allclose(u_half[:2], (u[:2] + 0.5) * 0.5 - 0.5, atol=1e-12)
    np.testing.assert_allclose(half.scaled(2.0).K, camera.K, atol=1e-12)
    with pytest.raises(ValueError, match="scale factor"):
        camera.scaled(0.0)


def _with_frame_at(scene: models.Scene, X_WO: np.ndarray) -> models.Scene:
    objects = tuple(
        dataclasses.replace(o, X_WO=X_WO) if o.name == "frame" else o for o in scene.objects
    )
    return dataclasses.replace(scene, objects=objects)


def test_the_frames_walls_come_from_its_parts(scene: models.Scene) -> None:
    # The puzzle scene's frame: a 0.20 m opening centred at (0.45, 0), 0.02 m bars 0.03 m tall;
    # exactly the round numbers, as the scripted operator typed them before.
    assert frame_opening_W(scene) == ((0.35, 0.55), (-0.10, 0.10))
    assert frame_outer_W(scene) == ((0.33, 0.57), (-0.12, 0.12))
    assert frame_bar_height_m(scene) == 0.03


def test_the_frames_walls_follow_the_frame_when_it_moves(scene: models.Scene) -> None:
    X = scene.object("frame").X_WO.copy()
    X[:3, 3] += (0.05, -0.03, 0.0)
    moved = _with_frame_at(scene, X)
    assert frame_opening_W(moved) == ((0.40, 0.60), (-0.13, 0.07))
    assert frame_outer_W(moved) == ((0.38, 0.62), (-0.15, 0.09))
    assert frame_bar_height_m(moved) == 0.03
    # A quarter turn about z maps the square frame onto itself; lifting it keeps its height.
    turned = X.copy()
    turned[:3, :3] = rpy_to_R(np.array([0.0, 0.0, np.pi / 2]))
    turned[2, 3] += 0.01
    assert frame_opening_W(_with_frame_at(scene, turned)) == frame_opening_W(moved)
    assert frame_bar_height_m(_with_frame_at(scene, turned)) == 0.03
    askew = X.copy()
    askew[:3, :3] = rpy_to_R(np.array([0.0, 0.0, 0.3]))
    with pytest.raises(ValueError, match="not square"):
        frame_opening_W(_with_frame_at(scene, askew))
    with pytest.raises(ValueError, match="no wall"):
        frame_opening_W(scene, "table")


def test_every_block_has_the_symmetries_of_its_shape() -> None:
    scene = load_scene()
    expected = {"cube": 24, "tall_block": 8, "plank": 4, "wedge": 2, "l_block": 2, "hex_prism": 12}
    for name, count in expected.items():
        model = scene.object(name).model
        S = model.symmetries
        assert len(S) == count, name
        np.testing.assert_array_equal(S[0], np.eye(3))
        corners = np.unique(np.round(model.feature_edges_O.reshape(-1, 3), 9), axis=0)
        for R in S:  # each maps every corner onto a corner, and each is a rotation
            d = np.linalg.norm((corners @ R.T)[:, None] - corners[None], axis=2).min(axis=1)
            assert d.max() < 1e-9 and abs(np.linalg.det(R) - 1.0) < 1e-12, name


@pytest.mark.parametrize("seed", [0, 7, 13])
def test_random_layouts_show_every_block_whole_to_the_off_calibration_camera(seed: int) -> None:
    """Rendered, not re-derived: each block covers as many pixels among the others as alone,
    and none touches the image's border, with the real camera where the seed puts it."""
    from models.layout import perturbed_camera_pose, random_layout
    from work_site.camera import render_grey
    from work_site.world import World

    scene = load_scene()
    camera = dataclasses.replace(scene.camera, X_WC=perturbed_camera_pose(scene.camera.X_WC, seed))
    layout = random_layout(scene, seed)
    world = World(dataclasses.replace(scene, camera=camera))
    try:
        away = {n: X.copy() for n, X in layout.items()}
        for X in away.values():
            X[2, 3] -= 5.0  # far below the table, out of sight
        for name, X_WO in layout.items():
            world.set_object_pose(name, X_WO)
        _, seg = render_grey(world.cid, camera, segmentation=True)
        among = {n: int(np.sum(seg == world.bodies[n])) for n in layout}
        for name in layout:
            assert not np.any(seg[[0, -1], :] == world.bodies[name]), name
            assert not np.any(seg[:, [0, -1]] == world.bodies[name]), name
        alone = {}
        for name in layout:
            for other, X in away.items():
                world.set_object_pose(other, layout[other] if other == name else X)
            _, seg = render_grey(world.cid, camera, segmentation=True)
            alone[name] = int(np.sum(seg == world.bodies[name]))
    finally:
        world.close()
    assert among == alone


def test_convex_gap_2d_on_hand_worked_cases() -> None:
    from models.geometry import convex_gap_2d

    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert convex_gap_2d(square, square + np.array([2.0, 0.0])) == pytest.approx(1.0)
    assert convex_gap_2d(square, square + np.array([2.0, 2.0])) == pytest.approx(np.sqrt(2.0))
    assert convex_gap_2d(square, square + np.array([0.5, 0.5])) == 0.0  # overlapping
    assert convex_gap_2d(np.array([[-1.0, 0.5], [2.0, 0.5]]), square) == 0.0  # a segment across
    assert convex_gap_2d(np.array([[-1.0, 1.5], [2.0, 1.5]]), square) == pytest.approx(0.5)
    assert convex_gap_2d(np.array([[0.5, 0.5]]), square) == 0.0  # a point inside
    assert convex_gap_2d(np.array([[3.0, 0.5]]), square) == pytest.approx(2.0)
    # The order the points come in does not matter: the hull is taken.
    assert convex_gap_2d(square[[0, 2, 1, 3]], square + np.array([2.0, 0.0])) == pytest.approx(1.0)
