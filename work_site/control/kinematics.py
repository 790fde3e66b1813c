"""Closed-form kinematics of the Puma-type arm (§III-A): all IK solutions, the nearest one within
joint limits, and the flange Jacobian.

The arm (``models/robots/puma.urdf``): joint 1 about z of the base; joints 2 and 3 about y, an
upper arm of length a and a forearm of length b pointing up (+z) at q = 0; a spherical wrist
(joints 4, 5, 6 about z, y, z, their axes meeting at the wrist centre); the flange a distance f
beyond it on joint 6's axis. The lengths are read from the model, and a model not of this shape is
refused with a ValueError (:func:`arm_geometry`).

Frames (Drake notation): W world, B robot base (the URDF root link), F flange, G gripper TCP.
``X_BF`` is the flange in the base frame, ``X_WF`` in world, ``X_WB`` the base in world. Angles
in rad, lengths in m.

Solving: the wrist centre ``p_BC = p_BF − f·z_F`` gives q1 (two ways: facing it or reaching over
the shoulder), q3 (elbow up or down) and q2 from planar two-link geometry; the wrist rotation
``R_36 = (Rz(q1)·Ry(q2 + q3))ᵀ·R_BF = Rz(q4)·Ry(q5)·Rz(q6)`` gives q4, q5, q6 (two ways: the
wrist flip). q5 and q6 are fitted to q4 (``Ry(q5)·Rz(q6) = Rz(−q4)·R_36``), so q4's rounding
when |q5| is small does not reach the pose.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.robot import FLANGE_LINK, TCP_LINK, RobotModel
from models.transforms import invert_pose, is_rigid_transform

STRUCTURE_TOL_M = 1e-9
"""Offsets and rotations the closed form needs to be zero must be below this (m, or rotation
matrix entries)."""
REACH_TOL_M = 1e-9
"""A wrist centre this little beyond the reach (or inside the inner reach) is rounding: it is
solved with the arm fully stretched (folded), and then reported as an elbow singularity."""
SINGULAR_WRIST_RAD = 1e-10
"""|sin q5| below this: joints 4 and 6 turn about one axis (wrist singularity). q4 is then kept
where it is and q6 takes up q4 + q6; that costs at most this much orientation (rad), so the pose
is still reproduced to the kinematics' accuracy."""
SINGULAR_SHOULDER_M = 1e-6
"""Wrist centre this close to joint 1's axis: q1 is undetermined and would spin at
(speed / distance) rad/s near it (shoulder singularity). :func:`ik_nearest` refuses it."""
KEEP_Q1_M = 1e-10
"""Wrist centre this close to joint 1's axis: :func:`ik_flange` keeps the hint's q1, which costs
at most this much position."""
SINGULAR_ELBOW_RAD = 1e-6
"""|q3| (or |π − |q3||) below this: the arm is fully stretched (folded), on the boundary of the
workspace (elbow singularity). :func:`ik_nearest` refuses it."""
JOINT_LIMIT_TOL_RAD = 1e-9
"""A solution this little outside a joint limit is put on the limit (rounding), not refused."""

_Z, _Y = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
_AXES = (_Z, _Y, _Y, _Z, _Y, _Z)
"""Joint axes 1–6 in their joint frames."""
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ArmGeometry:
    """The closed form's constants, read from a robot model (m; 4×4 poses)."""

    shoulder_height_m: float
    """Height of joint 2's axis above the base frame B."""
    upper_arm_m: float
    """Joint 2 to joint 3 (a)."""
    forearm_m: float
    """Joint 3 to the wrist centre (b)."""
    wrist_to_flange_m: float
    """Wrist centre to the flange origin along joint 6's axis (f)."""
    X_FG: np.ndarray
    """The gripper TCP G in the flange frame F (fixed joints of the model)."""
    joint_names: tuple[str, ...]
    q_lower: np.ndarray
    """(6,) rad."""
    q_upper: np.ndarray
    """(6,) rad."""

    @property
    def reach_m(self) -> float:
        """Largest distance of the wrist centre from the shoulder (a + b)."""
        return self.upper_arm_m + self.forearm_m

    @property
    def inner_reach_m(self) -> float:
        """Smallest distance of the wrist centre from the shoulder (|a − b|)."""
        return abs(self.upper_arm_m - self.forearm_m)


def _fixed_chain(robot: RobotModel, top: str, bottom: str) -> np.ndarray:
    """``X_TopBottom`` through fixed joints only; ValueError if a moving joint is in between."""
    by_child = {j.child: j for j in robot.joints}
    X = np.eye(4)
    link = bottom
    while link != top:
        joint = by_child.get(link)
        if joint is None:
            raise ValueError(f"{robot.source}: link {bottom!r} is not below {top!r}")
        if joint.type != "fixed":
            raise ValueError(
                f"{robot.source}: {joint.type} joint {joint.name!r} between {top!r} and "
                f"{bottom!r}; the closed form needs a rigid mount"
            )
        X = joint.X_PJ @ X
        link = joint.parent
    return X


def _off_identity(X: np.ndarray) -> float:
    """Largest deviation of X's rotation from I and of its origin from the z axis."""
    return float(max(np.max(np.abs(X[:3, :3] - np.eye(3))), np.max(np.abs(X[:2, 3]))))


def _frozen(a: np.ndarray) -> np.ndarray:
    out = np.array(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def arm_geometry(robot: RobotModel) -> ArmGeometry:
    """The closed form's lengths read from ``robot``.

    ValueError unless the model is a zero-offset Puma-type arm: six revolute joints in one chain
    from the root link with axes z, y, y, z, y, z, joint origins unrotated and on the parent's z
    axis, joints 5 and 6 at the wrist centre (so the wrist axes meet), and the flange and TCP
    rigidly mounted, the flange on joint 6's axis and unrotated.
    """
    names = robot.arm_joints
    if len(names) != 6:
        raise ValueError(f"{robot.source}: expected 6 arm joints, got {len(names)}")
    offsets = []
    parent = robot.root_link
    for name, axis in zip(names, _AXES, strict=True):
        j = robot.joint(name)
        if j.parent != parent:
            raise ValueError(
                f"{robot.source}: {name} hangs from {j.parent!r}, not {parent!r}: "
                "the arm joints must form one chain from the base"
            )
        parent = j.child
        if np.max(np.abs(j.axis - axis)) > STRUCTURE_TOL_M:
            raise ValueError(f"{robot.source}: {name} axis {j.axis.tolist()} is not {list(axis)}")
        if _off_identity(j.X_PJ) > STRUCTURE_TOL_M:
            raise ValueError(
                f"{robot.source}: {name} has a rotated or sideways origin "
                f"{j.X_PJ[:3, 3].tolist()}; the closed form needs offsets along z only"
            )
        offsets.append(float(j.X_PJ[2, 3]))
    if max(abs(offsets[4]), abs(offsets[5])) > STRUCTURE_TOL_M:
        raise ValueError(
            f"{robot.source}: joints 5 and 6 must sit at joint 4's end (the wrist centre) so "
            f"that the wrist axes meet; offsets {offsets[4]} m, {offsets[5]} m"
        )
    X_6F = _fixed_chain(robot, parent, FLANGE_LINK)
    if _off_identity(X_6F) > STRUCTURE_TOL_M:
        raise ValueError(f"{robot.source}: the flange must lie on joint 6's axis, unrotated")
    a, b, f = offsets[2], offsets[3], float(X_6F[2, 3])
    if a <= 0.0 or b <= 0.0:
        raise ValueError(f"{robot.source}: upper arm {a} m and forearm {b} m must be positive")
    return ArmGeometry(
        shoulder_height_m=offsets[0] + offsets[1],
        upper_arm_m=a,
        forearm_m=b,
        wrist_to_flange_m=f,
        X_FG=_frozen(_fixed_chain(robot, FLANGE_LINK, TCP_LINK)),
        joint_names=tuple(names),
        q_lower=_frozen(robot.q_lower),
        q_upper=_frozen(robot.q_upper),
    )


@dataclass(frozen=True)
class IkResult:
    """The chosen joint angles ``q`` (6,) rad, or None; ``ok`` whether q reaches the target.

    ``reason`` says why not ("unreachable: …", "outside joint limits (…)", "singular: shoulder
    …", "singular: elbow …"), or, with ``ok``, flags a wrist singularity ("singular: wrist
    (q5 ≈ 0)": q is valid, q4 kept at its current value, or as near as joint 6's limits allow).
    ``singular`` names the singularity ("wrist", "shoulder", "elbow") or is "".
    """

    q: np.ndarray | None
    ok: bool
    reason: str = ""
    singular: str = ""


@dataclass(frozen=True)
class _Solutions:
    """Everything one solve finds: the solutions and what the target's geometry is like."""

    q: list[np.ndarray]
    wrist_singular: list[bool]
    wrist_centre_distance_m: float
    """From the shoulder (joint 2's axis on joint 1's axis)."""
    wrist_centre_radius_m: float
    """From joint 1's axis."""
    q3_abs: float


def _Ry(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _Rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(angle: float) -> float:
    """``angle`` in (−π, π]."""
    w = math.remainder(angle, _TWO_PI)
    return math.pi if w == -math.pi else w


def _periodic_in_limits(value: float, lo: float, hi: float, target: float) -> float | None:
    """``value + 2πk`` within [lo, hi] (± :data:`JOINT_LIMIT_TOL_RAD`) nearest ``target``, or
    None when no turn of ``value`` is within the limits."""
    k = round((target - value) / _TWO_PI)
    lo_t, hi_t = lo - JOINT_LIMIT_TOL_RAD, hi + JOINT_LIMIT_TOL_RAD
    if math.isfinite(lo_t):
        k = max(k, math.ceil((lo_t - value) / _TWO_PI))
    if math.isfinite(hi_t):
        k = min(k, math.floor((hi_t - value) / _TWO_PI))
    v = value + _TWO_PI * k
    if not lo_t <= v <= hi_t:
        return None
    return min(max(v, lo), hi)


def _check_pose(X: np.ndarray, name: str) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if not is_rigid_transform(X):
        raise ValueError(f"{name} must be a finite 4×4 rigid transform")
    return X


def _check_q(q: np.ndarray | Sequence[float], name: str) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be 6 finite joint angles (rad), got {q!r}")
    return q


def _fit_q5_q6(R_36: np.ndarray, q4: float) -> tuple[float, float, float]:
    """(q4, q5, q6) with q5, q6 fitted to q4: ``Ry(q5)·Rz(q6) ≈ Rz(−q4)·R_36``."""
    M = _Rz(-q4) @ R_36
    return q4, math.atan2(M[0, 2], M[2, 2]), math.atan2(M[1, 0], M[1, 1])


def _wrist(
    R_36: np.ndarray, hint: np.ndarray, g: ArmGeometry, pull: bool
) -> tuple[bool, list[tuple[float, float, float]]]:
    """(wrist singular?, the wrist solutions (q4, q5, q6)) for ``R_36 = Rz(q4)·Ry(q5)·Rz(q6)``.

    Regular: q4 points joint 5's tilt, and the flip turns q4 half a turn and tilts back. With
    ``pull``, each q4 then moves toward the hint's by up to ``SINGULAR_WRIST_RAD / |sin q5|``
    (costing at most :data:`SINGULAR_WRIST_RAD` of orientation): near the singularity q4 follows
    the current q4 rather than rounding noise, and the blend into the singular case is smooth.
    Singular: one solution, q4 kept at the hint and q6 taking up q4 + q6, unless joint 6's
    limits cannot take it; then q6 goes to its nearer limit and q4 takes the rest.
    """
    s5 = math.hypot(R_36[0, 2], R_36[1, 2])
    if s5 >= SINGULAR_WRIST_RAD:
        q4 = math.atan2(R_36[1, 2], R_36[0, 2])
        wrists = []
        for q4_i in (q4, q4 + math.pi):
            if pull:
                most = SINGULAR_WRIST_RAD / s5
                q4_i += min(max(_wrap(float(hint[3]) - q4_i), -most), most)
            wrists.append(_fit_q5_q6(R_36, q4_i))
        return False, wrists
    q4, q5, q6 = _fit_q5_q6(R_36, float(hint[3]))
    lo, hi = g.q_lower[5], g.q_upper[5]
    if _periodic_in_limits(q6, lo, hi, float(hint[5])) is None:
        nearer_limit = hi if abs(_wrap(q6 - hi)) <= abs(_wrap(q6 - lo)) else lo
        q4, q5, q6 = _fit_q5_q6(R_36, q4 + _wrap(q6 - nearer_limit))
    return True, [(q4, q5, q6)]


def _solve(X_BF: np.ndarray, g: ArmGeometry, hint: np.ndarray | None) -> _Solutions:
    """All solutions for the flange pose ``X_BF``; the hint (default 0) fills the joints a
    singularity leaves free and picks each joint's turn (2πk) within its limits."""
    pull = hint is not None
    hint = np.zeros(6) if hint is None else hint
    R_BF = X_BF[:3, :3]
    p_BC = X_BF[:3, 3] - g.wrist_to_flange_m * R_BF[:, 2]  # the wrist centre
    x, y = float(p_BC[0]), float(p_BC[1])
    h = float(p_BC[2]) - g.shoulder_height_m
    rho = math.hypot(x, y)
    d = math.hypot(rho, h)
    a, b = g.upper_arm_m, g.forearm_m
    if d > g.reach_m + REACH_TOL_M or d < g.inner_reach_m - REACH_TOL_M:
        return _Solutions([], [], d, rho, math.nan)
    # q3 from tan²(q3/2) = ((a+b)² − d²)/(d² − (a−b)²): better conditioned than acos near
    # the stretched arm.
    outer = max(0.0, (g.reach_m - d) * (g.reach_m + d))
    inner = max(0.0, (d - g.inner_reach_m) * (d + g.inner_reach_m))
    q3_abs = 2.0 * math.atan2(math.sqrt(outer), math.sqrt(inner))
    if rho < KEEP_Q1_M:  # any q1 will do: keep the hint's, costs at most rho of position
        q1_front = float(hint[0])
    else:
        q1_front = math.atan2(y, x)
    shoulders = []
    for q1 in (q1_front, q1_front + math.pi):
        r = x * math.cos(q1) + y * math.sin(q1)  # wrist centre ahead of the shoulder, signed
        shoulders.append((q1, r))
    elbows = (q3_abs, -q3_abs) if q3_abs > 0.0 else (0.0,)
    solutions: list[np.ndarray] = []
    wrist_singular: list[bool] = []
    for q1, r in shoulders:
        for q3 in elbows:
            q2 = math.atan2(r, h) - math.atan2(b * math.sin(q3), a + b * math.cos(q3))
            R_36 = (_Rz(q1) @ _Ry(q2 + q3)).T @ R_BF  # = Rz(q4) Ry(q5) Rz(q6)
            singular, wrists = _wrist(R_36, hint, g, pull)
            for q4, q5, q6 in wrists:
                q = [q1, q2, q3, q4, q5, q6]
                for i in range(6):
                    v = _periodic_in_limits(q[i], g.q_lower[i], g.q_upper[i], float(hint[i]))
                    q[i] = _wrap(q[i]) if v is None else v
                solutions.append(np.array(q))
                wrist_singular.append(singular)
    return _Solutions(solutions, wrist_singular, d, rho, q3_abs)


def ik_flange(
    X_BF: np.ndarray,
    robot: RobotModel,
    q_hint: np.ndarray | Sequence[float] | None = None,
    geometry: ArmGeometry | None = None,
) -> list[np.ndarray]:
    """All joint solutions (each (6,) rad) that put the flange at ``X_BF`` (base frame B).

    Up to 8: shoulder (facing the wrist centre or reaching over) × elbow (up, down) × wrist
    (flipped or not); fewer at the stretched elbow and at a wrist singularity, none out of reach.
    Joint limits are not applied, but each angle is taken in the turn (2πk) within its limits
    nearest ``q_hint`` (default 0) where one exists, else in (−π, π]. ``q_hint`` also fills what a
    singularity leaves free: q4 at the wrist (q6 takes up q4 + q6), q1 on joint 1's axis; and near
    the wrist singularity q4 leans toward it within the accuracy budget (see ``_wrist``).
    """
    g = geometry or arm_geometry(robot)
    hint = None if q_hint is None else _check_q(q_hint, "q_hint")
    return _solve(_check_pose(X_BF, "X_BF"), g, hint).q


def fk_flange(
    q: np.ndarray | Sequence[float], robot: RobotModel, X_WB: np.ndarray | None = None
) -> np.ndarray:
    """Flange pose ``X_WF`` (``X_BF`` with the default ``X_WB`` = I) at joint angles q (rad)."""
    return robot.flange_pose_W(np.asarray(q, dtype=np.float64), X_WB)


def ik_nearest(
    X_WF: np.ndarray,
    q_current: np.ndarray | Sequence[float],
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
    weights: np.ndarray | Sequence[float] | None = None,
) -> IkResult:
    """The solution within joint limits nearest ``q_current`` for flange pose ``X_WF``.

    Nearest: least ``Σ wᵢ (qᵢ − q_currentᵢ)²`` (``weights`` default 1), each joint taken in its
    turn nearest its current angle within its limits. Refused, with ``reason``: wrist centre out
    of reach, on joint 1's axis (:data:`SINGULAR_SHOULDER_M`), arm fully stretched or folded
    (:data:`SINGULAR_ELBOW_RAD`), or every solution outside the joint limits. At a wrist
    singularity the result is ok, keeps q4 at its current value and says so in ``reason``.
    """
    g = geometry or arm_geometry(robot)
    X_WF = _check_pose(X_WF, "X_WF")
    X_BF = X_WF if X_WB is None else invert_pose(_check_pose(X_WB, "X_WB")) @ X_WF
    q_current = _check_q(q_current, "q_current")
    w = np.ones(6) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (6,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"weights must be 6 finite non-negative numbers, got {w!r}")
    sol = _solve(X_BF, g, q_current)
    d = sol.wrist_centre_distance_m
    if not sol.q:
        limit = (
            f"reach {g.reach_m:.3g} m" if d > g.reach_m else f"inner reach {g.inner_reach_m:.3g} m"
        )
        return IkResult(
            None, False, f"unreachable: wrist centre {d:.3g} m from the shoulder, {limit}"
        )
    if sol.q3_abs < SINGULAR_ELBOW_RAD:
        return IkResult(None, False, "singular: elbow (arm fully stretched)", "elbow")
    if math.pi - sol.q3_abs < SINGULAR_ELBOW_RAD:
        return IkResult(None, False, "singular: elbow (arm fully folded)", "elbow")
    if sol.wrist_centre_radius_m < SINGULAR_SHOULDER_M:
        return IkResult(
            None, False, "singular: shoulder (wrist centre on joint-1 axis)", "shoulder"
        )
    lo, hi = g.q_lower - JOINT_LIMIT_TOL_RAD, g.q_upper + JOINT_LIMIT_TOL_RAD
    best, best_cost, best_singular = None, math.inf, False
    nearest_outside, nearest_outside_cost = "", math.inf
    for q, singular in zip(sol.q, sol.wrist_singular, strict=True):
        cost = float(np.sum(w * (q - q_current) ** 2))
        outside = [
            f"{g.joint_names[i]} {q[i]:+.4f} not in [{g.q_lower[i]:+.4g}, {g.q_upper[i]:+.4g}]"
            for i in range(6)
            if not lo[i] <= q[i] <= hi[i]
        ]
        if outside:
            if cost < nearest_outside_cost:
                nearest_outside, nearest_outside_cost = "; ".join(outside), cost
        elif cost < best_cost:
            best, best_cost, best_singular = q, cost, singular
    if best is None:
        return IkResult(
            None,
            False,
            f"outside joint limits ({nearest_outside}) in the nearest of all {len(sol.q)} "
            "solutions",
        )
    q = np.clip(best, g.q_lower, g.q_upper)
    if best_singular:
        return IkResult(q, True, "singular: wrist (q5 ≈ 0)", "wrist")
    return IkResult(q, True)


def ik_tcp(
    X_WG: np.ndarray,
    q_current: np.ndarray | Sequence[float],
    robot: RobotModel,
    X_WB: np.ndarray | None = None,
    geometry: ArmGeometry | None = None,
    weights: np.ndarray | Sequence[float] | None = None,
) -> IkResult:
    """:func:`ik_nearest` for a gripper TCP target ``X_WG``: the flange at ``X_WG · X_FG⁻¹``."""
    g = geometry or arm_geometry(robot)
    X_WF = _check_pose(X_WG, "X_WG") @ invert_pose(g.X_FG)
    return ik_nearest(X_WF, q_current, robot, X_WB, g, weights)


def geometric_jacobian_W(
    q: np.ndarray | Sequence[float], robot: RobotModel, X_WB: np.ndarray | None = None
) -> np.ndarray:
    """(6, 6) Jacobian of the flange origin at q: rows 0–2 its linear velocity (m/s), rows 3–5
    the flange's angular velocity (rad/s), both expressed in W, per joint rate (rad/s)."""
    poses = robot.link_poses_W(_check_q(q, "q"), 0.0, X_WB)
    p_WF = poses[FLANGE_LINK][:3, 3]
    J = np.zeros((6, 6))
    for i, name in enumerate(robot.arm_joints):
        joint = robot.joint(name)
        X_WJ = poses[joint.child]  # the child link frame is the joint frame moved about its axis
        z_W = X_WJ[:3, :3] @ joint.axis
        J[:3, i] = np.cross(z_W, p_WF - X_WJ[:3, 3])
        J[3:, i] = z_W
    return J
