"""Recognised objects drawn over the camera image, and task files."""

from __future__ import annotations

import numpy as np

from models.scene import load_scene
from operator_site.ui.overlay import ACCEPTED_BGR, draw_wireframes, project_edges_px


def test_wireframes_land_on_the_projected_edges() -> None:
    scene = load_scene()
    cam, cube = scene.camera, scene.object("cube")
    edges = project_edges_px(cube.model, cube.X_WO, cam)
    assert len(edges) == 12  # a cube's feature edges, all in front of the camera
    image = np.zeros((cam.height, cam.width), dtype=np.uint8)
    out = draw_wireframes(image, cam, [(cube.model, cube.X_WO, True)])
    assert out.shape == (cam.height, cam.width, 3) and not image.any()  # input untouched
    for (u0, v0), (u1, v1) in edges:
        u, v = round((u0 + u1) / 2), round((v0 + v1) / 2)  # each edge's midpoint is drawn
        assert (
            out[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3).max(axis=0)[1] >= ACCEPTED_BGR[1] // 2
        )
    half = draw_wireframes(image, cam, [(cube.model, cube.X_WO, False)], scale=0.5)
    assert half.shape == (cam.height // 2, cam.width // 2, 3) and half.any()
