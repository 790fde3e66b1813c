"""The arm's closed-form kinematics, as the work site's controller uses it: the solver lives in
:mod:`models.kinematics`, where the operator site's reach check uses the same solutions."""

from models.kinematics import (
    ArmGeometry,
    IkResult,
    arm_geometry,
    geometric_jacobian_W,
    ik_flange,
    ik_nearest,
    ik_tcp,
)

__all__ = [
    "ArmGeometry",
    "IkResult",
    "arm_geometry",
    "geometric_jacobian_W",
    "ik_flange",
    "ik_nearest",
    "ik_tcp",
]
