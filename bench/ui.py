"""``python -m bench ui``: a first task done in the operator's page as a person would do it, in
Debian's headless Chromium against a real work site on loopback, timed step by step.

The steps (each screenshotted into ``--out``): the page loads; vision's recognitions arrive;
the operator accepts them; picks the cube; drags it along the table with the gizmo (mouse events
on the gizmo's arrow in the 3D view, not a back door); makes the program; sends it; the robot
does it ("done" in the log); the page offers the model brought up to date from vision, and the
operator takes it. The times: ``vision_wait_s`` (page loaded to the first recognitions),
``operator_s`` (the operator's clicks and drag, as scripted), ``program_s`` (making the
program), ``robot_s`` (sent to done), ``page_s`` (everything but vision and the robot).

The flow is :func:`first_task`, which the browser test runs too (``tests/test_browser_ui.py``).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from models.transforms import quat_wxyz_to_R
from operator_site.ui.access import check_view_dpr, page_url
from operator_site.ui.scene_view import block_label, view_from_above_W

VIEWPORT = {"width": 1400, "height": 900}
GRIP_FRACTIONS = (0.9, 0.85, 0.95, 0.8)
"""Where along a gizmo arrow (a fraction of its length, from the block) the mouse grips it,
in the order tried: its cone, beyond the rotation rings that cross the shafts."""
GRIP_CLEAR_PX = 6.0
"""A grip point this close to another object's outline on the screen is not used: the click
would go to that object."""
DRAG_STEPS = 12
"""Mouse moves in one drag (the gizmo follows pointer moves, not jumps)."""


@dataclass
class Timings:
    """What each part of the first task took, in seconds (see the module docstring)."""

    marks: dict[str, float] = field(default_factory=dict)
    parts: dict[str, float] = field(default_factory=dict)

    def add(self, part: str, seconds: float) -> None:
        self.parts[part] = self.parts.get(part, 0.0) + seconds


def project_px(camera, box: dict, p_W: np.ndarray) -> tuple[float, float]:
    """Where the page's 3D view shows world point ``p_W``: page pixels (x right, y down), from
    the client's camera (viser's: OpenCV axes, vertical ``fov``) and the canvas's box."""
    R_WC = quat_wxyz_to_R(np.asarray(camera.wxyz))
    p_C = R_WC.T @ (np.asarray(p_W, dtype=np.float64) - np.asarray(camera.position))
    f_px = (box["height"] / 2) / math.tan(camera.fov / 2)
    return (
        box["x"] + box["width"] / 2 + f_px * p_C[0] / p_C[2],
        box["y"] + box["height"] / 2 + f_px * p_C[1] / p_C[2],
    )


def outlines_px(page, camera, box: dict, skip: set[str]) -> list[np.ndarray]:
    """The screen outlines (convex hulls of their projected corners) of the objects in the
    page's 3D view that take clicks, except ``skip`` and the table (under everything)."""
    hulls = []
    for obj in page.scene.objects:
        if obj.name in skip or obj.name == "table" or not page.object_frames[obj.name].visible:
            continue
        X = page.session.X_WO.get(obj.name, obj.X_WO)
        corners_O = obj.model.feature_edges_O.reshape(-1, 3)
        pts = np.array([project_px(camera, box, X[:3, :3] @ c + X[:3, 3]) for c in corners_O])
        hulls.append(cv2.convexHull(pts.astype(np.float32)))
    return hulls


def gizmo_grip_px(page, camera, box: dict, axis: int, gizmo_px: float) -> tuple[float, float]:
    """A point on the gizmo's ``axis`` arrow (0, 1, 2: the table's x, y, z) that no other
    object's outline covers, in page pixels; ValueError when every candidate is covered."""
    p0 = np.asarray(page.dragger.position, dtype=np.float64)
    R_WG = quat_wxyz_to_R(np.asarray(page.dragger.wxyz))
    depth_m = float(np.linalg.norm(p0 - np.asarray(camera.position)))
    # The gizmo keeps its size in pixels: its arrow is gizmo_px long seen square-on.
    length_m = gizmo_px * 2 * depth_m * math.tan(camera.fov / 2) / box["height"]
    hulls = outlines_px(page, camera, box, {page.session.workpiece})
    for fraction in GRIP_FRACTIONS:
        u, v = project_px(camera, box, p0 + R_WG[:, axis] * fraction * length_m)
        clear = all(cv2.pointPolygonTest(h, (u, v), True) < -GRIP_CLEAR_PX for h in hulls)
        inside = box["x"] < u < box["x"] + box["width"] and box["y"] < v < box["y"] + box["height"]
        if clear and inside:
            return u, v
    raise ValueError(f"the gizmo's axis {axis} is covered by other objects on the screen")


def settled_camera(
    client,
    after: float = 0.0,
    timeout_s: float = 20.0,
    still_s: float = 0.5,
    expected: tuple[np.ndarray, np.ndarray] | None = None,
):
    """The client's camera once it has stopped changing: the browser reports its view on every
    change, so once its last report, made after ``after`` (a ``time.time()``: a view asked of
    the page then is not taken from the reports before it), is ``still_s`` old; or, given the
    view asked (``expected``: eye and look-at point in W), once it reports that view (the
    page's views are set at once, without a transition)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        reported = client.camera.update_timestamp  # viser stamps by time.time
        if reported > after:
            if expected is not None:
                camera = client.camera
                eye, look_at = (np.asarray(x, dtype=np.float64) for x in expected)
                if (
                    np.linalg.norm(np.asarray(camera.position) - eye) <= VIEW_MATCH_M
                    and np.linalg.norm(np.asarray(camera.look_at) - look_at) <= VIEW_MATCH_M
                ):
                    return camera
            elif time.time() - reported >= still_s:
                return client.camera
        time.sleep(0.02)
    raise TimeoutError(f"the page's camera kept moving or was not reported for {timeout_s:g} s")


NEXT_FRAME_DRAWN_JS = (
    "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
)
"""Resolves once the browser has drawn a frame after the call (the second animation frame
starts after the first one's drawing)."""
VIEW_MATCH_M = 1e-4
"""A reported camera is the view asked when its eye and look-at point are this close to it
(the browser reports them in float32: about 1e-7 m here)."""


def drag_gizmo(
    tab,
    page,
    axis: int,
    shift_m: float,
    gizmo_px: float,
    view_asked: float = 0.0,
    view: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, float]:
    """Drag the gizmo's ``axis`` arrow with the mouse so that the block's target moves about
    ``shift_m`` along it, in the view the browser reports after ``view_asked`` (a
    ``time.time()``; ``view``: the view asked then, see :func:`settled_camera`); how long (s)
    the view took to settle first and the mouse took."""
    client = next(iter(page.server.get_clients().values()))
    start = time.monotonic()
    camera = settled_camera(client, after=view_asked, expected=view)
    # The gizmo keeps its size on the screen by scaling itself as each frame is drawn: the
    # view reported is the one to aim in once a frame has been drawn with it.
    tab.evaluate(NEXT_FRAME_DRAWN_JS)
    settled = time.monotonic()
    box = tab.locator("canvas").first.bounding_box()
    u, v = gizmo_grip_px(page, camera, box, axis, gizmo_px)
    p0 = np.asarray(page.dragger.position, dtype=np.float64)
    R_WG = quat_wxyz_to_R(np.asarray(page.dragger.wxyz))
    u0, v0 = project_px(camera, box, p0)
    u1, v1 = project_px(camera, box, p0 + R_WG[:, axis] * shift_m)
    du, dv = u1 - u0, v1 - v0  # the screen motion that moves the gizmo shift_m along the axis
    aimed = time.monotonic()
    tab.mouse.move(u, v)
    tab.mouse.down()
    # One call for the moves (Playwright sends the same events, one per step, evenly spaced):
    # each call of its sync API costs the bench's process tens of ms of its own.
    tab.mouse.move(u + du, v + dv, steps=DRAG_STEPS)
    tab.mouse.up()
    return {
        "view_settle_s": settled - start,
        "aim_s": aimed - settled,
        "mouse_s": time.monotonic() - aimed,
    }


def run_page(page) -> Callable[[], None]:
    """Refresh ``page`` in a thread; the function that stops it."""
    stop = threading.Event()
    runner = threading.Thread(target=page.run, args=(stop,), daemon=True)
    runner.start()

    def stopper() -> None:
        stop.set()
        runner.join(timeout=10)

    return stopper


def shot(tab, out: Path | None, name: str, t: Timings, stem: str = "ui") -> None:
    """Screenshot ``tab`` to ``out/<stem>_<name>.png`` (``out`` None: none); its time is the
    bench's, kept apart in ``t`` as ``screenshots_s``."""
    if out is not None:
        start = time.monotonic()
        out.mkdir(parents=True, exist_ok=True)
        tab.screenshot(path=str(out / f"{stem}_{name}.png"))
        t.add("screenshots_s", time.monotonic() - start)


ENDED = re.compile(r"#\d+: (done|failed|stopped|refused)$")
"""The execution log's head once a program has ended."""


def click_block(tab, page, name: str) -> None:
    """Click block ``name`` in the 3D view, at its top face's centre, as a person picks it."""
    client = next(iter(page.server.get_clients().values()))
    camera = settled_camera(client)
    box = tab.locator("canvas").first.bounding_box()
    X = page.session.X_WO[name]
    top_O = max(float(p.vertices_O[:, 2].max()) for p in page.scene.object(name).model.parts)
    u, v = project_px(camera, box, X[:3, :3] @ np.array([0.0, 0.0, top_O]) + X[:3, 3])
    tab.mouse.click(u, v)


ACCEPT_TRIES = 5
"""Frames accepted at most until the block to move is in the model."""


def wait_for(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Wait until ``condition()``; TimeoutError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.05)


WAIT_TEXT_JS = """([source, timeoutMs]) => new Promise((resolve, reject) => {
  const re = new RegExp(source, "m");
  let done = false, queued = false;
  const finish = (ok) => { done = true; seen.disconnect(); clearTimeout(timer);
    ok ? resolve() : reject(new Error(`not within ${timeoutMs} ms`)); };
  const check = () => {
    queued = false;
    if (!done && re.test(document.body.innerText)) finish(true);
  };
  const seen = new MutationObserver(() => {
    if (!queued) { queued = true; queueMicrotask(check); }
  });
  const timer = setTimeout(() => done || finish(false), timeoutMs);
  seen.observe(document.body, {subtree: true, childList: true, characterData: true});
  check();
})"""
"""Resolves once a line of the page's rendered text matches a regular expression, looked at
on every change of the page's text (Playwright's own waits look every half second once the
first few looks fail: up to half a second of the harness counted as the page's)."""


def _wait_in_page(tab, script: str, arg: str, timeout_s: float, what: str) -> None:
    """Run one of the waits on the page's changes (``script`` given ``arg`` and the timeout in
    ms); TimeoutError naming ``what`` after ``timeout_s``."""
    from playwright.sync_api import Error as PlaywrightError

    try:
        tab.evaluate(script, [arg, timeout_s * 1e3])
    except PlaywrightError as e:
        if "not within" not in str(e):
            raise
        raise TimeoutError(f"{what}: not within {timeout_s:g} s") from None


def wait_text(tab, pattern: str | re.Pattern, timeout_s: float) -> None:
    """Wait until a line of ``tab``'s rendered text matches ``pattern`` (a string: contains
    it); TimeoutError naming it after ``timeout_s``."""
    source = pattern.pattern if isinstance(pattern, re.Pattern) else re.escape(pattern)
    _wait_in_page(tab, WAIT_TEXT_JS, source, timeout_s, f"the page's text {source!r}")


BUTTON_READY_JS = """([label, timeoutMs]) => new Promise((resolve, reject) => {
  let done = false, queued = false;
  const finish = (ok) => { done = true; seen.disconnect(); clearTimeout(timer);
    ok ? resolve() : reject(new Error(`not within ${timeoutMs} ms`)); };
  const ready = () => [...document.querySelectorAll("button")].some(b =>
    b.textContent.trim() === label && !b.disabled && b.getClientRects().length > 0);
  const check = () => { queued = false; if (!done && ready()) finish(true); };
  const seen = new MutationObserver(() => {
    if (!queued) { queued = true; queueMicrotask(check); }
  });
  const timer = setTimeout(() => done || finish(false), timeoutMs);
  seen.observe(document.body, {subtree: true, childList: true, attributes: true,
    characterData: true});
  check();
})"""
"""Resolves once the page shows an enabled button labelled ``label``, looked at on every change
of the page (as :data:`WAIT_TEXT_JS`)."""


def press(tab, label: str, timeout_s: float = 30.0) -> None:
    """Click the page's button ``label`` as a person does: once the page shows it enabled (a
    wait on the page's changes, counted as the page's), at once. Playwright's own click first
    checks that the button stays where it is over two drawn frames, each a frame of the 3D
    view drawn in software here: harness time that a person's click does not take
    (docs/benchmarks.md); ``force`` leaves those checks out, the mouse's events are the same."""
    _wait_in_page(tab, BUTTON_READY_JS, label, timeout_s, f"the page's button {label!r}")
    tab.get_by_role("button", name=label, exact=True).click(force=True)


def first_task(
    tab,
    page,
    out: Path | None = None,
    workpiece: str = "cube",
    shift_m: float = -0.04,
    gizmo_px: float = 150.0,
    stem: str = "ui",
) -> Timings:
    """The first task of the module docstring, in ``tab`` (a Playwright page already showing
    ``page``, an :class:`~operator_site.ui.page.OperatorPage` refreshed by :func:`run_page`);
    the timings. Raises (TimeoutError, AssertionError) at the first step that does not come."""
    t = Timings()
    now = time.monotonic
    wait_text(tab, "work site: connected", 60)
    t.marks["connected_at_s"] = now()
    shot(tab, out, "1_loaded", t, stem)
    start = now()  # after the screenshot: the total leaves the bench's screenshots out
    # Vision's recognitions: listed, outlined on the camera image, see-through in 3D. As a
    # person would, wait until the block to move is among them (vision misses a block in some
    # frames).
    wait_text(tab, re.compile(rf"^{re.escape(workpiece)}: score \d"), 180)
    t.add("vision_wait_s", now() - start)
    shot(tab, out, "2_recognised", t, stem)
    mark = now()
    press(tab, "accept the recognised blocks")
    wait_text(tab, re.compile(r"^model: \d+ blocks"), 30)
    t.add("operator_s", now() - mark)
    t.marks["accept_s"] = now() - mark
    for _ in range(ACCEPT_TRIES):
        if workpiece in page.model.poses:
            break
        # Vision lost it in the frame accepted, or saw another block where it is (the model
        # then refuses it, saying so): accept a later frame that has it, as a person would.
        seq = page.link.recognitions.seq
        wait_for(
            lambda seq=seq: (
                page.link.recognitions.seq != seq
                and any(r.model == workpiece for r in page.link.recognitions.objects)
            ),
            60,
            f"a later frame with the {workpiece}",
        )
        press(tab, "accept the recognised blocks")
        time.sleep(1.0)  # the page's answer (the model, or why not)
    if workpiece not in page.model.poses:
        raise AssertionError(f"the {workpiece} not in the model: {page.model_md.content}")
    # Each block of the model is named in the 3D view (the names are drawn in the canvas,
    # not the page's text: what the page sent it is checked).
    t.marks["blocks_accepted"] = len(page.model.poses)
    t.marks["labels_shown"] = sum(
        page.labels[n].text == block_label(n) and page.object_frames[n].visible
        for n in page.model.poses
    )
    # Pick the block with a click in the 3D view, look from above, drag the gizmo's x arrow.
    mark = now()
    click_block(tab, page, workpiece)
    wait_text(tab, f"dragging {workpiece}", 30)
    t.marks["pick_s"] = now() - mark
    step = now()
    view_asked = time.time()
    press(tab, "from above")
    t.marks["from_above_click_s"] = now() - step
    start_W = page.session.X_WO[workpiece][:3, 3].copy()
    view = view_from_above_W(page.scene, start_W)  # what the page's button asks
    t.marks.update(drag_gizmo(tab, page, 0, shift_m, gizmo_px, view_asked, view))
    t.marks["drag_s"] = now() - step
    step = now()
    wait_for(
        lambda: (
            abs(page.session.X_WO[workpiece][0, 3] - page.session.sim.state.X_WD[0, 3]) < 1e-3
            and abs(page.session.sim.state.X_WD[0, 3] - start_W[0]) > 1e-3
        ),
        30,
        "the block following the gizmo",
    )
    t.marks["follow_s"] = now() - step
    t.add("operator_s", now() - mark)
    t.marks["moved_m"] = float(page.session.sim.state.X_WD[0, 3] - start_W[0])
    shot(tab, out, "3_dragged", t, stem)
    mark = now()
    press(tab, "make the robot program")
    wait_text(tab, re.compile(r"\d+ commands; path"), 120)
    t.add("program_s", now() - mark)
    shot(tab, out, "4_program", t, stem)
    mark = now()
    press(tab, "send it to the robot")
    t.add("operator_s", now() - mark)
    mark = now()
    wait_text(tab, "checked and accepted by the work site", 60)
    # The log's newest line (its first) is in view without scrolling.
    t.marks["log_in_view"] = float(
        tab.get_by_text("checked and accepted by the work site").first.evaluate(
            "e => { const r = e.getBoundingClientRect();"
            " return r.top >= 0 && r.top + 20 <= window.innerHeight ? 1 : 0; }"
        )
    )
    wait_text(tab, ENDED, 300)
    ended = tab.get_by_text(ENDED).first
    t.add("robot_s", now() - mark)
    t.marks["outcome"] = ended.inner_text()
    shot(tab, out, "5_done", t, stem)
    # After the run, the page says what vision sees now; the operator takes it into the model.
    mark = now()
    # (Not the help text's "what vision sees": the offer after the program.)
    wait_text(tab, re.compile(r"after .+, vision (sees|agrees)"), 120)
    t.add("vision_wait_s", now() - mark)
    mark = now()
    press(tab, "update the model from vision")
    # The page always answers: updated, or why not.
    wait_text(tab, "updated from vision", 60)
    if not page.model_md.content.startswith("updated from vision:"):
        raise AssertionError(f"update from vision: {page.model_md.content}")
    t.add("operator_s", now() - mark)
    t.marks["update_s"] = now() - mark
    shot(tab, out, "6_updated", t, stem)
    return t


CHROMIUM = "/usr/bin/chromium"
MESA_SOFTWARE_GL = "/usr/lib/*/dri/swrast_dri.so"
"""Mesa's llvmpipe (Debian's libgl1-mesa-dri, which chromium recommends)."""


def chromium_flags() -> list[str]:
    """Debian's Chromium, headless, nothing fetched from outside, WebGL drawn in software:
    by Mesa's llvmpipe where it is installed, composited in Chromium's GPU process as with a
    graphics card; else by SwiftShader with the GPU process off, which reads every changed
    frame of the 3D view back for a software compositor (slower: docs/benchmarks.md)."""
    flags = [
        "--headless", "--no-sandbox", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
    ]  # fmt: skip
    if glob.glob(MESA_SOFTWARE_GL):
        return [*flags, "--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist"]
    return [*flags, "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"]


PARTS = ("vision_wait_s", "operator_s", "program_s", "robot_s", "page_s", "load_s")
"""``load_s``: the page's address opened to "work site: connected", within ``page_s``."""
STEPS = ("accept_s", "pick_s", "drag_s", "from_above_click_s", "view_settle_s", "aim_s",
         "mouse_s", "follow_s", "update_s")  # fmt: skip
"""The operator's steps within ``operator_s``: accept, pick the block (a click in 3D), look from
above and drag the gizmo (of which: the click on "from above", the view settling after it,
finding the gizmo's arrow on the screen, the mouse's press, moves and release), the block
following it on its spring, update the model."""


@contextmanager
def page_for(ws) -> Iterator:
    """The operator's page, its model empty, on work site ``ws`` (a started work-site process),
    refreshed in a thread; closed with its link on exit."""
    from models.scene import load_scene
    from operator_site.link import WorkSiteLink
    from operator_site.ui import OperatorPage
    from protocol import make_config
    from protocol.session import free_port_pair

    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    page = OperatorPage(load_scene(), link, port=free_port_pair(), initial_model="empty")
    stop = run_page(page)
    try:
        yield page
    finally:
        stop()
        page.close()
        link.close()


def page_address(page, dpr: float | None = None) -> str:
    """The address of ``page`` on loopback; with ``dpr``, its 3D view drawn at that fixed
    device-pixel ratio instead of the browser's, adapted."""
    return page_url("127.0.0.1", page.server.get_port(), None, view_dpr=dpr)


@contextmanager
def chromium_tab(pw, page=None) -> Iterator:
    """A tab of Debian's headless Chromium (``pw``: a started sync Playwright), showing
    ``page`` if given (else blank); the browser closed on exit."""
    browser = pw.chromium.launch(executable_path=CHROMIUM, args=chromium_flags())
    try:
        tab = browser.new_page(viewport=VIEWPORT)
        if page is not None:
            tab.goto(page_address(page))
        yield tab
    finally:
        browser.close()


def run(args: argparse.Namespace) -> dict:
    """One first task per run, each against its own work site; the summary (the median run's
    parts, and each run's)."""
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    from bench.netsafety import start_work_site
    from operator_site.ui.scene_view import GIZMO_PX

    if not Path(CHROMIUM).exists():
        raise SystemExit(f"bench ui: {CHROMIUM} is missing (Debian's chromium package)")
    args.out.mkdir(parents=True, exist_ok=True)
    logs = Path(tempfile.mkdtemp(prefix="bench-ui-"))  # the work sites' logs and journals
    print(f"bench ui: work-site logs in {logs}", file=sys.stderr, flush=True)
    stem = output_stem(args.dpr)
    rows = []
    for k in range(args.runs):
        ws = start_work_site(logs, k, site_id=f"ui{k}", vision=True)
        row: dict = {"run": k, "success": False, "dpr": args.dpr or "adaptive"}
        try:
            with page_for(ws) as page, sync_playwright() as pw, chromium_tab(pw) as tab:
                opened = time.monotonic()  # the operator opens the page's address
                tab.goto(page_address(page, args.dpr))
                t = first_task(
                    tab, page, args.out if k == 0 else None, gizmo_px=GIZMO_PX, stem=stem
                )
                row["total_s"] = time.monotonic() - opened - t.parts.pop("screenshots_s", 0.0)
                row.update(t.parts)
                row["load_s"] = t.marks["connected_at_s"] - opened
                row["page_s"] = row["total_s"] - row["vision_wait_s"] - row["robot_s"]
                row["success"] = t.marks["outcome"].endswith(": done")
                row["outcome"] = t.marks["outcome"]
                row.update({k: v for k, v in t.marks.items() if k in STEPS})
        except (TimeoutError, AssertionError, ValueError, PlaywrightError) as e:
            row["error"] = str(e).splitlines()[0]
        finally:
            ws.kill()
        print(f"bench ui: run {k + 1}/{args.runs}: {row}", file=sys.stderr, flush=True)
        rows.append(row)
    done = [r for r in rows if r["success"]]
    summary: dict = {"runs": len(rows), "success": len(done), "dpr": args.dpr or "adaptive"}
    if done:
        middle = sorted(done, key=lambda r: r["total_s"])[len(done) // 2]
        summary["total_s"] = round(middle["total_s"], 2)
        for part in (*PARTS, *STEPS):
            summary[part] = round(middle.get(part, 0.0), 2)
    write_outputs(args.out, rows, summary, stem)
    return summary


def output_stem(dpr: float | None) -> str:
    """``ui`` for the browser's own pixel ratio, ``ui_dpr0.5`` for a fixed one."""
    return "ui" if dpr is None else f"ui_dpr{dpr:g}"


def write_outputs(out: Path, rows: list[dict], summary: dict, stem: str = "ui") -> None:
    """<stem>.json (the summary), .csv (each run) and .png (each run's parts, stacked)."""
    import csv

    (out / f"{stem}.json").write_text(json.dumps(summary, indent=1) + "\n")
    with (out / f"{stem}.csv").open("w", newline="") as f:
        fields = ["run", "success", "dpr", "total_s", *PARTS, *STEPS, "outcome", "error"]
        w = csv.DictWriter(f, fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in w.fieldnames})
    import matplotlib  # the bench extras: after the figures are safe on disk

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.2))
    shown = ("vision_wait_s", "robot_s", "program_s", "operator_s")
    for k, r in enumerate(rows):
        left = 0.0
        for part, colour in zip(shown, ("#7aa6d8", "#e0a040", "#60b060", "#b080c0"), strict=True):
            width = r.get(part, 0.0)
            ax.barh(k, width, left=left, color=colour, label=part if k == 0 else None)
            left += width
        rest = r.get("total_s", left) - left
        ax.barh(
            k, max(rest, 0.0), left=left, color="#bbbbbb", label="page rest" if k == 0 else None
        )
    ax.set_xlabel("s from page load to the model updated after the run")
    ax.set_ylabel("run")
    ax.legend(loc="lower right", fontsize=7)
    ax.set_title("A first task in the page: where the time goes")
    fig.tight_layout()
    fig.savefig(out / f"{stem}.png", dpi=120)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench ui``."""
    parser.add_argument("--runs", type=int, default=3, help="first tasks, each with its own "
                        "work site (default: %(default)s)")  # fmt: skip
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for ui.json, ui.csv, ui.png and the first run's screenshots "
        "ui_*.png (default: %(default)s)",
    )
    parser.add_argument(
        "--dpr",
        type=float,
        default=None,
        help="draw the 3D view at this fixed device-pixel ratio (operator-site --view-dpr); "
        "outputs then named ui_dpr<DPR>.* "
        "(default: the browser's own ratio, which viser adapts to the frame rate)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    if args.runs < 1:
        raise SystemExit(f"bench ui: --runs must be at least 1, not {args.runs}")
    if args.dpr is not None:
        try:
            check_view_dpr(args.dpr)
        except ValueError as e:
            raise SystemExit(f"bench ui: --dpr: {e}") from None
    summary = run(args)
    print(json.dumps(summary), flush=True)
    return 0 if summary["success"] == summary["runs"] else 1
