"""The page in a real browser: Debian's headless Chromium, driven by Playwright, against a real
operator site connected to a real work site on loopback."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bench.ui import CHROMIUM, chromium_flags
from tests.conftest import LOG_TAIL_CHARS, REPO, free_port, stop_like_ctrl_c, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.integration]

SCREENSHOT_DIR = REPO / "out" / "screenshots"


def write_cube_task(path: Path) -> None:
    """A task file: on the scene file's layout, the cube dragged 6 cm along the table, saved
    as the page saves it (an operator session's recorded task)."""
    from models.scene import load_scene
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


def test_page_shows_scene_camera_and_connected_status(tmp_path: Path) -> None:
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
    playwright = pytest.importorskip("playwright.sync_api")
    http_port, zenoh_port = free_port(), free_port()
    log_path = tmp_path / "demo.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "operator_site",
                "demo",
                "--port",
                str(http_port),
                "--connect",
                f"tcp/127.0.0.1:{zenoh_port}",
                "--site-id",
                "browser",
            ],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    try:
        assert wait_until(lambda: "open http://" in log_path.read_text(), 60), log_path.read_text()
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=chromium_flags())
            try:
                page = browser.new_page(viewport={"width": 1400, "height": 900})
                page.goto(f"http://127.0.0.1:{http_port}/")
                page.get_by_text("work site: connected").wait_for(timeout=60_000)
                # The 3D view is a WebGL canvas filling most of the page.
                canvas = page.locator("canvas").first
                canvas.wait_for(timeout=30_000)
                box = canvas.bounding_box()
                assert box is not None and box["width"] > 600 and box["height"] > 400
                # The live camera image: a decoded 640×480 picture in the panel.
                page.get_by_text("last camera frame").wait_for(timeout=30_000)
                # viser shows GUI images as blob: URLs (its logos are inline SVG data); the
                # placeholder is half size, so 640×480 is a frame from the work site.
                image = page.locator('img[src^="blob:"]').first
                image.wait_for(timeout=30_000)
                size = "i => [i.naturalWidth, i.naturalHeight]"
                assert wait_until(lambda: image.evaluate(size) == [640, 480], 20)
                assert page.get_by_text("robot state").count() >= 1
                SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
                shot = tmp_path / "operator_page.png"
                page.screenshot(path=str(shot))
                shutil.copy(shot, SCREENSHOT_DIR / shot.name)
                assert shot.stat().st_size > 10_000
                # The demo's page starts with an empty model; the work site's vision lists
                # what it recognised; accepting builds the model.
                page.get_by_text("score").first.wait_for(timeout=120_000)
                page.get_by_role("button", name="accept the recognised blocks").click()
                page.get_by_text(re.compile(r"^model: [1-6] blocks")).wait_for(timeout=30_000)
                # A task saved by the same page code (the cube dragged 6 cm along the table),
                # loaded from a path typed into the page.
                task_file = tmp_path / "cube_task.json"
                write_cube_task(task_file)
                field = page.locator('input[value="task.json"]').first
                field.fill(str(task_file))
                page.keyboard.press("Enter")
                page.get_by_role("button", name="load a task").click()
                try:
                    page.get_by_text("cube 6 cm along the table").wait_for(timeout=30_000)
                finally:
                    page.screenshot(path=str(SCREENSHOT_DIR / "operator_page_task_loaded.png"))
                # Making and running a program from the page: tests/test_browser_ui.py.
                assert page.get_by_role("button", name="STOP the robot").is_visible()
            finally:
                browser.close()
    except BaseException:
        # What the two sites said is what explains a page that never got there.
        print(f"--- {log_path} ---\n{log_path.read_text()[-LOG_TAIL_CHARS:]}")
        raise
    finally:
        stop_like_ctrl_c(proc, log_path=log_path)
    assert "work site stopped (exit code 0)" in log_path.read_text()
