"""Wireframes of recognised objects drawn over the camera image (Fig. 5's camera window)."""

from __future__ import annotations

import cv2
import numpy as np

from models.scene import CameraModel, ObjectModel
from models.transforms import invert_pose

ACCEPTED_BGR = (60, 200, 60)
PENDING_BGR = (0, 190, 255)
MIN_DEPTH_M = 1e-3
"""Edges with an end closer to the camera plane than this are not drawn (m)."""


def project_edges_px(model: ObjectModel, X_WO: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The model's feature edges at ``X_WO`` in pixels, (m, 2, 2); edges behind the camera are
    dropped."""
    X_CO = invert_pose(camera.X_WC) @ np.asarray(X_WO, dtype=np.float64)
    E = model.feature_edges_O.reshape(-1, 3)
    p_C = E @ X_CO[:3, :3].T + X_CO[:3, 3]
    in_front = (p_C[:, 2] > MIN_DEPTH_M).reshape(-1, 2).all(axis=1)
    if not np.any(in_front):
        return np.zeros((0, 2, 2))
    uv, _ = cv2.projectPoints(
        p_C.reshape(-1, 2, 3)[in_front].reshape(-1, 3),
        np.zeros(3),
        np.zeros(3),
        camera.K,
        camera.dist,
    )
    return uv.reshape(-1, 2, 2)


def draw_wireframes(
    image: np.ndarray,
    camera: CameraModel,
    objects: list[tuple[ObjectModel, np.ndarray, bool]],
    scale: float = 1.0,
) -> np.ndarray:
    """``image`` (grey or BGR, camera-sized) as BGR scaled by ``scale``, with each
    (model, X_WO, accepted) drawn: green if accepted into the model, orange if not yet."""
    out = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if scale != 1.0:
        out = cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    else:
        out = out.copy()
    for model, X_WO, accepted in objects:
        colour = ACCEPTED_BGR if accepted else PENDING_BGR
        for (u0, v0), (u1, v1) in project_edges_px(model, X_WO, camera) * scale:
            cv2.line(
                out,
                (round(u0), round(v0)),
                (round(u1), round(v1)),
                colour,
                1,
                cv2.LINE_AA,
            )
    return out
