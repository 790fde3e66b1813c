"""`work-site recognize` and the benchmark's dataset renderer: clear refusals of bad input, JSON
as DESIGN.md says, and a rendered scene recognised end to end."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench import vision_dataset
from models.scene import DEFAULT_SCENE, load_scene
from work_site.vision.cli import main


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    # One index per test session, shared by the vision test modules.
    path = tmp_path_factory.getbasetemp() / "vision-index-cache"
    path.mkdir(exist_ok=True)
    return path


@pytest.fixture
def camera_json(tmp_path) -> Path:
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(load_scene(DEFAULT_SCENE).camera.to_json()))
    return path


def _recognize(image: Path, camera: Path, cache: Path, *extra: str) -> list[str]:
    return ["recognize", str(image), "--camera", str(camera), "--cache-dir", str(cache), *extra]


def test_a_file_that_is_not_an_image_is_refused(tmp_path, camera_json, cache_dir, capsys):
    bogus = tmp_path / "notes.png"
    bogus.write_text("this is not a PNG")
    assert main(_recognize(bogus, camera_json, cache_dir, "--json")) == 2
    assert "not an image file" in capsys.readouterr().err


def test_a_missing_image_is_refused(tmp_path, camera_json, cache_dir, capsys):
    assert main(_recognize(tmp_path / "nope.png", camera_json, cache_dir)) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_1x1_image_is_refused_with_the_sizes(tmp_path, camera_json, cache_dir, capsys):
    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), np.zeros((1, 1), np.uint8))
    assert main(_recognize(tiny, camera_json, cache_dir, "--json")) == 2
    assert "image is 1×1 but camera" in capsys.readouterr().err


@pytest.mark.parametrize(
    "K", [[[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 0, 320], [0, 0, 240], [0, 0, 1]]]
)
def test_a_camera_with_singular_K_is_refused(tmp_path, cache_dir, capsys, K):
    cam = load_scene(DEFAULT_SCENE).camera.to_json()
    cam["K"] = K
    path = tmp_path / "bad_camera.json"
    path.write_text(json.dumps(cam))
    image = tmp_path / "black.png"
    cv2.imwrite(str(image), np.zeros((480, 640), np.uint8))
    assert main(_recognize(image, path, cache_dir, "--json")) == 2
    assert "K must be" in capsys.readouterr().err


@pytest.mark.slow
def test_an_all_black_image_gives_no_objects(tmp_path, camera_json, cache_dir, capsys):
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((480, 640), np.uint8))
    assert main(_recognize(black, camera_json, cache_dir, "--json")) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["objects"] == [] and doc["elapsed_s"] >= 0


def _render_dataset(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    vision_dataset.add_arguments(parser)
    return vision_dataset.main(parser.parse_args(argv))


@pytest.mark.slow
def test_render_a_scene_then_recognise_it(tmp_path, cache_dir, capsys):
    out = tmp_path / "data"
    assert _render_dataset(["--n", "1", "--seed", "5", "--out", str(out)]) == 0
    truth = json.loads((out / "scene_0000.json").read_text())
    assert {o["model"] for o in truth["objects"]} == {
        "cube", "tall_block", "plank", "wedge", "l_block", "hex_prism"
    }  # fmt: skip
    assert all(0.0 <= o["visible_fraction"] <= 1.0 for o in truth["objects"])
    image = cv2.imread(str(out / "scene_0000.png"), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint8 and image.shape == (480, 640)
    capsys.readouterr()
    assert main(_recognize(out / "scene_0000.png", out / "camera.json", cache_dir, "--json")) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["objects"], "something is recognised in a rendered scene"
    gt = {o["model"]: np.array(o["X_WO"]) for o in truth["objects"]}
    for obj in doc["objects"]:
        X = np.array(obj["X_WO"])
        assert X.shape == (4, 4) and np.allclose(X[3], [0, 0, 0, 1])
        assert 0.0 <= obj["score"] <= 1.0
        assert np.linalg.norm(X[:3, 3] - gt[obj["model"]][:3, 3]) < 0.01


def test_render_dataset_refuses_bad_counts(tmp_path, capsys):
    assert _render_dataset(["--n", "0", "--out", str(tmp_path)]) == 2
    assert "--n must be" in capsys.readouterr().err
