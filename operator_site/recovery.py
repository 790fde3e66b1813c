"""Ways back after a failure or a stop, without restarting anything: short robot programs, made
from the robot's latest state, that the work site checks and runs like any other (so they get
reports, are run once, and a STOP ends them).

- ``release``: open the fingers where the gripper is.
- ``retract``: back away from what the gripper presses, along the force it feels (and up), at a
  contact move's speed; it fails, and stops, if the force grows instead.
- ``home``: rise straight up to a height clear of every block, then go to where the arm parks
  (its home configuration, out of the camera's view).
"""

from __future__ import annotations

import numpy as np

from models.robot import FT_SENSOR_JOINT, TCP_LINK, load_robot
from models.scene import GRAVITY_W, Scene
from operator_site.program import CommandParams, park_pose_W
from protocol import MotionCommand, MotionProgram, RobotState
from protocol.execution import SAFE_TCP_HEIGHT_M

RECOVERY_ACTIONS = ("release", "retract", "home")
RETRACT_M = 0.03
"""How far the gripper backs away from a pressed contact, and rises (m)."""
PRESSED_N = 2.0
"""A horizontal external force above this is a contact the gripper presses (N); below it, the
retreat is straight up."""
RETRACT_FORCE_MARGIN_N = 5.0
"""The retreat may meet this much more force than the gripper feels when it begins (N): it
starts pressed, and must fail if it presses harder."""


def external_force_W(state: RobotState, hand_mass_kg: float) -> np.ndarray:
    """The external force on the hand (N, in W) that ``state``'s wrist wrench says, the hand's
    weight removed (a held block's weight is not: it is vertical, and only the horizontal force
    picks the retreat's direction)."""
    R_WS = state.X_WF[:3, :3]  # the sensor is fixed at the flange, unrotated
    return -R_WS @ state.wrench_S[:3] - hand_mass_kg * np.asarray(GRAVITY_W)


def recovery_program(
    action: str, state: RobotState, scene: Scene, program_id: str
) -> MotionProgram:
    """The program for recovery ``action`` (:data:`RECOVERY_ACTIONS`) from the arm in
    ``state``; ValueError for an unknown action. The program's frame P is the gripper's G."""
    if action not in RECOVERY_ACTIONS:
        raise ValueError(f"unknown recovery {action!r}: one of {', '.join(RECOVERY_ACTIONS)}")
    robot = load_robot(scene.robot.urdf_path)
    X_WG = robot.link_poses_W(state.q, state.gripper_opening_m, scene.robot.X_WB)[TCP_LINK]
    params = CommandParams()
    if action == "release":
        commands = [MotionCommand("release", X_WG, 0.0, params.force_limit_n, ())]
    elif action == "retract":
        force_W = external_force_W(state, robot.mass_beyond_kg(FT_SENSOR_JOINT))
        away_W = np.array([force_W[0], force_W[1], 0.0])  # the surface pushes the hand away
        pressed_n = float(np.linalg.norm(away_W))
        away_W = away_W / pressed_n if pressed_n > PRESSED_N else np.zeros(3)
        target = X_WG.copy()
        target[:3, 3] += RETRACT_M * (away_W + np.array([0.0, 0.0, 1.0]))
        limit_n = min(
            params.max_force_limit_n,
            max(params.force_limit_n, float(np.linalg.norm(force_W)) + RETRACT_FORCE_MARGIN_N),
        )
        commands = [MotionCommand("move", target, params.contact_speed_mps, limit_n, ())]
    else:
        commands = []
        if X_WG[2, 3] < SAFE_TCP_HEIGHT_M:
            up = X_WG.copy()
            up[2, 3] = SAFE_TCP_HEIGHT_M
            commands.append(
                MotionCommand("move", up, params.free_speed_mps, params.force_limit_n, ())
            )
        commands.append(
            MotionCommand(
                "move", park_pose_W(scene), params.free_speed_mps, params.force_limit_n, ()
            )
        )
    return MotionProgram(program_id=program_id, X_GP=np.eye(4), commands=tuple(commands))
