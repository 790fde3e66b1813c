"""The operator's task: picking a block, dragging it, captures and reset, on a real simulator,
through the page's own callbacks (no browser)."""

from __future__ import annotations

import dataclasses
from html import unescape as shown  # the page's markdown escapes outside text

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import R_to_quat_wxyz, invert_pose, so3_log
from operator_site.link import WorkSiteLink
from operator_site.task import TaskSession
from operator_site.ui import NO_WORKPIECE, OperatorPage
from operator_site.ui.scene_view import FELT_RGB, GHOST_REDRAW_M, GHOST_RGBS
from protocol import Recognition, Recognitions, make_config
from tests.conftest import free_port, wait_until

CUBE_HALF = 0.025


def test_session_drags_the_selected_block_and_keeps_the_model() -> None:
    session = TaskSession(load_scene())
    assert session.step() is None  # nothing selected: nothing happens
    with pytest.raises(ValueError, match="select a workpiece first"):
        session.set_target(np.eye(4))
    with pytest.raises(ValueError, match="fixed environment"):
        session.select("frame")
    session.select("cube")
    start = session.X_WO["cube"].copy()
    target = start.copy()
    target[:3, 3] += [0.03, 0.0, -0.005]  # along the table, pressed onto it
    session.set_target(target)
    for _ in range(60):
        result = session.step()
    assert result.X_WO[0, 3] == pytest.approx(start[0, 3] + 0.03, abs=1e-4)
    assert {c.object for c in result.contacts} == {"table"}
    np.testing.assert_array_equal(session.X_WO["cube"], result.X_WO)
    # Another block: the cube stays where it was left, now an obstacle.
    session.select("plank")
    np.testing.assert_array_equal(session.X_WO["cube"], result.X_WO)
    assert session.workpiece == "plank"


def test_a_square_block_is_grasped_on_the_faces_whose_open_fingers_are_clear() -> None:
    from operator_site.grasp import GRASP_CLEARANCE_M, open_finger_clearance_m

    scene = load_scene()
    session = TaskSession(scene)
    session.select("cube")
    plain = session.X_GP.copy()  # nothing near the cube: fingers on its ±y faces, as always
    assert open_finger_clearance_m(session.robot, scene, "cube", session.X_WO, plain) > (
        GRASP_CLEARANCE_M
    )
    # The tall block 8 mm off the cube's +y face: inside the open fingers' reach (15 mm).
    X_cube = session.X_WO["cube"]
    beside = X_cube.copy()
    beside[:3, 3] += X_cube[:3, 1] * (CUBE_HALF + 0.008 + 0.025)
    beside[2, 3] = session.X_WO["tall_block"][2, 3]
    session.X_WO["tall_block"] = beside
    assert open_finger_clearance_m(session.robot, scene, "cube", session.X_WO, plain) <= 0.0
    session.select("cube")
    clearance = open_finger_clearance_m(session.robot, scene, "cube", session.X_WO, session.X_GP)
    assert clearance >= GRASP_CLEARANCE_M
    # The same grasp a quarter turn round: the fingers (G's y) now close along the cube's x,
    # the TCP where it was in the cube.
    X_OG, X_OG_plain = invert_pose(session.X_GP), invert_pose(plain)
    assert abs(X_OG[0, 1]) == pytest.approx(1.0) and abs(X_OG_plain[1, 1]) == pytest.approx(1.0)
    np.testing.assert_allclose(X_OG[:3, 3], X_OG_plain[:3, 3], atol=1e-12)


def test_capture_toggle_and_reset() -> None:
    session = TaskSession(load_scene())
    session.select("cube")
    with pytest.raises(ValueError, match="itself"):
        session.toggle_capture("cube")
    assert session.toggle_capture("table") is True
    assert session.captured == {"table"}
    start = session.X_WO["cube"].copy()
    target = start.copy()
    target[2, 3] += 0.05  # pull up: the captured table holds it
    session.set_target(target)
    for _ in range(20):
        session.step()
    assert session.X_WO["cube"][2, 3] - CUBE_HALF <= session.params.eps_capture_m
    assert session.toggle_capture("table") is False
    session.reset()
    np.testing.assert_array_equal(session.X_WO["cube"], start)


@pytest.fixture
def page():
    link = WorkSiteLink(make_config(connect=[f"tcp/127.0.0.1:{free_port()}"]), "task_test")
    page = OperatorPage(load_scene(), link, port=free_port())
    yield page
    page.close()
    link.close()


def test_every_block_is_labelled_and_coloured_its_own(page: OperatorPage) -> None:
    movable = [o.name for o in page.scene.movable]
    assert sorted(page.labels) == sorted(movable)
    assert page.labels["tall_block"].text == "tall block"
    colours = {tuple(page.object_meshes[n][0].color) for n in movable}
    assert len(colours) == len(movable)


def test_page_callbacks_pick_drag_capture_and_reset(page: OperatorPage) -> None:
    page.on_click_object("frame")  # fixed, no capture mode: nothing to pick
    assert page.session.workpiece is None and not page.dragger.visible
    page.on_click_object("cube")
    assert page.session.workpiece == "cube" and page.dragger.visible
    assert len(page.finger_meshes) == 2  # the gripper's fingers, shown where they will hold it
    assert page.workpiece_dropdown.value == "cube"
    start = page.session.X_WO["cube"].copy()
    np.testing.assert_allclose(page.dragger.position, start[:3, 3])
    # The operator drags the gizmo 4 cm along x and a little into the table.
    page.dragger.position = tuple(start[:3, 3] + [0.04, 0.0, -0.004])
    page.on_drag()
    for _ in range(60):
        page.step_task()
    moved = page.session.X_WO["cube"]
    assert moved[0, 3] == pytest.approx(start[0, 3] + 0.04, abs=1e-4)
    # viser skips updates closer than np.allclose's default tolerance (a few µm here).
    np.testing.assert_allclose(page.object_frames["cube"].position, moved[:3, 3], atol=1e-5)
    assert page.contact_points.visible and len(page.contact_points.points) == 4
    assert "touching: table (the robot can feel it)" in page.task_md.content
    assert np.all(np.asarray(page.contact_points.colors) == FELT_RGB)  # green: felt
    # Capture mode: a click on the table captures it, a second releases it.
    page.capture_mode.value = True
    page.on_click_object("table")
    assert page.session.captured == {"table"}
    page.on_click_object("table")
    assert page.session.captured == set()
    page.capture_mode.value = False
    page.on_reset()
    np.testing.assert_array_equal(page.session.X_WO["cube"], start)
    np.testing.assert_allclose(page.dragger.position, start[:3, 3])
    page.on_select(NO_WORKPIECE)
    assert not page.dragger.visible and not page.finger_meshes


def test_dragging_into_the_frame_corner_from_the_page(page: OperatorPage) -> None:
    page.on_select("cube")
    # Lift clear of the frame's 3 cm bars, carry it over, then press it into the corner.
    x0, y0 = page.session.X_WO["cube"][:2, 3]
    # And turn the gizmo (the table's axes) by the block's yaw back: square with the frame.
    page.dragger.wxyz = tuple(R_to_quat_wxyz(page.session.X_WO["cube"][:3, :3].T))
    for target in ((x0, y0, 0.08), (0.45, 0.0, 0.08), (0.36, -0.09, CUBE_HALF - 0.005)):
        page.dragger.position = target
        page.on_drag()
        for _ in range(100):
            page.step_task()
    X = page.session.X_WO["cube"]
    corner = np.array([0.35 + CUBE_HALF, -0.10 + CUBE_HALF, CUBE_HALF])
    gap = X[:3, 3] - corner
    params = page.session.params
    eps_b = params.eps_barrier_m
    # Held high, the fingers pass over the 30 mm bars: both walls and the table are met, the
    # barrier holding the block between the floor and ε_b from each, square to within that.
    distances = {c.object: c.distance_m for c in page.session.sim.state.contacts}
    assert distances.keys() == {"table", "frame"}
    assert all(params.floor_m < d <= eps_b for d in distances.values()), distances
    np.testing.assert_allclose(gap, [eps_b, eps_b, eps_b], atol=eps_b / 2)
    tilt_rad = np.linalg.norm(so3_log(X[:3, :3]))
    assert tilt_rad < 2 * eps_b / (2 * CUBE_HALF)


def test_a_ghost_moves_only_when_vision_moves_it_visibly(page: OperatorPage) -> None:
    """Tracking sends poses several times a second that differ by hundredths of a millimetre:
    a ghost is redrawn only for a move beyond GHOST_REDRAW_M (each redraw costs the browser a
    frame), at once for one beyond it."""
    X = page.scene.object("cube").X_WO.copy()

    def seen(seq: int, dx_m: float) -> np.ndarray:
        X_now = X.copy()
        X_now[0, 3] += dx_m
        page.link.recognitions = Recognitions(
            seq=seq, stamp_s=0.0, elapsed_s=0.01,
            objects=(Recognition(model="cube", X_WO=X_now, score=0.9),),
            tracked=seq > 1,
        )  # fmt: skip
        page.update()
        return np.asarray(page.ghosts["cube"][0].position)

    first = seen(1, 0.0)
    assert np.allclose(seen(2, 0.2 * GHOST_REDRAW_M), first)
    assert np.allclose(seen(3, 2 * GHOST_REDRAW_M), X[:3, 3] + [2 * GHOST_REDRAW_M, 0, 0])


def test_a_ghost_lost_for_a_frame_is_hidden_and_shown_again_not_sent_again(
    page: OperatorPage,
) -> None:
    """Vision misses a block in some frames: its ghost is hidden meanwhile and shown again
    where it is seen next, the same scene nodes (its meshes are not sent again)."""
    X = page.scene.object("cube").X_WO.copy()

    def seen(seq: int, objects: tuple) -> None:
        page.link.recognitions = Recognitions(
            seq=seq, stamp_s=0.0, elapsed_s=0.01, objects=objects
        )  # fmt: skip
        page.update()

    cube = (Recognition(model="cube", X_WO=X, score=0.9),)
    seen(1, cube)
    frame, meshes = page.ghosts["cube"]
    assert frame.visible
    seen(2, ())
    assert "cube" not in page.ghosts and not frame.visible
    X_now = X.copy()
    X_now[0, 3] += 0.01
    seen(3, (Recognition(model="cube", X_WO=X_now, score=0.9),))
    assert page.ghosts["cube"] == (frame, meshes) and frame.visible
    assert np.allclose(frame.position, X_now[:3, 3])


def test_accepting_recognitions_builds_a_consistent_model(page: OperatorPage) -> None:

    page.on_select(NO_WORKPIECE)
    for name in list(page.model.poses):
        page.on_remove(name)
    assert not page.object_frames["cube"].visible and page.object_frames["frame"].visible
    assert page.workpiece_dropdown.options == (NO_WORKPIECE,)
    assert page.on_accept_recognitions() == 0  # nothing recognised yet: says so
    assert "Nothing recognised yet" in page.model_md.content
    assert page.on_update_from_vision() == 0  # the update answers too, saying why not
    assert "nothing updated from vision" in page.model_md.content
    assert "Nothing recognised yet" in page.model_md.content
    scene = page.scene
    sunk = scene.object("cube").X_WO.copy()
    sunk[2, 3] -= 0.002  # vision put it 2 mm into the table
    page.link.recognitions = Recognitions(
        seq=7,
        stamp_s=0.0,
        elapsed_s=0.05,
        objects=(
            Recognition(
                model="cube", X_WO=sunk, score=0.9, frames=4, spread_m=3e-4, spread_rad=0.002
            ),
            Recognition(model="plank", X_WO=scene.object("plank").X_WO, score=0.8, rivals=1),
            Recognition(model="wedge", X_WO=scene.object("wedge").X_WO, score=0.2),  # too weak
        ),
    )
    page.update()
    # How sure vision is: the frames its pose fuses and their spread.
    assert (
        "cube: score 0.90, 4 frames within ±0.3 mm, ±0.1°, found by 1 search (not in the model)"
        in page.recognitions_md.content
    )
    assert (
        "plank: score 0.80, 1 frame, found by 1 search, also seen in 1 other place "
        "(not in the model)" in page.recognitions_md.content
    )
    assert set(page._rec_buttons) == {"cube", "plank", "wedge"}  # one "add" button each
    # What vision sees, see-through in the 3D view: blue, none of it is in the model yet.
    assert set(page.ghosts) == {"cube", "plank", "wedge"}
    assert {tuple(m.color) for _, ms in page.ghosts.values() for m in ms} == {GHOST_RGBS["new"]}
    assert page.on_accept_one("wedge")  # a click on one adds just that block
    assert set(page.model.poses) == {"wedge"} and set(page._rec_buttons) == {"cube", "plank"}
    page.on_remove("wedge")
    assert page.on_accept_recognitions() == 2
    assert set(page.model.poses) == {"cube", "plank"}
    assert page.object_frames["cube"].visible and not page.object_frames["wedge"].visible
    assert page.workpiece_dropdown.options == (NO_WORKPIECE, "cube", "plank")
    assert "cube: moved 2.1 mm" in page.model_md.content  # the correction, shown
    page.update()  # the ghosts recoloured: the model settled the cube 2.1 mm from vision's
    assert tuple(page.ghosts["cube"][1][0].color) == GHOST_RGBS["off"]
    assert tuple(page.ghosts["plank"][1][0].color) == GHOST_RGBS["agrees"]
    assert (
        "cube: score 0.90, 4 frames within ±0.3 mm, ±0.1°, found by 1 search (in the model, "
        "**a few mm off**)" in page.recognitions_md.content
    )
    assert page.session.X_WO["cube"][2, 3] == pytest.approx(
        CUBE_HALF + page.session.params.eps_barrier_m, abs=1e-5
    )
    page.on_select("cube")  # picked, then the model changes under it: nothing stays picked
    assert "dragging" in page.task_md.content
    assert page.on_accept_recognitions() == 2
    assert page.workpiece_dropdown.value == NO_WORKPIECE and not page.dragger.visible
    assert "dragging" not in page.task_md.content and "Pick a block" in page.task_md.content
    # Remove mode: a click in the 3D view takes a block out of the model.
    page.remove_mode.value = True
    page.on_click_object("plank")
    page.remove_mode.value = False
    assert set(page.model.poses) == {"cube"} and not page.object_frames["plank"].visible
    page.on_select("plank")  # no longer in the model: refused, with the reason
    assert page.session.workpiece is None and "no object 'plank'" in shown(page.message)


def test_the_stop_button_sends_a_stop(page: OperatorPage) -> None:
    from protocol import Stop, decode, key

    got = []
    sub = page.link.session.declare_subscriber(
        key(page.link.site_id, "stop"), lambda s: got.append(decode(s.payload.to_bytes(), Stop))
    )
    page.on_stop()
    assert wait_until(lambda: bool(got), 5.0)
    assert got[0].reason == "operator pressed stop"
    assert "stop sent" in page.program_md.content
    sub.undeclare()


def test_a_task_saved_and_loaded_comes_back(page: OperatorPage, tmp_path) -> None:
    page.on_select("cube")
    start = page.session.X_WO["cube"].copy()
    page.dragger.position = tuple(start[:3, 3] + [0.05, 0.02, -0.003])
    page.on_drag()
    for _ in range(60):
        page.step_task()
    end = page.session.X_WO["cube"].copy()
    path = tmp_path / "task.json"
    page.on_save(str(path))
    assert "saved to" in page.task_md.content and path.exists()
    page.on_reset()
    np.testing.assert_array_equal(page.session.X_WO["cube"], start)
    page.on_load(str(path))
    assert "loaded" in page.task_md.content and "(2 steps)" in page.task_md.content
    assert page.session.workpiece == "cube"
    # Dragged again target by target, each held until the block is within half a millimetre.
    np.testing.assert_allclose(page.session.X_WO["cube"][:3, 3], end[:3, 3], atol=0.6e-3)
    np.testing.assert_allclose(page.session.start_X_WO, start, atol=1e-12)
    # A bad file says what is wrong and changes nothing.
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    page.on_load(str(bad))
    assert "⚠" in page.task_md.content and "bad.json" in shown(page.task_md.content)
    assert page.session.workpiece == "cube"
    page.on_load(str(tmp_path / "missing.json"))
    assert "no such file" in page.task_md.content


def test_undo_takes_back_one_drag_at_a_time() -> None:
    session = TaskSession(load_scene())
    assert session.undo() is None  # nothing selected
    session.select("cube")
    assert session.undo() is None  # nothing dragged
    start = session.X_WO["cube"].copy()
    before, steps = [], []
    for dx in (-0.03, -0.06):
        before.append(session.sim.X_WO)
        steps.append(len(session.sim.history))
        session.mark()
        target = start.copy()
        target[0, 3] += dx
        session.set_target(target)
        for _ in range(100):
            session.step()
    assert session.X_WO["cube"][0, 3] == pytest.approx(start[0, 3] - 0.06, abs=1e-4)
    np.testing.assert_array_equal(session.undo(), before[1])
    np.testing.assert_array_equal(session.X_WO["cube"], before[1])
    assert len(session.sim.history) == steps[1] and len(session.path_history()) == steps[1] + 1
    session.step()  # the spring's target went back too: the block stays
    np.testing.assert_allclose(session.X_WO["cube"], before[1], atol=1e-6)
    np.testing.assert_array_equal(session.undo(), before[0])
    assert session.sim.history == [] and session.undo() is None


def test_page_undo_and_the_program_progress(page: OperatorPage, monkeypatch) -> None:
    page.on_click_object("cube")
    start = page.session.X_WO["cube"].copy()
    page.dragger.position = tuple(start[:3, 3] + [0.04, 0.0, -0.004])
    page.on_drag()
    for _ in range(60):
        page.step_task()
    seen: list[float] = []
    show = page._show_progress
    monkeypatch.setattr(page, "_show_progress", lambda f, stage: (seen.append(f), show(f, stage)))
    page.on_make_program()
    assert page.pending_program is not None
    assert seen == sorted(seen) and len(seen) == 5 and 0.0 < seen[0] and seen[-1] < 1.0
    assert "commands; path" in page.program_md.content  # the summary; the commands folded
    assert shown(page.commands_md.content).startswith("1\\. guarded_grasp to")
    assert not page.progress.visible
    page.on_undo()
    assert "undone" in page.task_md.content
    np.testing.assert_allclose(page.session.X_WO["cube"][:3, 3], start[:3, 3], atol=2e-4)
    np.testing.assert_allclose(page.dragger.position, page.session.sim.state.X_WD[:3, 3])
    page.on_undo()
    assert "nothing to undo" in page.task_md.content


def test_a_recovery_without_robot_state_says_why(page: OperatorPage) -> None:
    page.on_recover("retract")
    assert "back off" in page.program_md.content and "no robot state" in page.program_md.content


def test_resume_with_nothing_sent_says_so_and_a_loaded_program_is_resumed_by_its_id(
    page: OperatorPage, tmp_path
) -> None:
    from operator_site.session import save_program
    from tests.conftest import one_move_program

    page.on_resume()
    assert "no program sent or loaded" in page.program_md.content
    save_program(tmp_path / "p.msgpack", one_move_program("stopped-one"))
    page.on_load_program(str(tmp_path / "p.msgpack"))
    sent = []
    page.link.send_program = sent.append  # no work site here: what the page would send
    page.on_resume()
    (resumed,) = sent
    assert resumed.continues == "stopped-one" and resumed.program_id != "stopped-one"
    assert "resume" in page.program_md.content


def test_a_watcher_s_controls_are_disabled_but_stop(page: OperatorPage) -> None:
    page.link.status.work_site_alive = True
    page.link.status.holder = "someone-else"
    page._show_control()
    assert page.program_button.disabled and page.send_button.disabled
    assert all(b.disabled for b in page.recovery_buttons) and not page.stop_button.disabled
    assert "you watch" in shown(page._status_text())
    page.link.status.holder = page.link.operator_id
    page._show_control()
    assert not page.program_button.disabled and "control: **you**" in page._status_text()
    page.link.status.holder = ""


def test_the_gizmo_has_the_table_s_axes_snaps_nudges_and_takes_a_typed_pose(page) -> None:
    page.on_select("cube")
    start = page.session.X_WO["cube"].copy()  # yawed 15° in the scene file
    np.testing.assert_allclose(page.dragger.wxyz, (1.0, 0.0, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(page.pose_xyz.value, np.round(start[:3, 3] * 1e3, 2))
    page.own_axes_checkbox.value = True
    page._set_axes(True)  # what the checkbox's callback does for a person's click
    np.testing.assert_allclose(page.dragger.wxyz, R_to_quat_wxyz(start[:3, :3]), atol=1e-12)
    page._set_axes(False)
    # A drag of 12.3 mm along x ends 12 mm along: snapped to whole millimetres; the gizmo
    # jumps to the snapped pose when it is let go.
    at = np.array(page.dragger.position)
    step_x = np.array([0.012, 0.0, 0.0])
    page.dragger.position = tuple(at + np.array([0.0123, 0.0, 0.0]))
    page.on_drag("start")
    page.on_drag("update")
    page.on_drag("end")
    np.testing.assert_allclose(page.session.sim.state.X_WD[:3, 3], at + step_x, atol=1e-12)
    np.testing.assert_allclose(page.dragger.position, at + step_x, atol=1e-12)
    # A nudge: one millimetre, one undo step.
    page.on_nudge("+y")
    np.testing.assert_allclose(
        page.session.sim.state.X_WD[:3, 3], at + step_x + [0.0, 0.001, 0.0], atol=1e-12
    )
    page.on_nudge("↺z")
    yaw = np.degrees(np.arctan2(*page.session.sim.state.X_WD[1::-1, 0]))
    assert yaw == pytest.approx(20.0, abs=1e-9)
    # A typed pose, in millimetres and degrees in the table's frame.
    page.on_pose_typed((400.0, -50.0, 25.0), (0.0, 0.0, 30.0))
    np.testing.assert_allclose(page.session.sim.state.X_WD[:3, 3], [0.4, -0.05, 0.025])
    page.on_pose_typed((400.0, float("nan"), 25.0), (0.0, 0.0, 30.0))
    assert "six numbers" in page.task_md.content
    for _ in range(3):
        page.on_undo()  # the typed pose, the turn, the nudge
    np.testing.assert_allclose(page.session.sim.state.X_WD[:3, 3], at + step_x, atol=1e-12)


def test_the_camera_image_outlines_the_model_through_the_frame_s_calibration(page) -> None:
    from operator_site.ui.overlay import project_edges_px
    from protocol import CameraFrame

    cam = page.scene.camera
    # The camera stands 2 cm off the scene file's pose; each frame says where it is.
    X_WC = cam.X_WC.copy()
    X_WC[:3, 3] += [0.02, 0.0, 0.0]
    page.link.camera_frame = CameraFrame(
        seq=1, stamp_s=1.0, X_WC=X_WC, K=cam.K, dist=cam.dist,
        image=np.zeros((cam.height, cam.width), dtype=np.uint8),
    )  # fmt: skip
    out = page._camera_view()  # RGB
    cube = page.scene.object("cube")

    def midpoints_drawn(X_WC_drawn: np.ndarray) -> int:
        camera = dataclasses.replace(cam, X_WC=X_WC_drawn)
        edges = project_edges_px(cube.model, cube.X_WO, camera)
        mid = np.round(edges.mean(axis=1)).astype(int)
        return sum(out[v - 1 : v + 2, u - 1 : u + 2, 1].max() > 0 for u, v in mid)

    assert midpoints_drawn(X_WC) == 12  # every edge, through the frame's calibration
    assert midpoints_drawn(cam.X_WC) < 6  # not through the scene file's nominal pose


def test_after_a_program_the_page_offers_an_update_and_an_update_answers_it(page) -> None:
    from protocol import ExecutionReport, Recognition, Recognitions

    scene = page.scene

    def ended(pid: str, stamp_s: float) -> None:
        page.link.status.reports.append(
            ExecutionReport(program_id=pid, command_index=-1, status="done",
                            wrench_S=np.zeros(6), message="program complete", stamp_s=stamp_s,
                            seq=3)
        )  # fmt: skip

    def vision(seq: int, stamp_s: float, x_m: float) -> None:
        X_WO = scene.object("cube").X_WO.copy()
        X_WO[0, 3] += x_m
        page.link.recognitions = Recognitions(
            seq=seq, stamp_s=stamp_s, elapsed_s=0.05,
            objects=(Recognition(model="cube", X_WO=X_WO, score=0.9),),
        )  # fmt: skip

    ended("cube-1795000000-1", 1.0)
    vision(1, 0.5, 0.05)
    page._offer_update()  # vision has not looked since the program ended: nothing yet
    assert "vision sees" not in page.model_md.content
    vision(2, 2.0, 0.05)
    page._offer_update()
    assert "after cube #1, vision sees cube away from the model" in shown(page.model_md.content)
    assert page.on_update_from_vision() == 1
    ended("cube-1795000000-2", 3.0)
    assert page.on_update_from_vision() == 1  # before vision looked again: still an answer
    vision(3, 4.0, 0.0)
    page._offer_update()  # comes after the answer: it is not to replace it
    assert page.model_md.content.startswith("updated from vision:"), page.model_md.content


def test_a_block_seen_off_where_a_done_program_put_it_is_said_not_done(page) -> None:
    """ "done" says the commands were; the page says when vision sees the block elsewhere."""
    from protocol import (
        ExecutionReport,
        HeldBlock,
        MotionCommand,
        MotionProgram,
        Recognition,
        Recognitions,
    )

    page.link.send_program = lambda _program: None  # no work site here
    start = page.scene.object("wedge").X_WO
    goal = start.copy()
    goal[0, 3] += 0.1

    def sent_and_done(k: int) -> str:
        program = page.op.send(
            MotionProgram(
                program_id=f"wedge-1795000000-{k}",
                X_GP=np.eye(4),
                commands=(
                    MotionCommand("guarded_grasp", start, 0.05, 10.0, ()),
                    MotionCommand("release", goal, 0.0, 10.0, ()),
                ),
                holds=(HeldBlock("wedge", 0.1, 0.05, np.zeros(3)),),
            )
        )
        page.link.status.reports.append(
            ExecutionReport(program_id=program.program_id, command_index=-1, status="done",
                            wrench_S=np.zeros(6), message="program complete", stamp_s=k,
                            seq=3)
        )  # fmt: skip
        return program.program_id

    def vision(seq: int, X_WO: np.ndarray) -> None:
        page.link.recognitions = Recognitions(
            seq=seq, stamp_s=seq + 0.5, elapsed_s=0.05,
            objects=(Recognition(model="wedge", X_WO=X_WO, score=0.9),),
        )  # fmt: skip

    sent_and_done(1)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    turned = goal.copy()
    turned[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ goal[:3, :3]
    turned[1, 3] += 0.02
    vision(1, turned)
    page._offer_update()
    assert (
        "after wedge #1, vision sees the wedge 20.0 mm, 30.0° from where the program put it, not "
        "confirmed by another search: the task may not be done" in shown(page.model_md.content)
    )
    sent_and_done(2)
    vision(2, goal)  # where the program put it
    page._offer_update()
    assert "may not be done" not in page.model_md.content
    assert "after wedge #2" in shown(page.model_md.content)
