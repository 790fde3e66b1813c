"""The work site's vision process (a real child process): a full search when asked, tracking of
what the last frame found when asked to track, nothing to track before any search."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from models.scene import load_scene
from tests.conftest import yielded_niceness
from work_site.camera import RenderedFrame
from work_site.recognition import VisionProcess, VisionResult

pytestmark = pytest.mark.slow  # a child process that loads vision's index: seconds

WAIT_S = 120.0


def _result(vision: VisionProcess) -> VisionResult:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        result = vision.poll()
        if result is not None:
            return result
        assert not vision.failed, vision.failed
        time.sleep(0.01)
    raise AssertionError(f"vision gave no result within {WAIT_S} s")


def test_the_vision_process_searches_then_tracks_what_it_found() -> None:
    scene = load_scene()
    renderer = SceneRenderer(scene, supersample=3)
    try:
        image, _ = renderer.render(renderer.random_layout(np.random.default_rng(5)))
    finally:
        renderer.close()
    rng = np.random.default_rng(0)

    def frame(seq: int) -> RenderedFrame:
        noisy = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
        return RenderedFrame(seq, float(seq), noisy, b"", scene.robot.q_home_rad, 0.0)

    vision = VisionProcess(scene.path)
    try:
        deadline = time.monotonic() + WAIT_S
        while not vision.ready and time.monotonic() < deadline:
            assert vision.poll() is None and not vision.failed, vision.failed
            time.sleep(0.05)
        assert vision.ready
        niceness = os.getpriority(os.PRIO_PROCESS, vision._proc.pid)
        assert niceness == yielded_niceness()  # the control loop comes first
        assert vision.request(frame(1), track=True)  # nothing searched yet: nothing to track
        first = _result(vision)
        assert first.tracked and first.objects == () and not first.error
        assert vision.request(frame(2))
        searched = _result(vision)
        assert not searched.tracked and len(searched.objects) >= 3, searched
        assert vision.request(frame(3), track=True)
        tracked = _result(vision)
        assert tracked.tracked and not tracked.error
        found = {name: X for name, X, _ in searched.objects}
        assert {name for name, _, _ in tracked.objects} <= set(found)
        assert len(tracked.objects) >= len(found) - 1
        for name, X_WO, _ in tracked.objects:
            assert np.linalg.norm(X_WO[:3, 3] - found[name][:3, 3]) < 0.001, name
    finally:
        vision.close()


class _Vision:
    """Records what the server asks of vision (a stand-in for the child process, whose own
    test is above); never busy."""

    def __init__(self) -> None:
        self.asked: list[str] = []

    def request(self, frame: RenderedFrame, track: bool = False) -> bool:
        self.asked.append("track" if track else "search")
        return True


class _Execution:
    def __init__(self, finished: bool) -> None:
        self.finished = finished


def test_the_server_searches_at_its_rate_and_tracks_between_while_nothing_runs() -> None:
    from protocol import make_config
    from work_site.options import ServerOptions
    from work_site.server import WorkSiteServer

    server = WorkSiteServer(load_scene(), make_config(), ServerOptions(vision_rate_hz=1.0))
    server._vision = vision = _Vision()
    server._next_vision_s = 0.0  # as serve() starts it
    frame = RenderedFrame(0, 0.0, np.zeros((2, 2), np.uint8), b"", np.zeros(6), 0.0)
    for t_s in (0.0, 0.2, 0.4):
        server._recognize(frame, t_s)
    server._execution = _Execution(finished=False)  # a program moves things: searches only
    for t_s in (0.6, 0.8, 1.0, 1.2):
        server._recognize(frame, t_s)
    server._execution = _Execution(finished=True)
    server._recognize(frame, 1.4)
    assert vision.asked == ["search", "track", "track", "search", "track"]
    untracked = WorkSiteServer(
        load_scene(), make_config(), ServerOptions(vision_rate_hz=1.0, vision_tracking=False)
    )
    untracked._vision = vision = _Vision()
    untracked._next_vision_s = 0.0
    for t_s in (0.0, 0.2, 0.4, 1.0):
        untracked._recognize(frame, t_s)
    assert vision.asked == ["search", "search"]
