"""A pick-and-place program: the simplest robot program for a task (no §VI-A deformation)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.transforms import invert_pose, make_pose, rpy_to_R
from protocol import ContactState, MotionCommand, MotionProgram

CLEARANCE_M = 0.06
"""Lift, carry and lower this high above the start and goal poses (clears the 30 mm bars)."""
CARRY_SPEED_MPS = 0.1
PLACE_SPEED_MPS = 0.02
"""The last stretch down to the goal is slow: the block is set down, not dropped."""
PLACE_GUARD_N = 4.0
"""Setting the block down stops when the table pushes back this hard (N)."""
_HALF_TURN = make_pose(rpy_to_R(np.array([0.0, 0.0, np.pi])))


def choose_grasp_yaw(
    X_WP: np.ndarray, X_GP: np.ndarray, path_X_WP: Sequence[np.ndarray] = ()
) -> np.ndarray:
    """``X_GP`` or the same grasp turned half a turn about the gripper axis (a parallel gripper
    holds both alike), whichever points the gripper's x axis more along −x of W at the
    workpiece pose ``X_WP`` and, with ``path_X_WP`` (the poses the workpiece is carried
    through), at the worst pose of the whole way: the arm's wrist then stays well inside joint
    6's ±3.14 rad on a path that turns the block."""
    turned = _HALF_TURN @ X_GP
    poses = [np.asarray(X_WP, dtype=np.float64), *(np.asarray(X) for X in path_X_WP)]

    def worst_x(grasp: np.ndarray) -> float:
        X_PG = invert_pose(grasp)
        return max(float((X @ X_PG)[0, 0]) for X in poses)

    return X_GP if worst_x(X_GP) <= worst_x(turned) else turned


def _above(X_WP: np.ndarray) -> np.ndarray:
    X = X_WP.copy()
    X[2, 3] += CLEARANCE_M
    return X


def pick_and_place(
    program_id: str, X_WP_start: np.ndarray, X_WP_goal: np.ndarray, X_GP: np.ndarray
) -> MotionProgram:
    """Grasp the workpiece at ``X_WP_start``, lift, carry above ``X_WP_goal``, lower it there
    until the table is felt (a guarded move), release and back off upwards."""

    def cmd(
        kind: str, X: np.ndarray, speed: float = CARRY_SPEED_MPS, force_n: float = 10.0, contacts=()
    ) -> MotionCommand:
        return MotionCommand(
            kind=kind, X_WP=X, speed_mps=speed, force_limit_n=force_n, contacts=contacts
        )

    table = ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]]))
    commands = (
        cmd("guarded_grasp", X_WP_start),
        cmd("move", _above(X_WP_start)),
        cmd("move", _above(X_WP_goal)),
        # Set down by touch, not by position: where the model and the work site differ by a
        # fraction of a millimetre, a plain move onto the table presses on it hard.
        cmd("guarded_move", X_WP_goal, PLACE_SPEED_MPS, PLACE_GUARD_N, (table,)),
        cmd("release", X_WP_goal),
        cmd("move", _above(X_WP_goal)),
    )
    return MotionProgram(program_id=program_id, X_GP=X_GP, commands=commands)
