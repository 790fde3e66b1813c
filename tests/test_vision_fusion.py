"""Poses fused over frames: the median of a placement's sightings, a new track for another
placement, symmetric blocks aligned, tracks forgotten when unseen or on reset."""

from __future__ import annotations

import math

import numpy as np

from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R, so3_exp, so3_log
from work_site.vision.fusion import FUSED_FRAMES, SAME_PLACE_M, UNSEEN_FRAMES, PoseFusion

SCENE = load_scene()
SYMMETRIES = {o.name: o.model.symmetries for o in SCENE.objects}
X_TRUE = make_pose(rpy_to_R(np.array([0.0, 0.0, 0.4])), (0.3, 0.2, 0.025))


def angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(so3_log(R_a.T @ R_b))))


def noisy(rng: np.random.Generator, sigma_m: float, sigma_rad: float) -> np.ndarray:
    X = X_TRUE.copy()
    X[:3, 3] += rng.normal(0.0, sigma_m, 3)
    X[:3, :3] = X[:3, :3] @ so3_exp(rng.normal(0.0, sigma_rad, 3))
    return X


def test_one_outlier_among_a_placements_sightings_moves_the_fused_pose_little() -> None:
    rng = np.random.default_rng(3)
    fusion = PoseFusion(SYMMETRIES)
    sightings = [noisy(rng, 2e-4, math.radians(0.2)) for _ in range(FUSED_FRAMES)]
    outlier = sightings[2].copy()
    outlier[:3, :3] = outlier[:3, :3] @ so3_exp(np.array([0.0, 0.0, math.radians(2.0)]))
    sightings[2] = outlier
    for k, X in enumerate(sightings):
        (fused,) = fusion.add([("l_block", X, 0.8)])
        assert fused.frames == k + 1
    assert angle_deg(outlier[:3, :3], X_TRUE[:3, :3]) > 1.9
    assert angle_deg(fused.X_WO[:3, :3], X_TRUE[:3, :3]) < 0.4
    # The positions' median, component by component (an independent reference).
    np.testing.assert_allclose(
        fused.X_WO[:3, 3], np.median([X[:3, 3] for X in sightings], axis=0), atol=1e-12
    )
    assert 0.0 < fused.spread_m < 1e-3 and math.radians(0.5) < fused.spread_rad < math.radians(1.5)
    # Rigid: a rotation, not any matrix.
    np.testing.assert_allclose(fused.X_WO[:3, :3].T @ fused.X_WO[:3, :3], np.eye(3), atol=1e-12)


def test_a_sighting_of_another_placement_is_reported_as_it_was_seen() -> None:
    fusion = PoseFusion(SYMMETRIES)
    for _ in range(3):
        fusion.add([("cube", X_TRUE, 0.9)])
    moved = X_TRUE.copy()
    moved[0, 3] += 2 * SAME_PLACE_M
    (fused,) = fusion.add([("cube", moved, 0.9)])
    assert fused.frames == 1 and fused.spread_m == 0.0
    np.testing.assert_array_equal(fused.X_WO, moved)
    # The old placement, seen again, still has its track.
    (again,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert again.frames == 4


def test_a_symmetric_block_seen_a_quarter_turn_apart_is_one_placement() -> None:
    """The cube's frame may come out turned by any of its symmetries: the same look."""
    fusion = PoseFusion(SYMMETRIES)
    quarter = X_TRUE.copy()
    quarter[:3, :3] = X_TRUE[:3, :3] @ rpy_to_R(np.array([0.0, 0.0, math.pi / 2]))
    fusion.add([("cube", X_TRUE, 0.9)])
    (fused,) = fusion.add([("cube", quarter, 0.9)])
    assert fused.frames == 2 and fused.spread_rad < 1e-9
    # The L-block has no such symmetry: a quarter turn is another placement.
    fusion.add([("l_block", X_TRUE, 0.9)])
    (other,) = fusion.add([("l_block", quarter, 0.9)])
    assert other.frames == 1


def test_two_blocks_of_one_model_keep_their_own_tracks() -> None:
    fusion = PoseFusion(SYMMETRIES)
    far = X_TRUE.copy()
    far[1, 3] += 0.1
    for _ in range(3):
        a, b = fusion.add([("cube", X_TRUE, 0.9), ("cube", far, 0.8)])
    assert (a.frames, b.frames) == (3, 3)
    np.testing.assert_array_equal(b.X_WO, far)


def test_a_placement_unseen_for_some_frames_is_forgotten_and_reset_forgets_all() -> None:
    fusion = PoseFusion(SYMMETRIES)
    fusion.add([("cube", X_TRUE, 0.9)])
    for _ in range(UNSEEN_FRAMES - 1):
        fusion.add([])
    (kept,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert kept.frames == 2  # missed in fewer frames than UNSEEN_FRAMES: still tracked
    for _ in range(UNSEEN_FRAMES):
        fusion.add([])
    (new,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert new.frames == 1
    fusion.add([("cube", X_TRUE, 0.9)])
    fusion.reset()
    (after,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert after.frames == 1


def test_only_the_newest_sightings_are_fused() -> None:
    fusion = PoseFusion(SYMMETRIES)
    for _ in range(FUSED_FRAMES + 3):
        (fused,) = fusion.add([("wedge", X_TRUE, 0.9)])
    assert fused.frames == FUSED_FRAMES


def test_tracked_sightings_refine_a_placement_but_only_searches_confirm_or_forget_it() -> None:
    """Sightings tracked from the frame before add frames, not searches; a placement tracking
    lost is not forgotten over tracked frames, only over searches that miss it."""
    fusion = PoseFusion(SYMMETRIES)
    (first,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert (first.frames, first.searches) == (1, 1)
    for _ in range(3):
        (tracked,) = fusion.add([("cube", X_TRUE, 0.9)], searched=False)
    assert (tracked.frames, tracked.searches) == (4, 1)
    for _ in range(UNSEEN_FRAMES + 2):
        assert fusion.add([], searched=False) == []
    (again,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert (again.frames, again.searches) == (min(5, FUSED_FRAMES), 2)
    for _ in range(UNSEEN_FRAMES):
        fusion.add([])
    (new,) = fusion.add([("cube", X_TRUE, 0.9)], searched=False)
    assert (new.frames, new.searches) == (1, 0)


def test_a_placement_counts_the_other_placements_of_its_model_not_yet_forgotten() -> None:
    """Vision putting one block in two places by turns: each placement says there is one other
    (a second block of the model would too); once searches stop finding the other for
    UNSEEN_FRAMES frames, none. Tracked frames neither make nor forget one."""
    fusion = PoseFusion(SYMMETRIES)
    far = X_TRUE.copy()
    far[0, 3] += 0.05
    (first,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert first.rivals == 0
    (other,) = fusion.add([("cube", far, 0.9)])
    assert other.rivals == 1
    (again,) = fusion.add([("cube", X_TRUE, 0.9)])
    assert (again.searches, again.rivals) == (2, 1)
    (tracked,) = fusion.add([("cube", X_TRUE, 0.9)], searched=False)
    assert tracked.rivals == 1
    for _ in range(UNSEEN_FRAMES - 2):
        (still,) = fusion.add([("cube", X_TRUE, 0.9)])
        assert still.rivals == 1
    (alone,) = fusion.add([("cube", X_TRUE, 0.9)])  # the other unseen UNSEEN_FRAMES searches
    assert alone.rivals == 0
    a, b = fusion.add([("wedge", X_TRUE, 0.9), ("wedge", far, 0.8)])
    assert (a.rivals, b.rivals) == (1, 1)
