"""The vision benchmark's fused figures: a dataset's scenes seen again, several frames each
with their own noise, recognised once per frame and fused as the work site fuses them."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from bench.vision import score
from bench.vision_dataset import write_dataset
from bench.vision_fused import FusedRun, fused_scenes
from work_site.sensor import CameraConditions
from work_site.vision.recognizer import Recognizer


@pytest.mark.slow
def test_each_scene_is_seen_again_with_fresh_noise_and_scored_alone_and_fused(tmp_path) -> None:
    paths = write_dataset(tmp_path, 2, seed=5, supersample=1, conditions=CameraConditions())
    scenes = fused_scenes(paths, supersample=1, frames=3)
    stored = cv2.imread(str(tmp_path / json.loads(paths[0].read_text())["image"]), 0)
    images = scenes[0][0]
    assert len(images) == 3 and all(im.shape == stored.shape for im in images)
    assert not np.array_equal(images[0], images[1])  # each frame its own noise...
    # ...about the same scene: the frames differ from the stored image as its noise does.
    assert np.mean(np.abs(images[0].astype(float) - stored)) < 4.0
    recognizer = Recognizer()
    run = FusedRun(recognizer, {m.name: m.symmetries for m in recognizer.models})
    together = score(recognizer, scenes, recognize=run.fused)
    alone = score(recognizer, scenes, recognize=run.last_frame)  # the same frames' own
    assert together["scenes"] == alone["scenes"] == 2
    assert together["objects_visible_70"] == alone["objects_visible_70"] > 0
    assert together["recall"] is not None and alone["recall"] is not None
    # The first frame searched, the others tracked from it: timed, and never more found.
    tracked = score(recognizer, scenes, recognize=run.tracked)
    assert len(run.track_s) == len(run.track_cpu_s) == 2 * 2
    assert tracked["recall"] is not None
