"""The operator's model editor: accepting recognitions and making them consistent (§IV-C)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import rpy_to_R
from operator_site.model_editor import WorkSiteModel
from operator_site.simulator import SimParams

EPS_B = SimParams().eps_barrier_m


@pytest.fixture(scope="module")
def scene():
    return load_scene()


def truth(scene, name: str) -> np.ndarray:
    return scene.object(name).X_WO.copy()


def test_a_sunk_tilted_block_is_settled_flat_on_the_table(scene) -> None:
    model = WorkSiteModel(scene)
    X = truth(scene, "cube")
    X[2, 3] -= 0.002  # 2 mm into the table
    X[:3, :3] = rpy_to_R(np.array([math.radians(1.5), 0.0, 0.0])) @ X[:3, :3]
    model.accept("cube", X)
    (c,) = model.make_consistent()
    settled = model.poses["cube"]
    np.testing.assert_allclose(settled[:3, :3], truth(scene, "cube")[:3, :3], atol=1e-9)
    assert settled[2, 3] == pytest.approx(0.025 + EPS_B, abs=1e-5)  # ε_b above the table
    assert c.name == "cube" and c.turned_deg == pytest.approx(1.5, abs=1e-6)
    assert c.moved_mm == pytest.approx(2.1, abs=0.01)


def test_a_floating_block_comes_down(scene) -> None:
    model = WorkSiteModel(scene)
    X = truth(scene, "tall_block")
    X[2, 3] += 0.004
    model.accept("tall_block", X)
    model.make_consistent()
    assert model.poses["tall_block"][2, 3] == pytest.approx(0.05 + EPS_B, abs=1e-5)


def test_overlapping_blocks_are_pushed_apart_sideways_not_stacked(scene) -> None:
    model = WorkSiteModel(scene)
    hex_X = truth(scene, "hex_prism")
    l_X = truth(scene, "l_block")
    l_X[0, 3] = hex_X[0, 3] - 0.08 + 0.003  # the L's end 1.4 mm into the prism
    model.accept("hex_prism", hex_X, score=0.9)
    model.accept("l_block", l_X, score=0.5)
    corrections = {c.name: c for c in model.make_consistent()}
    assert "overlapped hex_prism" in corrections["l_block"].why
    assert corrections["hex_prism"].moved_mm < 0.2  # the surer recognition stays
    assert model.poses["l_block"][2, 3] == pytest.approx(l_X[2, 3] + EPS_B, abs=1e-5)
    depth, _ = model._overlap("l_block", "hex_prism")
    assert depth == 0.0


def test_blocks_overlapping_deeper_than_vision_errs_are_refused_not_pushed(scene) -> None:
    """A block seen as another, where a third is: not pushed centimetres aside, refused."""
    from operator_site.model_editor import CONFLICT_OVERLAP_M
    from operator_site.session import OperatorSession

    op = OperatorSession(scene)
    op.accept("cube", truth(scene, "cube"), score=0.9)
    into = truth(scene, "cube")
    into[0, 3] += 2 * CONFLICT_OVERLAP_M  # the wedge's pose, as vision mistook the cube for it
    with pytest.raises(ValueError, match=r"wedge and cube overlap by \d+ mm"):
        op.accept("wedge", into, score=0.8)
    assert set(op.model.poses) == {"cube"}  # the model unchanged


def test_the_scene_holds_only_the_environment_and_accepted_objects(scene) -> None:
    model = WorkSiteModel(scene)
    assert {o.name for o in model.scene().objects} == {"table", "frame"}
    model.accept("cube", truth(scene, "cube"))
    assert {o.name for o in model.scene().objects} == {"table", "frame", "cube"}
    model.remove("cube")
    assert "cube" not in {o.name for o in model.scene().objects}


def test_bad_recognitions_are_refused_with_the_reason(scene) -> None:
    model = WorkSiteModel(scene)
    with pytest.raises(KeyError, match="no object 'teapot'"):
        model.accept("teapot", np.eye(4))
    with pytest.raises(ValueError, match="fixed environment"):
        model.accept("frame", np.eye(4))
    with pytest.raises(ValueError, match="finite"):
        model.accept("cube", np.full((4, 4), math.nan))
    with pytest.raises(KeyError, match="not in the model"):
        model.remove("cube")


def test_a_symmetric_block_seen_upside_down_is_taken_upright(scene) -> None:
    model = WorkSiteModel(scene)
    X = truth(scene, "tall_block")
    flipped = X.copy()
    flipped[:3, :3] = X[:3, :3] @ rpy_to_R(np.array([math.pi, 0.0, 0.0]))
    model.accept("tall_block", flipped)
    upright = model.poses["tall_block"]
    assert upright[2, 2] == pytest.approx(1.0)
    np.testing.assert_array_equal(upright[:3, 3], X[:3, 3])
    V = np.vstack([p.vertices_O for p in scene.object("tall_block").model.parts])
    same = np.sort((V @ upright[:3, :3].T).round(9), axis=0)
    np.testing.assert_allclose(same, np.sort((V @ X[:3, :3].T).round(9), axis=0), atol=1e-9)
    # No symmetry of the L-block turns it upside up: whichever equivalent is kept, it is the
    # same solid in the same place (its corners where the given pose puts them), not upright.
    L = truth(scene, "l_block")
    L[:3, :3] = L[:3, :3] @ rpy_to_R(np.array([math.pi, 0.0, 0.0]))
    model.accept("l_block", L)
    kept = model.poses["l_block"]
    C = np.unique(np.round(scene.object("l_block").model.feature_edges_O.reshape(-1, 3), 9), axis=0)
    np.testing.assert_allclose(
        np.sort((C @ kept[:3, :3].T).round(9), axis=0),
        np.sort((C @ L[:3, :3].T).round(9), axis=0),
        atol=1e-9,
    )
    np.testing.assert_array_equal(kept[:3, 3], L[:3, 3])
    assert kept[2, 2] < 0.5
