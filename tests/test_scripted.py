"""The scripted operator's use of vision (issue 9): a block goes into the model once three of
vision's searches found it in the same place (frames tracked between refine it, never confirm
it), and frames are watched only while the task's workpiece is missing. The frames are real
protocol records made here, their poses fused as the work site fuses them
(:class:`~work_site.vision.fusion.PoseFusion`); the whole chain with a real work site is
tests/test_e2e.py's."""

from __future__ import annotations

import numpy as np
import pytest

from models.layout import random_layout
from models.scene import load_scene
from models.transforms import rpy_to_R, so3_log
from operator_site.chain import model_from_frames
from operator_site.scripted import workpiece_candidates
from operator_site.session import ACCEPT_SCORE
from protocol import Recognition, Recognitions
from work_site.vision.fusion import PoseFusion


@pytest.fixture(scope="module")
def layout() -> dict[str, np.ndarray]:
    return random_layout(load_scene(), 0)


def _frames(
    *seen: tuple[dict[str, np.ndarray], dict[str, float]], tracked_between: int = 0
) -> list[Recognitions]:
    """Searched frames of the blocks ``layout`` has, scoring ``scores``, each fused with those
    before as the work site does; after each, ``tracked_between`` frames that track what it
    found."""
    scene = load_scene()
    fusion = PoseFusion({o.name: o.model.symmetries for o in scene.objects})
    out: list[Recognitions] = []

    def frame(objects: list, tracked: bool) -> Recognitions:
        fused = fusion.add(objects, searched=not tracked)
        seq = len(out) + 1
        return Recognitions(
            seq=seq,
            stamp_s=float(seq),
            elapsed_s=0.01 if tracked else 0.07,
            objects=tuple(
                Recognition(
                    f.model,
                    f.X_WO,
                    f.score,
                    f.frames,
                    f.spread_m,
                    f.spread_rad,
                    f.searches,
                    f.rivals,
                )
                for f in fused
            ),
            tracked=tracked,
        )

    for layout, scores in seen:
        objects = [(n, layout[n], s) for n, s in scores.items()]
        out.append(frame(objects, tracked=False))
        for _ in range(tracked_between):
            out.append(frame(objects, tracked=True))
    return out


def _ready(task: str):
    """The scripted task's test of a model: a block fit for its workpiece is in it."""
    return lambda model: bool(workpiece_candidates(task, model))


def test_three_frames_that_agree_are_enough_when_they_have_the_workpiece(layout) -> None:
    frames = _frames(
        (layout, {"cube": 0.9, "plank": 0.8}),
        (layout, {"cube": 0.9, "plank": 0.8}),
        (layout, {"cube": 0.9, "plank": 0.8}),
        (layout, {"wedge": 0.9}),
    )
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"))
    assert rec.frames == 3 and set(rec.model.poses) == {"cube", "plank"}
    assert rec.vision_s == pytest.approx(3 * 0.07)
    assert [c.name for c in rec.corrections] == ["cube", "plank"]


def test_later_frames_add_the_missing_workpiece_and_their_vision_time(layout) -> None:
    scene = load_scene()
    low = ACCEPT_SCORE - 0.1
    frames = _frames(
        (layout, {"plank": 0.9}),
        (layout, {"plank": 0.8, "cube": low}),  # below the threshold: not accepted...
        (layout, {"plank": 0.8, "cube": low}),
        (layout, {"cube": 0.7, "wedge": 0.6}),  # ...but seen there: its third sighting
        (layout, {"tall_block": 0.9}),
    )
    rec = model_from_frames(scene, iter(frames), _ready("around-corner"))
    assert rec.frames == 4
    assert set(rec.model.poses) == {"plank", "cube"}
    assert workpiece_candidates("around-corner", rec.model) == ["cube"]
    assert rec.vision_s == pytest.approx(4 * 0.07)


def test_a_block_mistaken_for_another_in_one_frame_is_not_taken_at_its_word(layout) -> None:
    """Vision, in one frame of ten, saw the cube as the wedge (and missed the real wedge):
    the model has each where the frames after it agree, the cube where it is."""
    mistaken = dict(layout, wedge=layout["cube"])
    frames = _frames(
        (mistaken, {"wedge": 0.95, "plank": 0.9}),
        (layout, {"cube": 0.9, "wedge": 0.8, "plank": 0.9}),
        (layout, {"cube": 0.9, "wedge": 0.8, "plank": 0.9}),
        (layout, {"cube": 0.9, "wedge": 0.8, "plank": 0.9}),
    )
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"))
    assert rec.frames == 4 and set(rec.model.poses) == {"cube", "wedge", "plank"}
    for name in ("cube", "wedge"):
        error_m = np.linalg.norm(rec.model.poses[name][:2, 3] - layout[name][:2, 3])
        assert error_m < 1e-3, (name, error_m)


def test_two_blocks_vision_swaps_in_some_frames_are_not_taken_while_it_does(layout) -> None:
    """Vision puts the cube and the wedge each at the other's place in every other frame: each
    placement reaches three searches, but while the other is not forgotten neither is taken;
    once vision keeps to one for as many searches as it takes to forget the other, that one is
    taken."""
    swapped = dict(layout, cube=layout["wedge"], wedge=layout["cube"])
    scores = {"cube": 0.9, "wedge": 0.9, "plank": 0.9}
    frames = _frames(*[(swapped if k % 2 else layout, scores) for k in range(8)])
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"), max_frames=8)
    assert set(rec.model.poses) == {"plank"} and rec.contested == ("cube", "wedge")
    frames = _frames(
        *[(swapped if k % 2 else layout, scores) for k in range(4)], *[(layout, scores)] * 4
    )
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"), max_frames=8)
    assert set(rec.model.poses) == {"plank", "cube", "wedge"}
    for name in ("cube", "wedge"):
        assert np.linalg.norm(rec.model.poses[name][:3, 3] - layout[name][:3, 3]) < 1e-3


def test_a_block_missed_in_a_frame_between_sightings_is_still_taken(layout) -> None:
    frames = _frames(
        (layout, {"cube": 0.9, "plank": 0.9}),
        (layout, {"plank": 0.9}),  # vision missed the cube in this one
        (layout, {"cube": 0.8, "plank": 0.9}),
        (layout, {"cube": 0.8}),
    )
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"))
    assert rec.frames == 4 and set(rec.model.poses) == {"cube", "plank"}


def test_a_block_seen_turned_in_one_frame_is_taken_at_its_frames_median(layout) -> None:
    """One frame of three turns the cube by 2°: the model has it within a few tenths of a
    degree, not 2/3° as the mean would."""
    turned = layout["cube"].copy()
    turned[:3, :3] = turned[:3, :3] @ rpy_to_R(np.array([0.0, 0.0, np.radians(2.0)]))
    frames = _frames(
        (layout, {"cube": 0.9, "plank": 0.9}),
        (dict(layout, cube=turned), {"cube": 0.9, "plank": 0.9}),
        (layout, {"cube": 0.9, "plank": 0.9}),
    )
    rec = model_from_frames(load_scene(), iter(frames), _ready("corner"))
    R = rec.model.poses["cube"][:3, :3]
    assert np.degrees(np.linalg.norm(so3_log(layout["cube"][:3, :3].T @ R))) < 0.05


def test_the_frames_watched_are_bounded_when_the_workpiece_never_shows(layout) -> None:
    frames = iter(_frames(*[(layout, {"plank": 0.9})] * 99))
    rec = model_from_frames(load_scene(), frames, _ready("corner"), max_frames=4)
    assert rec.frames == 4 and set(rec.model.poses) == {"plank"}
    assert workpiece_candidates("corner", rec.model) == []


def test_no_frame_gives_an_empty_model() -> None:
    rec = model_from_frames(load_scene(), iter([]), _ready("corner"))
    assert rec.frames == 0 and rec.model.poses == {} and rec.vision_s == 0.0


def test_tracked_frames_refine_a_block_but_only_searches_confirm_it(layout) -> None:
    """A search's block tracked over many frames is not taken until three searches found it;
    the searched frames are what ``max_frames`` and ``rec.frames`` count."""
    frames = _frames(
        (layout, {"cube": 0.9, "plank": 0.8}),
        (layout, {"cube": 0.9, "plank": 0.8}),
        (layout, {"cube": 0.9, "plank": 0.8}),
        tracked_between=4,
    )
    taken_after = []

    def ready(model) -> bool:
        taken_after.append(set(model.poses))
        return bool(workpiece_candidates("corner", model))

    rec = model_from_frames(load_scene(), iter(frames), ready)
    assert taken_after[:10] == [set()] * 10  # two searches and the eight tracked frames after
    assert rec.frames == 3 and set(rec.model.poses) == {"cube", "plank"}
    assert rec.tracked_frames == 8
    assert rec.vision_s == pytest.approx(3 * 0.07 + 8 * 0.01)
    bounded = model_from_frames(load_scene(), iter(frames), _ready("corner"), max_frames=2)
    assert bounded.frames == 2 and bounded.model.poses == {}
