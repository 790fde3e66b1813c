"""The vision benchmark's realistic scenes: blocks dropped onto others come to rest as the
physics says and are labelled by how they rest; each scene has its own camera (issue 23)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.vision_dataset import SUPPORTS, SceneRenderer, read_truth, write_dataset
from models.transforms import make_pose, rpy_to_R
from work_site.sensor import CameraConditions
from work_site.vision.model import transform


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(supersample=1)
    yield r
    r.close()


def cube_pose(rpy, xy, lift_m, renderer) -> np.ndarray:
    V = renderer.scene.object("cube").model.parts[0].vertices_O
    R = rpy_to_R(np.array(rpy))
    return make_pose(R, [xy[0], xy[1], renderer.table_z - np.min(V @ R[2]) + lift_m])


def test_support_says_how_a_block_rests(renderer) -> None:
    assert renderer.support("cube", cube_pose((0, 0, 0.3), (0.4, 0.1), 0.0, renderer)) == "table"
    tilted = cube_pose((0.5, 0, 0.3), (0.4, 0.1), 0.0, renderer)
    assert renderer.support("cube", tilted) == "leaning"
    assert renderer.support("cube", cube_pose((0, 0, 0), (0.4, 0.1), 0.03, renderer)) == "stacked"


def test_dropped_blocks_come_to_rest_on_others_or_the_table(renderer) -> None:
    rng = np.random.default_rng(3)
    supports = []
    for _ in range(3):
        poses = renderer.dropped_layout(rng, drop_probability=1.0)
        for obj in renderer.movable:
            X = poses[obj.name]
            if X[2, 3] < -0.5:  # parked out of view: fell off the table
                continue
            V = np.vstack([pt.vertices_O for pt in obj.model.parts])
            low = transform(X, V)[:, 2].min()
            assert low > renderer.table_z - 2e-3, f"{obj.name} sank into the table"
            supports.append(renderer.support(obj.name, X))
    assert set(supports) <= set(SUPPORTS)
    assert "stacked" in supports or "leaning" in supports, supports


def test_a_realistic_dataset_gives_each_scene_its_camera_and_conditions(tmp_path) -> None:
    paths = write_dataset(
        tmp_path, 2, seed=5, supersample=1, conditions=CameraConditions(), drop_probability=0.5
    )
    cameras = []
    for path in paths:
        doc = json.loads(path.read_text())
        camera = json.loads((tmp_path / doc["camera"]).read_text())
        cameras.append(np.array(camera["X_WC"]))
        assert np.any(np.array(camera["dist"]) != 0)
        assert set(doc["conditions"]) >= {"sensor", "lighting", "camera_offset_m", "dist"}
        truth = read_truth(path)
        assert all(t.support in (*SUPPORTS, "") for t in truth)
        assert (tmp_path / doc["image"]).stat().st_size > 1000
    assert not np.allclose(cameras[0], cameras[1])
