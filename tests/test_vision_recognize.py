"""Recognition on scenes rendered by the test: floors below the benchmark's goals, so the suite
stays fast and stable; the benchmark (`python -m bench vision`) measures the real figures."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from bench.vision_evaluate import score_scene
from models.scene import load_scene
from models.transforms import invert_pose, make_pose
from work_site.vision.model import Occluders, parts_in, planes_in, transform
from work_site.vision.pose_sets import Candidate, _verified_among, select
from work_site.vision.recognizer import Recognizer
from work_site.vision.verification import fit_and_verify, verify

N_SCENES = 6

pytestmark = pytest.mark.slow  # renders its scenes and builds the index: seconds


@pytest.fixture(scope="module")
def recognizer(tmp_path_factory) -> Recognizer:
    # One index per test session, shared by the vision test modules.
    path = tmp_path_factory.getbasetemp() / "vision-index-cache"
    path.mkdir(exist_ok=True)
    return Recognizer(cache_dir=path)


@pytest.fixture(scope="module")
def scenes():
    renderer = SceneRenderer(load_scene(), supersample=3)
    rng = np.random.default_rng(2024)
    try:
        out = []
        for _ in range(N_SCENES):
            image, truth = renderer.render(renderer.random_layout(rng))
            noisy = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
            out.append((noisy, truth))
        empty = {
            o.name: make_pose(None, [5.0 + k, 5.0, -1.0]) for k, o in enumerate(renderer.movable)
        }
        blank, _ = renderer.render(empty)
        return out, blank, renderer.scene.camera
    finally:
        renderer.close()


def test_recall_and_precision_floors(recognizer, scenes) -> None:
    data, _, camera = scenes
    models = {m.name: m for m in recognizer.models}
    n_vis = hits = tp = fp = 0
    errors = []
    for image, truth in data:
        found = recognizer.recognize(image, camera)
        assert all(0.0 <= r.score <= 1.0 for r in found)
        sc = score_scene([(r.model, r.X_WO) for r in found], truth, models, camera)
        tp += len(sc.matches)
        fp += len(sc.false_positives)
        matched = {id(t) for t, _ in sc.matches}
        for t in truth:
            if t.visible_fraction >= 0.7:
                n_vis += 1
                hits += id(t) in matched
        errors.extend(e for _, e in sc.matches)
    assert n_vis >= 20
    assert hits / n_vis >= 0.65, f"recall {hits}/{n_vis}"
    assert tp / (tp + fp) >= 0.95, f"precision {tp}/{tp + fp}"
    assert np.median([e.reprojection_px for e in errors]) < 1.0
    assert np.median([e.lateral_m for e in errors]) < 0.002
    assert np.median([np.rad2deg(e.rotation_rad) for e in errors]) < 2.0


def test_an_empty_work_site_gives_nothing(recognizer, scenes) -> None:
    _, blank, camera = scenes
    assert recognizer.recognize(blank, camera) == []


@pytest.mark.parametrize(
    "image",
    [np.zeros((480, 640), np.uint8), np.full((480, 640), 255, np.uint8)],
    ids=["black", "white"],
)
def test_featureless_images_give_nothing(recognizer, scenes, image) -> None:
    assert recognizer.recognize(image, scenes[2]) == []


def test_bad_inputs_raise_clear_errors(recognizer, scenes) -> None:
    import dataclasses

    camera = scenes[2]
    with pytest.raises(ValueError, match="camera is 640×480"):
        recognizer.recognize(np.zeros((1, 1), np.uint8), camera)
    singular = dataclasses.replace(camera, K=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="singular"):
        recognizer.recognize(np.zeros((480, 640), np.uint8), singular)
    with pytest.raises(ValueError, match="8-bit"):
        recognizer.recognize(np.zeros((480, 640), np.float64), camera)


@pytest.fixture(scope="module")
def stacks():
    """A cube on a plank and a hexagonal prism on a tall block: the image, the poses, the
    camera."""
    renderer = SceneRenderer(load_scene(), supersample=3)
    try:
        V = {o.name: np.vstack([pt.vertices_O for pt in o.model.parts]) for o in renderer.movable}
        poses = {
            o.name: make_pose(None, [5.0 + k, 5.0, -1.0]) for k, o in enumerate(renderer.movable)
        }

        def on(name: str, yaw: float, xy, base_z: float) -> float:
            c, s = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            z = base_z - np.min(V[name] @ R[2])
            poses[name] = make_pose(R, [xy[0], xy[1], z])
            return base_z + np.ptp(V[name] @ R[2])  # its top

        top = on("plank", 0.3, (0.62, -0.18), renderer.table_z)
        on("cube", 0.7, (0.62, -0.18), top)
        top = on("tall_block", -0.2, (0.27, 0.17), renderer.table_z)
        on("hex_prism", 0.4, (0.27, 0.17), top)
        image, truth = renderer.render(poses)
        image = np.clip(image + np.random.default_rng(7).normal(0, 1.0, image.shape), 0, 255)
        camera = renderer.scene.camera
    finally:
        renderer.close()
    assert {t.model: t.support for t in truth if t.support} == {
        "plank": "table", "cube": "stacked", "tall_block": "table", "hex_prism": "stacked",
    }  # fmt: skip
    return image.astype(np.uint8), poses, camera


@pytest.mark.parametrize(
    "search",
    [{}, {"free_search": False}, {"stacked_search": False}],
    ids=["both", "stacked-alone", "free-alone"],
)
def test_blocks_stacked_on_blocks_are_found_where_they_are(recognizer, stacks, search) -> None:
    """No block of the stack rests on the table but the lowest: each is found, held up by the
    one under it, by either search for blocks off the table: junctions on the found blocks'
    top faces, or the fit without the table prior."""
    image, poses, camera = stacks
    rec = recognizer.with_params(dataclasses.replace(recognizer.params, **search))
    found = {r.model: r for r in rec.recognize(image, camera)}
    for name in ("cube", "hex_prism"):
        assert name in found, f"{name} on its stack not found: {sorted(found)}"
        off = found[name].X_WO[:3, 3] - poses[name][:3, 3]
        ray = poses[name][:3, 3] - camera.X_WC[:3, 3]
        ray /= np.linalg.norm(ray)
        along = abs(off @ ray)
        across = np.linalg.norm(off - (off @ ray) * ray)
        # Across the ray one view is sharp. Along it, without the table to rest on, a tenth
        # of a pixel of edge position is millimetres: within the tolerance by which a block
        # is taken to rest on its support (the model editor then settles it there).
        assert across < 0.0005, f"{name} found {1000 * across:.2f} mm off across the ray"
        assert along < recognizer.params.table_tol_m, f"{name}: {1000 * along:.1f} mm along it"


def test_the_arm_in_view_is_set_aside_when_vision_knows_its_joints(recognizer) -> None:
    """The gripper lowered into the frame: told the joint angles, vision explains the arm's
    lines by the arm and finds only the cube beside it."""
    from models.kinematics import ik_tcp
    from models.robot import load_robot

    renderer = SceneRenderer(load_scene(), supersample=3)
    try:
        placement = renderer.scene.robot
        robot = load_robot(placement.urdf_path)
        X_WG = make_pose(np.diag([1.0, -1.0, -1.0]), [0.45, -0.05, 0.08])  # pointing down
        ik = ik_tcp(X_WG, placement.q_home_rad, robot, placement.X_WB)
        assert ik.ok, ik.reason
        poses = {
            o.name: make_pose(None, [5.0 + k, 5.0, -1.0]) for k, o in enumerate(renderer.movable)
        }
        V = np.vstack([pt.vertices_O for pt in renderer.scene.object("cube").model.parts])
        poses["cube"] = make_pose(None, [0.62, -0.2, -V[:, 2].min()])
        renderer.world.set_robot_joint_positions(ik.q, np.array([0.02, 0.02]))
        image, _ = renderer.render(poses)
        camera = renderer.scene.camera
    finally:
        renderer.close()
    image = np.clip(image + np.random.default_rng(1).normal(0, 1.0, image.shape), 0, 255)
    image = image.astype(np.uint8)
    # The first pass's lines, from which hypotheses come (the faint pass's only weigh them).
    lines_all = recognizer._frame(image, camera).strong
    lines_left = recognizer._frame(image, camera, recognizer.robot.at(ik.q, 0.04)).strong
    assert len(lines_left) < 0.7 * len(lines_all), "the arm's lines should be set aside"
    found = recognizer.recognize(image, camera, ik.q, 0.04)
    assert [r.model for r in found] == ["cube"], [(r.model, r.score) for r in found]
    with pytest.raises(ValueError, match="6 finite angles"):
        recognizer.recognize(image, camera, np.zeros(5))


def test_the_selection_reuses_a_verification_only_where_nothing_changed(recognizer, scenes):
    """A candidate's own verification stands in the selection when no other candidate can
    hide it and the lines are the same; otherwise it is verified again, as it would be."""
    data, _, camera = scenes
    image, _ = data[0]
    found = recognizer.recognize(image, camera)
    assert found
    f = recognizer._frame(image, camera)
    p = recognizer.params
    model = next(m for m in recognizer.models if m.name == found[0].model)
    X_CO = invert_pose(f.X_WC) @ found[0].X_WO
    v = verify(model, X_CO, f.K, f.strong, f.gx, f.gy, f.occluders_C, p)
    c = Candidate(model, X_CO, found[0].X_WO, 0.0, v, [], None, True, f.strong)

    def fresh(segs, others):
        return verify(model, X_CO, f.K, segs, f.gx, f.gy, f.occluders_C + others, p)

    far = Occluders.joined([])
    assert _verified_among(c, f.strong.copy(), f.K, f.gx, f.gy, f.occluders_C, far, p) is v
    assert fresh(f.strong, far) == v
    # The same block moved halfway towards the camera covers it: verified again.
    X_near = X_CO.copy()
    X_near[:3, 3] *= 0.5
    cover = Occluders.of_parts(
        [transform(X_near, V) for V in model.parts_vertices_O],
        [planes_in(X_near, P) for P in model.planes_O],
        f.K,
    )
    again = _verified_among(c, f.strong, f.K, f.gx, f.gy, f.occluders_C, cover, p)
    assert again is not v and again == fresh(f.strong, cover)
    assert again.length_fraction < v.length_fraction
    # More lines (the faint pass's): verified again.
    more = np.vstack([f.strong, f.strong[:1] + 0.5])
    assert _verified_among(c, more, f.K, f.gx, f.gy, f.occluders_C, far, p) is not v


def test_a_block_is_held_up_by_something_hidden_only_when_the_table_cannot_hold_it(
    recognizer, scenes
) -> None:
    """A block that nothing found holds up, verified at ``hidden_support_min_score``, is kept
    (what holds it is hidden), unless another pose of it, sharing its lines, rests on the
    table: then that one, unless its lines reject the table."""
    data, _, camera = scenes
    p = recognizer.params
    models = {m.name: m for m in recognizer.models}

    def well_verified():  # a block found on the table, verified alone at the score
        for image, _ in data:
            f = recognizer._frame(image, camera)
            for r in recognizer.recognize(image, camera):
                X_CO = invert_pose(f.X_WC) @ r.X_WO
                m = models[r.model]
                v = verify(m, X_CO, f.K, f.segs, f.gx, f.gy, f.occluders_C, p)  # as selected
                if r.resting and v.score >= p.hidden_support_min_score:
                    return f, m, X_CO, v
        raise AssertionError("no block on the table verified at hidden_support_min_score")

    f, model, X_CO, v = well_verified()

    def candidate(X_CO: np.ndarray, v, resting: bool) -> Candidate:
        X_WO = f.X_WC @ X_CO
        return Candidate(model, X_CO, X_WO, 0.0, v, parts_in(X_WO, model), None, resting, f.segs)

    on_table = candidate(X_CO, v, True)
    # The same lines explained 15 mm nearer the camera, along the block's ray: in the air, and
    # (as given here) a little more of the image explained.
    X_up = X_CO.copy()
    X_up[:3, 3] *= 1 - 0.015 / np.linalg.norm(X_CO[:3, 3])
    assert (f.X_WC @ X_up)[2, 3] > (f.X_WC @ X_CO)[2, 3] + 0.005
    in_air = candidate(X_up, dataclasses.replace(v, covered_px=v.covered_px + 1.0), False)
    args = (f.segs, f.K, f.gx, f.gy, f.occluders_C, p, recognizer.surroundings,
            recognizer.max_height_m)  # fmt: skip
    alone = select([in_air], *args)
    assert [r.X_WO[2, 3] for r in alone] == [in_air.X_WO[2, 3]]
    both = select([in_air, on_table], *args)
    assert [r.X_WO[2, 3] for r in both] == [on_table.X_WO[2, 3]]
    rejected = dataclasses.replace(on_table, off_table=True)
    assert [r.X_WO[2, 3] for r in select([rejected, in_air], *args)] == [in_air.X_WO[2, 3]]


def test_the_lines_reject_the_table_under_a_stacked_block_and_not_under_the_one_below(
    recognizer, stacks
) -> None:
    """The cube on the plank, put on the table along its ray by the fit with the table prior:
    its lines reject that (the fit without the prior explains them far better than noise
    allows); the plank, which does rest on the table, is not rejected there."""
    image, poses, camera = stacks
    f = recognizer._frame(image, camera)
    p = recognizer.params
    X_CW = invert_pose(f.X_WC)
    models = {m.name: m for m in recognizer.models}
    cube = models["cube"]
    X_CO = X_CW @ poses["cube"]
    plank_m = np.ptp(models["plank"].vertices_O[:, 2])
    X_far = X_CO.copy()  # the plank's height further along the ray: the prior does the rest
    X_far[:3, 3] *= 1 + plank_m / np.linalg.norm(X_CO[:3, 3])
    table = fit_and_verify(
        cube, X_far, f.strong, f.K, f.gx, f.gy, f.occluders_C, p,
        recognizer._prior(cube, f.X_WC),
    )  # fmt: skip
    assert table is not None
    X_table_CO = table[0]
    lowest_m = transform(f.X_WC @ X_table_CO, cube.vertices_O)[:, 2].min()
    assert abs(lowest_m - recognizer.table_z) < p.table_tol_m  # the prior's work
    assert recognizer._table_rejected(cube, X_CO, X_table_CO, f)
    plank = models["plank"]
    X_plank_CO = X_CW @ poses["plank"]
    free = fit_and_verify(plank, X_plank_CO, f.strong, f.K, f.gx, f.gy, f.occluders_C, p)
    assert free is not None
    assert not recognizer._table_rejected(plank, free[0], X_plank_CO, f)
    # With the table prior off there is no table hypothesis to reject (the vision bench's
    # sweep runs so): the search goes on without the test.
    no_prior = recognizer.with_params(dataclasses.replace(p, table_prior=False))
    assert not no_prior._table_rejected(cube, X_CO, X_table_CO, f)
    assert no_prior.recognize(image, camera)


BLOCK_FOUND_M = 0.005
"""A block found where it is: within this of its true centre."""
SWAPPED_M = 0.1
"""The L and the tall block of the task bench's layout 4 stand 16 cm apart: an L found within
this of the tall block's centre took its place."""


def test_a_model_grown_around_a_block_does_not_take_that_block_s_place(recognizer) -> None:
    """A tall block beside an L: an L grown around the tall block (its bar) explained the tall
    block's lines first, and the true L was then taken for a tall block (the two swapped,
    16 cm apart). The selection without the grown L explains more of the image's lines, and
    stands."""
    from models.layout import laid_out, random_layout
    from models.robot import HOME_Q
    from work_site.camera import render_grey
    from work_site.options import DEFAULT_CAMERA_SENSOR
    from work_site.world import World

    scene = load_scene()
    scene = laid_out(scene, random_layout(scene, 4))  # the task bench's layout 4
    world = World(scene)
    try:
        ideal = render_grey(world.cid, scene.camera, 2)  # as the work site's camera
    finally:
        world.close()
    truth = {o.name: o.X_WO[:3, 3] for o in scene.movable}
    for seed in (0, 2, 4):  # each swapped the two before
        image = DEFAULT_CAMERA_SENSOR.apply(ideal, np.random.default_rng(seed))
        found = {r.model: r for r in recognizer.recognize(image, scene.camera, np.array(HOME_Q))}
        assert {"l_block", "tall_block"} <= set(found), (seed, sorted(found))
        tall, ell = (found[n].X_WO[:3, 3] for n in ("tall_block", "l_block"))
        assert np.linalg.norm(tall - truth["tall_block"]) < BLOCK_FOUND_M, seed
        assert np.linalg.norm(ell - truth["tall_block"]) > SWAPPED_M, seed
        if seed == 0:
            # (At the others the L itself is found about 2 cm off, outscoring its true pose:
            # another fault, not this one.)
            assert np.linalg.norm(ell - truth["l_block"]) < BLOCK_FOUND_M
