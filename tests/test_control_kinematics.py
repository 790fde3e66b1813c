"""Closed-form IK of the Puma-type arm (work_site/control/kinematics.py) against its forward
kinematics (models/robot.py) and against pybullet's."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import pybullet as p
import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from models.robot import FLANGE_LINK, HOME_Q, PUMA_URDF, RobotModel, load_robot
from models.scene import load_scene
from models.transforms import (
    invert_pose,
    make_pose,
    quat_wxyz_to_R,
    quat_xyzw_to_wxyz,
    rpy_to_R,
)
from operator_site.grasp import top_grasp
from operator_site.program.pick_place import choose_grasp_yaw
from work_site.control.kinematics import (
    SINGULAR_ELBOW_RAD,
    SINGULAR_SHOULDER_M,
    SINGULAR_WRIST_RAD,
    arm_geometry,
    fk_flange,
    geometric_jacobian_W,
    ik_flange,
    ik_nearest,
    ik_tcp,
)

ROBOT = load_robot(PUMA_URDF)
GEOMETRY = arm_geometry(ROBOT)
POS_TOL_M = 1e-9
ROT_TOL_RAD = 1e-9
Q_TOL_RAD = 1e-6
"""Recovering q from a pose, away from singularities (see :func:`q_tol` near them)."""
HOME = np.array(HOME_Q)
DOWN = rpy_to_R(np.array([math.pi, 0.0, 0.0]))
"""Gripper (and flange) z along −z of W, x along +x of W."""
HYPOTHESIS = settings(max_examples=500, deadline=None, database=None)


def pose_error(X: np.ndarray, Y: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation angle rad) between two poses."""
    R = X[:3, :3].T @ Y[:3, :3]
    sin_angle = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    angle = math.atan2(sin_angle, 0.5 * (np.trace(R) - 1.0))
    return float(np.linalg.norm(X[:3, 3] - Y[:3, 3])), angle


def assert_same_pose(X: np.ndarray, Y: np.ndarray) -> None:
    dp, da = pose_error(X, Y)
    assert dp <= POS_TOL_M and da <= ROT_TOL_RAD, (dp, da)


def angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.remainder(np.asarray(a) - b + math.pi, 2 * math.pi) - math.pi)


def wrist_centre_B(q: np.ndarray) -> np.ndarray:
    X = ROBOT.flange_pose_W(q)
    return X[:3, 3] - GEOMETRY.wrist_to_flange_m * X[:3, 2]


def arm_rounding(q: np.ndarray) -> float:
    """How well q1–q3 can be recovered from the pose (rad): ≈ ε/|sin q3| near the stretched
    elbow, at most ≈ √ε."""
    return min(1e-15 / max(abs(math.sin(q[2])), 1e-300), 1e-7)


def wrist_surely_singular(q: np.ndarray) -> bool:
    """The solver surely sees q's wrist as singular (and keeps q4), rounding included."""
    return abs(math.sin(q[4])) + arm_rounding(q) < 0.5 * SINGULAR_WRIST_RAD


def q_tol(q: np.ndarray) -> float:
    """How well q can be recovered from its pose (rad): q4 and q6 to ≈ (q1–q3's rounding + ε)
    over |sin q5|, unless the wrist is surely singular and q4 kept."""
    arm = arm_rounding(q)
    if wrist_surely_singular(q):
        return Q_TOL_RAD + arm
    return Q_TOL_RAD + arm + (arm + 1e-15) / max(abs(math.sin(q[4])), 1e-300)


limits = list(zip(ROBOT.q_lower.tolist(), ROBOT.q_upper.tolist(), strict=True))
joint_vectors = st.tuples(*[st.floats(lo, hi) for lo, hi in limits]).map(np.array)
"""Random q within the limits (hypothesis also tries 0, the limits and tiny numbers)."""
near_singular_q = st.tuples(
    st.floats(*limits[0]),
    st.floats(*limits[1]),
    st.sampled_from([1e-5, -1e-5, 1e-4, -3e-3, 0.4]),
    st.floats(*limits[3]),
    st.sampled_from([1e-7, -1e-7, 1e-9, -1e-9, 0.0, 2e-11, 0.7]),
    st.floats(*limits[5]),
).map(np.array)
"""q with the wrist near (or on) q5 = 0 and the elbow nearly straight."""


def check_round_trip(q: np.ndarray) -> None:
    """Every solution reproduces the pose; q itself is among them (with q as hint, which fills
    what a singularity leaves free; without one too, where nothing is free)."""
    X = ROBOT.flange_pose_W(q)
    solutions = ik_flange(X, ROBOT, geometry=GEOMETRY)
    assert 1 <= len(solutions) <= 8
    for s in solutions:
        assert_same_pose(ROBOT.flange_pose_W(s), X)
        assert np.all(np.abs(s) <= math.pi)  # this arm's limits are all within ±π
    hinted = ik_flange(X, ROBOT, q_hint=q, geometry=GEOMETRY)
    for s in hinted:
        assert_same_pose(ROBOT.flange_pose_W(s), X)
    assert min(angle_diff(s, q).max() for s in hinted) < q_tol(q)
    s5 = abs(math.sin(q[4]))
    if s5 > 2 * SINGULAR_WRIST_RAD and np.hypot(*wrist_centre_B(q)[:2]) > 1e-9:
        assert min(angle_diff(s, q).max() for s in solutions) < q_tol(q)
    elif wrist_surely_singular(q):
        # No hint: q4 = 0 and q6 takes up q4 + q6 in q's arm configuration.
        s = min(solutions, key=lambda s: angle_diff(s[:3], q[:3]).max())
        assert s[3] == 0.0
        assert angle_diff([s[4], s[5]], [q[4], q[3] + q[5]]).max() < q_tol(q)


@seed(20240611)
@HYPOTHESIS
@given(q=joint_vectors)
def test_every_solution_reproduces_the_pose_and_q_is_among_them(q: np.ndarray) -> None:
    check_round_trip(q)


@seed(20240612)
@HYPOTHESIS
@given(q=near_singular_q)
def test_round_trip_near_wrist_singularity_and_workspace_boundary(q: np.ndarray) -> None:
    check_round_trip(q)


@seed(20240613)
@HYPOTHESIS
@given(q=joint_vectors, weights=st.lists(st.floats(0.1, 10.0), min_size=6, max_size=6))
def test_nearest_is_q_itself_or_a_named_singularity(q: np.ndarray, weights: list[float]) -> None:
    X = ROBOT.flange_pose_W(q)
    result = ik_nearest(X, q, ROBOT, geometry=GEOMETRY, weights=weights)
    rho = float(np.hypot(*wrist_centre_B(q)[:2]))
    if abs(q[2]) < 0.5 * SINGULAR_ELBOW_RAD:
        assert (result.ok, result.q) == (False, None)
        assert result.reason == "singular: elbow (arm fully stretched)"
    elif abs(q[2]) > 2 * SINGULAR_ELBOW_RAD and rho < 0.5 * SINGULAR_SHOULDER_M:
        assert (result.ok, result.q) == (False, None)
        assert result.reason == "singular: shoulder (wrist centre on joint-1 axis)"
    elif abs(q[2]) > 2 * SINGULAR_ELBOW_RAD and rho > 2 * SINGULAR_SHOULDER_M:
        assert result.ok, result.reason
        assert np.all(ROBOT.q_lower <= result.q) and np.all(result.q <= ROBOT.q_upper)
        assert_same_pose(ROBOT.flange_pose_W(result.q), X)
        assert np.max(np.abs(result.q - q)) < q_tol(q)
        if wrist_surely_singular(q):
            assert (result.reason, result.singular) == ("singular: wrist (q5 ≈ 0)", "wrist")
        elif abs(math.sin(q[4])) > 2 * SINGULAR_WRIST_RAD + arm_rounding(q):
            assert (result.reason, result.singular) == ("", "")


@seed(20240614)
@settings(HYPOTHESIS, max_examples=200)
@given(
    q=joint_vectors,
    q_current=joint_vectors,
    weights=st.lists(st.floats(0.1, 10.0), min_size=6, max_size=6),
)
def test_nearest_is_the_least_weighted_distance_within_limits(
    q: np.ndarray, q_current: np.ndarray, weights: list[float]
) -> None:
    X = ROBOT.flange_pose_W(q)
    result = ik_nearest(X, q_current, ROBOT, weights=weights)
    if not result.ok:
        assert result.reason.startswith("singular: ")
        return
    w = np.array(weights)
    inside = [
        s
        for s in ik_flange(X, ROBOT, q_hint=q_current)
        if np.all(s >= ROBOT.q_lower - 1e-9) and np.all(s <= ROBOT.q_upper + 1e-9)
    ]
    best = min(float(np.sum(w * (s - q_current) ** 2)) for s in inside)
    assert float(np.sum(w * (result.q - q_current) ** 2)) <= best + 1e-9
    assert_same_pose(ROBOT.flange_pose_W(result.q), X)


def test_geometry_is_read_from_the_model() -> None:
    assert GEOMETRY.shoulder_height_m == pytest.approx(0.33, abs=1e-15)
    assert GEOMETRY.upper_arm_m == pytest.approx(0.305, abs=1e-15)
    assert GEOMETRY.forearm_m == pytest.approx(0.33, abs=1e-15)
    assert GEOMETRY.wrist_to_flange_m == pytest.approx(0.076, abs=1e-15)
    assert GEOMETRY.reach_m == pytest.approx(0.635, abs=1e-15)
    np.testing.assert_allclose(GEOMETRY.X_FG, make_pose(None, [0.0, 0.0, 0.115]), atol=1e-15)


def _changed(joint_name: str, **changes) -> RobotModel:
    joint = dataclasses.replace(ROBOT.joint(joint_name), **changes)
    joints = tuple(joint if j.name == joint_name else j for j in ROBOT.joints)
    return dataclasses.replace(ROBOT, joints=joints, _joint_by_name={j.name: j for j in joints})


@pytest.mark.parametrize(
    ("joint", "changes", "message"),
    [
        ("joint_2", {"axis": np.array([1.0, 0.0, 0.0])}, "joint_2 axis"),
        ("joint_3", {"X_PJ": make_pose(None, [0.0, 0.02, 0.305])}, "joint_3 has a rotated"),
        ("joint_4", {"X_PJ": make_pose(rpy_to_R(np.array([0.1, 0, 0])), [0, 0, 0.33])}, "rotated"),
        ("joint_5", {"X_PJ": make_pose(None, [0.0, 0.0, 0.01])}, "wrist axes meet"),
        ("joint_6", {"X_PJ": make_pose(None, [0.0, 0.0, 0.01])}, "wrist axes meet"),
        ("flange_joint", {"X_PJ": make_pose(None, [0.01, 0.0, 0.076])}, "flange must lie"),
        ("tcp_joint", {"type": "revolute"}, "rigid mount"),
    ],
)
def test_a_model_of_another_shape_is_refused(joint: str, changes: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        arm_geometry(_changed(joint, **changes))


def test_home_pose_gives_home() -> None:
    result = ik_nearest(fk_flange(HOME, ROBOT), HOME, ROBOT)
    assert (result.ok, result.reason) == (True, "")
    np.testing.assert_allclose(result.q, HOME, atol=1e-12)
    result = ik_tcp(ROBOT.tcp_pose_W(HOME), np.zeros(6), ROBOT)  # from far away, too
    assert result.ok
    np.testing.assert_allclose(result.q, HOME, atol=1e-12)


def test_fk_flange_is_the_models_and_a_base_pose_is_honoured() -> None:
    X_WB = make_pose(rpy_to_R(np.array([0.1, -0.2, 0.7])), [0.3, -0.1, 0.05])
    q = np.array([0.3, -0.4, 1.1, 0.5, -0.8, 1.9])
    np.testing.assert_array_equal(fk_flange(q, ROBOT, X_WB), ROBOT.flange_pose_W(q, X_WB))
    result = ik_nearest(fk_flange(q, ROBOT, X_WB), q, ROBOT, X_WB)
    assert result.ok
    np.testing.assert_allclose(result.q, q, atol=1e-12)
    result = ik_tcp(ROBOT.tcp_pose_W(q, X_WB), q, ROBOT, X_WB)
    np.testing.assert_allclose(result.q, q, atol=1e-12)


@pytest.mark.parametrize("q5", [0.0, 1e-11, -1e-11])
def test_singular_wrist_keeps_q4_and_still_reaches(q5: float) -> None:
    q = np.array([0.3, 0.4, 1.2, 0.7, q5, -0.5])
    X = ROBOT.flange_pose_W(q)
    for dq4 in (0.2, -1.5, 2.0):
        q_current = q + np.array([0.05, 0.0, 0.0, dq4, 0.0, 0.0])
        result = ik_nearest(X, q_current, ROBOT)
        assert (result.ok, result.reason, result.singular) == (
            True,
            "singular: wrist (q5 ≈ 0)",
            "wrist",
        )
        assert result.q[3] == q_current[3]
        assert angle_diff(result.q[3] + result.q[5], q[3] + q[5]) < 1e-12  # q6 takes it up
        np.testing.assert_allclose(result.q[:3], q[:3], atol=1e-12)
        assert_same_pose(ROBOT.flange_pose_W(result.q), X)


def test_singular_wrist_moves_q4_only_as_far_as_joint_6_needs() -> None:
    # q4 + q6 = 3.0; keeping q4 = -0.1412 would need q6 = 3.1412, past joint 6's 3.14 rad.
    q = np.array([0.3, 0.4, 1.2, 1.0, 0.0, 2.0])
    X = ROBOT.flange_pose_W(q)
    q_current = np.array([0.3, 0.4, 1.2, -0.1412, 0.0, 3.1])
    result = ik_nearest(X, q_current, ROBOT)
    assert (result.ok, result.singular) == (True, "wrist")
    assert result.q[5] == pytest.approx(ROBOT.q_upper[5], abs=1e-9)
    assert result.q[3] == pytest.approx(3.0 - ROBOT.q_upper[5], abs=1e-9)
    assert_same_pose(ROBOT.flange_pose_W(result.q), X)


@pytest.mark.parametrize("q5", [1e-7, -1e-7])
def test_nearly_singular_wrist_is_exact(q5: float) -> None:
    q = np.array([0.3, 0.4, 1.2, 0.7, q5, -0.5])
    X = ROBOT.flange_pose_W(q)
    result = ik_nearest(X, q, ROBOT)
    assert (result.ok, result.reason) == (True, "")
    assert_same_pose(ROBOT.flange_pose_W(result.q), X)
    np.testing.assert_allclose(result.q, q, atol=1e-12)  # q4 leans to the current one
    # From elsewhere q4 moves (≤ 1e-10/|q5| toward the current q4, or flips): still exact.
    for dq4 in (0.3, 2.0):
        result = ik_nearest(X, q + np.array([0, 0, 0, dq4, 0, 0]), ROBOT)
        assert result.ok
        assert_same_pose(ROBOT.flange_pose_W(result.q), X)


def _on_the_joint1_axis(offset_m: float) -> np.ndarray:
    """q with the wrist centre ``offset_m`` from joint 1's axis (a s2 + b s23 = offset)."""
    a, b = GEOMETRY.upper_arm_m, GEOMETRY.forearm_m
    q2 = 0.5
    q3 = -q2 - math.asin((a * math.sin(q2) - offset_m) / b)
    return np.array([0.2, q2, q3, 0.3, 0.5, 0.1])


def test_shoulder_singularity_is_refused_and_just_beside_it_is_exact() -> None:
    q = _on_the_joint1_axis(0.0)
    assert np.hypot(*wrist_centre_B(q)[:2]) < 1e-15
    result = ik_nearest(ROBOT.flange_pose_W(q), q, ROBOT)
    assert (result.ok, result.q) == (False, None)
    assert result.reason == "singular: shoulder (wrist centre on joint-1 axis)"
    assert result.singular == "shoulder"
    # ik_flange still solves it, keeping the hint's q1.
    solutions = ik_flange(ROBOT.flange_pose_W(q), ROBOT, q_hint=q)
    assert min(angle_diff(s, q).max() for s in solutions) < 1e-12
    q = _on_the_joint1_axis(2 * SINGULAR_SHOULDER_M)
    result = ik_nearest(ROBOT.flange_pose_W(q), q, ROBOT)
    assert result.ok, result.reason
    assert_same_pose(ROBOT.flange_pose_W(result.q), ROBOT.flange_pose_W(q))
    np.testing.assert_allclose(result.q, q, atol=1e-9)


@pytest.mark.parametrize("q3", [1e-5, -1e-5, 3e-6])
def test_near_the_workspace_boundary_is_exact(q3: float) -> None:
    q = np.array([0.2, 0.8, q3, 0.1, 0.6, 0.2])  # elbow all but straight
    X = ROBOT.flange_pose_W(q)
    result = ik_nearest(X, q, ROBOT)
    assert (result.ok, result.reason) == (True, "")
    assert_same_pose(ROBOT.flange_pose_W(result.q), X)
    np.testing.assert_allclose(result.q, q, atol=Q_TOL_RAD)
    assert len(ik_flange(X, ROBOT)) == 8  # elbow up and down are still two


def test_stretched_elbow_is_refused() -> None:
    q = np.array([0.2, 0.8, 0.0, 0.1, 0.6, 0.2])
    X = ROBOT.flange_pose_W(q)
    result = ik_nearest(X, q, ROBOT)
    assert (result.ok, result.q, result.singular) == (False, None, "elbow")
    assert result.reason == "singular: elbow (arm fully stretched)"
    for s in ik_flange(X, ROBOT):
        assert_same_pose(ROBOT.flange_pose_W(s), X)


def _flange_down_with_wrist_centre_at(p_BC: np.ndarray) -> np.ndarray:
    return make_pose(DOWN, p_BC + GEOMETRY.wrist_to_flange_m * DOWN[:, 2])


def test_unreachable_says_how_far() -> None:
    X = _flange_down_with_wrist_centre_at(np.array([0.71, 0.0, GEOMETRY.shoulder_height_m]))
    result = ik_nearest(X, HOME, ROBOT)
    assert (result.ok, result.q) == (False, None)
    assert result.reason == "unreachable: wrist centre 0.71 m from the shoulder, reach 0.635 m"
    assert ik_flange(X, ROBOT) == []
    X = _flange_down_with_wrist_centre_at(np.array([0.01, 0.0, GEOMETRY.shoulder_height_m]))
    result = ik_nearest(X, HOME, ROBOT)
    assert result.reason == (
        "unreachable: wrist centre 0.01 m from the shoulder, inner reach 0.025 m"
    )


@seed(20240615)
@settings(HYPOTHESIS, max_examples=200)
@given(
    direction=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1),
    beyond_m=st.floats(1e-6, 1.0),
    rpy=st.tuples(*[st.floats(-math.pi, math.pi)] * 3),
)
def test_targets_beyond_reach_are_unreachable(
    direction: tuple[float, float, float], beyond_m: float, rpy: tuple[float, float, float]
) -> None:
    u = np.array(direction) / np.linalg.norm(direction)
    p_BC = np.array([0, 0, GEOMETRY.shoulder_height_m]) + (GEOMETRY.reach_m + beyond_m) * u
    R = rpy_to_R(np.array(rpy))
    X = make_pose(R, p_BC + GEOMETRY.wrist_to_flange_m * R[:, 2])
    assert ik_flange(X, ROBOT) == []
    result = ik_nearest(X, HOME, ROBOT)
    assert not result.ok and result.reason.startswith("unreachable: wrist centre ")
    assert result.reason.endswith(" m from the shoulder, reach 0.635 m")


def test_out_of_limit_solutions_are_reported() -> None:
    # |q3| = 2.8 > 2.53 in every solution: the wrist centre is too near the shoulder for the
    # elbow's limits.
    q = np.array([0.1, 0.3, 2.8, 0.2, 0.5, 0.3])
    X = ROBOT.flange_pose_W(q)
    assert len(ik_flange(X, ROBOT)) == 8
    result = ik_nearest(X, HOME, ROBOT)
    assert (result.ok, result.q) == (False, None)
    assert result.reason.startswith("outside joint limits (joint_3 +2.8000 not in [-2.53, +2.53]")
    # Gripper down, its x along +x of W: q6 = ±π is just past joint 6's ±3.14 rad, and the
    # wrist flip needs q4 = ±π, past ±3.05.
    result = ik_tcp(make_pose(DOWN, [0.45, 0.0, 0.1]), HOME, ROBOT)
    assert (result.ok, result.q) == (False, None)
    assert result.reason.startswith("outside joint limits (joint_6 +3.1416 not in [-3.14, +3.14]")


def test_bad_input_is_refused() -> None:
    X = ROBOT.flange_pose_W(HOME)
    with pytest.raises(ValueError, match="X_WF"):
        ik_nearest(X * 2, HOME, ROBOT)
    with pytest.raises(ValueError, match="X_BF"):
        ik_flange(np.full((4, 4), np.nan), ROBOT)
    with pytest.raises(ValueError, match="q_current"):
        ik_nearest(X, HOME[:5], ROBOT)
    with pytest.raises(ValueError, match="weights"):
        ik_nearest(X, HOME, ROBOT, weights=[1, 1, 1, 1, 1, -1])


@pytest.fixture(scope="module")
def bullet_puma() -> Iterator[tuple[int, int, dict[str, int]]]:
    """(client, body, joint and link indices by name) of the Puma in a DIRECT pybullet client."""
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(PUMA_URDF), useFixedBase=True, physicsClientId=cid)
        index = {}
        for i in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, i, physicsClientId=cid)
            index[info[1].decode()] = i  # joint name
            index[info[12].decode()] = i  # child link name
        yield cid, body, index
    finally:
        p.disconnect(physicsClientId=cid)


def _bullet_pose(pos: tuple, quat_xyzw: tuple) -> np.ndarray:
    return make_pose(quat_wxyz_to_R(quat_xyzw_to_wxyz(np.array(quat_xyzw))), np.array(pos))


def test_ik_solutions_put_pybullets_flange_on_the_target(
    bullet_puma: tuple[int, int, dict[str, int]],
) -> None:
    cid, body, index = bullet_puma
    rng = np.random.default_rng(7)
    n_checked = 0
    for _ in range(40):
        X_BF = ROBOT.flange_pose_W(rng.uniform(ROBOT.q_lower, ROBOT.q_upper))
        for q in ik_flange(X_BF, ROBOT):
            for name, value in zip(ROBOT.arm_joints, q, strict=True):
                p.resetJointState(body, index[name], float(value), physicsClientId=cid)
            state = p.getLinkState(
                body, index[FLANGE_LINK], computeForwardKinematics=True, physicsClientId=cid
            )
            # Elements 4–5 (the link frame) are float32 in pybullet 3.2.7: use the inertial
            # frame (0–1) and its offset in the link (2–3), which are double.
            X_WF = _bullet_pose(state[0], state[1]) @ invert_pose(_bullet_pose(state[2], state[3]))
            assert_same_pose(X_WF, X_BF)
            n_checked += 1
    assert n_checked >= 200


def test_gripper_down_over_the_frame_is_reachable_and_regular() -> None:
    """Task targets: TCP over the puzzle frame's centre, gripper pointing down, any yaw. Only
    within 2 mrad of one yaw (gripper x along +x of W, q6 = ±π) is the grasp turned half a turn,
    as a parallel gripper allows (operator_site.program.pick_place.choose_grasp_yaw)."""
    half_turn = make_pose(rpy_to_R(np.array([0.0, 0.0, math.pi])))
    for z in np.linspace(0.03, 0.3, 10):
        for yaw in np.linspace(-math.pi, math.pi, 73):
            X_WG = make_pose(rpy_to_R(np.array([math.pi, 0.0, yaw])), [0.45, 0.0, z])
            result = ik_tcp(X_WG, HOME, ROBOT, geometry=GEOMETRY)
            if abs(angle_diff(yaw, 0.0)) < 2e-3:
                assert not result.ok
                X_WG = X_WG @ half_turn
                result = ik_tcp(X_WG, HOME, ROBOT, geometry=GEOMETRY)
            assert (result.ok, result.reason) == (True, ""), (z, yaw)
            assert_same_pose(ROBOT.tcp_pose_W(result.q), X_WG)
            assert abs(math.sin(result.q[4])) > 0.1  # far from the wrist singularity
            assert abs(result.q[2]) > 0.1  # and from the stretched elbow


def test_every_block_can_be_grasped_from_above_where_the_scene_puts_it() -> None:
    scene = load_scene()
    assert len(scene.movable) == 6
    for obj in scene.movable:
        X_GP, _ = top_grasp(ROBOT, obj.model.bbox_O)
        X_GP = choose_grasp_yaw(obj.X_WO, X_GP)
        X_WG = obj.X_WO @ invert_pose(X_GP)
        result = ik_tcp(X_WG, HOME, ROBOT, scene.robot.X_WB)
        assert (result.ok, result.reason) == (True, ""), obj.name
        assert_same_pose(ROBOT.tcp_pose_W(result.q, scene.robot.X_WB), X_WG)


def _finite_difference_jacobian(q: np.ndarray, X_WB: np.ndarray, h: float) -> np.ndarray:
    J = np.zeros((6, 6))
    R_WF = ROBOT.flange_pose_W(q, X_WB)[:3, :3]
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        Xp, Xm = ROBOT.flange_pose_W(q + dq, X_WB), ROBOT.flange_pose_W(q - dq, X_WB)
        J[:3, i] = (Xp[:3, 3] - Xm[:3, 3]) / (2 * h)
        W = (Xp[:3, :3] - Xm[:3, :3]) / (2 * h) @ R_WF.T  # skew(ω) = Ṙ Rᵀ
        J[3:, i] = [W[2, 1], W[0, 2], W[1, 0]]
    return J


def test_jacobian_matches_central_finite_differences() -> None:
    rng = np.random.default_rng(3)
    X_WB = make_pose(rpy_to_R(np.array([0.2, 0.1, -0.4])), [0.1, 0.2, 0.3])
    for k in range(50):
        q = rng.uniform(ROBOT.q_lower, ROBOT.q_upper)
        base = None if k % 2 else X_WB
        J = geometric_jacobian_W(q, ROBOT, base)
        J_fd = _finite_difference_jacobian(q, np.eye(4) if base is None else base, 1e-5)
        np.testing.assert_allclose(J, J_fd, atol=1e-6, rtol=0)
