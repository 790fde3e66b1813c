"""Scoring recognitions against ground truth: detection and symmetry-aware pose errors.

A recognition is a true positive when a ground-truth object of the same model lies within
``MATCH_POSITION_M`` and ``MATCH_ROTATION_RAD`` of it (rotation error taken modulo the model's
symmetries); every other recognition is a false positive. Position error is split into the part
across the viewing ray ("lateral") and along it ("depth"), because one camera measures the first
far better than the second (§IV-B).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.vision_dataset import GroundTruth
from models.scene import CameraModel
from models.transforms import invert_pose
from work_site.vision.model import VisionModel, project, transform

MATCH_POSITION_M = 0.01
MATCH_ROTATION_RAD = np.deg2rad(10.0)


@dataclass(frozen=True)
class PoseError:
    """Errors of one estimated pose against the truth (symmetry-aware where it matters)."""

    lateral_m: float
    depth_m: float
    rotation_rad: float
    reprojection_px: float


def pose_error(
    model: VisionModel, X_WO_est: np.ndarray, X_WO_true: np.ndarray, camera: CameraModel
) -> PoseError:
    """Errors of ``X_WO_est``: lateral/depth split along the camera ray through the true
    origin; rotation and mean vertex reprojection error minimised over the model's symmetries."""
    c = camera.X_WC[:3, 3]
    ray = X_WO_true[:3, 3] - c
    ray /= np.linalg.norm(ray)
    dp = X_WO_est[:3, 3] - X_WO_true[:3, 3]
    depth = float(abs(dp @ ray))
    lateral = float(np.linalg.norm(dp - (dp @ ray) * ray))
    X_CW = invert_pose(camera.X_WC)
    uv_true = project(transform(X_CW @ X_WO_true, model.vertices_O), camera.K)
    best_rot, best_px = np.inf, np.inf
    for S in model.symmetries:
        R_est = X_WO_est[:3, :3] @ S
        cosang = (np.trace(R_est.T @ X_WO_true[:3, :3]) - 1) / 2
        best_rot = min(best_rot, float(np.arccos(np.clip(cosang, -1.0, 1.0))))
        X = X_WO_est.copy()
        X[:3, :3] = R_est
        uv = project(transform(X_CW @ X, model.vertices_O), camera.K)
        best_px = min(best_px, float(np.mean(np.linalg.norm(uv - uv_true, axis=1))))
    return PoseError(lateral, depth, best_rot, best_px)


@dataclass(frozen=True)
class SceneScore:
    """Per-scene outcome: matched pairs with errors, false positives, ground truth."""

    matches: list[tuple[GroundTruth, PoseError]]
    false_positives: list[str]
    truth: list[GroundTruth]


def score_scene(
    recognitions: list[tuple[str, np.ndarray]],
    truth: list[GroundTruth],
    models: dict[str, VisionModel],
    camera: CameraModel,
) -> SceneScore:
    """Match ``(model, X_WO)`` recognitions to the ground truth (one-to-one)."""
    matches, fps = [], []
    used: set[int] = set()
    for name, X_WO in recognitions:
        hit = None
        for k, t in enumerate(truth):
            if k in used or t.model != name:
                continue
            err = pose_error(models[name], X_WO, t.X_WO, camera)
            dist = float(np.linalg.norm(X_WO[:3, 3] - t.X_WO[:3, 3]))
            if dist <= MATCH_POSITION_M and err.rotation_rad <= MATCH_ROTATION_RAD:
                hit = (k, err)
                break
        if hit is None:
            fps.append(name)
        else:
            used.add(hit[0])
            matches.append((truth[hit[0]], hit[1]))
    return SceneScore(matches, fps, truth)
