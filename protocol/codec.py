"""The msgpack codec: ``encode(msg) -> bytes`` and ``decode(payload, expected) -> message``.

Envelope: a msgpack map ``{"t": type_tag, "v": SCHEMA_VERSION, "b": body}``. The body maps each
field name to its value: ints, floats and strs as themselves; arrays as ``[shape, data]`` with
``shape`` a list of ints and ``data`` the raw little-endian bytes in C order (dtype fixed by the
schema); nested records as maps; tuples of records as lists of maps.

``decode`` trusts nothing: for any input it returns a valid message or raises
:class:`ProtocolError` saying what was wrong and where.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any, TypeVar, overload

import msgpack
import numpy as np

from ._fast import decoder as fast_decoder
from ._fast import fast_decode, fast_encode
from ._spec import (
    ArrayField,
    Checker,
    Field,
    ImageField,
    NestedField,
    Record,
    TupleField,
    check_field,
    checker,
    short_repr,
    type_name,
)
from .errors import ProtocolError
from .images import decode_image, encode_image
from .messages import MESSAGE_TYPES, SCHEMA_VERSION, Message

MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
"""Largest payload ``encode`` produces and ``decode`` accepts (bytes), checked before unpacking."""

_ENVELOPE_KEYS = frozenset(("t", "v", "b"))

# Limits handed to msgpack so that a small payload cannot make it allocate a lot. They are looser
# than the schema's own limits so that near misses get the schema's clearer error message.
_UNPACK_LIMITS = {
    "max_bin_len": MAX_PAYLOAD_BYTES,
    "max_str_len": 4 * 4096,  # bytes: 4096 characters of up to 4 UTF-8 bytes each
    "max_array_len": 4096,
    "max_map_len": 64,
    "max_ext_len": 0,
}


def _refuse_ext(code: int, data: bytes) -> Any:
    raise ValueError(f"msgpack extension type {code} is not allowed")


# ------------------------------------------------------------------------------------ encode


def _array_to_wire(arr: np.ndarray, field: ArrayField) -> list[Any]:
    data = np.ascontiguousarray(arr, dtype=field.dtype).tobytes()
    return [list(arr.shape), data]


_SCALAR, _ARRAY, _IMAGE, _NESTED, _TUPLE = range(5)


@functools.cache
def _plan(cls: type) -> tuple[tuple[str, Field, int, Checker], ...]:
    """``(name, field, kind, checker)`` of each field of record class ``cls``, worked out once:
    the codec runs on the command path, where a chain of isinstance tests per field showed."""
    kinds = (
        (ImageField, _IMAGE),
        (ArrayField, _ARRAY),
        (NestedField, _NESTED),
        (TupleField, _TUPLE),
    )
    return tuple(
        (name, field, next((k for t, k in kinds if isinstance(field, t)), _SCALAR), checker(field))
        for name, field in cls._SPEC.items()
    )


def _to_wire(record: Record) -> dict[str, Any]:
    body: dict[str, Any] = {}
    for name, field, kind, _ in _plan(type(record)):
        value = getattr(record, name)
        if kind == _SCALAR:
            body[name] = value
        elif kind == _ARRAY:
            body[name] = _array_to_wire(value, field)
        elif kind == _IMAGE:
            encoding = getattr(record, field.encoding_field)
            quality = getattr(record, field.quality_field)
            body[name] = [list(value.shape), encode_image(value, encoding, quality)]
        elif kind == _NESTED:
            body[name] = _to_wire(value)
        else:
            body[name] = [_to_wire(item) for item in value]
    return body


def _reference_encode(msg: Message) -> bytes:
    """``encode`` in Python, field by field (images, and the reference for the fast path)."""
    cls = type(msg)
    if not isinstance(msg, Message) or MESSAGE_TYPES.get(cls.TYPE) is not cls:
        raise ProtocolError(f"encode: expected a protocol message, got {type_name(msg)}")
    return msgpack.packb(
        {"t": cls.TYPE, "v": SCHEMA_VERSION, "b": _to_wire(msg)}, use_bin_type=True
    )


def encode(msg: Message) -> bytes:
    """Encode a message into its msgpack envelope.

    Raises :class:`ProtocolError` if ``msg`` is not a protocol message or the payload would
    exceed :data:`MAX_PAYLOAD_BYTES`.
    """
    payload = fast_encode(msg)
    if payload is None:
        payload = _reference_encode(msg)
    if len(payload) > MAX_PAYLOAD_BYTES:
        cls = type(msg)
        raise ProtocolError(
            f"{cls.__name__}: encoded payload is {len(payload)} bytes, "
            f"more than MAX_PAYLOAD_BYTES = {MAX_PAYLOAD_BYTES}"
        )
    return payload


# ------------------------------------------------------------------------------------ decode


def _wire_shape_and_data(field: ArrayField, value: Any, where: str) -> tuple[list[int], Any]:
    if not isinstance(value, list) or len(value) != 2:
        raise ProtocolError(f"{where}: expected array as [shape, data], got {type_name(value)}")
    shape, data = value
    if not isinstance(shape, list) or not all(
        type(n) is int and n >= 0
        for n in shape  # exact int: bool is not an int
    ):
        raise ProtocolError(
            f"{where}: array shape must be a list of non-negative ints, got {short_repr(shape)}"
        )
    if not field.shape_ok(tuple(shape)):
        raise ProtocolError(f"{where}: expected shape {field.shape_text()}, got {tuple(shape)}")
    if not isinstance(data, bytes):
        raise ProtocolError(f"{where}: array data must be bytes, got {type_name(data)}")
    return shape, data


def _image_from_wire(field: ImageField, value: Any, encoding: str, where: str) -> np.ndarray:
    shape, data = _wire_shape_and_data(field, value, where)
    try:
        return decode_image(data, encoding, (shape[0], shape[1]))
    except ProtocolError as e:
        raise ProtocolError(f"{where}: {e}") from None


def _array_from_wire(field: ArrayField, value: Any, where: str) -> np.ndarray:
    shape, data = _wire_shape_and_data(field, value, where)
    expected_len = math.prod(shape) * field.dtype.itemsize
    if len(data) != expected_len:
        raise ProtocolError(
            f"{where}: array data is {len(data)} bytes, expected {expected_len} for shape "
            f"{tuple(shape)} of {field.dtype.itemsize}-byte elements"
        )
    return np.frombuffer(data, dtype=field.dtype).reshape(shape)


def _record_from_wire(cls: type, body: Any, where: str) -> Any:
    if not isinstance(body, dict):
        raise ProtocolError(f"{where}: expected a map, got {type_name(body)}")
    spec: Mapping[str, Field] = cls._SPEC
    if body.keys() != spec.keys():
        missing = [name for name in spec if name not in body]
        if missing:
            raise ProtocolError(f"{where}: missing field(s) {missing}")
        extra = [key for key in body if key not in spec]
        raise ProtocolError(f"{where}: unknown field(s) {short_repr(extra)}")
    values: dict[str, Any] = {}
    for name, field, kind, check in _plan(cls):
        value = body[name]
        field_where = f"{where}.{name}"
        if kind == _SCALAR:
            pass
        elif kind == _IMAGE:
            encoding_spec = spec[field.encoding_field]
            encoding = check_field(
                encoding_spec, body[field.encoding_field], f"{where}.{field.encoding_field}"
            )
            value = _image_from_wire(field, value, encoding, field_where)
        elif kind == _ARRAY:
            value = _array_from_wire(field, value, field_where)
        elif kind == _NESTED:
            value = _record_from_wire(field.cls, value, field_where)
        else:
            if not isinstance(value, list):
                raise ProtocolError(f"{field_where}: expected a list, got {type_name(value)}")
            if len(value) > field.max_len:  # before decoding the items
                raise ProtocolError(
                    f"{field_where}: must have {field.min_len}..{field.max_len} items, "
                    f"got {len(value)}"
                )
            value = [
                _record_from_wire(field.cls, item, f"{field_where}[{i}]")
                for i, item in enumerate(value)
            ]
        values[name] = check(field, value, field_where, True)
    return cls._from_validated(values)


def _expected_types(expected: type | tuple[type, ...] | None) -> tuple[type, ...] | None:
    if expected is None:
        return None
    types = expected if isinstance(expected, tuple) else (expected,)
    for t in types:
        if not (isinstance(t, type) and MESSAGE_TYPES.get(getattr(t, "TYPE", None)) is t):
            raise TypeError(f"decode: expected must be protocol message classes, got {t!r}")
    return types


_FAST_DECODERS: dict[Any, Any] = {}
"""The fast path's decoder (or ``None``) for each ``expected`` argument seen."""


def _fast_decoder(expected: type | tuple[type, ...] | None) -> Any:
    types = _expected_types(expected)  # raises TypeError for a bad ``expected``
    fast = fast_decoder(tuple(MESSAGE_TYPES.values()) if types is None else types)
    _FAST_DECODERS[expected] = fast
    return fast


M = TypeVar("M", bound=Message)


@overload
def decode(payload: bytes, expected: type[M]) -> M: ...
@overload
def decode(payload: bytes, expected: tuple[type[Message], ...] | None = None) -> Message: ...


def decode(payload: bytes, expected: type | tuple[type, ...] | None = None) -> Any:
    """Decode and fully validate one message.

    ``expected``: a message class or tuple of classes to accept (others are refused).
    Raises :class:`ProtocolError` for any invalid payload (and only that); a ``TypeError``
    only if ``expected`` itself is not a message class or tuple of them (a programming error).
    """
    try:
        fast = _FAST_DECODERS[expected]
    except (KeyError, TypeError):  # not seen yet, or not hashable
        fast = _fast_decoder(expected)
    # The common case first, touching little: the command path runs it cold after each wake-up.
    if fast is not None and type(payload) is bytes and len(payload) <= MAX_PAYLOAD_BYTES:
        msg = fast_decode(fast, payload)
        if msg is not None:
            return msg
    return _reference_decode(payload, _expected_types(expected))


def _reference_decode(payload: bytes, types: tuple[type, ...] | None) -> Message:
    """``decode`` in Python, field by field: what was wrong and where, for any payload."""
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise ProtocolError(f"payload: expected bytes, got {type_name(payload)}")
    size = memoryview(payload).nbytes
    if size > MAX_PAYLOAD_BYTES:
        raise ProtocolError(
            f"payload: {size} bytes is more than MAX_PAYLOAD_BYTES = {MAX_PAYLOAD_BYTES}"
        )
    try:
        envelope = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, ext_hook=_refuse_ext, **_UNPACK_LIMITS
        )
    except Exception as exc:  # msgpack raises several types for truncated or garbage input
        raise ProtocolError(f"payload: not a valid msgpack document ({exc})") from None
    try:
        return _decode_envelope(envelope, types)
    except ProtocolError:
        raise
    except Exception as exc:  # a backstop: a bug here must still not leak another type
        raise ProtocolError(
            f"payload: internal error while decoding ({type(exc).__name__}: {exc})"
        ) from exc


def _decode_envelope(envelope: Any, types: tuple[type, ...] | None) -> Message:
    if not isinstance(envelope, dict):
        raise ProtocolError(f"envelope: expected a map, got {type_name(envelope)}")
    if envelope.keys() != _ENVELOPE_KEYS:
        missing = sorted(_ENVELOPE_KEYS - envelope.keys())
        extra = [k for k in envelope if k not in _ENVELOPE_KEYS]
        raise ProtocolError(
            f"envelope: expected keys ['b', 't', 'v'], missing {missing}, "
            f"unknown {short_repr(extra)}"
        )
    version = envelope["v"]
    if type(version) is not int or version != SCHEMA_VERSION:
        raise ProtocolError(
            f"envelope.v: unsupported schema version {short_repr(version)}, "
            f"this side speaks {SCHEMA_VERSION}"
        )
    tag = envelope["t"]
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise ProtocolError(f"envelope.t: unknown message type {short_repr(tag)}")
    if types is not None and cls not in types:
        names = ", ".join(t.__name__ for t in types)
        raise ProtocolError(f"envelope.t: expected {names}, got {cls.__name__}")
    return _record_from_wire(cls, envelope["b"], cls.__name__)
