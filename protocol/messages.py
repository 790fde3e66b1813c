"""All wire messages: frozen dataclasses, validated on construction, each with a type tag.

Frames and units follow ``protocol/README.md`` (Drake monogram notation, SI). Poses ``X_AB`` are
(4, 4) float64 rigid transforms; every array is stored read-only. Each field's annotation is the
single declaration of its type, shape and bounds (``protocol/_schema.py``), used by both the
constructor and the decoder. Constructors raise :class:`~protocol.errors.ProtocolError` for any
invalid field.
"""

from __future__ import annotations

import collections
import statistics
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal, get_args

import numpy as np
from msgspec import Meta

from ._schema import (
    FINITE,
    NON_NEGATIVE,
    Array,
    Image,
    Record,
    anchored,
    check_camera_matrix,
    check_pose,
    check_unit_rows,
)
from .images import DEFAULT_JPEG_QUALITY, ImageEncoding

SCHEMA_VERSION = 11
"""Version of the wire schema; bump on any incompatible change to a message.
2: ``CameraFrame`` carries its image's ``encoding`` and ``quality``.
3: ``ExecutionReport`` carries its number within its program (``seq``).
4: ``MotionProgram`` and ``Heartbeat`` carry an ``operator`` (the control lease).
6: ``Stop`` carries the programs it ``cancels``.
7: ``Heartbeat`` echoes the other side's latest beat (the round trip).
9: ``MotionProgram`` says what its grasp should hold (``holds``); a ``Recognition`` how many
frames its pose fuses and how they spread.
10: ``Recognitions`` says whether its frame was searched or ``tracked``; a ``Recognition`` how
many full ``searches`` found its placement.
11: a ``Recognition`` says how many other placements of its model searches found (``rivals``)."""
OLDEST_READ_VERSION = 6
"""The oldest schema version read, for a message type whose body has not changed since (a
program saved by the version before stays loadable)."""
BODY_CHANGED_IN: dict[str, int] = {"heartbeat": 8, "motion_program": 9, "recognitions": 11}
"""The version in which a type's body last changed, where that is after
:data:`OLDEST_READ_VERSION`: older envelopes of that type are refused (a saved file's are read
where :data:`FIELDS_ADDED` says what the older body meant)."""
FIELDS_ADDED: dict[str, dict[int, dict[str, object]]] = {"motion_program": {9: {"holds": []}}}
"""Fields a type's body gained in a version, each with the wire value a body from before meant
by leaving it out: files saved before read so (``protocol.codec.decode_saved``)."""


def readable_versions(type_tag: str) -> tuple[int, ...]:
    """The schema versions in which a message of ``type_tag`` is read."""
    oldest = max(OLDEST_READ_VERSION, BODY_CHANGED_IN.get(type_tag, OLDEST_READ_VERSION))
    return tuple(range(oldest, SCHEMA_VERSION + 1))


MAX_ROUND_TRIP_S = 30.0
"""A round trip measured by heartbeats longer than this is not believed (s)."""
MAX_NAME_LEN = 256
"""Longest name or id (characters)."""

MAX_TEXT_LEN = 4096
"""Longest free-text message (characters)."""

MAX_IMAGE_SIDE = 4096
"""Largest image height or width (pixels)."""

MAX_RECOGNITIONS = 256
MAX_FUSED_FRAMES = 1000
"""Most sightings one recognised pose may say it fuses."""
MAX_SEARCHES = 2**31 - 1
"""Most full searches one recognised placement may say found it (one a second for decades)."""
MAX_CONTACT_NORMALS = 16
MAX_CONTACTS = 16
MAX_COMMANDS = 1000
MAX_CANCELS = 64
"""Program ids one stop may cancel (the sender's unanswered programs)."""

NAME_PATTERN = r"[A-Za-z0-9_.-]+"
"""Names and ids (model, object, program ids)."""

SITE_ID_PATTERN = r"[A-Za-z0-9_-]+"
"""Site ids: a single zenoh key-expression chunk, so no dots."""

MotionKind = Literal[
    "guarded_grasp", "move", "guarded_move", "contact_move", "release", "open_gripper"
]
ReportStatus = Literal[
    "accepted",
    "started",
    "done",
    "contact_verified",
    "failed",
    "refused",
    "stopped",
]
Role = Literal["work_site", "operator_site"]
MOTION_KINDS: tuple[str, ...] = get_args(MotionKind)
REPORT_STATUSES: tuple[str, ...] = get_args(ReportStatus)
ROLES: tuple[str, ...] = get_args(Role)

# Field types: each says what the wire and the constructors accept (msgspec's constraints, and
# Array's shape, dtype and check for arrays).
Seq = Annotated[int, Meta(ge=0, le=2**63 - 1)]
Real = Annotated[float, FINITE]
NonNegative = Annotated[float, NON_NEGATIVE]
Name = Annotated[str, Meta(max_length=MAX_NAME_LEN, pattern=anchored(NAME_PATTERN))]
STOP_REPLY_ID = "stop"
"""The program id under which a work site answers a stop that found no program running."""
INVALID_PROGRAM_ID = "invalid"
"""The program id under which a work site refuses a program it cannot tell the id of."""
RESERVED_PROGRAM_IDS = frozenset({STOP_REPLY_ID, INVALID_PROGRAM_ID})
"""Program ids the work site answers under itself: a program named so is refused, or these
answers would be taken for its reports."""
NameOrNone = Annotated[str, Meta(max_length=MAX_NAME_LEN, pattern=anchored(f"(?:{NAME_PATTERN})?"))]
"""A name, or "" for none."""
SiteId = Annotated[str, Meta(max_length=MAX_NAME_LEN, pattern=anchored(SITE_ID_PATTERN))]
Text = Annotated[str, Meta(max_length=MAX_TEXT_LEN)]
Pose = Annotated[np.ndarray, Array((4, 4), check=check_pose)]
Wrench = Annotated[np.ndarray, Array((6,))]


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
    seq: Seq
    stamp_s: NonNegative
    X_WC: Pose
    K: Annotated[np.ndarray, Array((3, 3), check=check_camera_matrix)]
    dist: Annotated[np.ndarray, Array((5,))]
    image: Annotated[np.ndarray, Image(((1, MAX_IMAGE_SIDE), (1, MAX_IMAGE_SIDE)))]
    encoding: ImageEncoding = "raw"
    quality: Annotated[int, Meta(ge=1, le=100)] = DEFAULT_JPEG_QUALITY


# ---------------------------------------------------------------------------- recognitions


@dataclass(frozen=True, eq=False)
class Recognition(Record):
    """One recognised object (nested in :class:`Recognitions`): model name, pose, score; the
    pose fused over ``frames`` sightings of that placement, which spread about it by
    ``spread_m`` (RMS distance) and ``spread_rad`` (RMS angle): how sure vision is; and how
    many full ``searches`` have found that placement (sightings tracked from the frame before
    refine a pose but do not confirm it); ``rivals``: how many other placements of the same
    model recent searches have found (vision is not sure where this block is)."""

    model: Name
    X_WO: Pose
    score: Real
    frames: Annotated[int, Meta(ge=1, le=MAX_FUSED_FRAMES)] = 1
    spread_m: NonNegative = 0.0
    spread_rad: NonNegative = 0.0
    searches: Annotated[int, Meta(ge=0, le=MAX_SEARCHES)] = 1
    rivals: Annotated[int, Meta(ge=0, le=MAX_SEARCHES)] = 0


@dataclass(frozen=True, eq=False)
class Recognitions(Message):
    """What vision found in camera frame ``seq``, and how long it took (``elapsed_s``);
    ``tracked``: the frame's objects were followed from the frame before, not searched for
    (a tracked frame that lacks a block has not looked for it)."""

    TYPE: ClassVar[str] = "recognitions"
    seq: Seq
    stamp_s: NonNegative
    elapsed_s: NonNegative
    objects: Annotated[tuple[Recognition, ...], Meta(max_length=MAX_RECOGNITIONS)]
    tracked: bool = False


# ------------------------------------------------------------------------------ robot state


@dataclass(frozen=True, eq=False)
class RobotState(Message):
    """Arm state: joints ``q`` (6,) rad, flange pose ``X_WF``, gripper opening (m), and the
    wrist wrench ``wrench_S`` (6,) ``[fx, fy, fz, tx, ty, tz]`` (N, N·m) in the sensor frame S."""

    TYPE: ClassVar[str] = "robot_state"
    seq: Seq
    stamp_s: NonNegative
    q: Annotated[np.ndarray, Array((6,))]
    X_WF: Pose
    gripper_opening_m: NonNegative
    wrench_S: Wrench


# ---------------------------------------------------------------------------------- program


@dataclass(frozen=True, eq=False)
class ContactState(Record):
    """Contact of the workpiece with ``object``: unit contact normals ``normals_W`` (k, 3) in W."""

    object: Name
    normals_W: Annotated[np.ndarray, Array(((1, MAX_CONTACT_NORMALS), 3), check=check_unit_rows)]


SAME_CONTACT_DIRECTION_RAD = 0.3490658503988659  # 20°
"""Normals of one object closer than this are one contact direction, at both sites: a face
reports one normal per point, and a wrist force cannot tell two normals apart inside the
friction cone (μ = 0.5, the blocks' friction: 26.6°), so asking each of two such normals for
its own contact force can leave one of them without any."""


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


def target_bias(
    normals_W: np.ndarray, d_m: float | np.ndarray, max_m: float = np.inf
) -> np.ndarray:
    """The impedance target bias Δp (3,) of §VI-B, the same at both sites: ``N Δp ≈ −d`` (rows
    of ``normals_W`` point into the workpiece; ``d_m`` one depth for all, or one a row) in the
    least-squares, least-norm sense over the directions the normals agree on
    (:data:`BIAS_RCOND`), its norm bounded by ``max_m``."""
    N = np.asarray(normals_W, dtype=np.float64).reshape(-1, 3)
    if len(N) == 0:
        return np.zeros(3)
    d = np.broadcast_to(np.asarray(d_m, dtype=np.float64), (len(N),))
    dp = np.linalg.lstsq(N, -d, rcond=BIAS_RCOND)[0]
    size = float(np.linalg.norm(dp))
    return dp * (max_m / size) if size > max_m else dp


@dataclass(frozen=True, eq=False)
class MotionCommand(Record):
    """One program step (nested in :class:`MotionProgram`): move the workpiece to ``X_WP``.

    ``kind`` is one of :data:`MOTION_KINDS`; ``speed_mps`` ≥ 0; ``force_limit_n`` ≥ 0; ``contacts``
    the contact state expected at the target (≤ 16).
    """

    kind: MotionKind
    X_WP: Pose
    speed_mps: NonNegative
    force_limit_n: NonNegative
    contacts: Annotated[tuple[ContactState, ...], Meta(max_length=MAX_CONTACTS)]


MAX_HELD_MASS_KG = 100.0
"""Heaviest block a program may say it holds (kg): a bound on the wire; each work site refuses
what its own arm cannot carry."""
MAX_HELD_OPENING_M = 1.0
"""Widest grip a program may say it holds (m): a bound on the wire, as above; a held block's
centre of mass lies no farther from the gripper either."""


def _check_held_com(p_G: np.ndarray) -> str | None:
    bound_m = MAX_HELD_OPENING_M
    # An entry beyond the bound says it alone (the norm of a huge one would overflow).
    if float(np.max(np.abs(p_G))) <= bound_m and float(np.linalg.norm(p_G)) <= bound_m:
        return None
    return f"farther than {bound_m} m from G"


@dataclass(frozen=True, eq=False)
class HeldBlock(Record):
    """What a program's grasp should hold, from the operator's model (nested in
    :class:`MotionProgram`): block ``name``, its mass, the finger opening that holds it and its
    centre of mass in the gripper frame G. The work site weighs the grip against it before
    carrying anything: another block, or this one not where or as the model has it, is set back
    down and the program fails."""

    name: Name
    mass_kg: Annotated[float, Meta(gt=0.0, le=MAX_HELD_MASS_KG)]
    opening_m: Annotated[float, Meta(gt=0.0, le=MAX_HELD_OPENING_M)]
    com_G: Annotated[np.ndarray, Array((3,), check=_check_held_com)]


@dataclass(frozen=True, eq=False)
class MotionProgram(Message):
    """A robot program: the grasp ``X_GP`` (workpiece in gripper frame) and 1..1000 commands;
    ``operator`` is the sending operator site's id, which the control lease goes by ("": an
    anonymous sender, which holds no lease). ``continues``: the id of a stopped program this one
    resumes ("": none): with the same grasp and commands, it starts at the command that one was
    stopped in, holding what it held; the work site runs it only while no other program has run
    since. ``holds``: what its grasps should hold (none: the grip is only checked to hold
    something)."""

    TYPE: ClassVar[str] = "motion_program"
    program_id: Name
    X_GP: Pose
    commands: Annotated[tuple[MotionCommand, ...], Meta(min_length=1, max_length=MAX_COMMANDS)]
    operator: NameOrNone = ""
    continues: NameOrNone = ""
    holds: Annotated[tuple[HeldBlock, ...], Meta(max_length=1)] = ()


@dataclass(frozen=True, eq=False)
class ExecutionReport(Message):
    """Progress of program ``program_id`` at command ``command_index`` (-1: the whole program).

    ``status`` is one of :data:`REPORT_STATUSES`; ``wrench_S`` (6,) the wrist wrench (N, N·m) in S;
    ``message`` free text for the operator; ``seq`` this report's number within its program
    (0, 1, 2, …: the work site's order, which replays after a reconnection or a restart keep;
    the operator orders and de-duplicates by it, whatever the arrival order).
    """

    TYPE: ClassVar[str] = "execution_report"
    program_id: Name
    command_index: Annotated[int, Meta(ge=-1, le=MAX_COMMANDS - 1)]
    status: ReportStatus
    wrench_S: Wrench
    message: Text
    stamp_s: NonNegative
    seq: Seq = 0


# ------------------------------------------------------------------------------------ control


@dataclass(frozen=True, eq=False)
class Stop(Message):
    """Stop the robot now, with a free-text ``reason``. ``cancels``: programs the sender sent
    and has no answer for, which must never start: a stop travels ahead of programs (a higher
    priority, a separate queue), so a program sent just before it, or sent again after a lost
    sample, can reach the work site after it."""

    TYPE: ClassVar[str] = "stop"
    reason: Text
    stamp_s: NonNegative
    cancels: Annotated[tuple[Name, ...], Meta(max_length=MAX_CANCELS)] = ()


@dataclass(frozen=True, eq=False)
class Heartbeat(Message):
    """Periodic liveness message from a site; ``role`` is one of :data:`ROLES`. ``operator``:
    an operator site's own id; a work site's, the operator holding its control lease ("":
    nobody). The round trip is ``now − echo_stamp_s − echo_held_s`` on the echoed side's
    clock."""

    TYPE: ClassVar[str] = "heartbeat"
    site_id: SiteId
    role: Role
    seq: Seq
    stamp_s: NonNegative
    operator: NameOrNone = ""
    echo_stamp_s: NonNegative = 0.0
    """The ``stamp_s`` of the other side's latest heartbeat this side heard (0: none), so that
    the other side measures the round trip on its own clock."""
    echo_held_s: NonNegative = 0.0
    """How long before this beat was sent that echoed one was heard (s)."""
    echo_operator: NameOrNone = ""
    """A work site's: whose beat it echoes (the operators it heard lately take turns, so that
    each can measure its round trip and clock offset, watchers too); "" for an operator site's."""
    state_echo_s: NonNegative = 0.0
    """An operator site's: the ``stamp_s`` of the newest robot state it received (0: none), so
    that the work site measures how long its streams take to arrive (``work_site.pacing``)."""
    state_echo_held_s: NonNegative = 0.0
    """How long before this beat was sent that state arrived (s)."""

    def round_trip_s(self, now_s: float) -> float | None:
        """The round trip this beat's echo measures, ``now_s`` being the echoed side's
        ``time.time()`` as it reads the beat; None without an echo, or when the figure is
        negative or over :data:`MAX_ROUND_TRIP_S` (a clock stepped, an echo not ours)."""
        return _round_trip_s(now_s, self.echo_stamp_s, self.echo_held_s)

    def state_round_trip_s(self, now_s: float) -> float | None:
        """The same for the echoed robot state: out with the work site's streams, back with
        this beat."""
        return _round_trip_s(now_s, self.state_echo_s, self.state_echo_held_s)

    def clock_offset_s(self, now_s: float) -> float | None:
        """How far the sender's clock is ahead of the echoed side's, ``now_s`` being the
        echoed side's ``time.time()`` as it reads the beat: NTP's estimate, the mean of the
        two one-way differences, wrong by at most half the round trip when the two ways take
        unequal times; None where :meth:`round_trip_s` is."""
        if self.round_trip_s(now_s) is None:
            return None
        heard_s = self.stamp_s - self.echo_held_s  # when our echoed beat arrived, its clock
        return ((heard_s - self.echo_stamp_s) + (self.stamp_s - now_s)) / 2.0


def _round_trip_s(now_s: float, echo_stamp_s: float, echo_held_s: float) -> float | None:
    if echo_stamp_s <= 0.0:
        return None
    round_trip_s = now_s - echo_stamp_s - echo_held_s
    return round_trip_s if 0.0 <= round_trip_s <= MAX_ROUND_TRIP_S else None


ROUND_TRIP_SAMPLES = 5
"""A round trip is the median of the last this many measurements, one per beat echoed (one a
second): a beat held up by a resend does not move it."""


class RoundTrips:
    """One side's recent round trips to another, as the other's heartbeats echo this side's
    (:meth:`Heartbeat.round_trip_s`). Only the first beat to echo one of ours counts: the next
    ones echo the same beat again, and their figures grow with the wait for our next. Not
    thread-safe."""

    def __init__(self, samples: int = ROUND_TRIP_SAMPLES) -> None:
        if samples < 1:
            raise ValueError(f"samples = {samples}: must be at least 1")
        self._samples_s: collections.deque[float] = collections.deque(maxlen=samples)
        self._offsets_s: collections.deque[float] = collections.deque(maxlen=samples)
        self._echoed_stamp_s: float | None = None

    def add(
        self, round_trip_s: float | None, echo_stamp_s: float, clock_offset_s: float | None = None
    ) -> None:
        """Take the round trip (s) a beat measured (:meth:`Heartbeat.round_trip_s`; None:
        none) by echoing our beat stamped ``echo_stamp_s``, and the other side's clock offset
        it measured (:meth:`Heartbeat.clock_offset_s`; None: not kept)."""
        if round_trip_s is None or echo_stamp_s == self._echoed_stamp_s:
            return
        self._echoed_stamp_s = echo_stamp_s
        self._samples_s.append(round_trip_s)
        if clock_offset_s is not None:
            self._offsets_s.append(clock_offset_s)

    def add_beat(self, beat: Heartbeat, now_s: float) -> None:
        """Take what ``beat`` measured, read at our ``time.time()`` ``now_s``."""
        self.add(beat.round_trip_s(now_s), beat.echo_stamp_s, beat.clock_offset_s(now_s))

    def median_s(self) -> float | None:
        """The median of the recent round trips (s; None before the first)."""
        return statistics.median(self._samples_s) if self._samples_s else None

    def clock_offset_s(self) -> float | None:
        """The median of the recent measures of how far the other side's clock is ahead of
        ours (s; None before the first)."""
        return statistics.median(self._offsets_s) if self._offsets_s else None


@dataclass(frozen=True, eq=False)
class ObjectPose(Record):
    """One object's name and pose ``X_WO`` (nested in :class:`TruthPoses`)."""

    name: Name
    X_WO: Pose


@dataclass(frozen=True, eq=False)
class TruthPoses(Message):
    """Where the simulated work site's objects really are: its ground truth, published for
    evaluating the system end to end, only when started with ``--publish-truth`` (a real
    work site has none to publish)."""

    TYPE: ClassVar[str] = "truth_poses"
    seq: Seq
    stamp_s: NonNegative
    objects: Annotated[tuple[ObjectPose, ...], Meta(max_length=MAX_RECOGNITIONS)]


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
