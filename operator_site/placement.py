"""Whether vision sees the block where the program put it, once the work site says "done".

The work site verifies a program's contacts by force before it releases the block, but not
what happens after: a block can tip or turn as the fingers open, or be dragged as they leave.
Vision then tells, as far as it can: a block seen where the program put it (within the bounds
by which vision's fusion calls two sightings one placement) is there; a block found
elsewhere by more than one search has moved, and the run did not do its task, whatever the
program's report says. A block vision does not find again proves nothing either way. The
other blocks are looked at in the same frames: one found with its centre away from where
the model had it was disturbed (pushed, dragged, knocked over).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from operator_site.taskfile import pose_error
from protocol import Recognitions

PLACED_M = 0.0075
PLACED_RAD = math.radians(7.5)
"""A block seen this close to its goal (both bounds) is where the program put it: the bounds by
which the work site's vision calls two sightings one placement, well outside one frame's error
and well inside a block that tipped, turned or was dragged."""
MOVED_SEARCHES = 2
"""Searches that must find the block in one placement away from its goal before it is called
moved: one search's mistake (a block taken for another, turned) is not taken at its word."""
CHECK_FRAMES = 4
"""Searched frames looked at, at most, for the block (2 s at the scripted work site's rate)."""

VERDICTS = ("placed", "moved", "unsure", "unseen")


@dataclass(frozen=True)
class PlacementCheck:
    """What vision saw of ``block`` after the program: ``verdict`` one of :data:`VERDICTS`
    (placed: where the program put it; moved: found elsewhere by :data:`MOVED_SEARCHES`
    searches; unsure: found elsewhere by fewer; unseen: not found), the pose seen against the
    goal (m, rad; None if unseen), the searched frames looked at, and the other blocks found
    with their centres away from where the model had them by :data:`MOVED_SEARCHES` searches
    in those frames: ``(name, m, rad)`` each."""

    block: str
    verdict: str
    error_m: float | None
    error_rad: float | None
    frames: int
    disturbed: tuple[tuple[str, float, float], ...] = ()

    def sentence(self) -> str:
        """The check in words, for the operator."""
        also = "".join(
            f"; it also sees the {name} {_off(error_m, error_rad)} from where the model had it"
            for name, error_m, error_rad in self.disturbed
        )
        if self.error_m is None or self.error_rad is None:
            return (
                f"vision did not find the {self.block} after the program ({self.frames} "
                f"searches){also}"
            )
        off = _off(self.error_m, self.error_rad)
        if self.verdict == "placed":
            return f"vision sees the {self.block} where the program put it ({off} off){also}"
        sure = "" if self.verdict == "moved" else ", not confirmed by another search"
        return f"vision sees the {self.block} {off} from where the program put it{sure}{also}"

    def to_json(self) -> dict:
        """The check as a run's result carries it (``vision_check``: mm and degrees)."""
        return {
            "block": self.block,
            "verdict": self.verdict,
            "error_mm": None if self.error_m is None else round(self.error_m * 1e3, 2),
            "error_deg": None if self.error_rad is None else round(math.degrees(self.error_rad), 2),
            "frames": self.frames,
            "disturbed": [
                {
                    "block": name,
                    "error_mm": round(error_m * 1e3, 2),
                    "error_deg": round(math.degrees(error_rad), 2),
                }
                for name, error_m, error_rad in self.disturbed
            ],
        }


def _off(error_m: float, error_rad: float) -> str:
    return f"{error_m * 1e3:.1f} mm, {math.degrees(error_rad):.1f}°"


def check_placement(
    block: str,
    X_goal_WO: np.ndarray,
    symmetries: Sequence[np.ndarray],
    frames: Iterable[Recognitions],
    max_frames: int = CHECK_FRAMES,
    others: Mapping[str, tuple[np.ndarray, Sequence[np.ndarray]]] | None = None,
) -> PlacementCheck:
    """Read vision's frames taken after the program (searched ones; tracked ones are passed
    over) until ``block`` is seen within vision's same-placement bounds of ``X_goal_WO``
    (placed), or seen away from it by :data:`MOVED_SEARCHES` searches (moved), or
    ``max_frames`` searched frames have come (unsure if it was seen away, else unseen).

    ``others``: the blocks the program was not to move, each's pose in the model and its
    symmetries; in the frames read, one seen last with its centre more than :data:`PLACED_M`
    from that pose's by :data:`MOVED_SEARCHES` searches is :attr:`PlacementCheck.disturbed`."""
    n = 0
    away: tuple[float, float] | None = None
    disturbed: dict[str, tuple[float, float]] = {}

    def check(verdict: str, error_m: float | None, error_rad: float | None) -> PlacementCheck:
        moved = tuple((name, *disturbed[name]) for name in sorted(disturbed))
        return PlacementCheck(block, verdict, error_m, error_rad, n, moved)

    for recs in frames:
        if recs.tracked:
            continue
        n += 1
        for r in recs.objects:
            if others and r.model in others and r.model != block:
                # By where its centre is: a block pushed or knocked over moves it, while a
                # block partly hidden by the one put on it can be seen turned in place.
                X_model_WO, its_symmetries = others[r.model]
                error_m, error_rad = pose_error(X_model_WO, r.X_WO, its_symmetries)
                if error_m <= PLACED_M:
                    disturbed.pop(r.model, None)
                elif r.searches >= MOVED_SEARCHES:
                    disturbed[r.model] = (error_m, error_rad)
        errors = sorted(
            (pose_error(X_goal_WO, r.X_WO, symmetries), r.searches)
            for r in recs.objects
            if r.model == block
        )
        for (error_m, error_rad), searches in errors:
            if error_m <= PLACED_M and error_rad <= PLACED_RAD:
                return check("placed", error_m, error_rad)
            if searches >= MOVED_SEARCHES:
                return check("moved", error_m, error_rad)
        if errors:
            away = errors[0][0]
        if n >= max_frames:
            break
    if away is not None:
        return check("unsure", *away)
    return check("unseen", None, None)
