"""The vision package's public API is what its ``__init__`` exports, and all of it exists."""

from __future__ import annotations

import work_site.vision as vision


def test_exported_names_exist_and_are_public() -> None:
    assert sorted(vision.__all__) == sorted(set(vision.__all__))
    for name in vision.__all__:
        assert not name.startswith("_")
        assert getattr(vision, name) is not None


def test_exports_are_what_the_work_site_server_needs() -> None:
    assert {"Recognizer", "Detection", "recognize"} <= set(vision.__all__)


def test_a_detection_unpacks_as_model_pose_score() -> None:
    import numpy as np

    r = vision.Detection("cube", np.eye(4), 0.9)
    name, X_WO, score = r
    assert name == "cube" and X_WO.shape == (4, 4) and score == 0.9
