"""The codec's one validation path (msgspec, ``protocol/codec.py``) and the constructors
(``protocol/_schema.py``) against an independent reference written here: a brute-force reading
of the wire format and of constructor arguments, straight from ``protocol/README.md`` and not
from the schema's annotations. For any payload, ``decode`` must accept exactly what the
reference accepts, and give the same values; for any field value, so must a constructor. The
reference itself must accept every valid message (a reference refusing everything would agree
with a codec refusing everything)."""

from __future__ import annotations

import dataclasses
import math
import re
import sys
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import MESSAGE_TYPES, ProtocolError, Stop, decode, encode
from protocol.images import decode_image
from protocol.messages import ExecutionReport
from tests.test_protocol_codec import (
    MANY,
    corrupted,
    leaves,
    msgpack_values,
    pack,
    random_message,
    same_float,
    small_messages,
    unpack,
)

ALL_TYPES = tuple(MESSAGE_TYPES.values())

# ---------------------------------------------------------------------- the reference schema

SEQ = ("int", 0, 2**63)
NON_NEGATIVE = ("float", 0.0)
NAME = ("str", 256, r"[A-Za-z0-9_.-]+")
NAME_OR_NONE = ("str", 256, r"(?:[A-Za-z0-9_.-]+)?")
TEXT = ("str", 4096, None)
POSE = ("array", ((4, 4), (4, 4)), "pose")
VECTOR6 = ("array", ((6, 6),), None)

SCHEMA: dict[str, dict[str, tuple[Any, ...]]] = {
    "CameraFrame": {
        "seq": SEQ,
        "stamp_s": NON_NEGATIVE,
        "X_WC": POSE,
        "K": ("array", ((3, 3), (3, 3)), "intrinsics"),
        "dist": ("array", ((5, 5),), None),
        "image": ("image",),
        "encoding": ("choice", ("raw", "png", "jpeg")),
        "quality": ("int", 1, 101),
    },
    "Recognition": {
        "model": NAME,
        "X_WO": POSE,
        "score": ("float", None),
        "frames": ("int", 1, 1001),
        "spread_m": NON_NEGATIVE,
        "spread_rad": NON_NEGATIVE,
        "searches": ("int", 0, 2**31),
        "rivals": ("int", 0, 2**31),
    },
    "Recognitions": {
        "seq": SEQ,
        "stamp_s": NON_NEGATIVE,
        "elapsed_s": NON_NEGATIVE,
        "objects": ("records", "Recognition", 0, 256),
        "tracked": ("bool",),
    },
    "RobotState": {
        "seq": SEQ,
        "stamp_s": NON_NEGATIVE,
        "q": VECTOR6,
        "X_WF": POSE,
        "gripper_opening_m": NON_NEGATIVE,
        "wrench_S": VECTOR6,
    },
    "ContactState": {"object": NAME, "normals_W": ("array", ((1, 16), (3, 3)), "unit rows")},
    "MotionCommand": {
        "kind": (
            "choice",
            ("guarded_grasp", "move", "guarded_move", "contact_move", "release", "open_gripper"),
        ),
        "X_WP": POSE,
        "speed_mps": NON_NEGATIVE,
        "force_limit_n": NON_NEGATIVE,
        "contacts": ("records", "ContactState", 0, 16),
    },
    "HeldBlock": {
        "name": NAME,
        "mass_kg": ("positive float", 100.0),
        "opening_m": ("positive float", 1.0),
        "com_G": ("array", ((3, 3),), "within 1 m"),
    },
    "MotionProgram": {
        "program_id": NAME,
        "X_GP": POSE,
        "commands": ("records", "MotionCommand", 1, 1000),
        "operator": NAME_OR_NONE,
        "continues": NAME_OR_NONE,
        "holds": ("records", "HeldBlock", 0, 1),
    },
    "ExecutionReport": {
        "program_id": NAME,
        "command_index": ("int", -1, 1000),
        "status": (
            "choice",
            ("accepted", "started", "done", "contact_verified", "failed", "refused", "stopped"),
        ),
        "wrench_S": VECTOR6,
        "message": TEXT,
        "stamp_s": NON_NEGATIVE,
        "seq": SEQ,
    },
    "Stop": {"reason": TEXT, "stamp_s": NON_NEGATIVE, "cancels": ("names", 0, 64)},
    "Heartbeat": {
        "site_id": ("str", 256, r"[A-Za-z0-9_-]+"),
        "role": ("choice", ("work_site", "operator_site")),
        "seq": SEQ,
        "stamp_s": NON_NEGATIVE,
        "operator": NAME_OR_NONE,
        "echo_stamp_s": NON_NEGATIVE,
        "echo_held_s": NON_NEGATIVE,
        "echo_operator": NAME_OR_NONE,
        "state_echo_s": NON_NEGATIVE,
        "state_echo_held_s": NON_NEGATIVE,
    },
    "ObjectPose": {"name": NAME, "X_WO": POSE},
    "TruthPoses": {
        "seq": SEQ,
        "stamp_s": NON_NEGATIVE,
        "objects": ("records", "ObjectPose", 0, 256),
    },
}
TAGS = {
    "camera_frame": "CameraFrame",
    "recognitions": "Recognitions",
    "robot_state": "RobotState",
    "motion_program": "MotionProgram",
    "execution_report": "ExecutionReport",
    "stop": "Stop",
    "heartbeat": "Heartbeat",
    "truth_poses": "TruthPoses",
}


class RefusedError(Exception):
    """The reference refuses."""


def need(condition: bool) -> None:
    if not condition:
        raise RefusedError


def ref_array_content(check: str | None, arr: np.ndarray) -> np.ndarray:
    """Finite elements, and the README's rule for poses, intrinsics and unit normals."""
    need(bool(np.isfinite(arr).all()))
    if check == "pose":
        R = arr[:3, :3]
        need(bool(np.all(np.abs(arr[3] - [0.0, 0.0, 0.0, 1.0]) <= 1e-9)))
        with np.errstate(over="ignore", invalid="ignore"):  # a huge entry: inf, refused
            need(bool(np.all(np.abs(R.T @ R - np.eye(3)) <= 1e-6)))
        need(bool(np.linalg.det(R) > 0.0))
    elif check == "intrinsics":
        need(arr[1, 0] == 0.0 and arr[2, 0] == 0.0 and arr[2, 1] == 0.0 and arr[2, 2] == 1.0)
        need(arr[0, 0] > 0.0 and arr[1, 1] > 0.0)
    elif check == "within 1 m":
        with np.errstate(over="ignore", invalid="ignore"):
            need(bool(np.linalg.norm(arr) <= 1.0))
    elif check == "unit rows":
        with np.errstate(over="ignore", invalid="ignore"):
            need(bool(np.all(np.abs(np.linalg.norm(arr, axis=1) - 1.0) <= 1e-6)))
    return arr


def shape_in(shape: tuple[int, ...], ranges: tuple[tuple[int, int], ...]) -> bool:
    return len(shape) == len(ranges) and all(
        lo <= n <= hi for n, (lo, hi) in zip(shape, ranges, strict=True)
    )


def ref_float(value: Any, lo: float | None) -> float:
    try:
        number = float(value)
    except OverflowError:
        raise RefusedError from None
    need(math.isfinite(number) and (lo is None or number >= lo))
    return number


def ref_str(kind: tuple[Any, ...], value: Any) -> str:
    if kind[0] == "choice":
        need(isinstance(value, str) and value in kind[1])
        return str.__str__(value)
    _, max_len, pattern = kind
    need(isinstance(value, str) and len(value) <= max_len)
    need(pattern is None or re.fullmatch(pattern, value) is not None)
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise RefusedError from None
    return str.__str__(value)  # a plain str, whatever subclass came


# ----------------------------------------------------------------- the reference: the wire


def ref_wire_record(name: str, body: Any) -> dict[str, Any]:
    fields = SCHEMA[name]
    need(isinstance(body, dict) and sorted(body) == sorted(fields))
    return {f: ref_wire_value(kind, body[f], body) for f, kind in fields.items()}


def ref_wire_value(kind: tuple[Any, ...], value: Any, body: dict[str, Any]) -> Any:
    if kind[0] == "bool":
        need(type(value) is bool)
        return value
    if kind[0] == "int":
        need(type(value) is int and kind[1] <= value < kind[2])
        return value
    if kind[0] == "float":
        need(type(value) in (int, float))
        return ref_float(value, kind[1])
    if kind[0] == "positive float":
        need(type(value) in (int, float))
        number = ref_float(value, None)
        need(0.0 < number <= kind[1])
        return number
    if kind[0] in ("str", "choice"):
        need(type(value) is str)
        return ref_str(kind, value)
    if kind[0] == "records":
        _, item, lo, hi = kind
        need(type(value) is list and lo <= len(value) <= hi)
        return tuple(ref_wire_record(item, v) for v in value)
    if kind[0] == "names":
        need(type(value) is list and kind[1] <= len(value) <= kind[2])
        return tuple(ref_str(NAME, v) for v in value)
    need(type(value) is list and len(value) == 2)
    shape, data = value
    need(type(shape) is list and all(type(n) is int for n in shape) and type(data) is bytes)
    if kind[0] == "image":
        need(shape_in(tuple(shape), ((1, 4096), (1, 4096))))
        encoding = ref_str(SCHEMA["CameraFrame"]["encoding"], body["encoding"])
        if encoding == "raw":
            need(len(data) == shape[0] * shape[1])
            return np.frombuffer(data, np.uint8).reshape(shape)
        try:
            return decode_image(data, encoding, (shape[0], shape[1]))
        except ProtocolError:
            raise RefusedError from None
    _, ranges, check = kind
    need(shape_in(tuple(shape), ranges) and len(data) == 8 * math.prod(shape))
    return ref_array_content(check, np.frombuffer(data, "<f8").reshape(shape))


def ref_decode(payload: bytes) -> tuple[str, dict[str, Any]]:
    """(class name, field values) of a valid payload; RefusedError for any other."""
    try:
        env = msgpack.unpackb(payload, raw=False)
    except Exception:
        raise RefusedError from None
    need(isinstance(env, dict) and sorted(env) == ["b", "t", "v"])
    need(isinstance(env["t"], str) and env["t"] in TAGS)
    # Version 8 changed the heartbeat, 9 the program, 11 the recognitions; the other types
    # are read back to 6.
    versions = {
        "heartbeat": (8, 9, 10, 11),
        "motion_program": (9, 10, 11),
        "recognitions": (11,),
    }.get(env["t"], (6, 7, 8, 9, 10, 11))
    need(type(env["v"]) is int and env["v"] in versions)
    name = TAGS[env["t"]]
    return name, ref_wire_record(name, env["b"])


def assert_matches(record: Any, values: dict[str, Any], where: str) -> None:
    """``record``'s fields are ``values``: arrays bit-exact and read-only, floats with sign."""
    assert [f.name for f in dataclasses.fields(record)] == list(values), where
    for name, want in values.items():
        got, w = getattr(record, name), f"{where}.{name}"
        if isinstance(want, np.ndarray):
            assert isinstance(got, np.ndarray) and not got.flags.writeable, w
            assert got.dtype == want.dtype.newbyteorder("=") and got.shape == want.shape, w
            assert got.tobytes() == want.tobytes(), w
        elif isinstance(want, tuple):
            assert isinstance(got, tuple) and len(got) == len(want), w
            for i, (g, v) in enumerate(zip(got, want, strict=True)):
                if isinstance(v, str):  # a tuple of names
                    assert type(g) is str and g == v, f"{w}[{i}]"
                    continue
                assert_matches(g, v if isinstance(v, dict) else fields_of(v), f"{w}[{i}]")
        elif isinstance(want, float):
            assert type(got) is float and same_float(got, want), w
        else:
            assert type(got) is type(want) and got == want, w


def fields_of(record: Any) -> dict[str, Any]:
    return {f.name: getattr(record, f.name) for f in dataclasses.fields(record)}


def assert_agree(payload: bytes) -> None:
    try:
        name, values = ref_decode(payload)
    except RefusedError:
        with pytest.raises(ProtocolError) as info:
            decode(payload)
        assert "internal error" not in str(info.value)
        return
    msg = decode(payload)
    assert type(msg).__name__ == name
    assert_matches(msg, values, name)


# Values on either side of the schema's bounds, for any leaf of any message.
EDGE_VALUES: list[Any] = [
    -(2**63),
    -2,
    -1,
    0,
    1,
    99,
    100,
    101,
    999,
    1000,
    2**63 - 1,
    2**63,
    2**64 - 1,
    -0.0,
    0.0,
    5e-324,
    -5e-324,
    sys.float_info.max,
    -sys.float_info.max,
    float("inf"),
    float("-inf"),
    float("nan"),
    True,
    None,
    "",
    "a" * 32,
    "a" * 33,
    "a" * 256,
    "a" * 257,
    "é" * 256,
    "é" * 257,
    "x" * 4096,
    "é" * 4096,
    "é" * 4097,
    "a\n",
    "a b",
    "site.x",
    "stopped",
    "move",
    "work_site",
    "jpeg",
    b"",
    bytes(48),
    [],
    [[6], bytes(48)],
    [[6], bytes(47)],
    [(6,), bytes(48)],
    [[3, 2], bytes(48)],
    [[-6], bytes(48)],
    [[True] * 6, bytes(48)],
    [[6.0], bytes(48)],
    [[6], "x" * 48],
    [[4, 4], bytes(128)],
    [[4, 4], np.eye(4).tobytes()],
    [[4, 4], np.diag([1.0, 1.0, -1.0, 1.0]).tobytes()],
    [[1, 3], np.array([0.0, 0.0, 1.0]).tobytes()],
    [[1, 3], np.array([0.0, 0.0, 1.1]).tobytes()],
    [[17, 3], np.tile([0.0, 0.0, 1.0], 17).tobytes()],
    [[3, 3], np.array([[5.0, 0, 1], [0, 5, 1], [0, 0, 1]]).tobytes()],
    [[1, 1], bytes(1)],
    [[0, 1], b""],
    {},
]


def test_the_reference_takes_every_valid_message() -> None:
    for cls in ALL_TYPES:
        for seed in range(20):
            msg = random_message(cls, seed)
            name, values = ref_decode(encode(msg))
            assert name == cls.__name__
            assert_matches(msg, values, name)


@pytest.mark.parametrize(
    "change",
    [
        lambda b: b.update(seq=-1),
        lambda b: b.update(stamp_s=float("nan")),
        lambda b: b.update(q=[[6], np.full(6, np.inf).tobytes()]),
        lambda b: b.update(X_WF=[[4, 4], (2 * np.eye(4)).tobytes()]),
        lambda b: b.update(extra=1),
        lambda b: b.pop("q"),
    ],
)
def test_the_reference_and_decode_refuse_hand_written_faults(change: Any) -> None:
    env = unpack(encode(random_message(MESSAGE_TYPES["robot_state"], 0)))
    change(env["b"])
    with pytest.raises(RefusedError):
        ref_decode(pack(env))
    with pytest.raises(ProtocolError):
        decode(pack(env))


@MANY
@given(small_messages, st.data())
def test_decode_agrees_with_the_reference_on_edge_values_in_any_field(
    msg: Any, data: st.DataObject
) -> None:
    env = unpack(encode(msg))
    _, holder, name = data.draw(st.sampled_from(leaves(env["b"], type(msg).__name__)))
    holder[name] = data.draw(st.sampled_from(EDGE_VALUES) | msgpack_values)
    assert_agree(pack(env))


@MANY
@given(small_messages, st.data())
def test_decode_agrees_with_the_reference_on_corrupted_bytes(msg: Any, data: st.DataObject) -> None:
    assert_agree(corrupted(encode(msg), data))


@MANY
@given(st.sampled_from(sorted(TAGS)), msgpack_values, st.sampled_from([8, 7, 6, 3, True]))
def test_decode_agrees_with_the_reference_on_random_bodies(
    tag: str, body: Any, version: Any
) -> None:
    assert_agree(pack({"t": tag, "v": version, "b": body}))


def test_the_envelope_in_another_key_order_or_with_a_key_twice() -> None:
    payload = encode(Stop(reason="x", stamp_s=1.0))
    env = unpack(payload)
    reordered = msgpack.packb({"b": env["b"], "v": env["v"], "t": env["t"]})
    assert isinstance(decode(reordered), Stop)
    assert_agree(reordered)
    # A map with the key "v" twice: msgpack keeps the last, and so must decode.
    twice = b"\x84" + payload[1:] + msgpack.packb("v") + msgpack.packb(2)
    with pytest.raises(ProtocolError, match=r"envelope\.v: unsupported schema version 2"):
        decode(twice)
    assert_agree(twice)


# --------------------------------------------------------- the reference: constructor values


def ref_python_value(kind: tuple[Any, ...], value: Any) -> Any:
    """What a constructor must make of ``value`` for a field of ``kind``, or RefusedError."""
    if kind[0] == "bool":
        need(isinstance(value, bool | np.bool_))
        return bool(value)
    if kind[0] == "int":
        need(not isinstance(value, bool | np.bool_) and isinstance(value, int | np.integer))
        need(kind[1] <= int(value) < kind[2])
        return int(value)
    if kind[0] == "float":
        need(not isinstance(value, bool | np.bool_))
        need(isinstance(value, int | float | np.integer | np.floating))
        return ref_float(value, kind[1])
    if kind[0] == "positive float":
        need(not isinstance(value, bool | np.bool_))
        need(isinstance(value, int | float | np.integer | np.floating))
        number = ref_float(value, None)
        need(0.0 < number <= kind[1])
        return number
    if kind[0] in ("str", "choice"):
        return ref_str(kind, value)
    if kind[0] == "records":
        _, item, lo, hi = kind
        need(isinstance(value, list | tuple) and lo <= len(value) <= hi)
        need(all(type(v).__name__ == item for v in value))
        return tuple(value)
    if kind[0] == "names":
        need(isinstance(value, list | tuple) and kind[1] <= len(value) <= kind[2])
        return tuple(ref_str(NAME, v) for v in value)
    need(isinstance(value, np.ndarray | list | tuple))
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError):
        raise RefusedError from None
    if kind[0] == "image":
        need(shape_in(arr.shape, ((1, 4096), (1, 4096))) and arr.dtype.kind in "iu")
        need(arr.size == 0 or (arr.min() >= 0 and arr.max() <= 255))
        return arr.astype(np.uint8)
    _, ranges, check = kind
    need(shape_in(arr.shape, ranges) and arr.dtype.kind in "fiu")
    return ref_array_content(check, arr.astype("<f8"))


CONSTRUCTOR_VALUES: list[Any] = [
    *EDGE_VALUES,
    np.float64(1.5),
    np.float32(1.5),
    np.float64(np.nan),
    np.int64(3),
    np.int64(-1),
    np.uint64(2**64 - 1),
    np.int8(-1),
    np.bool_(True),
    np.str_("done"),
    1,
    2.5,
    type("Text", (str,), {})("stopped"),
    "\udc80",
    np.zeros(6),
    np.zeros(6, np.float32),
    np.zeros(6, ">f8"),
    np.zeros(6, np.int64),
    np.zeros(6, np.uint8),
    np.zeros(6, bool),
    np.zeros(7),
    np.zeros((6, 1)),
    np.arange(12.0)[::2],
    np.full(6, np.nan),
    np.array([0.0, 0.0, 0.0, 0.0, 0.0, -np.inf]),
    np.eye(4),
    np.eye(4).T.copy(order="F"),
    np.eye(4)[::-1],
    np.eye(4) * 2.0,
    np.zeros((3, 3)),
    np.ones((2, 3)) / np.sqrt(3.0),
    np.zeros((0, 3)),
    np.full((2, 2), 300),
    np.full((2, 2), 7, np.int16),
    [0.0] * 6,
    (1, 2, 3, 4, 5, 6),
    [[1.0, 0.0], [0.0]],
    ["0"] * 6,
]


def records_in(record: Any) -> list[Any]:
    """``record`` and every record nested in it."""
    out = [record]
    for value in fields_of(record).values():
        items = value if isinstance(value, tuple) else (value,)
        out.extend(r for item in items if dataclasses.is_dataclass(item) for r in records_in(item))
    return out


@MANY
@given(small_messages, st.data())
def test_constructors_agree_with_the_reference_on_any_value(msg: Any, data: st.DataObject) -> None:
    """Same verdict and same values as the reference, for a message or any record in it, one
    field replaced; a refusal names the record and the field."""
    record = data.draw(st.sampled_from(records_in(msg)))
    cls = type(record)
    values = fields_of(record)
    name = data.draw(st.sampled_from(sorted(values)))
    values[name] = data.draw(st.sampled_from(CONSTRUCTOR_VALUES) | msgpack_values)
    kinds = SCHEMA[cls.__name__]
    try:
        want = {f: ref_python_value(kinds[f], v) for f, v in values.items()}
    except RefusedError:
        with pytest.raises(ProtocolError) as info:
            cls(**values)
        assert str(info.value).startswith(f"{cls.__name__}.{name}"), str(info.value)
        return
    new = cls(**values)
    assert_matches(new, want, cls.__name__)
    if isinstance(values[name], np.ndarray):  # a copy, never the caller's array
        assert not np.shares_memory(getattr(new, name), values[name])


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.__name__)
def test_constructors_copy_the_callers_arrays(cls: type) -> None:
    """Every array field of every record: the record holds a read-only copy; the caller's array
    is left as it was, writable."""
    for record in records_in(random_message(cls, 1)):
        for name, held in fields_of(record).items():
            if not isinstance(held, np.ndarray):
                continue
            values = fields_of(record)
            values[name] = mine = held.copy()
            new = type(record)(**values)
            assert not np.shares_memory(getattr(new, name), mine), name
            assert mine.flags.writeable and not getattr(new, name).flags.writeable, name


def test_text_fields_are_plain_str_whatever_str_subclass_came() -> None:
    """A choice (Literal) and a free text field given numpy's or a caller's str subclass."""
    mine = type("Text", (str,), {})
    for text in (np.str_("done"), mine("done")):
        values = fields_of(random_message(ExecutionReport, 1))
        values.update(status=text, message=text)
        report = ExecutionReport(**values)
        assert type(report.status) is str and type(report.message) is str
        assert report.status == report.message == "done"


@pytest.mark.parametrize(
    "cancels, said",
    [
        ("\udc80", "Stop.cancels: expected array, got str"),  # msgspec's refusal names no field
        (("ok", 3), "Stop.cancels"),
    ],
)
def test_a_constructor_names_a_tuple_field_it_refuses(cancels: Any, said: str) -> None:
    with pytest.raises(ProtocolError) as info:
        Stop(reason="x", stamp_s=1.0, cancels=cancels)
    assert str(info.value).startswith(said), str(info.value)
