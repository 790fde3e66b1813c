"""The arm's closed-form kinematics, as the work site's controller uses it: the solver lives in
:mod:`models.kinematics`, where the operator site's reach check uses the same solutions."""

from models.kinematics import (
    BRANCH_JUMP_RAD,
    Approach,
    ArmGeometry,
    IkResult,
    PathFollow,
    arm_geometry,
    follow_line_tcp,
    follow_tcp,
    geometric_jacobian_W,
    ik_all_tcp,
    ik_flange,
    ik_nearest,
    ik_tcp,
    plan_approach,
)

__all__ = [
    "BRANCH_JUMP_RAD",
    "Approach",
    "ArmGeometry",
    "IkResult",
    "PathFollow",
    "arm_geometry",
    "follow_line_tcp",
    "follow_tcp",
    "geometric_jacobian_W",
    "ik_all_tcp",
    "ik_flange",
    "ik_nearest",
    "ik_tcp",
    "plan_approach",
]
