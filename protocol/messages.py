"""All wire messages: frozen dataclasses, validated on construction, each with a type tag.

Frames and units follow ``protocol/README.md`` (Drake monogram notation, SI). Poses ``X_AB`` are
(4, 4) float64 rigid transforms; every array is stored read-only. Each class's ``_SPEC`` table is
the single declaration of its fields' types, shapes and bounds, used by both the constructor and
the decoder. Constructors raise :class:`~protocol.errors.ProtocolError` for any invalid field.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ._spec import (
    FLOAT64,
    UINT8,
    ArrayField,
    Field,
    FloatField,
    ImageField,
    IntField,
    Record,
    StrField,
    TupleField,
    check_camera_matrix,
    check_pose,
    check_unit_rows,
    install_validating_init,
)
from .images import DEFAULT_JPEG_QUALITY, IMAGE_ENCODINGS

SCHEMA_VERSION = 3
"""Version of the wire schema; bump on any incompatible change to a message.
2: ``CameraFrame`` carries its image's ``encoding`` and ``quality``.
3: ``ExecutionReport`` carries its number within its program (``seq``)."""

MAX_NAME_LEN = 256
"""Longest name or id (characters)."""

MAX_TEXT_LEN = 4096
"""Longest free-text message (characters)."""

MAX_IMAGE_SIDE = 4096
"""Largest image height or width (pixels)."""

MAX_RECOGNITIONS = 256
MAX_CONTACT_NORMALS = 16
MAX_CONTACTS = 16
MAX_COMMANDS = 1000

NAME_PATTERN = r"[A-Za-z0-9_.-]+"
"""Names and ids (model, object, program ids)."""

SITE_ID_PATTERN = r"[A-Za-z0-9_-]+"
"""Site ids: a single zenoh key-expression chunk, so no dots."""

MOTION_KINDS = ("guarded_grasp", "move", "guarded_move", "contact_move", "release", "open_gripper")
REPORT_STATUSES = (
    "accepted",
    "started",
    "done",
    "contact_verified",
    "failed",
    "refused",
    "stopped",
)
ROLES = ("work_site", "operator_site")

_SEQ = IntField(0, 2**63)
_STAMP = FloatField(lo=0.0)
_NAME = StrField(MAX_NAME_LEN, pattern=NAME_PATTERN)
_TEXT = StrField(MAX_TEXT_LEN)
_POSE = ArrayField(((4, 4), (4, 4)), FLOAT64, check_pose)
_WRENCH = ArrayField(((6, 6),), FLOAT64)


class Message(Record):
    """Base of the top-level messages; ``TYPE`` is the envelope's type tag."""

    TYPE: ClassVar[str]


# --------------------------------------------------------------------------------- camera


@dataclass(frozen=True, eq=False)
class CameraFrame(Message):
    """One grey camera image with the calibration it was taken with.

    ``X_WC``: camera pose (C: OpenCV, x right, y down, z forward); ``K`` (3, 3) intrinsics in
    pixels; ``dist`` (5,) OpenCV distortion ``[k1, k2, p1, p2, k3]``; ``image`` (h, w) uint8.

    ``encoding`` is how ``image`` travels on the wire (:data:`~protocol.images.IMAGE_ENCODINGS`:
    ``raw``, ``png`` lossless, ``jpeg`` lossy at ``quality`` 1..100, which the other encodings
    ignore). In memory ``image`` is always the decoded pixels: a decoded ``jpeg`` frame holds what
    the JPEG decoder gave, not the sender's original.
    """

    TYPE: ClassVar[str] = "camera_frame"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "seq": _SEQ,
        "stamp_s": _STAMP,
        "X_WC": _POSE,
        "K": ArrayField(((3, 3), (3, 3)), FLOAT64, check_camera_matrix),
        "dist": ArrayField(((5, 5),), FLOAT64),
        "image": ImageField(((1, MAX_IMAGE_SIDE), (1, MAX_IMAGE_SIDE)), UINT8),
        "encoding": StrField(16, choices=IMAGE_ENCODINGS),
        "quality": IntField(1, 101),
    }

    seq: int
    stamp_s: float
    X_WC: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    image: np.ndarray
    encoding: str = "raw"
    quality: int = DEFAULT_JPEG_QUALITY


# ---------------------------------------------------------------------------- recognitions


@dataclass(frozen=True, eq=False)
class Recognition(Record):
    """One recognised object (nested in :class:`Recognitions`): model name, pose, score."""

    _SPEC: ClassVar[Mapping[str, Field]] = {
        "model": _NAME,
        "X_WO": _POSE,
        "score": FloatField(),
    }

    model: str
    X_WO: np.ndarray
    score: float


@dataclass(frozen=True, eq=False)
class Recognitions(Message):
    """What vision found in camera frame ``seq``, and how long it took (``elapsed_s``)."""

    TYPE: ClassVar[str] = "recognitions"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "seq": _SEQ,
        "stamp_s": _STAMP,
        "elapsed_s": FloatField(lo=0.0),
        "objects": TupleField(Recognition, 0, MAX_RECOGNITIONS),
    }

    seq: int
    stamp_s: float
    elapsed_s: float
    objects: tuple[Recognition, ...]


# ------------------------------------------------------------------------------ robot state


@dataclass(frozen=True, eq=False)
class RobotState(Message):
    """Arm state: joints ``q`` (6,) rad, flange pose ``X_WF``, gripper opening (m), and the
    wrist wrench ``wrench_S`` (6,) ``[fx, fy, fz, tx, ty, tz]`` (N, N·m) in the sensor frame S."""

    TYPE: ClassVar[str] = "robot_state"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "seq": _SEQ,
        "stamp_s": _STAMP,
        "q": ArrayField(((6, 6),), FLOAT64),
        "X_WF": _POSE,
        "gripper_opening_m": FloatField(lo=0.0),
        "wrench_S": _WRENCH,
    }

    seq: int
    stamp_s: float
    q: np.ndarray
    X_WF: np.ndarray
    gripper_opening_m: float
    wrench_S: np.ndarray


# ---------------------------------------------------------------------------------- program


@dataclass(frozen=True, eq=False)
class ContactState(Record):
    """Contact of the workpiece with ``object``: unit contact normals ``normals_W`` (k, 3) in W."""

    _SPEC: ClassVar[Mapping[str, Field]] = {
        "object": _NAME,
        "normals_W": ArrayField(((1, MAX_CONTACT_NORMALS), (3, 3)), FLOAT64, check_unit_rows),
    }

    object: str
    normals_W: np.ndarray


SAME_CONTACT_DIRECTION_RAD = 0.3490658503988659  # 20°
"""Normals of one object closer than this are one contact direction, at both sites: a face
reports one normal per point, and a wrist force cannot tell two normals apart inside the
friction cone (μ = 0.5, the blocks' friction: 26.6°). End to end, normals 7.5° apart each asked
for 1 N of contact force and one of them got 0 N."""


def contact_directions(contacts: tuple[ContactState, ...]) -> list[tuple[str, np.ndarray]]:
    """The distinct (object, unit normal into the workpiece) directions of ``contacts``: the first
    normal of each group closer than :data:`SAME_CONTACT_DIRECTION_RAD`."""
    cos_same = float(np.cos(SAME_CONTACT_DIRECTION_RAD))
    out: list[tuple[str, np.ndarray]] = []
    for c in contacts:
        for n in np.asarray(c.normals_W, dtype=np.float64):
            n = n / np.linalg.norm(n)
            if all(name != c.object or float(m @ n) < cos_same for name, m in out):
                out.append((c.object, n))
    return out


BIAS_RCOND = 0.3
"""Directions in which the contact normals disagree (singular value of the stacked normals below
this fraction of the largest: nearly opposite walls) get no target bias: the least-squares
bias there is large, along the surfaces, and presses nothing."""


def target_bias(normals_W: np.ndarray, d_m: float, max_m: float = np.inf) -> np.ndarray:
    """The impedance target bias Δp (3,) of §VI-B, the same at both sites: ``N Δp ≈ −d·1`` (rows
    of ``normals_W`` point into the workpiece) in the least-squares, least-norm sense over the
    directions the normals agree on (:data:`BIAS_RCOND`), its norm bounded by ``max_m``."""
    N = np.asarray(normals_W, dtype=np.float64).reshape(-1, 3)
    if len(N) == 0:
        return np.zeros(3)
    dp = np.linalg.lstsq(N, -d_m * np.ones(len(N)), rcond=BIAS_RCOND)[0]
    size = float(np.linalg.norm(dp))
    return dp * (max_m / size) if size > max_m else dp


@dataclass(frozen=True, eq=False)
class MotionCommand(Record):
    """One program step (nested in :class:`MotionProgram`): move the workpiece to ``X_WP``.

    ``kind`` is one of :data:`MOTION_KINDS`; ``speed_mps`` ≥ 0; ``force_limit_n`` ≥ 0; ``contacts``
    the contact state expected at the target (≤ 16).
    """

    _SPEC: ClassVar[Mapping[str, Field]] = {
        "kind": StrField(32, choices=MOTION_KINDS),
        "X_WP": _POSE,
        "speed_mps": FloatField(lo=0.0),
        "force_limit_n": FloatField(lo=0.0),
        "contacts": TupleField(ContactState, 0, MAX_CONTACTS),
    }

    kind: str
    X_WP: np.ndarray
    speed_mps: float
    force_limit_n: float
    contacts: tuple[ContactState, ...]


@dataclass(frozen=True, eq=False)
class MotionProgram(Message):
    """A robot program: the grasp ``X_GP`` (workpiece in gripper frame) and 1..1000 commands."""

    TYPE: ClassVar[str] = "motion_program"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "program_id": _NAME,
        "X_GP": _POSE,
        "commands": TupleField(MotionCommand, 1, MAX_COMMANDS),
    }

    program_id: str
    X_GP: np.ndarray
    commands: tuple[MotionCommand, ...]


@dataclass(frozen=True, eq=False)
class ExecutionReport(Message):
    """Progress of program ``program_id`` at command ``command_index`` (-1: the whole program).

    ``status`` is one of :data:`REPORT_STATUSES`; ``wrench_S`` (6,) the wrist wrench (N, N·m) in S;
    ``message`` free text for the operator; ``seq`` this report's number within its program
    (0, 1, 2, …: the work site's order, which replays after a reconnection or a restart keep;
    the operator orders and de-duplicates by it, whatever the arrival order).
    """

    TYPE: ClassVar[str] = "execution_report"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "program_id": _NAME,
        "command_index": IntField(-1, MAX_COMMANDS),
        "status": StrField(32, choices=REPORT_STATUSES),
        "wrench_S": _WRENCH,
        "message": _TEXT,
        "stamp_s": _STAMP,
        "seq": _SEQ,
    }

    program_id: str
    command_index: int
    status: str
    wrench_S: np.ndarray
    message: str
    stamp_s: float
    seq: int = 0


# ------------------------------------------------------------------------------------ control


@dataclass(frozen=True, eq=False)
class Stop(Message):
    """Stop the robot now, with a free-text ``reason``."""

    TYPE: ClassVar[str] = "stop"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "reason": _TEXT,
        "stamp_s": _STAMP,
    }

    reason: str
    stamp_s: float


@dataclass(frozen=True, eq=False)
class Heartbeat(Message):
    """Periodic liveness message from a site; ``role`` is one of :data:`ROLES`."""

    TYPE: ClassVar[str] = "heartbeat"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "site_id": StrField(MAX_NAME_LEN, pattern=SITE_ID_PATTERN),
        "role": StrField(32, choices=ROLES),
        "seq": _SEQ,
        "stamp_s": _STAMP,
    }

    site_id: str
    role: str
    seq: int
    stamp_s: float


@dataclass(frozen=True, eq=False)
class ObjectPose(Record):
    """One object's name and pose ``X_WO`` (nested in :class:`TruthPoses`)."""

    _SPEC: ClassVar[Mapping[str, Field]] = {"name": _NAME, "X_WO": _POSE}

    name: str
    X_WO: np.ndarray


@dataclass(frozen=True, eq=False)
class TruthPoses(Message):
    """Where the simulated work site's objects really are: its ground truth, published for
    evaluating the system end to end (a real work site has none to publish)."""

    TYPE: ClassVar[str] = "truth_poses"
    _SPEC: ClassVar[Mapping[str, Field]] = {
        "seq": _SEQ,
        "stamp_s": _STAMP,
        "objects": TupleField(ObjectPose, 0, MAX_RECOGNITIONS),
    }

    seq: int
    stamp_s: float
    objects: tuple[ObjectPose, ...]


MESSAGE_TYPES: Mapping[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        CameraFrame,
        Recognitions,
        RobotState,
        MotionProgram,
        ExecutionReport,
        Stop,
        Heartbeat,
        TruthPoses,
    )
}
"""Top-level message classes by type tag."""

for _cls in (*MESSAGE_TYPES.values(), Recognition, ContactState, MotionCommand, ObjectPose):
    install_validating_init(_cls)
del _cls
