"""Poses fused over frames: each block vision finds again in the same place is reported with
the median of its last sightings, and how far they spread.

One frame's pose of a block carries that frame's sensor noise: most are a fraction of a
millimetre and a few tenths of a degree off, and now and then one is turned by a degree or
two. While the scene holds still (no program running), a block seen again within
:data:`SAME_PLACE_M` and :data:`SAME_PLACE_RAD` of its track is the same placement: the
reported pose is the median of the track's last :data:`FUSED_FRAMES` sightings (a single
outlier among three or more moves it little), with their spread about it. A sighting beyond
those bounds is another placement (or another block) and starts a track of its own, so a
block that moved, or a frame that put a block somewhere else, is reported as that frame saw
it, never averaged with what came before.

A frame's sightings come from a full search or from tracking (refitted from the frame before).
Tracked sightings refine a pose; they do not confirm it as another search does: a track counts
the searches that found it (:attr:`Fused.searches`) apart from its sightings. Each fused pose
also says how many other placements of its model searches have found and not yet forgotten
(:attr:`Fused.rivals`): a block that vision puts in one place in some frames and in another in
others (mistaken for another block, or another for it) is not sure in either.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from models.transforms import so3_exp, so3_log

FUSED_FRAMES = 5
"""Sightings of one placement fused at most: the newest this many."""
SAME_PLACE_M = 0.0075
SAME_PLACE_RAD = math.radians(7.5)
"""A sighting this close to a track (both bounds) is the same placement seen again: five
times the operator's default tolerance, well outside one frame's error, well inside the
distance to another placement or another block."""
UNSEEN_FRAMES = 3
"""A track not seen in this many searched frames in a row is dropped (a block taken away, or a
pose no frame gives again). Tracked frames do not count: tracking follows only what the frame
before had, so a placement it lost stays unseen until the next search, whatever is there."""


@dataclass(frozen=True)
class Fused:
    """One block in one frame: the fused pose ``X_WO``, the sightings fused, and their spread
    about it (RMS distance, m, and RMS angle, rad; 0 for one sighting); ``searches``: how many
    full searches have found this placement since its track began; ``rivals``: how many other
    placements of this model searches have found and not forgotten."""

    model: str
    X_WO: np.ndarray
    score: float
    frames: int
    spread_m: float
    spread_rad: float
    searches: int
    rivals: int = 0


class _Track:
    def __init__(self, X_WO: np.ndarray) -> None:
        self.seen: deque[np.ndarray] = deque([X_WO], maxlen=FUSED_FRAMES)
        self.fused = X_WO
        self.unseen = 0
        self.searches = 0


class PoseFusion:
    """Tracks of each model's placements across frames (:meth:`add` one frame at a time);
    :meth:`reset` forgets them all (when the scene may have moved)."""

    def __init__(self, symmetries: Mapping[str, np.ndarray]) -> None:
        """``symmetries``: each model's symmetry rotations (s, 3, 3) in its own frame."""
        self._symmetries = {k: np.asarray(v, dtype=np.float64) for k, v in symmetries.items()}
        self._tracks: dict[str, list[_Track]] = {}

    def reset(self) -> None:
        """Forget every track: the next frame starts afresh."""
        self._tracks.clear()

    def add(
        self, objects: Sequence[tuple[str, np.ndarray, float]], searched: bool = True
    ) -> list[Fused]:
        """The frame's ``(model, X_WO, score)`` sightings, each fused with its track;
        ``searched``: they come from a full search (else from tracking)."""
        out: list[tuple[_Track, Fused]] = []
        matched: set[int] = set()
        for name, X_WO, score in objects:
            X_WO = np.asarray(X_WO, dtype=np.float64)
            tracks = self._tracks.setdefault(name, [])
            S = self._symmetries.get(name, np.eye(3)[None])
            best, best_k = None, -1
            for k, track in enumerate(tracks):
                if id(track) in matched:
                    continue
                d_m = float(np.linalg.norm(X_WO[:3, 3] - track.fused[:3, 3]))
                angle = _angle_rad(track.fused[:3, :3], X_WO[:3, :3], S)
                if d_m <= SAME_PLACE_M and angle <= SAME_PLACE_RAD:
                    key = max(d_m / SAME_PLACE_M, angle / SAME_PLACE_RAD)
                    if best is None or key < best:
                        best, best_k = key, k
            if best_k < 0:
                track = _Track(X_WO)
                tracks.append(track)
            else:
                track = tracks[best_k]
                track.seen.append(X_WO)
                track.fused = _median_pose(list(track.seen), S)
            track.unseen = -1  # seen in this frame (counted up to 0 below)
            track.searches += searched
            matched.add(id(track))
            spread_m, spread_rad = _spread(list(track.seen), track.fused, S)
            out.append(
                (
                    track,
                    Fused(
                        name, track.fused.copy(), float(score), len(track.seen), spread_m,
                        spread_rad, track.searches,
                    ),
                )
            )  # fmt: skip
        if searched:
            for name in list(self._tracks):
                kept = []
                for track in self._tracks[name]:
                    track.unseen += 1
                    if track.unseen < UNSEEN_FRAMES:
                        kept.append(track)
                self._tracks[name] = kept
        return [
            replace(
                f,
                rivals=sum(
                    1 for t in self._tracks.get(f.model, []) if t is not track and t.searches > 0
                ),
            )
            for track, f in out
        ]


def _aligned(R_ref: np.ndarray, R: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Of the rotations ``R · S_k`` (the same look), the one nearest ``R_ref``."""
    candidates = R @ S  # (s, 3, 3)
    traces = np.einsum("ij,kij->k", R_ref, candidates)
    return candidates[int(np.argmax(traces))]


def _angle_rad(R_ref: np.ndarray, R: np.ndarray, S: np.ndarray) -> float:
    return float(np.linalg.norm(so3_log(R_ref.T @ _aligned(R_ref, R, S))))


def _median_pose(poses: list[np.ndarray], S: np.ndarray) -> np.ndarray:
    """The component-wise median of the positions and of the rotations' vectors about the
    newest rotation (each aligned to it by the symmetries): robust to one outlier among three
    or more, and for small spreads (all within :data:`SAME_PLACE_RAD`) the rotations' own."""
    R_ref = poses[-1][:3, :3]
    w = np.median([so3_log(R_ref.T @ _aligned(R_ref, X[:3, :3], S)) for X in poses], axis=0)
    X = np.eye(4)
    X[:3, :3] = R_ref @ so3_exp(w)
    X[:3, 3] = np.median([X[:3, 3] for X in poses], axis=0)
    return X


def _spread(poses: list[np.ndarray], fused: np.ndarray, S: np.ndarray) -> tuple[float, float]:
    """RMS distance (m) and RMS angle (rad) of ``poses`` about ``fused``."""
    d = [float(np.linalg.norm(X[:3, 3] - fused[:3, 3])) for X in poses]
    a = [_angle_rad(fused[:3, :3], X[:3, :3], S) for X in poses]
    return math.sqrt(float(np.mean(np.square(d)))), math.sqrt(float(np.mean(np.square(a))))
