"""Seeded variations of a scene for end-to-end runs: where the blocks lie, and how far the real
camera is from its calibrated model."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import cv2
import numpy as np

from models.geometry import convex_gap_2d
from models.scene import Scene
from models.transforms import make_pose, rpy_to_R, so3_exp

LAYOUT_REGION_W = ((0.18, 0.63), (-0.32, 0.32))
"""Where block centres may go (x from, to; y from, to; m): on the table within the arm's easy
reach around the frame."""
FRAME_OUTLINE_W = ((0.33, 0.57), (-0.12, 0.12))
"""The frame's outer faces (x from, to; y from, to; m)."""
LANE_M = 0.06
"""Blocks start at least this far outside the frame (between the frame and a block's bounding
circle): its inside corners are free, and a block can be slid round its outside."""
MAX_REACH_XY_M = 0.58
"""No block centre further than this from the robot's base axis (m): the wrist keeps ≥ 20 mm
of reach in hand for grasps from above (the arm reaches 0.635 m from the shoulder)."""
MIN_REACH_XY_M = 0.21
"""No part of a block nearer than this to the robot's base axis (m): nearer, a grasp from above
folds the elbow past joint 3's limit, and a block may be set anywhere on another
(tests/test_control_kinematics.py checks seeded layouts)."""
CLEARANCE_M = 0.012
"""Blocks start at least this far apart (between their bounding circles), room for fingers."""
MAX_TRIES = 2000
CAMERA_SHIFT_M = 0.002
"""How far the real camera is from its calibrated pose in seeded runs (m)."""
CAMERA_TURN_RAD = math.radians(0.2)
"""How far the real camera is turned from its calibrated pose in seeded runs (rad)."""


def radius_xy(scene: Scene, name: str) -> float:
    """The radius of the object's footprint's bounding circle about its origin (m)."""
    V = np.vstack([p.vertices_O for p in scene.object(name).model.parts])
    return float(np.max(np.linalg.norm(V[:, :2], axis=1)))


def _image_hull_px(scene: Scene, name: str, X_WO: np.ndarray) -> tuple[np.ndarray, float]:
    """The convex hull (k, 2) of the object's image in the scene's camera (px), and how far
    that image may move when the real camera is off its calibration as
    :func:`perturbed_camera_pose` puts it (px)."""
    V_O = np.vstack([p.vertices_O for p in scene.object(name).model.parts])
    X_CW = np.linalg.inv(scene.camera.X_WC)
    p_C = (X_CW[:3, :3] @ (X_WO[:3, :3] @ V_O.T + X_WO[:3, 3:4]) + X_CW[:3, 3:4]).T
    uv = (scene.camera.K @ p_C.T).T
    uv = uv[:, :2] / uv[:, 2:3]
    focal_px = float(scene.camera.K[0, 0])
    slack_px = focal_px * (CAMERA_TURN_RAD + CAMERA_SHIFT_M / float(p_C[:, 2].min()))
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    return hull, slack_px


def laid_out(scene: Scene, X_WO: Mapping[str, np.ndarray]) -> Scene:
    """``scene`` with the objects named in ``X_WO`` at those poses (a layout)."""
    return dataclasses.replace(
        scene,
        objects=tuple(
            dataclasses.replace(o, X_WO=X_WO[o.name]) if o.name in X_WO else o
            for o in scene.objects
        ),
    )


def random_layout(scene: Scene, seed: int) -> dict[str, np.ndarray]:
    """``X_WO`` for every movable object: standing as in the scene file, turned by a random yaw,
    at a random place on the table at least :data:`LANE_M` outside the frame, none touching
    another, and each seen whole by the camera (inside its image, not behind another block's
    image) wherever :func:`perturbed_camera_pose` may put the real camera. A block the camera
    cannot see is not in the operator's model; that refusal is tested on its own, not drawn
    here by chance."""
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = LAYOUT_REGION_W
    (fx0, fx1), (fy0, fy1) = FRAME_OUTLINE_W
    placed: dict[str, tuple[np.ndarray, float]] = {}
    hulls: dict[str, tuple[np.ndarray, float]] = {}
    out: dict[str, np.ndarray] = {}
    for obj in scene.movable:
        r = radius_xy(scene, obj.name)
        for _ in range(MAX_TRIES):
            xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            outside = np.maximum([fx0 - xy[0], fy0 - xy[1]], [xy[0] - fx1, xy[1] - fy1])
            if np.linalg.norm(np.maximum(outside, 0.0)) < r + LANE_M:
                continue
            if not MIN_REACH_XY_M + r <= np.linalg.norm(xy) <= MAX_REACH_XY_M:
                continue
            if any(np.linalg.norm(xy - c) < r + rc + CLEARANCE_M for c, rc in placed.values()):
                continue
            yaw = rng.uniform(-math.pi, math.pi)
            R = rpy_to_R(np.array([0.0, 0.0, yaw])) @ obj.X_WO[:3, :3]
            X_WO = make_pose(R, (xy[0], xy[1], obj.X_WO[2, 3]))
            hull, slack_px = _image_hull_px(scene, obj.name, X_WO)
            size = np.array([scene.camera.width - 1, scene.camera.height - 1], dtype=np.float64)
            if np.any(hull < slack_px) or np.any(hull > size - slack_px):
                continue
            if any(convex_gap_2d(hull, h) < slack_px + s for h, s in hulls.values()):
                continue
            break
        else:
            raise ValueError(f"seed {seed}: no room for {obj.name} in {LAYOUT_REGION_W}")
        out[obj.name] = X_WO
        placed[obj.name] = (xy, r)
        hulls[obj.name] = (hull, slack_px)
    return out


def perturbed_camera_pose(
    X_WC: np.ndarray, seed: int, shift_m: float = CAMERA_SHIFT_M, turn_rad: float = CAMERA_TURN_RAD
) -> np.ndarray:
    """``X_WC`` moved by a random ``shift_m`` and turned by a random ``turn_rad`` (the real
    camera's offset from its calibration)."""
    rng = np.random.default_rng(seed + 1_000_003)

    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    X = np.array(X_WC, dtype=np.float64)
    return make_pose(so3_exp(unit() * turn_rad) @ X[:3, :3], X[:3, 3] + unit() * shift_m)
