"""Our pinhole projection of a model agrees with pybullet's rendering of it (issue 4)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from bench.vision_dataset import SceneRenderer
from models.scene import load_scene
from models.transforms import invert_pose, make_pose, rpy_to_R
from work_site.camera import render_grey
from work_site.vision.model import project, transform, vision_model

SUPERSAMPLE = 4


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(load_scene(), supersample=SUPERSAMPLE)
    yield r
    r.close()


@pytest.mark.parametrize(
    ("name", "rpy", "xy", "dist"),
    [
        ("cube", (0.0, 0.0, 0.5), (0.45, -0.2), None),
        ("l_block", (np.pi / 2, 0.0, -0.4), (0.55, 0.05), None),
        ("hex_prism", (0.0, 0.0, 0.2), (0.63, 0.18), None),
        # A lens: its corners land where OpenCV's distortion model puts them.
        ("cube", (0.0, 0.0, 0.5), (0.45, -0.2), (-0.12, 0.05, 0.0, 0.0, 0.0)),
        ("hex_prism", (0.0, 0.0, 0.2), (0.63, 0.18), (0.04, -0.02, 1e-3, -1e-3, 0.0)),
    ],
)
def test_projected_silhouette_corners_match_the_rendering(renderer, name, rpy, xy, dist) -> None:
    scene = renderer.scene
    camera = scene.camera
    if dist is not None:
        camera = dataclasses.replace(camera, dist=np.array(dist))
    obj = scene.object(name)
    R = rpy_to_R(np.array(rpy))
    V_O = np.vstack([p.vertices_O for p in obj.model.parts])
    X_WO = make_pose(R, [xy[0], xy[1], -np.min(V_O @ R[2])])
    # Everything else off the table and out of view.
    for k, other in enumerate(renderer.movable):
        renderer.world.set_object_pose(other.name, make_pose(None, [5.0 + k, 5.0, -1.0]))
    renderer.world.set_object_pose(name, X_WO)
    _, seg = render_grey(renderer.world.cid, camera, SUPERSAMPLE, segmentation=True)
    mask = (seg == renderer.world.bodies[name]).astype(np.uint8)
    assert mask.sum() > 1000, "the object must be in view"
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)
    model = vision_model(obj.model)
    p_C = transform(invert_pose(camera.X_WC) @ X_WO, model.vertices_O)
    uv = cv2.projectPoints(p_C, np.zeros(3), np.zeros(3), camera.K, camera.dist)[0].reshape(-1, 2)
    if dist is None:
        assert np.allclose(uv, project(p_C, camera.K))
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    # Keep real corners of the silhouette (drop hull points on a straight stretch).
    corners = []
    for i in range(len(hull)):
        a, b, c = hull[i - 1], hull[i], hull[(i + 1) % len(hull)]
        u, v = b - a, c - b
        turn = abs(np.arctan2(u[0] * v[1] - u[1] * v[0], u @ v))
        if turn > np.deg2rad(5):
            corners.append(b)
    assert len(corners) >= 4
    # Each corner on the rendered outline (its pixels' boundary, in supersampled pixels):
    # within half an image pixel, where the outline's own steps are a quarter of one.
    dist = [
        abs(cv2.pointPolygonTest(contour, tuple(map(float, (c + 0.5) * SUPERSAMPLE - 0.5)), True))
        / SUPERSAMPLE
        for c in corners
    ]
    assert max(dist) <= 0.5, f"corner distances (px): {np.round(dist, 3)}"


@pytest.mark.parametrize("supersample", [1, 2])
def test_the_rendering_has_no_sub_pixel_offset_from_the_camera_model(supersample) -> None:
    """A block's rendered silhouette and its projection by the camera model share their
    centroid to a twentieth of a pixel (the renderer's own sampling made up for)."""
    renderer = SceneRenderer(load_scene(), supersample=supersample)
    try:
        camera = renderer.scene.camera
        for k, other in enumerate(renderer.movable):
            renderer.world.set_object_pose(other.name, make_pose(None, [5.0 + k, 5.0, -1.0]))
        obj = renderer.scene.object("plank")
        V = np.vstack([pt.vertices_O for pt in obj.model.parts])
        rng = np.random.default_rng(0)
        offsets = []
        for _ in range(8):  # sub-pixel phases: a mask's centroid is exact only on average
            xy = (0.45 + rng.uniform(-0.02, 0.02), -0.27 + rng.uniform(-0.02, 0.02))
            X_WO = make_pose(None, [xy[0], xy[1], -V[:, 2].min()])
            renderer.world.set_object_pose("plank", X_WO)
            _, seg = render_grey(renderer.world.cid, camera, supersample, segmentation=True)
            m = cv2.moments((seg == renderer.world.bodies["plank"]).astype(np.uint8), True)
            rendered = (np.array([m["m10"], m["m01"]]) / m["m00"] + 0.5) / supersample - 0.5
            uv = project(transform(invert_pose(camera.X_WC) @ X_WO, V), camera.K)
            h = cv2.moments(cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2))
            offsets.append(rendered - np.array([h["m10"], h["m01"]]) / h["m00"])
    finally:
        renderer.close()
    mean = np.mean(offsets, axis=0)
    assert np.all(np.abs(mean) < 0.05), f"rendered − projected centroid: {mean.round(3)} px"
