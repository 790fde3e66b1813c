"""Camera calibration in simulation: intrinsics from a rendered chessboard, pose from the frame."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from models.scene import load_camera, load_scene
from models.transforms import make_pose, rpy_to_R, so3_log
from work_site.vision.calibration import (
    calibrate_extrinsics,
    calibrate_intrinsics,
    frame_object,
    render_board_views,
)
from work_site.vision.cli import main


@pytest.fixture(scope="module")
def scene():
    return load_scene()


def test_intrinsics_from_a_rendered_chessboard(scene) -> None:
    camera = scene.camera
    result = calibrate_intrinsics(render_board_views(camera, 12, seed=1, supersample=2))
    assert result.views >= 10
    assert result.rms_px < 0.3
    # Within 3 standard deviations of the calibration's own estimate (a dozen views leave
    # fx, fy, cx, cy about 2 px uncertain), and that uncertainty is a few pixels at most.
    estimate = np.array([result.K[0, 0], result.K[1, 1], result.K[0, 2], result.K[1, 2]])
    truth = np.array([camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]])
    assert np.all(result.std_f_c_px < 4.0), result.std_f_c_px
    assert np.all(np.abs(estimate - truth) < 3 * result.std_f_c_px), (estimate, truth)
    assert np.all(np.abs(result.dist[:2]) < 0.05)  # the renderer has no lens distortion


def test_too_few_boards_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="chessboard was found in only 0 images"):
        calibrate_intrinsics([np.zeros((480, 640), np.uint8)] * 5)


def test_camera_pose_from_the_frame(scene) -> None:
    camera = scene.camera
    renderer = SceneRenderer(scene, supersample=3)
    try:
        image, _ = renderer.render(renderer.random_layout(np.random.default_rng(12)))
    finally:
        renderer.close()
    X_err = make_pose(rpy_to_R(np.deg2rad([0.5, -0.4, 0.6])), [0.004, -0.003, 0.005])
    guess = dataclasses.replace(camera, X_WC=camera.X_WC @ X_err)
    result = calibrate_extrinsics(image, guess, frame_object(scene))
    assert result.edges >= 8
    # Lines split at the frame's shallow corners are shorter and their ends noisier: the line
    # residual rises as the pose gets better, so it is held only well inside the work site's
    # trust bound; the pose itself is what is checked.
    assert result.rms_px < 0.5 and result.corner_rms_px < 1.5
    assert np.linalg.norm(result.X_WC[:3, 3] - camera.X_WC[:3, 3]) < 0.0015
    R = result.X_WC[:3, :3].T @ camera.X_WC[:3, :3]
    assert np.rad2deg(np.linalg.norm(so3_log(R))) < 0.15


@pytest.mark.slow
def test_calibrate_command_writes_a_loadable_camera(tmp_path, capsys) -> None:
    out = tmp_path / "camera.json"
    assert main(["calibrate", "--out", str(out), "--views", "8"]) == 0
    text = capsys.readouterr().out
    assert "RMS reprojection" in text and "corner RMS" in text
    camera = load_camera(out)
    assert abs(camera.K[0, 0] - 580.0) < 5.0
    assert set(json.loads(out.read_text())) >= {"width", "height", "K", "dist", "X_WC"}
