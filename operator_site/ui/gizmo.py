"""The gizmo the operator drags a block with, free of viser: where it sits, which way its axes
point, and how its motion becomes the block's target, snapped.

The gizmo and the block are two frames: the gizmo's axes are the world's by default (red along
the table's x, whatever the block's own frame, which is an arbitrary one of its symmetries), or
the block's own on a toggle. Its origin is the block's. When it is placed on a block the block's
pose in the gizmo's frame, ``X_GO``, is kept; a gizmo pose ``X_WG`` then asks for the block at
``X_WG · X_GO``.

Snapping acts on the motion since the drag began, not on absolute coordinates (a block lies
where vision put it, off any grid): the translation in steps along the world's axes, the turn
in steps about its own axis (the gizmo turns about one axis at a time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.transforms import invert_pose, make_pose, so3_exp, so3_log

SNAP_STEP_M = 1e-3
SNAP_STEP_RAD = math.radians(5.0)
"""The default snapping steps: a millimetre and five degrees."""
SNAP_STEP_M_RANGE = (1e-5, 0.05)
SNAP_STEP_RAD_RANGE = (math.radians(0.01), math.radians(90.0))


@dataclass(frozen=True)
class Snap:
    """Snapping steps (None: that part is not snapped)."""

    step_m: float | None = SNAP_STEP_M
    step_rad: float | None = SNAP_STEP_RAD

    def __post_init__(self) -> None:
        for value, (lo, hi), what in (
            (self.step_m, SNAP_STEP_M_RANGE, "step_m (m)"),
            (self.step_rad, SNAP_STEP_RAD_RANGE, "step_rad (rad)"),
        ):
            if value is not None and not (lo <= value <= hi):
                raise ValueError(f"snap {what} must be in [{lo:g}, {hi:g}], not {value!r}")


NO_SNAP = Snap(None, None)


def gizmo_pose_W(X_WO: np.ndarray, world_axes: bool) -> np.ndarray:
    """Where the gizmo sits on a block at ``X_WO``: at its origin, with the world's axes or the
    block's own."""
    if not world_axes:
        return np.array(X_WO, dtype=np.float64)
    return make_pose(np.eye(3), np.asarray(X_WO, dtype=np.float64)[:3, 3])


def snapped_motion(X_WG0: np.ndarray, X_WG: np.ndarray, snap: Snap) -> np.ndarray:
    """The gizmo moved from ``X_WG0`` (where the drag began) to ``X_WG``: that pose with the
    translation and the turn since ``X_WG0`` snapped to ``snap``'s steps."""
    X_WG0 = np.asarray(X_WG0, dtype=np.float64)
    X_WG = np.asarray(X_WG, dtype=np.float64)
    shift_W = X_WG[:3, 3] - X_WG0[:3, 3]
    if snap.step_m is not None:
        shift_W = np.round(shift_W / snap.step_m) * snap.step_m
    turn_W = so3_log(X_WG[:3, :3] @ X_WG0[:3, :3].T)
    if snap.step_rad is not None:
        angle = float(np.linalg.norm(turn_W))
        if angle > 0.0:
            turn_W = turn_W / angle * (round(angle / snap.step_rad) * snap.step_rad)
    R_W = so3_exp(turn_W) @ X_WG0[:3, :3]
    return make_pose(R_W, X_WG0[:3, 3] + shift_W)


class Gizmo:
    """The gizmo's state on one block: its frame relative to the block, where the current drag
    began, and the snapping."""

    def __init__(self, world_axes: bool = True, snap: Snap = Snap()) -> None:
        self.world_axes = world_axes
        self.snap = snap
        self.X_GO = np.eye(4)
        self.X_WG_placed = np.eye(4)
        self.X_WG0: np.ndarray | None = None

    def place(self, X_WO: np.ndarray) -> np.ndarray:
        """Put the gizmo on a block at ``X_WO``; the gizmo's pose."""
        X_WG = gizmo_pose_W(X_WO, self.world_axes)
        self.X_GO = invert_pose(X_WG) @ np.asarray(X_WO, dtype=np.float64)
        self.X_WG_placed, self.X_WG0 = X_WG, None
        return X_WG

    def begin(self) -> None:
        """A drag begins, from where the gizmo was placed (the browser's first event of a drag
        may already carry some motion)."""
        self.X_WG0 = self.X_WG_placed.copy()

    def target_W(self, X_WG: np.ndarray) -> np.ndarray:
        """The gizmo dragged to ``X_WG``: the block's target pose, the motion since the drag
        began snapped."""
        X_WG = np.asarray(X_WG, dtype=np.float64)
        if self.X_WG0 is not None:
            X_WG = snapped_motion(self.X_WG0, X_WG, self.snap)
        return X_WG @ self.X_GO
