"""Closed-form IK of the Puma-type arm against its forward kinematics (itself checked against
pybullet in test_robot_model.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from models.robot import HOME_Q, PUMA_URDF, load_robot
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R
from tests.conftest import examples
from work_site.control.kinematics import (
    BRANCH_JUMP_RAD,
    arm_geometry,
    follow_line_tcp,
    geometric_jacobian_W,
    ik_flange,
    ik_nearest,
    ik_tcp,
    plan_approach,
)

ROBOT = load_robot(PUMA_URDF)
GEOMETRY = arm_geometry(ROBOT)
POSE_TOL = 1e-9  # m and rotation-matrix entries
Q_TOL_RAD = 1e-7  # a recovered joint angle
ARM_ANGLE_ERR_RAD = 1e-10  # joints 1-3's rounding, 10× the worst seen (at a nearly stretched arm)


def angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


joint_vectors = st.tuples(
    *[st.floats(float(lo), float(hi)) for lo, hi in zip(ROBOT.q_lower, ROBOT.q_upper, strict=True)]
).map(np.array)


def test_geometry_is_read_from_the_model() -> None:
    assert GEOMETRY.shoulder_height_m == pytest.approx(0.33)
    assert GEOMETRY.upper_arm_m == pytest.approx(0.305)
    assert GEOMETRY.forearm_m == pytest.approx(0.33)
    assert GEOMETRY.wrist_to_flange_m == pytest.approx(0.076)
    np.testing.assert_allclose(GEOMETRY.X_FG[:3, 3], [0, 0, 0.115], atol=1e-12)


@settings(max_examples=examples(500), deadline=None)
@given(q=joint_vectors)
def test_every_solution_reproduces_the_pose_and_q_is_among_them(q: np.ndarray) -> None:
    X = ROBOT.flange_pose_W(q)
    solutions, singular = ik_flange(X, ROBOT, q)
    assert solutions
    # At a wrist (shoulder) singularity q4 (q1) is kept, which costs at most π·1e-6 rad of
    # rotation (1e-6 m of position): the price of not spinning a joint for nothing.
    tol = 1e-5 if {"wrist", "shoulder"} & set(singular.split("+")) else POSE_TOL
    for s in solutions:
        np.testing.assert_allclose(ROBOT.flange_pose_W(s), X, atol=tol)
    if not singular:
        # Near the wrist singularity joints 4 and 6 turn about almost one axis: an error ε in
        # the arm's angles moves both by ε / sin q5 in opposite senses, which the pose does not
        # see (q3 = 6e-5 rad, nearly stretched, gave ε ≈ 1e-11 rad and 1.05e-7 rad at q5 = 5e-5).
        tol = np.full(6, Q_TOL_RAD)
        tol[[3, 5]] += ARM_ANGLE_ERR_RAD / abs(np.sin(q[4]))
        assert min((angle_diff(s, q) / tol).max() for s in solutions) < 1.0


@settings(max_examples=examples(500), deadline=None)
@given(q=joint_vectors)
# Stretched elbow and the wrist at its limit: q5 inherits the elbow's rounding.
@example(q=np.array((0.0, 0.0, -4.6191020691002035e-09, 0.0, -2.09, 0.0)))
def test_nearest_solution_to_q_is_q(q: np.ndarray) -> None:
    result = ik_nearest(ROBOT.flange_pose_W(q), q, ROBOT)
    assert result.ok, result.reason
    singular = set(result.singular.split("+"))
    tol = 1e-5 if {"wrist", "shoulder"} & singular else POSE_TOL
    if "elbow" in singular:
        # q3 = acos(cos q3) near ±1 turns the cosine's rounding into √(2δ) ≈ 5e-8 rad
        # (ELBOW_LIMIT_TOL_RAD's reason), ~1e-8 m at the flange: hypothesis found q3 = 0.
        tol = max(tol, 1e-7)
    np.testing.assert_allclose(ROBOT.flange_pose_W(result.q), ROBOT.flange_pose_W(q), atol=tol)
    if not result.singular:
        # Near the wrist singularity q4 and q6 carry the arm's angle error over sin q5, as in
        # the test above (hypothesis found q5 = 5e-5 rad: 3.1e-7 rad on each).
        tol_q = np.full(6, 1e-7)
        tol_q[[3, 5]] += ARM_ANGLE_ERR_RAD / abs(np.sin(q[4]))
        assert np.all(np.abs(angle_diff(result.q, q)) <= tol_q), (result.q, q)


def test_a_joint_on_its_limit_with_the_arm_stretched_is_reached() -> None:
    """Found by hypothesis: q2 on its lower limit, q3 ≈ 0 (elbow singularity) and q5 = 0. The
    solutions' q2 came out 2e-9 and 6e-8 rad beyond the limit (acos near 1) and were refused."""
    q = np.array([0.0, ROBOT.q_lower[1], -5.96e-8, 0.0, 0.0, 0.0])
    result = ik_nearest(ROBOT.flange_pose_W(q), q, ROBOT)
    assert result.ok, result.reason
    assert "elbow" in result.singular
    assert ROBOT.q_lower[1] <= result.q[1] <= ROBOT.q_upper[1]
    np.testing.assert_allclose(ROBOT.flange_pose_W(result.q), ROBOT.flange_pose_W(q), atol=1e-5)


def test_home_pose_gives_home() -> None:
    result = ik_nearest(ROBOT.flange_pose_W(np.array(HOME_Q)), np.array(HOME_Q), ROBOT)
    assert result.ok and not result.singular
    np.testing.assert_allclose(result.q, HOME_Q, atol=1e-12)


@pytest.mark.parametrize("q5", [0.0, 1e-7, -1e-7])
def test_singular_wrist_keeps_q4_and_still_reaches(q5: float) -> None:
    q = np.array([0.3, 0.4, 1.2, 0.7, q5, -0.5])
    q_current = q + np.array([0.0, 0.0, 0.0, 0.2, 0.0, 0.0])
    result = ik_nearest(ROBOT.flange_pose_W(q), q_current, ROBOT)
    assert result.ok and "wrist" in result.singular
    assert result.q[3] == pytest.approx(q_current[3])
    np.testing.assert_allclose(ROBOT.flange_pose_W(result.q), ROBOT.flange_pose_W(q), atol=1e-6)


def test_shoulder_singularity_keeps_q1() -> None:
    # Wrist centre on the joint-1 axis: a sin q2 + b sin(q2 + q3) = 0.
    a, b = GEOMETRY.upper_arm_m, GEOMETRY.forearm_m
    q2 = 0.5
    q3 = -q2 - math.asin(a / b * math.sin(q2))
    q = np.array([0.0, q2, q3, 0.3, 0.5, 0.0])
    X = ROBOT.flange_pose_W(q)
    q_current = q.copy()
    q_current[0] = 1.1
    result = ik_nearest(X, q_current, ROBOT)
    assert result.ok and "shoulder" in result.singular
    assert result.q[0] == pytest.approx(1.1)
    np.testing.assert_allclose(ROBOT.flange_pose_W(result.q), X, atol=1e-6)


def test_near_the_workspace_boundary() -> None:
    q = np.array([0.2, 0.8, 1e-5, 0.1, 0.6, 0.2])  # elbow all but straight
    result = ik_nearest(ROBOT.flange_pose_W(q), q, ROBOT)
    assert result.ok
    np.testing.assert_allclose(ROBOT.flange_pose_W(result.q), ROBOT.flange_pose_W(q), atol=1e-9)


def test_unreachable_and_out_of_limits_say_why() -> None:
    far = make_pose(rpy_to_R(np.array([math.pi, 0.0, 0.0])), (1.2, 0.0, 0.2))
    result = ik_nearest(far, np.array(HOME_Q), ROBOT)
    assert not result.ok and result.q is None
    assert result.reason.startswith("unreachable: wrist centre")
    assert "reach 0.635 m" in result.reason
    # Gripper down with its x along +x of W needs q6 = ±π, just past joint 6's ±3.14 rad.
    down = make_pose(rpy_to_R(np.array([math.pi, 0.0, 0.0])), (0.45, 0.0, 0.03))
    result = ik_tcp(down, np.array(HOME_Q), ROBOT)
    assert not result.ok and result.q is None
    assert result.reason.startswith("outside joint limits (joint_6")


def ik_symmetric_grasp(X_WG: np.ndarray):
    """A parallel gripper grasps the same turned half a turn about its axis; joint 6 reaches
    ±3.14 rad, so one of the two is always inside its limits."""
    flipped = X_WG @ make_pose(rpy_to_R(np.array([0.0, 0.0, math.pi])))
    results = [ik_tcp(X, np.array(HOME_Q), ROBOT) for X in (X_WG, flipped)]
    return next((r for r in results if r.ok), results[0]), results


def test_gripper_down_over_the_frame_is_reachable_and_regular() -> None:
    for z in np.linspace(0.03, 0.3, 10):
        for yaw in np.linspace(-math.pi, math.pi, 9):
            X_WG = make_pose(rpy_to_R(np.array([math.pi, 0.0, yaw])), (0.45, 0.0, z))
            result, both = ik_symmetric_grasp(X_WG)
            assert result.ok, (z, yaw, [r.reason for r in both])
            assert result.singular == ""
            X = ROBOT.tcp_pose_W(result.q)
            np.testing.assert_allclose(X[:3, 3], X_WG[:3, 3], atol=1e-9)
            np.testing.assert_allclose(X[:3, 2], X_WG[:3, 2], atol=1e-9)


def test_every_block_can_be_grasped_from_above_where_the_scene_puts_it() -> None:
    for obj in load_scene().movable:
        p = obj.X_WO[:3, 3]
        X_WG = make_pose(rpy_to_R(np.array([math.pi, 0.0, 0.0])), p)
        result, both = ik_symmetric_grasp(X_WG)
        assert result.ok and not result.singular, (obj.name, [r.reason for r in both])


def test_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    h = 1e-6
    for _ in range(20):
        q = rng.uniform(ROBOT.q_lower, ROBOT.q_upper) * 0.8
        J = geometric_jacobian_W(q, ROBOT)
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            Xp, Xm = ROBOT.flange_pose_W(q + dq), ROBOT.flange_pose_W(q - dq)
            v = (Xp[:3, 3] - Xm[:3, 3]) / (2 * h)
            dR = (Xp[:3, :3] - Xm[:3, :3]) / (2 * h) @ ROBOT.flange_pose_W(q)[:3, :3].T
            w = np.array([dR[2, 1], dR[0, 2], dR[1, 0]])
            np.testing.assert_allclose(J[:3, i], v, atol=1e-6)
            np.testing.assert_allclose(J[3:, i], w, atol=1e-6)


def test_a_model_of_another_shape_is_refused() -> None:
    import dataclasses

    joint = ROBOT.joint("joint_2")
    bent = dataclasses.replace(joint, axis=np.array([1.0, 0.0, 0.0]))
    joints = tuple(bent if j.name == "joint_2" else j for j in ROBOT.joints)
    other = dataclasses.replace(ROBOT, joints=joints, _joint_by_name={j.name: j for j in joints})
    with pytest.raises(ValueError, match="joint_2 axis"):
        arm_geometry(other)


def test_every_block_of_a_seeded_layout_can_be_grasped_from_above() -> None:
    """The end-to-end layouts (models/layout.py) put blocks only where the arm reaches their
    grasp and its approach from above within its joint limits (a tall block at 0.189 m from the
    base axis needed the elbow past its limit: issue 9, corner seed 33)."""
    from models.layout import random_layout
    from models.transforms import invert_pose
    from operator_site.model_editor import WorkSiteModel
    from operator_site.task import TaskSession
    from protocol.execution import GRASP_APPROACH_M

    scene = load_scene()
    robot = load_robot(PUMA_URDF)
    for seed in range(30):
        layout = random_layout(scene, seed)
        session = TaskSession(WorkSiteModel(scene, layout).scene())
        for name, X_WO in layout.items():
            session.select(name)
            X_WG = X_WO @ invert_pose(session.X_GP)
            for lift_m in (0.0, GRASP_APPROACH_M):
                X = X_WG.copy()
                X[2, 3] += lift_m
                result = ik_tcp(X, np.asarray(HOME_Q), robot)
                assert result.ok, (seed, name, lift_m, result.reason)


def _dense_line_ok(X_from, X_to, q, n: int) -> bool:
    """Brute force: the nearest IK solution at ``n`` samples, every step continuous."""
    from models.transforms import so3_exp, so3_log

    w = so3_log(X_from[:3, :3].T @ X_to[:3, :3])
    for i in range(1, n + 1):
        s = i / n
        X = make_pose(X_from[:3, :3] @ so3_exp(s * w), X_from[:3, 3] + s * (X_to - X_from)[:3, 3])
        result = ik_tcp(X, q, ROBOT)
        if not result.ok or np.max(np.abs(result.q - q)) > BRANCH_JUMP_RAD:
            return False
        q = result.q
    return True


def test_a_line_whose_ends_are_reachable_is_followed_only_if_its_middle_is() -> None:
    """Straight down beside the base the elbow folds past its limit half way, though both ends
    are reachable; along the table to the same pose it does not. A dense brute-force sampling
    agrees with the follower in both cases."""
    home = ROBOT.tcp_pose_W(np.asarray(HOME_Q))
    near = home.copy()
    near[:3, 3] = (0.19, 0.0, 0.06)
    beside = near.copy()
    beside[0, 3] = 0.25
    assert ik_tcp(near, np.asarray(HOME_Q), ROBOT).ok
    down = follow_line_tcp(home, near, np.asarray(HOME_Q), ROBOT)
    assert not down.ok and "joint_3" in down.reason and "of the way" in down.reason
    assert not _dense_line_ok(home, near, np.asarray(HOME_Q), 2000)
    to_beside = follow_line_tcp(home, beside, np.asarray(HOME_Q), ROBOT)
    along = follow_line_tcp(beside, near, to_beside.q, ROBOT)
    assert to_beside.ok and along.ok and along.margin_rad > 0.0
    assert _dense_line_ok(beside, near, to_beside.q, 2000)
    np.testing.assert_allclose(ROBOT.tcp_pose_W(along.q), near, atol=POSE_TOL)


def test_a_turn_past_the_wrist_limit_is_a_swing_not_a_move() -> None:
    """Turning the gripper on the spot from joint 6 near +3.0 rad a further 0.4 rad: the nearest
    solution inside the limits is a whole turn back, which the follower refuses by name."""
    q = np.array([0.0, 0.3, 1.8, 0.0, 0.6, 3.0])
    X = ROBOT.tcp_pose_W(q)
    turned = X @ make_pose(rpy_to_R(np.array([0.0, 0.0, 0.4])))
    back = X @ make_pose(rpy_to_R(np.array([0.0, 0.0, -0.4])))
    result = follow_line_tcp(X, turned, q, ROBOT)
    assert not result.ok and "joint_6 would swing" in result.reason
    other_way = follow_line_tcp(X, back, q, ROBOT)
    assert other_way.ok and abs(other_way.q[5] - 3.0) == pytest.approx(0.4, abs=1e-6)


def test_an_approach_the_short_turn_cannot_make_goes_through_joint_space() -> None:
    """From home to a grasp's approach whose wrist angle lies past joint 6's limit the short
    way round: the straight TCP move swings; the plan is the joint-space move to the solution
    itself, along which the hand stays above the approach, and from which the descent follows.
    With a rest of the program no solution can follow, the plan is refused with the reason."""
    home_q = np.asarray(HOME_Q)
    home = ROBOT.tcp_pose_W(home_q)
    q = np.array([0.85, 0.6, 2.19, 0.0, 0.34, -2.8])
    above = ROBOT.tcp_pose_W(q)
    grasp = above.copy()
    grasp[2, 3] -= 0.05
    assert not follow_line_tcp(home, above, home_q, ROBOT).ok
    plan = plan_approach(home, home_q, above, [grasp], ROBOT)
    assert plan.ok and plan.q_joint is not None
    np.testing.assert_allclose(ROBOT.tcp_pose_W(plan.q_joint), above, atol=POSE_TOL)
    for s in np.linspace(0.0, 1.0, 101):
        assert ROBOT.tcp_pose_W(home_q + s * (plan.q_joint - home_q))[2, 3] >= above[2, 3] - 1e-12
    far = grasp.copy()
    far[:3, 3] = (0.74, 0.44, 0.49)
    refused = plan_approach(home, home_q, above, [grasp, far], ROBOT)
    assert not refused.ok and "joint_6 would swing" in refused.reason
