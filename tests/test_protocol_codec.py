"""Property tests of the codec: round trips of every message type and rejection of bad payloads.

Valid messages come from hypothesis strategies; invalid payloads are made by unpacking a valid
payload, breaking one thing, and packing it again, so each test isolates one kind of fault.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from protocol import (
    MAX_PAYLOAD_BYTES,
    MESSAGE_TYPES,
    MOTION_KINDS,
    REPORT_STATUSES,
    ROLES,
    SCHEMA_VERSION,
    CameraFrame,
    ContactState,
    ExecutionReport,
    Heartbeat,
    HeldBlock,
    MotionCommand,
    MotionProgram,
    ObjectPose,
    ProtocolError,
    Recognition,
    Recognitions,
    RobotState,
    Stop,
    TruthPoses,
    decode,
    encode,
)
from protocol.codec import decode_saved
from protocol.messages import BODY_CHANGED_IN, OLDEST_READ_VERSION, readable_versions
from tests.conftest import examples

MANY = settings(
    max_examples=examples(1000), deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

# ------------------------------------------------------------------------------- strategies

NAME_ALPHABET = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"
SITE_ALPHABET = NAME_ALPHABET.replace(".", "")

finite = st.floats(allow_nan=False, allow_infinity=False)
nonneg = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False)
seqs = st.integers(0, 2**63 - 1)
names = st.text(NAME_ALPHABET, min_size=1, max_size=12) | st.builds(
    lambda c, n: c * n, st.sampled_from(NAME_ALPHABET), st.integers(250, 256)
)
texts = st.text(max_size=40) | st.builds(
    lambda c, n: c * n, st.characters(exclude_categories=["Cs"]), st.integers(4000, 4096)
)


def float_arrays(shape: tuple[int, ...]) -> st.SearchStrategy[np.ndarray]:
    n = int(np.prod(shape))
    return st.lists(finite, min_size=n, max_size=n).map(
        lambda v: np.array(v, dtype=np.float64).reshape(shape)
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@st.composite
def rotations(draw: st.DrawFn) -> np.ndarray:
    """A random rotation matrix from a normalised quaternion (w, x, y, z)."""
    q = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 4)))
    if np.linalg.norm(q) < 0.1:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    w, x, y, z = _unit(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = draw(rotations())
    X[:3, 3] = draw(float_arrays((3,)))
    return X


def random_unit_rows(k: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(k, 3))
    v[np.linalg.norm(v, axis=1) < 1e-3] = (0.0, 0.0, 1.0)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


unit_rows = st.builds(random_unit_rows, st.integers(1, 16), st.integers(0, 2**32 - 1))


@st.composite
def camera_matrices(draw: st.DrawFn) -> np.ndarray:
    f = st.floats(1e-3, 1e6)
    fx, fy, s, cx, cy = draw(f), draw(f), draw(finite), draw(finite), draw(finite)
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def images(max_side: int = 4096) -> st.SearchStrategy[np.ndarray]:
    small = st.tuples(st.integers(1, min(64, max_side)), st.integers(1, min(64, max_side)))
    shapes = small
    if max_side >= 4096:
        shapes = st.one_of(
            small,
            st.just((480, 640)),
            st.tuples(st.just(1), st.integers(1, 4096)),
            st.tuples(st.integers(1, 4096), st.just(1)),
        )
    return st.builds(
        lambda shape, seed: np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8),
        shapes,
        st.integers(0, 2**32 - 1),
    )


def camera_frames(max_side: int = 4096) -> st.SearchStrategy[CameraFrame]:
    return st.builds(
        CameraFrame,
        seq=seqs,
        stamp_s=nonneg,
        X_WC=poses(),
        K=camera_matrices(),
        dist=float_arrays((5,)),
        image=images(max_side),
    )


recognition = st.builds(Recognition, model=names, X_WO=poses(), score=finite)
recognitions = st.builds(
    Recognitions,
    seq=seqs,
    stamp_s=nonneg,
    elapsed_s=nonneg,
    objects=st.lists(recognition, max_size=4).map(tuple),
)
robot_states = st.builds(
    RobotState,
    seq=seqs,
    stamp_s=nonneg,
    q=float_arrays((6,)),
    X_WF=poses(),
    gripper_opening_m=nonneg,
    wrench_S=float_arrays((6,)),
)
contact_states = st.builds(ContactState, object=names, normals_W=unit_rows)
motion_commands = st.builds(
    MotionCommand,
    kind=st.sampled_from(MOTION_KINDS),
    X_WP=poses(),
    speed_mps=nonneg,
    force_limit_n=nonneg,
    contacts=st.lists(contact_states, max_size=2).map(tuple),
)
motion_programs = st.builds(
    MotionProgram,
    program_id=names,
    X_GP=poses(),
    commands=st.lists(motion_commands, min_size=1, max_size=3).map(tuple),
)
execution_reports = st.builds(
    ExecutionReport,
    program_id=names,
    command_index=st.integers(-1, 999),
    status=st.sampled_from(REPORT_STATUSES),
    wrench_S=float_arrays((6,)),
    message=texts,
    stamp_s=nonneg,
    seq=seqs,
)
stops = st.builds(Stop, reason=texts, stamp_s=nonneg)
heartbeats = st.builds(
    Heartbeat,
    site_id=st.text(SITE_ALPHABET, min_size=1, max_size=256),
    role=st.sampled_from(ROLES),
    seq=seqs,
    stamp_s=nonneg,
)

truth_poses = st.builds(
    TruthPoses,
    seq=seqs,
    stamp_s=nonneg,
    objects=st.lists(st.builds(ObjectPose, name=names, X_WO=poses()), max_size=3).map(tuple),
)

STRATEGIES: dict[type, st.SearchStrategy[Any]] = {
    CameraFrame: camera_frames(),
    Recognitions: recognitions,
    RobotState: robot_states,
    MotionProgram: motion_programs,
    ExecutionReport: execution_reports,
    Stop: stops,
    Heartbeat: heartbeats,
    TruthPoses: truth_poses,
}


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    X = np.eye(4)
    X[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    X[:3, 3] = rng.normal(size=3)
    return X


def random_message(cls: type, seed: int) -> Any:
    """A small valid message of type ``cls`` from a seeded generator (cheap to generate)."""
    rng = np.random.default_rng(seed)
    name = "".join(rng.choice(list(NAME_ALPHABET), size=rng.integers(1, 8)))
    stamp = float(rng.uniform(0, 1e4))
    seq = int(rng.integers(0, 2**63 - 1))
    if cls is CameraFrame:
        K = np.array([[rng.uniform(1, 1e3), 0.0, 3.0], [0.0, rng.uniform(1, 1e3), 2.0], [0, 0, 1]])
        shape = rng.integers(1, 9, size=2)
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        return CameraFrame(seq, stamp, random_pose(rng), K, rng.normal(size=5), image)
    if cls is Recognitions:
        objects = tuple(
            Recognition(
                name,
                random_pose(rng),
                float(rng.uniform()),
                int(rng.integers(1, 6)),
                float(rng.uniform(0, 1e-3)),
                float(rng.uniform(0, 0.01)),
                int(rng.integers(0, 6)),
            )
            for _ in range(rng.integers(0, 4))
        )
        return Recognitions(seq, stamp, float(rng.uniform()), objects, bool(rng.integers(2)))
    if cls is RobotState:
        q, wrench = rng.normal(size=6), rng.normal(size=6)
        return RobotState(seq, stamp, q, random_pose(rng), float(rng.uniform()), wrench)
    if cls is MotionProgram:
        commands = tuple(
            MotionCommand(
                str(rng.choice(MOTION_KINDS)),
                random_pose(rng),
                float(rng.uniform()),
                float(rng.uniform()),
                tuple(
                    ContactState(name, random_unit_rows(int(rng.integers(1, 4)), seed + i))
                    for i in range(rng.integers(0, 3))
                ),
            )
            for _ in range(rng.integers(1, 4))
        )
        holds = tuple(
            HeldBlock(name, float(rng.uniform(0.01, 1.0)), float(rng.uniform(0.01, 0.08)),
                      rng.uniform(-0.05, 0.05, size=3))
            for _ in range(rng.integers(0, 2))
        )  # fmt: skip
        return MotionProgram(name, random_pose(rng), commands, holds=holds)
    if cls is ExecutionReport:
        status = str(rng.choice(REPORT_STATUSES))
        return ExecutionReport(
            name, int(rng.integers(-1, 5)), status, rng.normal(size=6), "ok", stamp, seq
        )
    if cls is Stop:
        cancels = tuple(f"{name}-{k}" for k in range(rng.integers(0, 3)))
        return Stop("operator pressed stop", stamp, cancels)
    if cls is TruthPoses:
        objects = tuple(ObjectPose(name, random_pose(rng)) for _ in range(rng.integers(0, 4)))
        return TruthPoses(seq, stamp, objects)
    assert cls is Heartbeat
    return Heartbeat(name.replace(".", "_"), str(rng.choice(ROLES)), seq, stamp)


def seeded_messages(*types: type) -> st.SearchStrategy[Any]:
    """Small valid messages of the given types (all types if none given)."""
    return st.builds(
        random_message,
        st.sampled_from(types or tuple(STRATEGIES)),
        st.integers(0, 2**32 - 1),
    )


small_messages = seeded_messages()
with_arrays = seeded_messages(CameraFrame, Recognitions, RobotState, MotionProgram, ExecutionReport)


def test_every_message_type_has_a_strategy() -> None:
    assert set(STRATEGIES) == set(MESSAGE_TYPES.values())


# ------------------------------------------------------------------------------- round trips


def same_float(a: float, b: float) -> bool:
    return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)


def assert_same(a: Any, b: Any, where: str) -> None:
    """Field-by-field equality; arrays bit-exact with dtype and shape; floats keep their sign."""
    assert type(a) is type(b), where
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        w = f"{where}.{f.name}"
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), w
            assert y.dtype == x.dtype and y.shape == x.shape, w
            assert np.array_equal(x, y), w
            assert x.tobytes() == y.tobytes(), w  # bit-exact, including -0.0
            assert not y.flags.writeable, w
        elif isinstance(x, tuple):
            assert isinstance(y, tuple) and len(x) == len(y), w
            for i, (xi, yi) in enumerate(zip(x, y, strict=True)):
                if dataclasses.is_dataclass(xi):
                    assert_same(xi, yi, f"{w}[{i}]")
                else:  # a tuple of names
                    assert type(yi) is type(xi) and xi == yi, f"{w}[{i}]"
        elif isinstance(x, float):
            assert type(y) is float and same_float(x, y), w
        else:
            assert type(y) is type(x) and x == y, w


def check_round_trip(msg: Any) -> None:
    payload = encode(msg)
    assert isinstance(payload, bytes)
    decoded = decode(payload, expected=type(msg))
    assert_same(msg, decoded, type(msg).__name__)
    assert encode(decoded) == payload  # the encoding is canonical


@MANY
@given(camera_frames())
def test_round_trip_camera_frame(msg: CameraFrame) -> None:
    check_round_trip(msg)


@MANY
@given(recognitions)
def test_round_trip_recognitions(msg: Recognitions) -> None:
    check_round_trip(msg)


@MANY
@given(robot_states)
def test_round_trip_robot_state(msg: RobotState) -> None:
    check_round_trip(msg)


@MANY
@given(motion_programs)
def test_round_trip_motion_program(msg: MotionProgram) -> None:
    check_round_trip(msg)


@MANY
@given(execution_reports)
def test_round_trip_execution_report(msg: ExecutionReport) -> None:
    check_round_trip(msg)


@MANY
@given(stops)
def test_round_trip_stop(msg: Stop) -> None:
    check_round_trip(msg)


@MANY
@given(heartbeats)
def test_round_trip_heartbeat(msg: Heartbeat) -> None:
    check_round_trip(msg)


@MANY
@given(truth_poses)
def test_round_trip_truth_poses(msg: TruthPoses) -> None:
    check_round_trip(msg)


def test_round_trip_at_the_size_limits() -> None:
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(16, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    contacts = tuple(ContactState(f"obj{i}", normals) for i in range(16))
    command = MotionCommand("contact_move", np.eye(4), 0.4, 20.0, contacts)
    program = MotionProgram("p" * 256, np.eye(4), (command,) * 1000)
    check_round_trip(program)
    objects = tuple(Recognition("cube", np.eye(4), 1.0) for _ in range(256))
    check_round_trip(Recognitions(2**63 - 1, 0.0, 0.0, objects))
    with pytest.raises(ProtocolError, match=r"MotionProgram\.commands: must have 1\.\.1000"):
        MotionProgram("p", np.eye(4), (command,) * 1001)


def test_vga_image_codec_is_fast() -> None:
    import time

    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    image = np.random.default_rng(1).integers(0, 256, (480, 640), dtype=np.uint8)
    msg = CameraFrame(1, 0.0, np.eye(4), K, np.zeros(5), image)
    best = math.inf
    for _ in range(20):
        t0 = time.perf_counter()
        decode(encode(msg), expected=CameraFrame)
        best = min(best, time.perf_counter() - t0)
    assert best < 5e-3, f"encode + decode of a 640×480 frame took {best * 1e3:.2f} ms"


# ------------------------------------------------------------------ helpers for rejection tests


def unpack(payload: bytes) -> Any:
    return msgpack.unpackb(payload, raw=False)


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def is_wire_array(v: Any) -> bool:
    return isinstance(v, list) and len(v) == 2 and isinstance(v[1], bytes)


def leaves(body: dict[str, Any], where: str) -> list[tuple[str, dict[str, Any], str]]:
    """Every leaf field in a body as (path text, the map holding it, its key)."""
    out = []
    for name, v in body.items():
        path = f"{where}.{name}"
        if isinstance(v, list) and v and all(isinstance(item, dict) for item in v):
            for i, item in enumerate(v):
                out.extend(leaves(item, f"{path}[{i}]"))
        out.append((path, body, name))
    return out


def maps(body: dict[str, Any], where: str) -> list[tuple[str, dict[str, Any]]]:
    """The body and every nested record map in it, with their path texts."""
    out = [(where, body)]
    for name, v in body.items():
        if isinstance(v, list) and v and all(isinstance(item, dict) for item in v):
            for i, item in enumerate(v):
                out.extend(maps(item, f"{where}.{name}[{i}]"))
    return out


def reject(payload: bytes | Any, *patterns: str) -> ProtocolError:
    """Decode must raise ProtocolError whose message contains every pattern (literal text)."""
    with pytest.raises(ProtocolError) as info:
        decode(payload)
    text = str(info.value)
    for p in patterns:
        assert p in text, f"{p!r} not in {text!r}"
    assert "internal error" not in text, text
    return info.value


# Expected array shapes per field name, written independently of the schema's tables.
ARRAY_SHAPES: dict[str, tuple[tuple[int, int], ...]] = {
    "X_WC": ((4, 4), (4, 4)),
    "K": ((3, 3), (3, 3)),
    "dist": ((5, 5),),
    "image": ((1, 4096), (1, 4096)),
    "X_WO": ((4, 4), (4, 4)),
    "q": ((6, 6),),
    "X_WF": ((4, 4), (4, 4)),
    "wrench_S": ((6, 6),),
    "normals_W": ((1, 16), (3, 3)),
    "X_WP": ((4, 4), (4, 4)),
    "X_GP": ((4, 4), (4, 4)),
    "com_G": ((3, 3),),
}

WRONG_VALUES: dict[str, Any] = {
    "none": None,
    "bool": True,
    "int": 7,
    "float": 1.5,
    "str": "x",
    "bytes": b"x",
    "list": [],
    "map": {},
}


def category(v: Any) -> str:
    if v is None:
        return "none"
    for name, t in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if isinstance(v, t):
            return name
    return {bytes: "bytes", list: "list", dict: "map"}[type(v)]


# ------------------------------------------------------------------------------ rejections


@MANY
@given(small_messages, st.data())
def test_wrong_type_in_any_field_is_rejected(msg: Any, data: st.DataObject) -> None:
    env = unpack(encode(msg))
    path, holder, name = data.draw(st.sampled_from(leaves(env["b"], type(msg).__name__)))
    valid = category(holder[name])
    allowed = {valid, "int"} if valid == "float" else {valid}
    wrong = data.draw(st.sampled_from(sorted(set(WRONG_VALUES) - allowed)))
    holder[name] = WRONG_VALUES[wrong]
    reject(pack(env), path + ":")


@MANY
@given(with_arrays, st.data())
def test_wrong_array_shape_is_rejected(msg: Any, data: st.DataObject) -> None:
    env = unpack(encode(msg))
    arrays = [
        leaf for leaf in leaves(env["b"], type(msg).__name__) if is_wire_array(leaf[1][leaf[2]])
    ]
    assume(arrays)  # a Recognitions with no objects has none
    path, holder, name = data.draw(st.sampled_from(arrays))
    ranges = ARRAY_SHAPES[name]
    shape = data.draw(
        st.lists(st.integers(0, 20), max_size=3)
        | st.lists(
            st.sampled_from([lo - 1 for lo, _ in ranges] + [hi + 1 for _, hi in ranges]),
            min_size=len(ranges),
            max_size=len(ranges),
        ).map(lambda s: [max(n, 0) for n in s])
    )
    ok = len(shape) == len(ranges) and all(
        lo <= n <= hi for n, (lo, hi) in zip(shape, ranges, strict=True)
    )
    if ok:  # the draw happened to be valid: make it invalid by adding an axis
        shape = [*shape, 1]
    itemsize = 1 if name == "image" else 8
    nbytes = int(np.prod(shape)) * itemsize
    # Data consistent with the shape, so that the shape is what is wrong (unless it is huge).
    holder[name] = [shape, bytes(nbytes if nbytes <= 1 << 20 else 0)]
    reject(pack(env), path + ":", "expected shape")


@MANY
@given(with_arrays, st.data())
def test_wrong_array_byte_count_is_rejected(msg: Any, data: st.DataObject) -> None:
    env = unpack(encode(msg))
    arrays = [
        leaf for leaf in leaves(env["b"], type(msg).__name__) if is_wire_array(leaf[1][leaf[2]])
    ]
    assume(arrays)  # a Recognitions with no objects has none
    path, holder, name = data.draw(st.sampled_from(arrays))
    shape, raw = holder[name]
    delta = data.draw(st.integers(-len(raw), 64).filter(lambda d: d != 0))
    holder[name] = [shape, raw[:delta] if delta < 0 else raw + bytes(delta)]
    reject(pack(env), path + ":", "bytes, expected")


@MANY
@given(small_messages, st.data(), st.sampled_from([math.nan, math.inf, -math.inf]))
def test_non_finite_floats_are_rejected(msg: Any, data: st.DataObject, bad: float) -> None:
    env = unpack(encode(msg))
    floats = [
        leaf
        for leaf in leaves(env["b"], type(msg).__name__)
        if isinstance(leaf[1][leaf[2]], float)
        or (is_wire_array(leaf[1][leaf[2]]) and leaf[2] != "image")
    ]
    path, holder, name = data.draw(st.sampled_from(floats))
    if isinstance(holder[name], float):
        holder[name] = bad
    else:
        shape, raw = holder[name]
        values = np.frombuffer(raw, "<f8").copy()
        values[data.draw(st.integers(0, values.size - 1))] = bad
        holder[name] = [shape, values.astype("<f8").tobytes()]
    reject(pack(env), path + ":", "finite")


@MANY
@given(small_messages)
def test_every_truncated_payload_is_rejected(msg: Any) -> None:
    payload = encode(msg)
    for n in range(len(payload)):
        with pytest.raises(ProtocolError):
            decode(payload[:n])


_BIG = bytes(MAX_PAYLOAD_BYTES + 4096)


@MANY
@given(st.integers(1, 4096))
def test_oversized_payload_is_rejected_before_unpacking(extra: int) -> None:
    reject(memoryview(_BIG)[: MAX_PAYLOAD_BYTES + extra], "MAX_PAYLOAD_BYTES")


def test_oversized_payloads_of_every_kind_are_rejected() -> None:
    # A well-formed envelope whose bin is over the limit: refused on size, not unpacked.
    env = {
        "t": "camera_frame",
        "v": SCHEMA_VERSION,
        "b": {"image": [[1], bytes(MAX_PAYLOAD_BYTES)]},
    }
    reject(pack(env), "MAX_PAYLOAD_BYTES")
    reject(bytearray(MAX_PAYLOAD_BYTES + 1), "MAX_PAYLOAD_BYTES")
    # The largest image the schema allows does not fit in one payload; encode says so.
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    huge = CameraFrame(0, 0.0, np.eye(4), K, np.zeros(5), np.zeros((4096, 4096), np.uint8))
    with pytest.raises(ProtocolError, match="MAX_PAYLOAD_BYTES"):
        encode(huge)


@MANY
@given(
    small_messages,
    st.one_of(
        st.integers(-(2**63), 2**64 - 1).filter(lambda v: v != SCHEMA_VERSION),
        st.booleans(),
        st.floats(),
        st.text(max_size=5),
        st.none(),
        st.binary(max_size=5),
    ),
)
def test_unknown_schema_version_is_rejected(msg: Any, version: Any) -> None:
    assume(not (type(version) is int and version in readable_versions(msg.TYPE)))
    env = unpack(encode(msg))
    env["v"] = version
    reject(pack(env), "envelope.v:", "schema version")


def test_an_older_version_is_read_for_a_type_whose_fields_have_not_changed_since() -> None:
    stop = Stop(reason="x", stamp_s=1.0, cancels=("a",))
    env = unpack(encode(stop))
    env["v"] = OLDEST_READ_VERSION
    assert decode(pack(env), Stop).cancels == stop.cancels  # a program saved before version 7 loads
    env["v"] = OLDEST_READ_VERSION - 1
    reject(pack(env), "envelope.v: unsupported schema version")
    beat = Heartbeat(site_id="s", role="work_site", seq=0, stamp_s=1.0)
    env = unpack(encode(beat))
    env["v"] = BODY_CHANGED_IN["heartbeat"] - 1
    reject(pack(env), "envelope.v: a heartbeat of schema version", "changed in")
    # A program of the version before programs said what they hold: refused on the wire, read
    # from a file (holding nothing said).
    command = MotionCommand("move", np.eye(4), 0.1, 5.0, ())
    env = unpack(encode(MotionProgram("p", np.eye(4), (command,))))
    del env["b"]["holds"]
    env["v"] = BODY_CHANGED_IN["motion_program"] - 1
    reject(pack(env), "envelope.v: a motion_program of schema version", "changed in")
    assert decode_saved(pack(env), MotionProgram).holds == ()
    env["v"] = OLDEST_READ_VERSION - 1
    with pytest.raises(ProtocolError, match="unsupported schema version"):
        decode_saved(pack(env), MotionProgram)
    with pytest.raises(ProtocolError, match="not a valid msgpack document"):
        decode_saved(b"\xc1", MotionProgram)


def test_a_heartbeat_echo_measures_the_round_trip_on_the_echoed_clock() -> None:
    beat = Heartbeat(site_id="s", role="operator_site", seq=0, stamp_s=500.0,
                     echo_stamp_s=1000.0, echo_held_s=0.25)  # fmt: skip
    assert beat.round_trip_s(1000.75) == pytest.approx(0.5)  # the sender's clock is not used
    assert beat.round_trip_s(1000.1) is None  # negative: a clock stepped back
    assert beat.round_trip_s(1000.25 + 31.0) is None  # beyond MAX_ROUND_TRIP_S
    assert dataclasses.replace(beat, echo_stamp_s=0.0).round_trip_s(1000.75) is None


@given(
    st.floats(-1e4, 1e4),  # how far the sender's clock is ahead of ours (s)
    st.floats(1e-3, 5.0),  # our beat's way to the sender (s)
    st.floats(1e-3, 5.0),  # its beat's way back (s)
    st.floats(0.0, 2.0),  # how long it held our beat before its own (s)
)
def test_a_heartbeat_echo_measures_the_clock_offset_to_half_the_round_trip(
    ahead_s: float, there_s: float, back_s: float, held_s: float
) -> None:
    sent_s = 1e6  # our clock
    stamp_s = sent_s + there_s + held_s + ahead_s  # its clock
    read_s = sent_s + there_s + held_s + back_s  # ours
    beat = Heartbeat(site_id="s", role="work_site", seq=0, stamp_s=stamp_s,
                     echo_stamp_s=sent_s, echo_held_s=held_s)  # fmt: skip
    offset_s = beat.clock_offset_s(read_s)
    assert offset_s == pytest.approx(ahead_s + (there_s - back_s) / 2.0, abs=1e-6)
    assert abs(offset_s - ahead_s) <= beat.round_trip_s(read_s) / 2.0 + 1e-6
    assert dataclasses.replace(beat, echo_stamp_s=0.0).clock_offset_s(read_s) is None


@MANY
@given(
    small_messages,
    st.one_of(
        st.text(max_size=20).filter(lambda t: t not in MESSAGE_TYPES),
        st.sampled_from(["CameraFrame", "RobotState", "Recognition", "motion_command"]),
        st.integers(-(2**63), 2**64 - 1),
        st.none(),
        st.binary(max_size=8),
    ),
)
def test_unknown_type_tag_is_rejected(msg: Any, tag: Any) -> None:
    env = unpack(encode(msg))
    env["t"] = tag
    reject(pack(env), "envelope.t:", "unknown message type")


@MANY
@given(small_messages, st.data(), st.text(max_size=10), st.integers(-3, 3))
def test_extra_keys_are_rejected(msg: Any, data: st.DataObject, extra: str, value: int) -> None:
    env = unpack(encode(msg))
    candidates = [("envelope", env), *maps(env["b"], type(msg).__name__)]
    where, holder = data.draw(st.sampled_from(candidates))
    if extra in holder:
        extra += "_extra"
    holder[extra] = value
    reject(pack(env), where + ":", "unknown")


@MANY
@given(small_messages, st.data())
def test_missing_keys_are_rejected(msg: Any, data: st.DataObject) -> None:
    env = unpack(encode(msg))
    candidates = [("envelope", env), *maps(env["b"], type(msg).__name__)]
    where, holder = data.draw(st.sampled_from(candidates))
    del holder[data.draw(st.sampled_from(sorted(holder)))]
    reject(pack(env), where + ":", "missing")


@MANY
@given(st.binary(max_size=512))
def test_random_bytes_only_raise_protocol_error(payload: bytes) -> None:
    try:
        msg = decode(payload)
    except ProtocolError as exc:
        assert "internal error" not in str(exc)
    else:  # astronomically unlikely, but then it must be a valid message
        assert decode(encode(msg)) is not None


def corrupted(payload: bytes, data: st.DataObject) -> bytes:
    """``payload`` with 1 to 4 bytes overwritten at drawn places by drawn values."""
    out = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 4))):
        out[data.draw(st.integers(0, len(out) - 1))] = data.draw(st.integers(0, 255))
    return bytes(out)


@MANY
@given(small_messages, st.data())
def test_corrupted_payloads_decode_to_valid_messages_or_protocol_error(
    msg: Any, data: st.DataObject
) -> None:
    payload = corrupted(encode(msg), data)
    try:
        decoded = decode(payload)
    except ProtocolError as exc:
        assert "internal error" not in str(exc)
    else:
        check_round_trip(decoded)


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)


@MANY
@given(st.sampled_from(sorted(MESSAGE_TYPES)), msgpack_values)
def test_random_structured_bodies_only_raise_protocol_error(tag: str, body: Any) -> None:
    payload = pack({"t": tag, "v": SCHEMA_VERSION, "b": body})
    with pytest.raises(ProtocolError) as info:
        decode(payload)
    assert "internal error" not in str(info.value)


def test_msgpack_extensions_and_non_string_keys_are_rejected() -> None:
    reject(pack(msgpack.ExtType(1, b"abc")), "not a valid msgpack document")
    reject(pack({1: 2}), "not a valid msgpack document")
    reject(
        pack({"t": "stop", "v": SCHEMA_VERSION, "b": {"reason": "x", "stamp_s": 0.0}}) + b"\x00",
        "msgpack",
    )
    reject(pack([1, 2, 3]), "envelope: expected a map")
    reject("not bytes", "payload: expected bytes")
    # A header claiming 2**32 - 1 array items must not allocate them.
    reject(b"\xdd\xff\xff\xff\xff", "not a valid msgpack document")


def test_decode_refuses_an_unexpected_message_type() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    frame = CameraFrame(3, 1.0, np.eye(4), K, np.zeros(5), np.zeros((2, 2), np.uint8))
    payload = encode(frame)
    with pytest.raises(ProtocolError, match=r"envelope\.t: expected RobotState, got CameraFrame"):
        decode(payload, expected=RobotState)
    with pytest.raises(ProtocolError, match="expected RobotState, Stop, got CameraFrame"):
        decode(payload, expected=(RobotState, Stop))
    assert isinstance(decode(payload, expected=(RobotState, CameraFrame)), CameraFrame)
    with pytest.raises(TypeError):
        decode(payload, expected=Recognition)  # a nested record is not a message


def test_error_messages_name_the_field() -> None:
    state = RobotState(1, 0.0, np.zeros(6), np.eye(4), 0.05, np.zeros(6))
    env = unpack(encode(state))
    env["b"]["q"] = [[5], bytes(40)]
    reject(pack(env), "RobotState.q: expected shape (6,), got (5,)")
    env = unpack(encode(state))
    env["b"]["seq"] = True
    reject(pack(env), "RobotState.seq: expected int, got bool")
    env["b"]["seq"] = -1
    reject(pack(env), "RobotState.seq: must be in [0, 2**63), got -1")
    env["b"]["seq"] = 2**63
    reject(pack(env), "RobotState.seq: must be in [0, 2**63)")
    normals = np.array([[0.0, 0.0, 1.0]])
    command = MotionCommand("move", np.eye(4), 0.1, 5.0, (ContactState("frame", normals),))
    env = unpack(encode(MotionProgram("p1", np.eye(4), (command, command))))
    X = np.eye(4)
    X[0, 0] = 1.1
    env["b"]["commands"][1]["X_WP"] = [[4, 4], X.astype("<f8").tobytes()]
    reject(pack(env), "MotionProgram.commands[1].X_WP: rotation block is not orthonormal")
    env = unpack(encode(MotionProgram("p1", np.eye(4), (command,))))
    env["b"]["commands"][0]["contacts"][0]["normals_W"] = [[1, 3], np.array([0, 0, 2.0]).tobytes()]
    reject(pack(env), "MotionProgram.commands[0].contacts[0].normals_W: row 0 is not a unit")
    env["b"]["commands"] = []
    reject(pack(env), "MotionProgram.commands: must have 1..1000 items, got 0")
    held = HeldBlock("cube", 0.075, 0.05, np.zeros(3))
    env = unpack(encode(MotionProgram("p1", np.eye(4), (command,), holds=(held,))))
    env["b"]["holds"][0]["mass_kg"] = 0.0
    reject(pack(env), "MotionProgram.holds[0].mass_kg: Expected `float` > 0.0")
    env["b"]["holds"][0]["mass_kg"] = 0.075
    env["b"]["holds"][0]["com_G"] = [[3], np.array([0.0, 0.0, 2.0]).tobytes()]
    reject(pack(env), "MotionProgram.holds[0].com_G: farther than 1.0 m from G")
    env["b"]["holds"] = [env["b"]["holds"][0]] * 2
    reject(pack(env), "MotionProgram.holds: must have 0..1 items, got 2")
    stop = unpack(encode(Stop("why", 0.0)))
    stop["b"]["reason"] = "x" * 4097
    reject(pack(stop), "Stop.reason: must be at most 4096 characters, got 4097")
    stop["b"]["reason"] = b"\xff"
    reject(pack(stop), "Stop.reason: expected str, got bytes")
    stop["b"]["reason"] = msgpack.ExtType(0, b"")
    reject(pack(stop), "not a valid msgpack document")
    # invalid UTF-8 inside a msgpack str
    raw = pack({"t": "stop", "v": SCHEMA_VERSION, "b": {"reason": "ab", "stamp_s": 0.0}})
    reject(raw.replace(b"\xa2ab", b"\xa2\xff\xfe"), "not a valid msgpack document")
