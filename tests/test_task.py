"""The operator's task: picking a block, dragging it, captures and reset, on a real simulator,
through the page's own callbacks (no browser)."""

from __future__ import annotations

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import make_pose
from operator_site.link import WorkSiteLink
from operator_site.task import TaskSession
from operator_site.ui import NO_WORKPIECE, OperatorPage
from protocol import make_config
from tests.conftest import free_port

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
    assert "touching: table" in page.task_md.content
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
    page.dragger.wxyz = (1.0, 0.0, 0.0, 0.0)  # and turn the gizmo square with the frame
    for target in ((x0, y0, 0.08), (0.45, 0.0, 0.08), (0.36, -0.09, CUBE_HALF - 0.005)):
        page.dragger.position = target
        page.on_drag()
        for _ in range(100):
            page.step_task()
    X = page.session.X_WO["cube"]
    corner = np.array([0.35 + CUBE_HALF, -0.10 + CUBE_HALF, CUBE_HALF])
    gap = X[:3, 3] - corner
    eps_b = page.session.params.eps_barrier_m
    # Held at mid-height, the fingers are on the cube's ±y faces: the one facing the y wall
    # keeps it a finger (15 mm) away, while the x wall and the table are met at ε_b.
    np.testing.assert_allclose(gap, [eps_b, 0.015 + eps_b, eps_b], atol=1e-6)
    np.testing.assert_allclose(X[:3, :3], make_pose()[:3, :3], atol=1e-6)
