"""The task controller (§III-A): Cartesian moves of the gripper at 100 Hz over 1 kHz joint servos.

Each control period the commanded TCP pose of the current :class:`LinearMove` is turned into
joint targets by the closed-form IK (nearest solution to the last target), with the joint
velocities that carry the move forward as feed-forward (pybullet's servo otherwise lags).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.robot import RobotModel
from models.transforms import invert_pose
from work_site.control.kinematics import arm_geometry, geometric_jacobian_W, ik_tcp
from work_site.control.trajectory import LinearMove
from work_site.world import World

CONTROL_PERIOD_S = 0.01
"""The task controller's period (§III-A: 100 Hz)."""
MAX_TCP_SPEED_MPS = 0.25
"""No move, however commanded, is faster than this."""
TCP_ACCEL_MPS2 = 0.5


@dataclass(frozen=True)
class TickResult:
    """``status``: "idle", "moving", "done" or "failed" (with ``reason``)."""

    status: str
    reason: str = ""


class TaskController:
    """Drives ``world``'s arm through linear TCP moves; call :meth:`tick` every 10 ms."""

    def __init__(self, world: World, robot: RobotModel) -> None:
        self.world, self.robot = world, robot
        self.geometry = arm_geometry(robot)
        self.X_WB = world.scene.robot.X_WB
        self.move: LinearMove | None = None
        self.t_s = 0.0
        self.steps_per_tick = max(1, round(CONTROL_PERIOD_S / world.time_step_s))

    def commanded_tcp_W(self) -> np.ndarray:
        """The TCP pose the joint targets command (``X_WG``)."""
        return self.robot.tcp_pose_W(self.world.q_target, self.X_WB)

    def measured_tcp_W(self) -> np.ndarray:
        """The TCP pose of the measured joint angles."""
        return self.robot.tcp_pose_W(self.world.robot_joint_positions()[0], self.X_WB)

    def start_move(self, X_WG_goal: np.ndarray, speed_mps: float) -> None:
        """Begin a straight TCP move to ``X_WG_goal``; ValueError if it cannot be done."""
        if not (math.isfinite(speed_mps) and 0 < speed_mps <= MAX_TCP_SPEED_MPS):
            raise ValueError(f"speed {speed_mps} m/s not in (0, {MAX_TCP_SPEED_MPS}]")
        goal = ik_tcp(X_WG_goal, self.world.q_target, self.robot, self.X_WB, self.geometry)
        if not goal.ok:
            raise ValueError(f"target cannot be reached: {goal.reason}")
        self.move = LinearMove(
            self.commanded_tcp_W(), np.array(X_WG_goal, dtype=np.float64), speed_mps, TCP_ACCEL_MPS2
        )
        self.t_s = 0.0

    def stop(self) -> None:
        """Hold where the arm is now (within one control period)."""
        self.world.q_target = self.world.robot_joint_positions()[0]
        self.world.q_dot_target = np.zeros(6)
        self.move = None

    def tick(self) -> TickResult:
        """One control period: the next setpoint, then the physics steps of the period."""
        if self.move is None:
            self.world.step(self.steps_per_tick)
            return TickResult("idle")
        self.t_s += CONTROL_PERIOD_S
        X = self.move.pose_at(self.t_s)
        result = ik_tcp(X, self.world.q_target, self.robot, self.X_WB, self.geometry)
        if not result.ok:
            self.stop()
            return TickResult("failed", f"on the way: {result.reason}")
        # Feed-forward joint rates from the path's velocity (finite difference over a period).
        X_next = self.move.pose_at(self.t_s + CONTROL_PERIOD_S)
        X_WF = X @ invert_pose(self.geometry.X_FG)
        X_WF_next = X_next @ invert_pose(self.geometry.X_FG)
        v_F = (X_WF_next[:3, 3] - X_WF[:3, 3]) / CONTROL_PERIOD_S
        dR = X_WF_next[:3, :3] @ X_WF[:3, :3].T
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (
            2 * CONTROL_PERIOD_S
        )
        J = geometric_jacobian_W(result.q, self.robot, self.X_WB)
        q_dot = np.linalg.lstsq(J, np.concatenate([v_F, w]), rcond=None)[0]
        self.world.q_target = result.q
        self.world.q_dot_target = q_dot
        self.world.step(self.steps_per_tick)
        if self.t_s >= self.move.duration_s:
            self.move = None
            self.world.q_dot_target = np.zeros(6)
            return TickResult("done")
        return TickResult("moving")
