"""A first task in the page as a person does it, in Debian's headless Chromium against a real
work site with vision on loopback (:func:`bench.ui.first_task`: recognitions, accept, pick the
cube with a click, look from above, drag the gizmo's arrow with the mouse, make the program,
send, "done", update the model from vision), what the page must show on the way, and after it
its answers to saving and loading tasks and the live camera image."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from bench.ui import CHROMIUM, chromium_tab, first_task, page_for
from models.scene import load_scene
from operator_site.ui import NO_WORKPIECE
from operator_site.ui.scene_view import GIZMO_PX
from tests.conftest import REPO, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.integration]

SHIFT_M = -0.04
"""The drag: the cube 4 cm along the table towards the robot."""


def write_cube_task(path: Path) -> None:
    """A task file: on the scene file's layout, the cube dragged 6 cm along the table, saved
    as the page saves it (an operator session's recorded task)."""
    from operator_site.session import OperatorSession
    from operator_site.taskfile import save_task

    op = OperatorSession(load_scene())
    op.use_scene_layout()
    op.select("cube")
    target = op.task.X_WO["cube"].copy()
    target[:3, 3] += [-0.06, 0.0, -0.003]
    op.set_target(target)
    for _ in range(60):
        op.step()
    save_task(op.recorded_task("cube 6 cm along the table"), path)


def test_a_first_task_as_a_person_does_it(work_site, tmp_path: Path) -> None:
    if not os.access(CHROMIUM, os.X_OK):
        print(f"skipping: {CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
        pytest.skip(f"{CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
    playwright = pytest.importorskip("playwright.sync_api")
    # This test is the page's; the dead-man's timing is tested on its own (test_net_deadman).
    # Chromium drawing in software beside another test's whole chain on two cores has left the
    # work site's receiving thread unscheduled for longer than the default 0.5 s: a stop.
    ws = work_site("--deadman-s", "1.0", vision=True)
    with page_for(ws) as page, playwright.sync_playwright() as pw, chromium_tab(pw, page) as tab:
        try:
            timings = first_task(tab, page, REPO / "out" / "screenshots", shift_m=SHIFT_M,
                                 gizmo_px=GIZMO_PX)  # fmt: skip
        finally:
            tab.screenshot(path=str(tmp_path / "last.png"))
        if not timings.marks["outcome"].endswith(": done"):
            # The work site's log says why (a failure's assertion message is cut short).
            print(f"marks: {timings.marks}\nthe work site's log, last lines:\n{ws.log()[-4000:]}")
        assert timings.marks["outcome"].endswith(": done"), timings.marks["outcome"]
        # Each block accepted into the model is named in the 3D view.
        assert timings.marks["labels_shown"] == timings.marks["blocks_accepted"] > 0
        # The drag moved the target a whole number of millimetres (snapping) along the table's x
        # (the gizmo's red arrow is the table's x, whatever the cube's own frame).
        moved_mm = timings.marks["moved_m"] * 1e3
        assert moved_mm == pytest.approx(round(moved_mm), abs=1e-6) and moved_mm < -10.0
        # The log was in view right after the send, without scrolling.
        assert timings.marks["log_in_view"] == 1.0
        # What vision saw was drawn in 3D; after the update the model has the cube where the robot
        # put it, and nothing is left picked from before.
        assert page.ghosts
        assert page.workpiece_dropdown.value == NO_WORKPIECE
        assert "dragging" not in page.task_md.content
        placed = page.model.poses["cube"][:3, 3]
        start = load_scene().object("cube").X_WO[:3, 3]
        expected = start[:2] + np.array([moved_mm * 1e-3, 0.0])
        assert np.linalg.norm(placed[:2] - expected) < 5e-3, placed
        # Then saving and loading: bad paths are said, not swallowed (saving where nothing can
        # be written, loading a file that is not there). The path field is held on to: its
        # value is what finds it, and that changes.
        field = tab.locator('input[value="task.json"]').first.element_handle()
        field.fill("/proc/no-such-dir/task.json")
        tab.keyboard.press("Enter")
        tab.get_by_role("button", name="save the task").click()
        said = tab.get_by_text("nothing saved").or_(tab.get_by_text("could not save"))
        said.first.wait_for(timeout=30_000)
        tab.get_by_role("button", name="load a task").click()
        tab.get_by_text("no such file").first.wait_for(timeout=30_000)
        # A task saved by the same page code, loaded from a path typed into the page.
        task_file = tmp_path / "cube_task.json"
        write_cube_task(task_file)
        field.fill(str(task_file))
        tab.keyboard.press("Enter")
        tab.get_by_role("button", name="load a task").click()
        tab.get_by_text("cube 6 cm along the table").first.wait_for(timeout=30_000)
        # The live camera image: viser shows GUI images as blob: URLs (its logos are inline
        # SVG data), and its placeholder is half size: 640×480 is a frame from the work site.
        image = tab.locator('img[src^="blob:"]').first
        size = "i => [i.naturalWidth, i.naturalHeight]"
        assert wait_until(lambda: image.evaluate(size) == [640, 480], 20)
