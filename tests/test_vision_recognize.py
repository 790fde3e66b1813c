"""Recognition on scenes rendered by the test: floors below the benchmark's goals, so the suite
stays fast and stable; the benchmark (`python -m bench vision`) measures the real figures."""

from __future__ import annotations

import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from bench.vision_evaluate import score_scene
from models.scene import load_scene
from models.transforms import make_pose
from work_site.vision.recognizer import Recognizer

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
