"""The work site's vision process (a real child process): a full search when asked, tracking of
what the last frame found when asked to track, nothing to track before any search."""

from __future__ import annotations

import time

import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from models.scene import load_scene
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
