"""Tracking (:meth:`Recognizer.track`): objects recognised in one frame are found again in the
next from their poses there, followed when they move a little, and lost when they are gone."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from bench.vision_evaluate import score_scene
from models.scene import load_scene
from models.transforms import make_pose
from work_site.vision.pose_sets import Detection
from work_site.vision.recognizer import Recognizer

pytestmark = pytest.mark.slow  # renders its scenes and builds the index: seconds

NUDGE_M = 0.004
NUDGE_RAD = np.deg2rad(3.0)
"""How far the test moves a block between two frames: more than a still block's frame-to-frame
error, well within what tracking is meant to follow."""
SAME_FIT_M = 0.00025
SAME_FIT_RAD = np.deg2rad(0.25)
"""A tracked pose this close to the truth, or closer, than the full search's of the same frame
is as precise (a few times one frame's median error)."""


@pytest.fixture(scope="module")
def recognizer(tmp_path_factory) -> Recognizer:
    # One index per test session, shared by the vision test modules.
    path = tmp_path_factory.getbasetemp() / "vision-index-cache"
    path.mkdir(exist_ok=True)
    return Recognizer(cache_dir=path)


def _noisy(image: np.ndarray, seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).normal(0, 1.0, image.shape)
    return np.clip(image + noise, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def frames():
    """Layouts each seen twice (fresh noise), then with its first block nudged and turned, then
    with that block taken away: ``(images, poses, nudged poses, moved name)`` per layout, and
    the camera."""
    renderer = SceneRenderer(load_scene(), supersample=3)
    rng = np.random.default_rng(77)
    try:
        out = []
        for k in range(4):
            poses = renderer.random_layout(rng)
            name = sorted(n for n, X in poses.items() if X[2, 3] > 0.0)[k % 3]
            c, s = np.cos(NUDGE_RAD), np.sin(NUDGE_RAD)
            turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            X = poses[name]
            nudged = {**poses, name: make_pose(turn @ X[:3, :3], X[:3, 3] + [NUDGE_M, 0, 0])}
            gone = {**poses, name: make_pose(None, [5.0, 5.0, -1.0])}
            images = [renderer.render(p)[0] for p in (poses, nudged, gone)]
            seen = (_noisy(images[0], 10 * k), _noisy(images[0], 10 * k + 1))
            out.append((seen, _noisy(images[1], 10 * k + 2), _noisy(images[2], 10 * k + 3),
                        renderer.render(poses)[1], nudged, name))  # fmt: skip
        return out, renderer.scene.camera
    finally:
        renderer.close()


def test_tracking_finds_again_what_recognition_found_as_precisely(recognizer, frames) -> None:
    """The next frame of a still scene: what the full search found is found again, nothing
    else, each as close to the truth as a full search of that frame puts it (the fit
    converges to the same pose from either start)."""
    data, camera = frames
    models = {m.name: m for m in recognizer.models}
    kept = found_n = compared = 0
    for (first, second), _, _, truth, _, _ in data:
        found = recognizer.recognize(first, camera)
        tracked = recognizer.track(second, camera, found)
        assert {r.model for r in tracked} <= {r.model for r in found}
        kept += len(tracked)
        found_n += len(found)
        full = score_scene(found_poses(recognizer.recognize(second, camera)), truth, models, camera)
        again = score_scene(found_poses(tracked), truth, models, camera)
        assert len(again.false_positives) <= len(full.false_positives)
        full_error = {t.model: e for t, e in full.matches}
        for t, e in again.matches:
            if t.model in full_error:
                f = full_error[t.model]
                assert e.lateral_m <= f.lateral_m + SAME_FIT_M, (t.model, e, f)
                assert e.rotation_rad <= f.rotation_rad + SAME_FIT_RAD, (t.model, e, f)
                compared += 1
    assert found_n >= 10 and compared >= 10
    assert kept >= 0.9 * found_n, f"tracking kept {kept} of {found_n}"


def test_tracking_follows_a_block_nudged_between_frames(recognizer, frames) -> None:
    data, camera = frames
    followed = 0
    for (first, _), nudged_image, _, _, nudged, name in data:
        found = recognizer.recognize(first, camera)
        if name not in {r.model for r in found}:
            continue  # not found in the first place: nothing to follow
        tracked = {r.model: r for r in recognizer.track(nudged_image, camera, found)}
        assert name in tracked, f"{name} nudged by {NUDGE_M * 1e3} mm lost"
        off_m = np.linalg.norm(tracked[name].X_WO[:3, 3] - nudged[name][:3, 3])
        assert off_m < 0.001, f"{name} followed to {off_m * 1e3:.2f} mm from where it went"
        followed += 1
    assert followed >= 2


def test_tracking_loses_a_block_taken_away(recognizer, frames) -> None:
    data, camera = frames
    checked = 0
    for (first, _), _, gone_image, _, _, name in data:
        found = recognizer.recognize(first, camera)
        if name not in {r.model for r in found}:
            continue
        tracked = recognizer.track(gone_image, camera, found)
        assert name not in {r.model for r in tracked}
        checked += 1
    assert checked >= 2


def test_tracking_nothing_or_an_unknown_model(recognizer, frames) -> None:
    data, camera = frames
    image = data[0][0][0]
    assert recognizer.track(image, camera, []) == []
    with pytest.raises(ValueError, match="no model 'teapot'"):
        recognizer.track(image, camera, [Detection("teapot", np.eye(4), 1.0)])
    behind = make_pose(None, camera.X_WC[:3, 3] - 0.5 * camera.X_WC[:3, 2])
    assert recognizer.track(image, camera, [Detection("cube", behind, 1.0)]) == []


def test_the_kept_undistortion_maps_undistort_as_opencv_does(recognizer, frames) -> None:
    import dataclasses

    camera = frames[1]
    camera = dataclasses.replace(camera, dist=np.array([-0.08, 0.02, 0.0, 0.0, 0.0]))
    image = frames[0][0][0][0]
    K = np.asarray(camera.K, dtype=np.float64)
    maps = recognizer._undistort_maps(K, camera.dist, image.shape)
    ours = cv2.remap(image, *maps, cv2.INTER_LINEAR)
    assert np.array_equal(ours, cv2.undistort(image, K, camera.dist))


def found_poses(found) -> list[tuple[str, np.ndarray]]:
    return [(r.model, r.X_WO) for r in found]


def test_a_frame_worked_out_in_boxes_is_the_whole_frame_there(recognizer, frames) -> None:
    """Tracking undistorts and differentiates the image only in its boxes: there, the same
    values as the whole image's (zero elsewhere); and the faint pass added later (as tracking
    does when an object is not found without it) gives the lines found at once."""
    data, camera = frames
    image = data[0][0][0]
    camera = dataclasses.replace(camera, dist=np.array([-0.02, 0.03, 0.001, -0.001, 0.0]))
    K, dist = np.asarray(camera.K), camera.dist
    h, w = image.shape
    rects = [(w // 4, h // 4, w // 2 + 60, h // 2 + 60), (w - 220, h - 160, w, h)]  # a corner
    img_all, (gx_all, gy_all) = recognizer._undistorted(image, K, dist, None)
    img_in, (gx_in, gy_in) = recognizer._undistorted(image, K, dist, rects)
    inside = np.zeros(image.shape, bool)
    for x0, y0, x1, y1 in rects:
        inside[y0:y1, x0:x1] = True
    for whole, part in ((img_all, img_in), (gx_all, gx_in), (gy_all, gy_in)):
        assert np.array_equal(whole[inside], part[inside])
        assert not part[~inside].any()
    boxes = [np.array(r, dtype=np.float64) for r in rects]
    at_once = recognizer._frame(image, camera, rois_px=boxes)
    later = Recognizer._with_faint(recognizer._frame(image, camera, rois_px=boxes, faint=False))
    assert 0 < at_once.n_strong == later.n_strong < len(later.segs)
    assert np.array_equal(at_once.segs, later.segs)
