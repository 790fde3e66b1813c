"""Spatially-linear moves: the profile's timing and limits, and the arm tracking a line in
pybullet."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.robot import load_robot
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R, so3_log
from work_site.control.controller import MAX_TCP_SPEED_MPS, TaskController
from work_site.control.trajectory import LinearMove
from work_site.world import World

DOWN = rpy_to_R(np.array([math.pi, 0.0, math.pi]))  # gripper pointing at the table
TRACKING_TOL_M = 0.5e-3  # issue 5: linear-move tracking error ≤ 0.5 mm at 0.1 m/s


def test_profile_respects_limits_and_arrives() -> None:
    start = make_pose(DOWN, (0.3, 0.0, 0.2))
    goal = make_pose(DOWN @ rpy_to_R(np.array([0.0, 0.0, 0.3])), (0.4, 0.05, 0.15))
    move = LinearMove(start, goal, v_max_mps=0.1, a_max_mps2=0.5)
    times = np.arange(0.0, move.duration_s + 0.01, 0.001)
    P = np.array([move.pose_at(t)[:3, 3] for t in times])
    speed = np.linalg.norm(np.diff(P, axis=0), axis=1) / 0.001
    assert speed.max() <= 0.1 + 1e-6
    assert np.abs(np.diff(speed)).max() / 0.001 <= 0.5 + 1e-3
    np.testing.assert_allclose(move.pose_at(move.duration_s), goal, atol=1e-12)
    np.testing.assert_allclose(move.pose_at(0.0), start, atol=1e-12)
    # Every intermediate position is on the straight line, and the rotation on the short arc.
    d = (goal[:3, 3] - start[:3, 3]) / np.linalg.norm(goal[:3, 3] - start[:3, 3])
    off_line = (P - start[:3, 3]) - np.outer((P - start[:3, 3]) @ d, d)
    assert np.abs(off_line).max() < 1e-12
    w = so3_log(start[:3, :3].T @ goal[:3, :3])
    mid = move.pose_at(move.duration_s / 2)
    np.testing.assert_allclose(so3_log(start[:3, :3].T @ mid[:3, :3]), w / 2, atol=1e-9)


def test_pure_rotation_and_no_motion() -> None:
    start = make_pose(DOWN, (0.3, 0.0, 0.2))
    turn = make_pose(DOWN @ rpy_to_R(np.array([0.0, 0.0, 1.0])), (0.3, 0.0, 0.2))
    move = LinearMove(start, turn, 0.1, 0.5, w_max_rps=0.5, alpha_max_rps2=2.0)
    assert move.duration_s == pytest.approx(1.0 / 0.5 + 0.5 / 2.0)
    assert LinearMove(start, start, 0.1, 0.5).duration_s == 0.0
    with pytest.raises(ValueError, match="v_max_mps"):
        LinearMove(start, turn, float("nan"), 0.5)


@pytest.fixture(scope="module")
def arm():
    scene = load_scene()
    world = World(scene)
    controller = TaskController(world, load_robot(scene.robot.urdf_path))
    yield world, controller
    world.close()


def run_move(controller: TaskController, goal: np.ndarray, speed: float) -> float:
    """Execute a move; the largest distance between commanded and measured TCP (m)."""
    controller.start_move(goal, speed)
    worst = 0.0
    while True:
        result = controller.tick()
        if controller.move is not None:
            X_cmd = controller.move.pose_at(controller.t_s)
            worst = max(
                worst, float(np.linalg.norm(controller.measured_tcp_W()[:3, 3] - X_cmd[:3, 3]))
            )
        if result.status != "moving":
            assert result.status == "done", result.reason
            return worst


def test_arm_tracks_a_line_at_a_tenth_of_a_metre_per_second(arm) -> None:
    _, controller = arm
    start = make_pose(DOWN, (0.35, -0.1, 0.15))
    goal = make_pose(DOWN, (0.45, -0.1, 0.15))
    run_move(controller, start, 0.2)
    for _ in range(30):
        controller.tick()
    worst = run_move(controller, goal, 0.1)
    assert worst < TRACKING_TOL_M
    for _ in range(30):
        controller.tick()
    np.testing.assert_allclose(controller.measured_tcp_W()[:3, 3], goal[:3, 3], atol=1e-4)


def test_unreachable_or_too_fast_moves_are_refused_before_motion(arm) -> None:
    world, controller = arm
    q_before = world.q_target.copy()
    with pytest.raises(ValueError, match="cannot be reached: unreachable"):
        controller.start_move(make_pose(DOWN, (1.5, 0.0, 0.1)), 0.1)
    with pytest.raises(ValueError, match="speed"):
        controller.start_move(make_pose(DOWN, (0.4, 0.0, 0.1)), MAX_TCP_SPEED_MPS * 2)
    with pytest.raises(ValueError, match="speed"):
        controller.start_move(make_pose(DOWN, (0.4, 0.0, 0.1)), float("nan"))
    np.testing.assert_array_equal(world.q_target, q_before)
    assert controller.move is None
