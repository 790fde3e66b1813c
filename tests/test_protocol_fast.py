"""The codec's fast path (msgspec, ``protocol/_fast.py``) against its reference (Python, field by
field, ``protocol/codec.py``): the same bytes out, and for any payload the same verdict and the
same message. The fast path must also really take every valid message it is meant to: a fast
path that refused everything would pass every other test here, only slowly."""

from __future__ import annotations

import sys
from typing import Any

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import MESSAGE_TYPES, CameraFrame, ExecutionReport, ProtocolError, Stop, encode
from protocol._fast import decoder, fast_decode, fast_encode
from protocol.codec import _reference_decode, _reference_encode
from tests.test_protocol_codec import (
    MANY,
    assert_same,
    corrupted,
    leaves,
    msgpack_values,
    pack,
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
