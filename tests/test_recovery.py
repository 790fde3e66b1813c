"""The recovery programs made from a robot state: their moves, against the robot model's own
kinematics and the wrist's sign convention."""

from __future__ import annotations

import numpy as np
import pytest

from models.kinematics import ik_tcp
from models.robot import FT_SENSOR_JOINT, TCP_LINK, load_robot
from models.scene import GRAVITY_W, load_scene
from models.transforms import make_pose
from operator_site.program import park_pose_W
from operator_site.recovery import (
    RETRACT_M,
    external_force_W,
    recovery_program,
)
from protocol import RobotState
from protocol.execution import SAFE_TCP_HEIGHT_M

SCENE = load_scene()
ROBOT = load_robot(SCENE.robot.urdf_path)
GRIPPER_DOWN_LOW_W = make_pose(np.diag([-1.0, 1.0, -1.0]), (0.45, -0.05, 0.08))
"""The gripper low over the table, pointing down (TCP 8 cm up)."""
Q_LOW = ik_tcp(GRIPPER_DOWN_LOW_W, SCENE.robot.q_home_rad, ROBOT, SCENE.robot.X_WB).q


def _state(q: np.ndarray, force_W: np.ndarray) -> RobotState:
    """The state of the arm at ``q`` with the wrist feeling external force ``force_W``."""
    X_WF = ROBOT.link_poses_W(q, 0.0, SCENE.robot.X_WB)["flange"]
    hand_kg = ROBOT.mass_beyond_kg(FT_SENSOR_JOINT)
    f_S = -X_WF[:3, :3].T @ (np.asarray(force_W) + hand_kg * np.asarray(GRAVITY_W))
    return RobotState(seq=0, stamp_s=0.0, q=q, X_WF=X_WF, gripper_opening_m=0.05,
                      wrench_S=np.concatenate([f_S, np.zeros(3)]))  # fmt: skip


def test_the_wrist_reading_is_undone() -> None:
    state = _state(Q_LOW, [4.0, -3.0, 1.0])
    np.testing.assert_allclose(external_force_W(state, ROBOT.mass_beyond_kg(FT_SENSOR_JOINT)),
                               [4.0, -3.0, 1.0], atol=1e-9)  # fmt: skip


@pytest.mark.parametrize(("force_W", "away"), [([6.0, 0, 0], [1, 0, 0]), ([0, -5.0, 0], [0, -1, 0]),
                                               ([0.5, 0.5, 0], [0, 0, 0])])  # fmt: skip
def test_retract_backs_away_along_the_felt_force_and_up(force_W, away) -> None:
    state = _state(Q_LOW, force_W)
    X_WG = ROBOT.link_poses_W(Q_LOW, 0.05, SCENE.robot.X_WB)[TCP_LINK]
    program = recovery_program("retract", state, SCENE, "r")
    (move,) = program.commands
    assert move.kind == "move" and np.allclose(program.X_GP, np.eye(4))
    expected = X_WG[:3, 3] + RETRACT_M * (np.array(away, float) + np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(move.X_WP[:3, 3], expected, atol=1e-9)
    np.testing.assert_allclose(move.X_WP[:3, :3], X_WG[:3, :3], atol=1e-9)
    assert move.force_limit_n >= np.linalg.norm(force_W)  # it may start pressed


def test_home_rises_clear_then_parks_and_release_opens() -> None:
    state = _state(Q_LOW, [0.0, 0.0, 0.0])
    up, park = recovery_program("home", state, SCENE, "h").commands
    np.testing.assert_allclose(
        up.X_WP[:3, 3], [*GRIPPER_DOWN_LOW_W[:2, 3], SAFE_TCP_HEIGHT_M], atol=1e-6
    )
    np.testing.assert_allclose(park.X_WP, park_pose_W(SCENE), atol=1e-12)
    (release,) = recovery_program("release", state, SCENE, "o").commands
    assert release.kind == "release"
    with pytest.raises(ValueError, match="unknown recovery 'dance'"):
        recovery_program("dance", state, SCENE, "x")
