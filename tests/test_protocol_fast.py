"""The codec's fast path (msgspec, ``protocol/_fast.py``) against its reference (Python, field by
field, ``protocol/codec.py``): the same bytes out, and for any payload the same verdict and the
same message. The fast path must also really take every valid message it is meant to: a fast
path that refused everything would pass every other test here, only slowly."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import MESSAGE_TYPES, CameraFrame, ExecutionReport, ProtocolError, Stop, encode
from protocol._fast import decoder, fast_decode, fast_encode
from protocol._spec import REFERENCE_INITS
from protocol.codec import _reference_decode, _reference_encode
from tests.test_protocol_codec import (
    MANY,
    assert_same,
    corrupted,
    leaves,
    msgpack_values,
    pack,
    random_message,
    small_messages,
    unpack,
)

ALL_TYPES = tuple(MESSAGE_TYPES.values())
FAST_TYPES = tuple(cls for cls in ALL_TYPES if cls is not CameraFrame)
ANY = decoder(ALL_TYPES)

# Values on either side of the schema's bounds, for any leaf of any message.
EDGE_VALUES: list[Any] = [
    -(2**63),
    -2,
    -1,
    0,
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
    b"",
    bytes(48),
    [],
    [[6], bytes(48)],
    [[6], bytes(47)],
    [(6,), bytes(48)],
    [[3, 2], bytes(48)],
    [[-6], bytes(48)],
    [[4, 4], bytes(128)],
    {},
]


def verdicts(payload: bytes) -> tuple[Any, Any]:
    """(fast result or None, reference result or the ProtocolError it raised)."""
    fast = fast_decode(ANY, payload)
    try:
        ref: Any = _reference_decode(payload, None)
    except ProtocolError as exc:
        ref = exc
    return fast, ref


def assert_agree(payload: bytes) -> None:
    fast, ref = verdicts(payload)
    if isinstance(ref, ProtocolError):
        assert fast is None, f"fast path accepted what the reference refuses: {ref}"
    elif fast is not None:
        assert_same(ref, fast, type(ref).__name__)
    else:  # only camera frames, and envelopes written in another key order, may go around
        assert isinstance(ref, CameraFrame) or next(iter(unpack(payload))) != "t"


@MANY
@given(small_messages)
def test_fast_path_writes_the_reference_bytes_and_takes_them_back(msg: Any) -> None:
    reference = _reference_encode(msg)
    fast = fast_encode(msg)
    if isinstance(msg, CameraFrame):
        assert fast is None
        return
    assert fast == reference
    decoded = fast_decode(decoder((type(msg),)), reference)
    assert decoded is not None, "the fast path refused a valid message"
    assert_same(msg, decoded, type(msg).__name__)


@MANY
@given(small_messages, st.data())
def test_fast_and_reference_agree_on_edge_values_in_any_field(
    msg: Any, data: st.DataObject
) -> None:
    env = unpack(encode(msg))
    _, holder, name = data.draw(st.sampled_from(leaves(env["b"], type(msg).__name__)))
    holder[name] = data.draw(st.sampled_from(EDGE_VALUES) | msgpack_values)
    assert_agree(pack(env))


@MANY
@given(small_messages, st.data())
def test_fast_and_reference_agree_on_corrupted_bytes(msg: Any, data: st.DataObject) -> None:
    payload = corrupted(encode(msg), data)
    try:
        unpack(payload)
    except Exception:  # not msgpack: both must refuse
        assert verdicts(payload)[0] is None
        return
    assert_agree(payload)


@MANY
@given(st.sampled_from(sorted(MESSAGE_TYPES)), msgpack_values, st.sampled_from([3, 2, True]))
def test_fast_and_reference_agree_on_random_bodies(tag: str, body: Any, version: Any) -> None:
    assert_agree(pack({"t": tag, "v": version, "b": body}))


def test_the_envelope_in_another_key_order_or_with_a_key_twice_still_decodes() -> None:
    payload = encode(Stop(reason="x", stamp_s=1.0))
    env = unpack(payload)
    reordered = msgpack.packb({"b": env["b"], "v": env["v"], "t": env["t"]})
    fast, ref = verdicts(reordered)
    assert isinstance(ref, Stop)
    if fast is not None:
        assert_same(ref, fast, "Stop")
    # A map with the key "v" twice: msgpack keeps the last, and so must the fast path.
    twice = b"\x84" + payload[1:] + msgpack.packb("v") + msgpack.packb(2)
    assert isinstance(verdicts(twice)[1], ProtocolError)
    assert verdicts(twice)[0] is None


@pytest.mark.parametrize("cls", FAST_TYPES, ids=lambda c: c.__name__)
def test_every_message_type_but_camera_frames_has_a_fast_path(cls: type) -> None:
    assert decoder((cls,)) is not None
    assert decoder((CameraFrame,)) is None


def test_fast_path_refuses_a_message_of_another_expected_type() -> None:
    payload = encode(Stop(reason="x", stamp_s=1.0))
    assert fast_decode(decoder((ExecutionReport,)), payload) is None
    assert isinstance(fast_decode(decoder((ExecutionReport, Stop)), payload), Stop)


# ----------------------------------------------------------------- the generated constructors

# Python values a caller may pass to a constructor: besides the wire's edge values, numpy
# scalars and arrays of other dtypes, shapes, orders and contents, and subclasses of str.
CONSTRUCTOR_VALUES: list[Any] = [
    *EDGE_VALUES,
    np.float64(1.5),
    np.float32(1.5),
    np.int64(3),
    np.int8(-1),
    np.bool_(True),
    1,
    2.5,
    type("Text", (str,), {})("stopped"),
    np.zeros(6),
    np.zeros(6, np.float32),
    np.zeros(6, ">f8"),
    np.zeros(6, np.int64),
    np.zeros(7),
    np.zeros((6, 1)),
    np.arange(12.0)[::2],
    np.full(6, np.nan),
    np.array([0.0, 0.0, 0.0, 0.0, 0.0, -np.inf]),
    np.eye(4),
    np.eye(4).T.copy(order="F"),
    np.eye(4) * 2.0,
    np.zeros((3, 3)),
    np.ones((2, 3)) / np.sqrt(3.0),
    np.zeros((0, 3)),
    [0.0] * 6,
    (1, 2, 3, 4, 5, 6),
    [[1.0, 0.0], [0.0]],
]


def records_in(record: Any) -> list[Any]:
    """``record`` and every record nested in it."""
    out = [record]
    for f in dataclasses.fields(record):
        value = getattr(record, f.name)
        items = value if isinstance(value, tuple) else (value,)
        out.extend(r for item in items if dataclasses.is_dataclass(item) for r in records_in(item))
    return out


def construct(init: Any, cls: type, values: dict[str, Any]) -> Any:
    """The record ``init`` makes of ``values``, or the ProtocolError it raised."""
    obj = object.__new__(cls)
    try:
        init(obj, **values)
    except ProtocolError as exc:
        return exc
    return obj


@MANY
@given(small_messages, st.data())
def test_generated_constructors_agree_with_the_reference_on_any_value(
    msg: Any, data: st.DataObject
) -> None:
    """Same record or same error text, for a message or any record in it, one field replaced."""
    record = data.draw(st.sampled_from(records_in(msg)))
    cls = type(record)
    values = {f.name: getattr(record, f.name) for f in dataclasses.fields(record)}
    name = data.draw(st.sampled_from(sorted(values)))
    values[name] = data.draw(st.sampled_from(CONSTRUCTOR_VALUES) | msgpack_values)
    ref = construct(REFERENCE_INITS[cls], cls, values)
    new = construct(cls.__init__, cls, values)
    if isinstance(ref, ProtocolError):
        assert isinstance(new, ProtocolError) and str(new) == str(ref)
        return
    assert not isinstance(new, ProtocolError), f"refused what the reference accepts: {new}"
    assert_same(ref, new, cls.__name__)
    if isinstance(values[name], np.ndarray):  # a copy, never the caller's array
        assert not np.shares_memory(getattr(new, name), values[name])


def test_every_record_class_has_a_generated_constructor() -> None:
    for msg in (random_message(cls, 0) for cls in ALL_TYPES):
        for record in records_in(msg):
            assert type(record).__init__ is not REFERENCE_INITS[type(record)]


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.__name__)
def test_generated_constructors_copy_the_callers_arrays(cls: type) -> None:
    """Every array field of every record: the record holds a read-only copy; the caller's array
    is left as it was, writable (the common case of the generated code, taken every time)."""
    for record in records_in(random_message(cls, 1)):
        for f in dataclasses.fields(record):
            held = getattr(record, f.name)
            if not isinstance(held, np.ndarray):
                continue
            values = {g.name: getattr(record, g.name) for g in dataclasses.fields(record)}
            values[f.name] = mine = held.copy()
            new = type(record)(**values)
            assert not np.shares_memory(getattr(new, f.name), mine), f.name
            assert mine.flags.writeable and not getattr(new, f.name).flags.writeable, f.name
