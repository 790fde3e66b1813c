"""Closed-form kinematics of the Puma-type arm (§III-A): all IK solutions, the nearest one, and
the flange Jacobian.

The arm (models/robots/puma.urdf): joint 1 about z at the base; joints 2 and 3 about y, an upper
arm of length a and a forearm of length b pointing up (+z) at q = 0; a spherical wrist (z, y, z
axes meeting at the wrist centre); the flange a distance f beyond it. The lengths are read from
the model, and a model that is not of this shape is refused. Frames: B robot base, F flange,
G gripper TCP; ``X_BF`` is the flange in the base frame.

Shared by both sites: the work site moves the arm with it, and the operator site checks a
program's reach with the same solutions before sending it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.robot import FLANGE_LINK, TCP_LINK, RobotModel
from models.transforms import invert_pose, make_pose, so3_exp, so3_log

STRUCTURE_TOL_M = 1e-9
"""Offsets the closed form assumes to be zero must be below this (m)."""
SINGULAR_WRIST_RAD = 1e-6
"""|sin q5| below this: joints 4 and 6 turn about one axis (wrist singularity)."""
SINGULAR_SHOULDER_M = 1e-6
"""Wrist centre this close to the joint-1 axis: q1 is undetermined (shoulder singularity)."""
SINGULAR_ELBOW = 1e-9
"""|cos q3| within this of 1: the arm is fully stretched or folded (elbow singularity)."""
JOINT_LIMIT_TOL_RAD = 1e-9
"""A solution this close outside a joint limit is put on the limit (rounding), not refused."""
ELBOW_LIMIT_TOL_RAD = 3e-7
"""The same for q2 to q6 at the elbow singularity: there q3 = acos(cos q3) with cos q3 ≈ ±1,
where a rounding error δ of the cosine (~1e-15) becomes √(2δ) ≈ 5e-8 rad of q3, q2 follows,
and the wrist, solved from the rotation the arm leaves it, takes up the error of q2 + q3."""
REACH_TOL_M = 1e-9
"""A wrist centre this much beyond reach is still taken as reachable (rounding)."""
PATH_SAMPLE_M = 0.005
"""A straight TCP move is followed in steps no longer than this (m) ..."""
PATH_SAMPLE_RAD = math.radians(2.0)
"""... and turning no more than this (rad)."""
BRANCH_JUMP_RAD = 0.5
"""Between path samples this close, a joint that turns more than this (rad) has left its
continuous solution for another IK branch (the arm would swing through space); away from the
singularities a continuous path turns every joint by a few hundredths of this."""
JOINT_SAMPLE_RAD = 0.02
"""A straight move in joint space is checked at samples no more than this apart in any joint."""
MAX_PATH_SAMPLES = 4000
"""At most this many samples per move: the workspace's diagonal and a half turn need fewer."""
_AXES = ((0, 0, 1), (0, 1, 0), (0, 1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1))


@dataclass(frozen=True)
class ArmGeometry:
    """The lengths of the closed form (m), read from a robot model."""

    shoulder_height_m: float
    upper_arm_m: float
    forearm_m: float
    wrist_to_flange_m: float
    X_FG: np.ndarray
    """The gripper TCP in the flange frame (fixed)."""


def arm_geometry(robot: RobotModel) -> ArmGeometry:
    """Read the lengths from ``robot``; ValueError if it is not a zero-offset Puma-type arm."""
    if len(robot.arm_joints) != 6:
        raise ValueError(f"{robot.source}: expected 6 arm joints, got {len(robot.arm_joints)}")
    offsets = []
    for name, axis in zip(robot.arm_joints, _AXES, strict=True):
        j = robot.joint(name)
        if not np.allclose(j.axis, axis, atol=STRUCTURE_TOL_M):
            raise ValueError(f"{robot.source}: {name} axis {j.axis.tolist()} is not {axis}")
        if (
            np.max(np.abs(j.X_PJ[:3, :3] - np.eye(3))) > STRUCTURE_TOL_M
            or np.max(np.abs(j.X_PJ[:2, 3])) > STRUCTURE_TOL_M
        ):
            raise ValueError(
                f"{robot.source}: {name} has a rotated or sideways origin; the "
                "closed form needs offsets along z only"
            )
        offsets.append(float(j.X_PJ[2, 3]))
    if abs(offsets[0]) > STRUCTURE_TOL_M or max(abs(offsets[4]), abs(offsets[5])) > STRUCTURE_TOL_M:
        raise ValueError(f"{robot.source}: joints 1, 5 and 6 must sit where their parents end")
    q0 = np.zeros(6)
    poses = robot.link_poses_W(q0)
    X_W6 = poses[robot.joint(robot.arm_joints[5]).child]
    X_WF = poses[FLANGE_LINK]
    X_6F = invert_pose(X_W6) @ X_WF
    if (
        np.max(np.abs(X_6F[:3, :3] - np.eye(3))) > STRUCTURE_TOL_M
        or np.max(np.abs(X_6F[:2, 3])) > STRUCTURE_TOL_M
    ):
        raise ValueError(f"{robot.source}: the flange must lie on joint 6's axis, unrotated")
    return ArmGeometry(
        shoulder_height_m=offsets[1],
        upper_arm_m=offsets[2],
        forearm_m=offsets[3],
        wrist_to_flange_m=float(X_6F[2, 3]),
        X_FG=invert_pose(X_WF) @ poses[TCP_LINK],
    )


@dataclass(frozen=True)
class IkResult:
    """The chosen joint angles (6,) rad, whether they reach the target, and why not."""

    q: np.ndarray | None
    ok: bool
    reason: str = ""
    singular: str = ""
    """The singularities the target sits on ("elbow", "shoulder", "wrist", joined by "+"); q is
    still valid there."""


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _Ry(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _Rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ik_flange(
    X_BF: np.ndarray,
    robot: RobotModel,
    q_hint: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> tuple[list[np.ndarray], str]:
    """All joint solutions for flange pose ``X_BF`` and the singularities met.

    Each solution is (6,) rad in (−π, π], joint limits not applied; singularities are "" or
    names joined by "+". ``q_hint`` fills the joints a singularity leaves free (q1 at the
    shoulder, q4 at the wrist). An empty list: the wrist centre is out of reach."""
    g = geometry or arm_geometry(robot)
    hint = np.zeros(6) if q_hint is None else np.asarray(q_hint, dtype=np.float64)
    R = X_BF[:3, :3]
    p_wrist = X_BF[:3, 3] - g.wrist_to_flange_m * R[:, 2]
    x, y = p_wrist[0], p_wrist[1]
    h = p_wrist[2] - g.shoulder_height_m
    rho = math.hypot(x, y)
    a, b = g.upper_arm_m, g.forearm_m
    cos3 = (rho * rho + h * h - a * a - b * b) / (2 * a * b)
    if abs(cos3) > 1 + REACH_TOL_M / (a * b):
        return [], ""
    cos3 = max(-1.0, min(1.0, cos3))
    singular: set[str] = set()
    if rho < SINGULAR_SHOULDER_M:
        singular.add("shoulder")
        # Any q1 will do; keeping the current one costs at most SINGULAR_SHOULDER_M of position.
        q1_options = [(float(hint[0]), 0.0)]
    else:
        q1 = math.atan2(y, x)
        q1_options = [(q1, rho), (_wrap(q1 + math.pi), -rho)]
    if 1 - abs(cos3) < SINGULAR_ELBOW:
        singular.add("elbow")
    solutions = []
    for (q1, r), sign3 in itertools.product(q1_options, (1.0, -1.0)):
        q3 = sign3 * math.acos(cos3)
        q2 = math.atan2(r, h) - math.atan2(b * math.sin(q3), a + b * math.cos(q3))
        R_36 = (_Rz(q1) @ _Ry(q2 + q3)).T @ R  # the wrist's rotation: Rz(q4) Ry(q5) Rz(q6)
        s5 = math.hypot(R_36[0, 2], R_36[1, 2])
        if s5 < SINGULAR_WRIST_RAD:
            # Keep q4 where it is and solve Ry(q5) Rz(q6) = Rz(−q4) R_36 for the rest: the pose
            # error is at most sin(q5)·|Δq4| < SINGULAR_WRIST_RAD·π, and q4 does not spin.
            singular.add("wrist")
            q4 = float(hint[3])
            M = _Rz(-q4) @ R_36
            q5 = math.atan2(M[0, 2], M[2, 2])
            q6 = math.atan2(M[1, 0], M[1, 1])
            wrists = [(q4, q5, q6)]
        else:
            q4 = math.atan2(R_36[1, 2], R_36[0, 2])
            q5 = math.atan2(s5, R_36[2, 2])
            q6 = math.atan2(R_36[2, 1], -R_36[2, 0])
            wrists = [(q4, q5, q6), (q4 + math.pi, -q5, q6 + math.pi)]
        for q4, q5, q6 in wrists:
            solutions.append(np.array([_wrap(v) for v in (q1, q2, q3, q4, q5, q6)]))
    return solutions, "+".join(sorted(singular))


def ik_nearest(
    X_WF: np.ndarray,
    q_current: np.ndarray,
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
    weights: np.ndarray | None = None,
) -> IkResult:
    """The solution within joint limits nearest ``q_current`` (weighted, each joint taken the
    short way round where its limits allow), or the reason there is none."""
    g = geometry or arm_geometry(robot)
    X_BF = X_WF if X_WB is None else invert_pose(X_WB) @ X_WF
    q_current = np.asarray(q_current, dtype=np.float64)
    solutions, singular = ik_flange(X_BF, robot, q_current, g)
    if not solutions:
        p_wrist = X_BF[:3, 3] - g.wrist_to_flange_m * X_BF[:3, 2]
        d = float(np.linalg.norm(p_wrist - [0.0, 0.0, g.shoulder_height_m]))
        return IkResult(
            None,
            False,
            f"unreachable: wrist centre {d:.3f} m from the shoulder, "
            f"reach {g.upper_arm_m + g.forearm_m:.3f} m",
        )
    limit_tol = np.full(6, JOINT_LIMIT_TOL_RAD)
    if "elbow" in singular.split("+"):
        limit_tol[1:] = ELBOW_LIMIT_TOL_RAD
    lo, hi = robot.q_lower - limit_tol, robot.q_upper + limit_tol
    w = np.ones(6) if weights is None else np.asarray(weights, dtype=np.float64)
    best, best_cost, violations = None, math.inf, []
    for q in solutions:
        # Each joint may also be reached one turn away, if that is inside its limits.
        q = q.copy()
        for i in range(6):
            for candidate in (q[i] - 2 * math.pi, q[i], q[i] + 2 * math.pi):
                if lo[i] <= candidate <= hi[i] and (
                    not lo[i] <= q[i] <= hi[i]
                    or abs(candidate - q_current[i]) < abs(q[i] - q_current[i])
                ):
                    q[i] = candidate
        outside = [
            f"{robot.arm_joints[i]} {q[i]:+.3f} not in [{lo[i]:+.3f}, {hi[i]:+.3f}]"
            for i in range(6)
            if not lo[i] <= q[i] <= hi[i]
        ]
        if outside:
            violations.append(outside[0])
            continue
        q = np.clip(q, robot.q_lower, robot.q_upper)
        cost = float(np.sum(w * (q - q_current) ** 2))
        if cost < best_cost:
            best, best_cost = q, cost
    if best is None:
        return IkResult(None, False, f"outside joint limits ({violations[0]})", singular)
    return IkResult(best, True, "", singular)


def ik_tcp(
    X_WG: np.ndarray,
    q_current: np.ndarray,
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> IkResult:
    """:func:`ik_nearest` for a gripper TCP target ``X_WG``."""
    g = geometry or arm_geometry(robot)
    return ik_nearest(X_WG @ invert_pose(g.X_FG), q_current, robot, X_WB, g)


def geometric_jacobian_W(
    q: np.ndarray, robot: RobotModel, X_WB: np.ndarray | None = None
) -> np.ndarray:
    """(6, 6) Jacobian of the flange origin: rows 0–2 linear velocity (m/s), 3–5 angular
    velocity (rad/s), both in W, per joint rate (rad/s)."""
    poses = robot.link_poses_W(q, 0.0, X_WB)
    p_F = poses[FLANGE_LINK][:3, 3]
    J = np.zeros((6, 6))
    for i, name in enumerate(robot.arm_joints):
        joint = robot.joint(name)
        X_WJ = poses[joint.child]  # the child link frame is the joint frame at q
        z = X_WJ[:3, :3] @ joint.axis
        J[:3, i] = np.cross(z, p_F - X_WJ[:3, 3])
        J[3:, i] = z
    return J


@dataclass(frozen=True)
class PathFollow:
    """How the arm follows a straight TCP move: ``ok`` with the joints at its end ``q`` (rad)
    and the smallest distance to a joint limit on the way ``margin_rad``; else the ``reason``."""

    ok: bool
    q: np.ndarray | None
    margin_rad: float = math.inf
    reason: str = ""


def follow_line_tcp(
    X_WG_from: np.ndarray,
    X_WG_to: np.ndarray,
    q_from: np.ndarray,
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> PathFollow:
    """Follow the straight TCP move from ``X_WG_from`` (where the arm is, at ``q_from``) to
    ``X_WG_to`` as the work site does: a straight line in position and the shortest arc in
    orientation, the nearest IK solution at each sample (:data:`PATH_SAMPLE_M`,
    :data:`PATH_SAMPLE_RAD` apart). Fails where a sample is out of reach or the joints jump to
    another branch (:data:`BRANCH_JUMP_RAD`): checking only the move's end misses both."""
    g = geometry or arm_geometry(robot)
    p0, p1 = X_WG_from[:3, 3], X_WG_to[:3, 3]
    R0 = X_WG_from[:3, :3]
    w = so3_log(R0.T @ X_WG_to[:3, :3])
    n = math.ceil(
        max(np.linalg.norm(p1 - p0) / PATH_SAMPLE_M, np.linalg.norm(w) / PATH_SAMPLE_RAD, 1.0)
    )
    if n > MAX_PATH_SAMPLES:  # only a move far beyond the workspace gets here
        return PathFollow(
            False,
            None,
            reason=f"a move of {np.linalg.norm(p1 - p0):.2f} m is longer than any in reach",
        )
    q = np.asarray(q_from, dtype=np.float64)
    lo, hi = robot.q_lower, robot.q_upper
    margin = float(np.min(np.minimum(q - lo, hi - q)))
    # A move that is mostly a turn of the gripper fails where its end point looks like its
    # start: say the turn.
    turn_deg = math.degrees(float(np.linalg.norm(w)))
    turning = f", turning the gripper {turn_deg:.0f}°" if turn_deg >= 1.0 else ""
    for i in range(1, n + 1):
        s = i / n
        X = make_pose(R0 @ so3_exp(s * w), p0 + s * (p1 - p0))
        result = ik_tcp(X, q, robot, X_WB, g)
        where = f"{s * 100:.0f} % of the way to {np.round(p1, 3).tolist()} m{turning}"
        if not result.ok:
            return PathFollow(False, None, margin, f"{where}: {result.reason}")
        jump = np.abs(result.q - q)
        j = int(np.argmax(jump))
        if jump[j] > BRANCH_JUMP_RAD:
            return PathFollow(
                False,
                None,
                margin,
                f"{where}: {robot.arm_joints[j]} would swing {jump[j]:.2f} rad at once to "
                "another arm configuration (a joint at its limit)",
            )
        q = result.q
        margin = min(margin, float(np.min(np.minimum(q - lo, hi - q))))
    return PathFollow(True, q, margin)


def ik_all_tcp(
    X_WG: np.ndarray,
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> list[np.ndarray]:
    """Every joint solution (rad) within the limits for gripper TCP pose ``X_WG``, each joint
    also a whole turn away where its limits allow."""
    g = geometry or arm_geometry(robot)
    X_WF = X_WG @ invert_pose(g.X_FG)
    X_BF = X_WF if X_WB is None else invert_pose(X_WB) @ X_WF
    lo, hi = robot.q_lower - JOINT_LIMIT_TOL_RAD, robot.q_upper + JOINT_LIMIT_TOL_RAD
    out = []
    for q in ik_flange(X_BF, robot, None, g)[0]:
        options = [
            [c for c in (q[i] - 2 * math.pi, q[i], q[i] + 2 * math.pi) if lo[i] <= c <= hi[i]]
            for i in range(6)
        ]
        out += [
            np.clip(np.array(c), robot.q_lower, robot.q_upper) for c in itertools.product(*options)
        ]
    return out


def follow_tcp(
    X_WG_from: np.ndarray,
    q_from: np.ndarray,
    targets_WG: Sequence[np.ndarray],
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> PathFollow:
    """:func:`follow_line_tcp` through ``targets_WG`` in turn, from ``X_WG_from`` at ``q_from``."""
    g = geometry or arm_geometry(robot)
    q, here, margin = np.asarray(q_from, dtype=np.float64), X_WG_from, math.inf
    for X_WG in targets_WG:
        result = follow_line_tcp(here, X_WG, q, robot, X_WB, g)
        if not result.ok:
            return result
        q, here, margin = result.q, X_WG, min(margin, result.margin_rad)
    return PathFollow(True, q, margin)


@dataclass(frozen=True)
class Approach:
    """How the empty hand gets to a grasp's approach pose: ``ok``; ``q_joint`` None for a
    straight TCP move, else the joints (rad) to go to in a straight joint-space move; else the
    ``reason``."""

    ok: bool
    q_joint: np.ndarray | None = None
    reason: str = ""


def _stays_above(
    q_from: np.ndarray, q_to: np.ndarray, floor_z_m: float, robot: RobotModel, X_WB
) -> bool:
    """Whether the TCP stays at or above ``floor_z_m`` along the joint-space line."""
    n = max(1, math.ceil(float(np.max(np.abs(q_to - q_from))) / JOINT_SAMPLE_RAD))
    if n > MAX_PATH_SAMPLES:
        return False
    return all(
        robot.tcp_pose_W(q_from + (q_to - q_from) * i / n, X_WB)[2, 3] >= floor_z_m
        for i in range(1, n)
    )


def plan_approach(
    X_WG_here: np.ndarray,
    q_here: np.ndarray,
    X_WG_above: np.ndarray,
    then_WG: Sequence[np.ndarray],
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
) -> Approach:
    """The empty hand's way from ``X_WG_here`` (joints ``q_here``) to a grasp's approach pose
    ``X_WG_above``, from where the program goes on through ``then_WG``: a straight TCP move
    when the arm can follow it; else a straight move in joint space to the solution at the
    approach pose nearest ``q_here`` from which the rest can be followed, along which the hand
    stays no lower than the lower of its two ends (it passes over the blocks, not into them).
    A straight TCP move turns the hand the short way round; the joint move turns each joint
    within its limits, whichever way round that takes the hand."""
    g = geometry or arm_geometry(robot)
    straight = follow_line_tcp(X_WG_here, X_WG_above, q_here, robot, X_WB, g)
    if straight.ok:
        return Approach(True)
    floor_z_m = min(float(X_WG_here[2, 3]), float(X_WG_above[2, 3]))
    q_here = np.asarray(q_here, dtype=np.float64)
    candidates = sorted(
        ik_all_tcp(X_WG_above, robot, X_WB, g), key=lambda q: float(np.sum((q - q_here) ** 2))
    )
    for q in candidates:
        if follow_tcp(X_WG_above, q, then_WG, robot, X_WB, g).ok and _stays_above(
            q_here, q, floor_z_m, robot, X_WB
        ):
            return Approach(True, q)
    return Approach(
        False,
        reason=f"{straight.reason}, and no joint-space move reaches the approach with the rest "
        "of the program followable from there",
    )
