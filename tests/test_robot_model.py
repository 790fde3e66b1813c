"""The Puma URDF and the numpy kinematics reader (models/robot.py), checked against pybullet."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from models.errors import ModelError
from models.robot import HOME_Q, PUMA_URDF, RobotModel, load_robot
from models.transforms import make_pose, quat_wxyz_to_R, quat_xyzw_to_wxyz, rpy_to_R

FK_TOL = 1e-9
"""Agreement of numpy FK with pybullet's double-precision frames (m, and rotation entries)."""
FLOAT32_TOL = 1e-6
"""Agreement with getLinkState's link frame (elements 4, 5), which pybullet rounds to float32."""


@pytest.fixture(scope="module")
def puma() -> RobotModel:
    return load_robot(PUMA_URDF)


@pytest.fixture(scope="module")
def bullet() -> Iterator[int]:
    cid = p.connect(p.DIRECT)
    try:
        yield cid
    finally:
        p.disconnect(physicsClientId=cid)


def _pose_from_bullet(pos: tuple, quat_xyzw: tuple) -> np.ndarray:
    return make_pose(quat_wxyz_to_R(quat_xyzw_to_wxyz(np.array(quat_xyzw))), np.array(pos))


def _bullet_link_poses_W(cid: int, body: int) -> tuple[dict, dict]:
    """URDF link frames X_WL from pybullet, two ways: (double, float32).

    pybullet 3.2.7 computes getLinkState's link frame (elements 4, 5) in single precision
    (errors up to ~5e-7 m), while the centre-of-mass frame (0, 1) and the local inertial frame
    (2, 3) are double: X_WL = X_WI · X_LI⁻¹ from those is exact to ~1e-15. The base pose is its
    inertial frame too (getDynamicsInfo gives X_BI; identity for the Puma's base_link).
    """
    name = p.getBodyInfo(body, physicsClientId=cid)[0].decode()
    X_WBi = _pose_from_bullet(*p.getBasePositionAndOrientation(body, physicsClientId=cid))
    X_BI = _pose_from_bullet(*p.getDynamicsInfo(body, -1, physicsClientId=cid)[3:5])
    X_WB = X_WBi @ np.linalg.inv(X_BI)
    exact, single = {name: X_WB}, {name: X_WB}
    for i in range(p.getNumJoints(body, physicsClientId=cid)):
        link = p.getJointInfo(body, i, physicsClientId=cid)[12].decode()
        state = p.getLinkState(body, i, computeForwardKinematics=True, physicsClientId=cid)
        X_WI = _pose_from_bullet(state[0], state[1])
        X_LI = _pose_from_bullet(state[2], state[3])
        exact[link] = X_WI @ np.linalg.inv(X_LI)
        single[link] = _pose_from_bullet(state[4], state[5])
    return exact, single


def test_model_matches_the_specification(puma: RobotModel) -> None:
    assert puma.root_link == "base_link"
    assert puma.arm_joints == tuple(f"joint_{i}" for i in range(1, 7))
    assert puma.finger_joints == ("finger_left", "finger_right")
    expected_axes = [(0, 0, 1), (0, 1, 0), (0, 1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1)]
    expected_p = [(0, 0, 0), (0, 0, 0.33), (0, 0, 0.305), (0, 0, 0.33), (0, 0, 0), (0, 0, 0)]
    for name, axis, p_PJ in zip(puma.arm_joints, expected_axes, expected_p, strict=True):
        j = puma.joint(name)
        assert j.type == "revolute"
        np.testing.assert_array_equal(j.axis, axis)
        np.testing.assert_array_equal(j.X_PJ, make_pose(p_AB=np.array(p_PJ, dtype=float)))
        assert 50.0 <= j.effort <= 150.0 and j.velocity == 3.0
    np.testing.assert_array_equal(puma.q_upper, [2.97, 1.92, 2.53, 3.05, 2.09, 3.14])
    np.testing.assert_array_equal(puma.q_lower, -puma.q_upper)
    np.testing.assert_array_equal(puma.joint("finger_left").axis, (0, 1, 0))
    np.testing.assert_array_equal(puma.joint("finger_right").axis, (0, -1, 0))
    assert puma.finger_opening_max == pytest.approx(0.08)
    np.testing.assert_array_equal(puma.links["base_link"].X_LI, np.eye(4))  # base pose = frame B
    assert puma.joint("ft_sensor_joint").type == "fixed"
    assert puma.joint("ft_sensor_joint").parent == "flange"
    for link in puma.links.values():
        assert link.mass > 0.0, link.name
        eig = np.linalg.eigvalsh(link.I_I)
        assert eig.min() > 0.0, link.name
        assert 2 * eig.max() <= eig.sum() * (1 + 1e-12), link.name  # triangle inequality
        for shape in (*link.visuals, *link.collisions):
            assert shape.kind in ("box", "cylinder", "sphere")
    arm_mass = [puma.links[f"link_{i}"].mass for i in range(1, 7)]
    assert all(0.5 <= m <= 5.0 for m in arm_mass)
    assert puma.links["gripper_base"].visuals[0].size == pytest.approx((0.04, 0.10, 0.03))


def test_flange_at_q_zero_points_straight_up(puma: RobotModel) -> None:
    X_WF = puma.flange_pose_W(np.zeros(6))
    np.testing.assert_allclose(X_WF, make_pose(p_AB=np.array([0.0, 0.0, 1.041])), atol=1e-15)
    X_WG = puma.tcp_pose_W(np.zeros(6))
    np.testing.assert_allclose(X_WG[:3, 3], [0.0, 0.0, 1.041 + 0.03 + 0.085], atol=1e-15)


@pytest.mark.parametrize("with_base_pose", [False, True])
def test_fk_equals_pybullet_link_frames(
    puma: RobotModel, bullet: int, with_base_pose: bool
) -> None:
    rng = np.random.default_rng(20251122 + with_base_pose)
    X_WB = np.eye(4)
    if with_base_pose:
        X_WB = make_pose(rpy_to_R(rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-1.0, 1.0, 3))
    body = p.loadURDF(
        str(PUMA_URDF),
        basePosition=X_WB[:3, 3].tolist(),
        baseOrientation=p.getQuaternionFromEuler(
            _R_to_rpy(X_WB[:3, :3]).tolist(), physicsClientId=bullet
        ),
        useFixedBase=True,
        physicsClientId=bullet,
    )
    X_WB = _bullet_link_poses_W(bullet, body)[0]["base_link"]  # as pybullet placed it
    index = {
        p.getJointInfo(body, i, physicsClientId=bullet)[1].decode(): i
        for i in range(p.getNumJoints(body, physicsClientId=bullet))
    }
    n_configs = 200 if not with_base_pose else 50
    worst_exact = worst_single = 0.0
    for _ in range(n_configs):
        q = rng.uniform(puma.q_lower, puma.q_upper)
        opening = rng.uniform(0.0, puma.finger_opening_max)
        for name, value in puma.joint_positions(q, opening).items():
            p.resetJointState(body, index[name], value, physicsClientId=bullet)
        exact, single = _bullet_link_poses_W(bullet, body)
        got = puma.link_poses_W(q, opening, X_WB)
        assert got.keys() == exact.keys() == puma.links.keys()
        for link, X_WL in got.items():
            worst_exact = max(worst_exact, float(np.max(np.abs(X_WL - exact[link]))))
            worst_single = max(worst_single, float(np.max(np.abs(X_WL - single[link]))))
    assert worst_exact < FK_TOL
    assert worst_single < FLOAT32_TOL
    p.removeBody(body, physicsClientId=bullet)


def test_fk_with_random_joint_origins_and_axes_equals_pybullet(tmp_path: Path, bullet: int) -> None:
    """URDF rpy (Rz·Ry·Rx), joint axes and prismatic joints agree with pybullet's reading."""
    rng = np.random.default_rng(7)
    n = 5
    types = ["revolute", "prismatic", "revolute", "continuous", "revolute"]

    def nums(v: np.ndarray) -> str:
        return " ".join(repr(float(x)) for x in v)

    links = "".join(
        f'<link name="l{i}"><inertial><origin xyz="{nums(rng.uniform(-0.1, 0.1, 3))}"/>'
        '<mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>'
        "</inertial></link>"
        for i in range(n + 1)
    )
    joints = "".join(
        f'<joint name="j{i}" type="{types[i]}"><parent link="l{i}"/><child link="l{i + 1}"/>'
        f'<origin xyz="{nums(rng.uniform(-0.3, 0.3, 3))}" rpy="{nums(rng.uniform(-3, 3, 3))}"/>'
        f'<axis xyz="{nums(_unit(rng.normal(size=3)))}"/>'
        '<limit lower="-3" upper="3" effort="10" velocity="1"/></joint>'
        for i in range(n)
    )
    path = tmp_path / "random_chain.urdf"
    path.write_text(f'<?xml version="1.0"?><robot name="chain">{links}{joints}</robot>')
    model = load_robot(path)
    assert model.arm_joints == ("j0", "j2", "j3", "j4") and model.finger_joints == ("j1",)
    body = p.loadURDF(str(path), useFixedBase=True, physicsClientId=bullet)
    worst = 0.0
    for _ in range(50):
        q = rng.uniform(-3, 3, 4)
        opening = rng.uniform(-1, 1)  # the single prismatic joint moves opening / 2
        for name, value in model.joint_positions(q, opening).items():
            p.resetJointState(body, int(name[1:]), value, physicsClientId=bullet)
        exact, _single = _bullet_link_poses_W(bullet, body)
        got = model.link_poses_W(q, opening)
        worst = max(worst, max(float(np.max(np.abs(got[k] - exact[k]))) for k in got))
    assert worst < FK_TOL
    p.removeBody(body, physicsClientId=bullet)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _R_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of rpy_to_R away from pitch = ±π/2 (test helper only)."""
    return np.array(
        [math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0]), math.atan2(R[1, 0], R[0, 0])]
    )


def test_fingers_move_half_the_opening_each(puma: RobotModel) -> None:
    poses = puma.link_poses_W(np.array(HOME_Q), 0.06)
    X_GW = np.linalg.inv(poses["gripper_tcp"])
    p_G_left = (X_GW @ poses["finger_left"])[:3, 3]
    p_G_right = (X_GW @ poses["finger_right"])[:3, 3]
    np.testing.assert_allclose(p_G_left, [0.0, 0.03, -0.055], atol=1e-12)
    np.testing.assert_allclose(p_G_right, [0.0, -0.03, -0.055], atol=1e-12)


def test_home_configuration(puma: RobotModel) -> None:
    q = np.array(HOME_Q)
    assert q.shape == (6,)
    assert np.all(q > puma.q_lower) and np.all(q < puma.q_upper)
    poses = puma.link_poses_W(q)
    X_WG = poses["gripper_tcp"]
    np.testing.assert_allclose(X_WG[:3, 3], [0.18, 0.0, 0.40], atol=1e-6)
    np.testing.assert_allclose(X_WG[:3, 2], [0.0, 0.0, -1.0], atol=1e-6)
    assert abs(q[4]) > 0.5  # wrist pitch far from the q5 = 0 singularity
    # Elbow up: the elbow lies above the shoulder-to-wrist-centre line in the arm's plane.
    p_shoulder, p_elbow, p_wrist = (poses[n][:3, 3] for n in ("link_2", "link_3", "link_4"))
    u = p_wrist - p_shoulder
    n = np.cross(u, [0.0, 0.0, 1.0])  # horizontal normal of the vertical arm plane
    up_in_plane = np.cross(n, u) / np.linalg.norm(np.cross(n, u))
    assert up_in_plane[2] > 0.0
    assert float(np.dot(p_elbow - p_shoulder, up_in_plane)) > 0.05
    # The whole arm and gripper stay above the table.
    assert all(X[2, 3] > 0.2 for name, X in poses.items() if name not in ("base_link", "link_1"))


_STEP_SCRIPT = textwrap.dedent(
    """
    import json, math, sys
    import pybullet as p
    urdf, home = sys.argv[1], json.loads(sys.argv[2])
    cid = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(1e-3, physicsClientId=cid)
    body = p.loadURDF(urdf, useFixedBase=True, physicsClientId=cid)
    n = p.getNumJoints(body, physicsClientId=cid)
    info = [p.getJointInfo(body, i, physicsClientId=cid) for i in range(n)]
    moving = [i for i in range(n) if info[i][2] != p.JOINT_FIXED]
    names = [info[i][1].decode() for i in range(n)]
    target = {f"joint_{k + 1}": v for k, v in enumerate(home)}
    target.update(finger_left=0.02, finger_right=0.02)
    sensor = names.index("ft_sensor_joint")
    p.enableJointForceTorqueSensor(body, sensor, True, physicsClientId=cid)
    for i in moving:
        p.resetJointState(body, i, target[names[i]], physicsClientId=cid)
    p.setJointMotorControlArray(
        body, moving, p.POSITION_CONTROL,
        targetPositions=[target[names[i]] for i in moving],
        forces=[info[i][10] for i in moving], physicsClientId=cid,
    )
    finite = True
    for _ in range(1000):
        p.stepSimulation(physicsClientId=cid)
        for i in range(n):
            s = p.getLinkState(body, i, computeForwardKinematics=True, physicsClientId=cid)
            finite &= all(math.isfinite(v) for v in (*s[4], *s[5]))
    err = max(
        abs(p.getJointState(body, i, physicsClientId=cid)[0] - target[names[i]]) for i in moving
    )
    wrench = list(p.getJointState(body, sensor, physicsClientId=cid)[2])
    p.disconnect(physicsClientId=cid)
    print("RESULT " + json.dumps({"finite": finite, "max_err": err, "wrench": wrench}))
    """
)


def test_urdf_loads_and_holds_position_for_one_second_without_warnings() -> None:
    run = subprocess.run(
        [sys.executable, "-c", _STEP_SCRIPT, str(PUMA_URDF), json.dumps(list(HOME_Q))],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    lines = run.stdout.splitlines()
    # pybullet prints its build time on import; anything else is a warning.
    other = [
        ln
        for ln in lines[:-1] + run.stderr.splitlines()
        if not ln.startswith("pybullet build time")
    ]
    assert other == []
    assert lines[-1].startswith("RESULT ")
    result = json.loads(lines[-1].removeprefix("RESULT "))
    assert result["finite"]
    assert result["max_err"] < 1e-3
    # Gripper down (z_S = −z_W): pybullet reports the weight of everything on the sensor joint's
    # child side (the ft_sensor link itself included) as −m·g along z_S, no moment.
    puma = load_robot(PUMA_URDF)
    tool = ("ft_sensor", "gripper_base", "finger_left", "finger_right", "gripper_tcp")
    m_tool = sum(puma.links[name].mass for name in tool)
    np.testing.assert_allclose(result["wrench"][:3], [0.0, 0.0, -m_tool * 9.81], atol=0.01)
    np.testing.assert_allclose(result["wrench"][3:], 0.0, atol=1e-3)


def _joint(name: str, parent: str, child: str, origin: str = 'xyz="0 0 0.1" rpy="0 0 0"') -> str:
    return f"""
  <joint name="{name}" type="revolute">
    <parent link="{parent}"/><child link="{child}"/>
    <origin {origin}/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/>
  </joint>"""


_GOOD_JOINT = _joint("j", "a", "b")
_LINKS_BC = '<link name="b"/><link name="c"/>'


def _urdf(body: str) -> str:
    return f'<?xml version="1.0"?>\n<robot name="bad">\n  <link name="a"/>\n{body}\n</robot>\n'


_MALFORMED = {
    "unknown joint type": (
        _urdf('<link name="b"/>' + _GOOD_JOINT.replace("revolute", "hinge")),
        "unsupported joint type 'hinge'",
    ),
    "missing parent link": (
        _urdf('<link name="b"/>' + _GOOD_JOINT.replace('parent link="a"', 'parent link="z"')),
        "parent link 'z' is not defined",
    ),
    "nan in origin": (
        _urdf('<link name="b"/>' + _joint("j", "a", "b", 'xyz="0 nan 0.1"')),
        "NaN or infinity",
    ),
    "inf in origin": (
        _urdf('<link name="b"/>' + _joint("j", "a", "b", 'rpy="0 inf 0"')),
        "NaN or infinity",
    ),
    "loop": (
        _urdf(_LINKS_BC + _GOOD_JOINT + _joint("k", "b", "c") + _joint("m", "c", "b")),
        "kinematic loop",
    ),
    "cycle apart from the root": (
        _urdf(_LINKS_BC + _joint("k", "b", "c") + _joint("m", "c", "b")),
        "kinematic loop",
    ),
    "axis not a unit vector": (
        _urdf('<link name="b"/>' + _GOOD_JOINT.replace('xyz="0 0 1"', 'xyz="0 2 1"')),
        "is not a unit vector",
    ),
    "not xml": ("<robot><link name='a'>", "cannot read URDF"),
    "revolute without limit": (
        _urdf('<link name="b"/>' + _GOOD_JOINT.split("<limit")[0] + "</joint>"),
        "needs a <limit>",
    ),
}


@pytest.mark.parametrize("case", sorted(_MALFORMED))
def test_malformed_urdf_raises_model_error_naming_the_file(tmp_path: Path, case: str) -> None:
    text, problem = _MALFORMED[case]
    path = tmp_path / f"{case.replace(' ', '_')}.urdf"
    path.write_text(text)
    with pytest.raises(ModelError) as err:
        load_robot(path)
    assert str(path) in str(err.value)
    assert problem in str(err.value)


def test_missing_file_raises_model_error(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.urdf"
    with pytest.raises(ModelError, match="file not found") as err:
        load_robot(path)
    assert str(path) in str(err.value)


def test_well_formed_minimal_urdf_loads(tmp_path: Path) -> None:
    """The malformed cases above are single edits of this file, which loads."""
    path = tmp_path / "good.urdf"
    path.write_text(_urdf('<link name="b"/>' + _GOOD_JOINT))
    model = load_robot(path)
    assert model.arm_joints == ("j",)
    X_WB = model.link_poses_W(np.array([np.pi / 2]))["b"]
    np.testing.assert_allclose(X_WB, make_pose(rpy_to_R([0, 0, np.pi / 2]), [0, 0, 0.1]))


def test_bad_arguments_raise_value_error(puma: RobotModel) -> None:
    with pytest.raises(ValueError, match="shape"):
        puma.link_poses_W(np.zeros(5))
    with pytest.raises(ValueError, match="finite"):
        puma.link_poses_W(np.array([0, 0, np.nan, 0, 0, 0]))
    assert not issubclass(ValueError, ModelError)
