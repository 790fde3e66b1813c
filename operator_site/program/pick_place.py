"""A pick-and-place program: the simplest robot program for a task (no §VI-A deformation)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.kinematics import PathFollow, arm_geometry, follow_tcp, plan_approach
from models.robot import RobotModel
from models.transforms import invert_pose, make_pose, rpy_to_R
from protocol import ContactState, MotionCommand, MotionProgram
from protocol.execution import grasp_approach_W

CLEARANCE_M = 0.06
"""Lift, carry and lower this high above the start and goal poses (clears the 30 mm bars)."""
CARRY_SPEED_MPS = 0.1
PLACE_SPEED_MPS = 0.02
"""The last stretch down to the goal is slow: the block is set down, not dropped."""
PLACE_GUARD_N = 4.0
"""Setting the block down stops when the table pushes back this hard (N)."""
HALF_TURN = make_pose(rpy_to_R(np.array([0.0, 0.0, np.pi])))
"""A grasp turned half a turn about the gripper's axis: a parallel gripper holds it alike."""


def carried_arm_path(
    robot: RobotModel,
    X_WB: np.ndarray,
    q_start: np.ndarray,
    X_WP_start: np.ndarray,
    X_GP: np.ndarray,
    path_X_WP: Sequence[np.ndarray],
) -> PathFollow:
    """The arm, from joints ``q_start`` (rad), taking the workpiece at ``X_WP_start`` in grasp
    ``X_GP`` from above and carrying it through ``path_X_WP``, each straight move followed as
    the work site does (:func:`~models.kinematics.follow_line_tcp`)."""
    X_PG = invert_pose(X_GP)
    grasp = np.asarray(X_WP_start) @ X_PG
    over, *above = grasp_approach_W(grasp)  # as the work site comes to it
    geometry = arm_geometry(robot)
    q = np.asarray(q_start, dtype=np.float64)
    here = robot.tcp_pose_W(q, X_WB)
    then = [*above, grasp, *(np.asarray(X) @ X_PG for X in path_X_WP)]
    plan = plan_approach(here, q, over, then, robot, X_WB, geometry)
    if not plan.ok:
        return PathFollow(False, None, reason=plan.reason)
    if plan.q_joint is not None:
        return follow_tcp(over, plan.q_joint, then, robot, X_WB, geometry)
    return follow_tcp(here, q, [over, *then], robot, X_WB, geometry)


def choose_grasp_yaw(
    X_WP: np.ndarray,
    X_GP: np.ndarray,
    path_X_WP: Sequence[np.ndarray] = (),
    arm: tuple[RobotModel, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """``X_GP`` or the same grasp turned half a turn about the gripper axis (a parallel gripper
    holds both alike). With ``arm`` (robot, ``X_WB``, joints at the start), the one the arm can
    carry through the whole way (:func:`carried_arm_path`) farthest from its joint limits.
    Otherwise, or when the arm can carry neither, the one that points the gripper's x axis more
    along −x of W at the workpiece pose ``X_WP`` and at the worst pose of ``path_X_WP``: the
    wrist then stays well inside joint 6's ±3.14 rad on most paths that turn the block."""
    turned = HALF_TURN @ X_GP
    poses = [np.asarray(X_WP, dtype=np.float64), *(np.asarray(X) for X in path_X_WP)]

    def worst_x(grasp: np.ndarray) -> float:
        X_PG = invert_pose(grasp)
        return max(float((X @ X_PG)[0, 0]) for X in poses)

    by_wrist = (X_GP, turned) if worst_x(X_GP) <= worst_x(turned) else (turned, X_GP)
    if arm is None:
        return by_wrist[0]
    follows = [carried_arm_path(*arm, X_WP, grasp, path_X_WP) for grasp in by_wrist]
    best = max(
        range(2), key=lambda i: (follows[i].ok, follows[i].margin_rad if follows[i].ok else 0)
    )
    return by_wrist[best] if follows[best].ok else by_wrist[0]


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
