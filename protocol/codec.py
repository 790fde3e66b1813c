"""The msgpack codec: ``encode(msg) -> bytes`` and ``decode(payload, expected) -> message``.

Envelope: a msgpack map ``{"t": type_tag, "v": SCHEMA_VERSION, "b": body}``. The body maps each
field name to its value: ints, floats and strs as themselves; arrays as ``[shape, data]`` with
``shape`` a list of ints and ``data`` the raw little-endian bytes in C order (dtype fixed by the
schema); nested records as maps; tuples of records as lists of maps.

``decode`` trusts nothing: for any input it returns a valid message or raises
:class:`ProtocolError` saying what was wrong and where. msgspec decodes a payload into structs
derived from the messages' annotations and checks, in one C call, everything those express;
:func:`~protocol._schema.array_problem` checks the arrays. A refused payload is unpacked once
more, by msgpack with tight limits, only to say what was wrong.
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Annotated, Any, Literal, TypeVar, overload

import msgpack
import msgspec
import numpy as np

from ._schema import (
    ARRAY,
    IMAGE,
    RECORDS,
    Array,
    FieldInfo,
    array_problem,
    explain_at,
    path_of,
    plan_of,
    short_repr,
    type_name,
)
from .errors import ProtocolError
from .images import decode_image, encode_image
from .messages import (
    BODY_CHANGED_IN,
    FIELDS_ADDED,
    MESSAGE_TYPES,
    OLDEST_READ_VERSION,
    SCHEMA_VERSION,
    Message,
    MotionProgram,
    Name,
    readable_versions,
)

MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
"""Largest payload ``encode`` produces and ``decode`` accepts (bytes), checked before unpacking."""

_ENVELOPE_KEYS = frozenset(("t", "v", "b"))

# Limits for unpacking a refused payload to explain it, so that a small payload cannot make
# msgpack allocate a lot; looser than the schema's, so that near misses get its clearer words.
_UNPACK_LIMITS = {
    "max_bin_len": MAX_PAYLOAD_BYTES,
    "max_str_len": 4 * 4096,  # bytes: 4096 characters of up to 4 UTF-8 bytes each
    "max_array_len": 4096,
    "max_map_len": 64,
    "max_ext_len": 0,
}


# ------------------------------------------------------------------------------- wire types


def _axis_type(lo: int, hi: int) -> Any:
    return Literal[lo] if lo == hi else Annotated[int, msgspec.Meta(ge=lo, le=hi)]


def _wire_type(field: FieldInfo) -> Any:
    """The msgspec type of ``field``'s wire value."""
    if field.array is not None:
        shape = tuple[tuple(_axis_type(lo, hi) for lo, hi in field.array.ranges)]  # type: ignore[misc]
        return tuple[shape, bytes]
    if field.kind == RECORDS:
        assert field.item is not None
        items = list[_body_type(field.item)]  # type: ignore[misc]
        return Annotated[items, field.meta]
    return field.hint


class _Wire:
    """How one record class travels: its body struct and the conversion back to the record."""

    def __init__(self, cls: type) -> None:
        plan = plan_of(cls)
        self.cls = cls
        self.body = msgspec.defstruct(
            f"{cls.__name__}Wire",
            [(f.name, _wire_type(f)) for f in plan.fields],
            forbid_unknown_fields=True,
        )
        self.arrays = tuple((f.name, f.array) for f in plan.fields if f.kind == ARRAY)
        self.images = tuple(f.name for f in plan.fields if f.kind == IMAGE)
        self.records = tuple(  # their bodies were made with this one's
            (f.name, _WIRE[_body_type(f.item)]) for f in plan.fields if f.kind == RECORDS
        )
        self.simple = not (self.arrays or self.images or self.records)

    def record(self, wire: Any) -> Any:
        """The record of a decoded body struct; raises :class:`_RefusedError` for a bad array."""
        values = msgspec.structs.asdict(wire)  # in field order
        if not self.simple:
            self._convert(values)
        obj = object.__new__(self.cls)
        object.__setattr__(obj, "__dict__", values)  # frozen: set, not assigned
        return obj

    def _convert(self, values: dict[str, Any]) -> None:
        """Arrays, images and nested records of a body, from their wire form, in place."""
        for name, spec in self.arrays:
            try:
                values[name] = _array_from_wire(spec, *values[name])
            except _RefusedError as e:
                raise e.at(f".{name}") from None
        for name in self.images:
            (height, width), data = values[name]
            try:
                image = decode_image(data, values["encoding"], (height, width))
            except ProtocolError as e:
                raise _RefusedError(str(e)).at(f".{name}") from None
            image.setflags(write=False)
            values[name] = image
        for name, items_wire in self.records:
            convert = items_wire.record
            items: list[Any] = []
            try:
                for item in values[name]:
                    items.append(convert(item))
            except _RefusedError as e:
                raise e.at(f".{name}[{len(items)}]") from None
            values[name] = tuple(items)


class _RefusedError(Exception):
    """An array refused while converting a decoded body; ``path`` grows on the way out."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.path: list[str] = []

    def at(self, step: str) -> _RefusedError:
        self.path.append(step)
        return self


def _array_from_wire(spec: Array, shape: tuple[int, ...], data: bytes) -> np.ndarray:
    expected = math.prod(shape) * spec.dtype.itemsize
    if len(data) != expected:
        raise _RefusedError(
            f"array data is {len(data)} bytes, expected {expected} for shape "
            f"{tuple(shape)} of {spec.dtype.itemsize}-byte elements"
        )
    arr = np.frombuffer(data, spec.dtype)  # read-only: a view of bytes
    if len(shape) != 1:
        arr = arr.reshape(shape)
    if (text := array_problem(spec, arr)) is not None:
        raise _RefusedError(text)
    return arr


_WIRE: dict[type, _Wire] = {}
"""Each body struct's :class:`_Wire`."""


@functools.cache
def _body_type(cls: type) -> type:
    wire = _Wire(cls)
    _WIRE[wire.body] = wire
    return wire.body


@functools.cache
def _envelope_type(cls: type) -> type:
    return msgspec.defstruct(
        f"{cls.__name__}Envelope",
        [("v", Literal[readable_versions(cls.TYPE)]), ("b", _body_type(cls))],
        tag_field="t",
        tag=cls.TYPE,
        forbid_unknown_fields=True,
    )


# ------------------------------------------------------------------------------------ encode


def _array_to_wire(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):  # a message's: little-endian, C order (see Array)
        return [list(obj.shape), obj.tobytes()]
    raise TypeError(f"cannot encode {type_name(obj)}")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_array_to_wire)

_IMAGES: dict[type, tuple[str, ...]] = {}
"""The image fields of each message class encoded so far."""


def encode(msg: Message) -> bytes:
    """Encode a message into its msgpack envelope.

    Raises :class:`ProtocolError` if ``msg`` is not a protocol message or the payload would
    exceed :data:`MAX_PAYLOAD_BYTES`.
    """
    cls = type(msg)
    images = _IMAGES.get(cls)
    if images is None:
        if MESSAGE_TYPES.get(getattr(cls, "TYPE", None)) is not cls:  # type: ignore[arg-type]
            raise ProtocolError(f"encode: expected a protocol message, got {type_name(msg)}")
        images = _IMAGES[cls] = _WIRE[_body_type(cls)].images
    body: Any = msg  # a dataclass: msgspec writes its fields in order
    if images:
        body = {name: getattr(msg, name) for name in plan_of(cls).names}
        for name in images:
            image = body[name]
            body[name] = [list(image.shape), encode_image(image, msg.encoding, msg.quality)]  # type: ignore[attr-defined]
    payload = _ENCODER.encode({"t": cls.TYPE, "v": SCHEMA_VERSION, "b": body})
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ProtocolError(
            f"{cls.__name__}: encoded payload is {len(payload)} bytes, "
            f"more than MAX_PAYLOAD_BYTES = {MAX_PAYLOAD_BYTES}"
        )
    return payload


# ------------------------------------------------------------------------------------ decode


def _expected_types(expected: type | tuple[type, ...] | None) -> tuple[type, ...]:
    if expected is None:
        return tuple(MESSAGE_TYPES.values())
    types = expected if isinstance(expected, tuple) else (expected,)
    for t in types:
        if not (isinstance(t, type) and MESSAGE_TYPES.get(getattr(t, "TYPE", None)) is t):
            raise TypeError(f"decode: expected must be protocol message classes, got {t!r}")
    return types


_DECODERS: dict[Any, tuple[msgspec.msgpack.Decoder, tuple[type, ...]]] = {}
"""The decoder (and the types it takes) for each ``expected`` argument seen."""


def _decoder(expected: type | tuple[type, ...] | None) -> tuple[Any, tuple[type, ...]]:
    types = _expected_types(expected)  # raises TypeError for a bad ``expected``
    union = functools.reduce(operator.or_, map(_envelope_type, types))
    entry = (msgspec.msgpack.Decoder(union), types)
    _DECODERS[expected] = entry
    return entry


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
        decoder, types = _DECODERS[expected]
    except (KeyError, TypeError):  # not seen yet, or not hashable
        decoder, types = _decoder(expected)
    if type(payload) is not bytes or len(payload) > MAX_PAYLOAD_BYTES:
        if not isinstance(payload, bytes | bytearray | memoryview):
            raise ProtocolError(f"payload: expected bytes, got {type_name(payload)}")
        size = memoryview(payload).nbytes
        if size > MAX_PAYLOAD_BYTES:
            raise ProtocolError(
                f"payload: {size} bytes is more than MAX_PAYLOAD_BYTES = {MAX_PAYLOAD_BYTES}"
            )
    try:
        body = decoder.decode(payload).b
    except Exception as exc:  # msgspec's ValidationError, DecodeError, UnicodeDecodeError
        raise _refusal(payload, exc, types) from None
    wire = _WIRE[type(body)]
    try:
        return wire.record(body)
    except _RefusedError as e:
        raise ProtocolError(f"{wire.cls.__name__}{''.join(reversed(e.path))}: {e.text}") from None


def decode_saved(payload: bytes, expected: type[M]) -> M:
    """:func:`decode` for a message saved to a file by an earlier version: a body from before
    its type last changed is read with the fields added since set as :data:`FIELDS_ADDED`
    says it meant them; the payload's own refusal where that cannot be done."""
    try:
        return decode(payload, expected=expected)
    except ProtocolError as refusal:
        try:
            env = msgpack.unpackb(
                payload, raw=False, strict_map_key=True, ext_hook=_refuse_ext, **_UNPACK_LIMITS
            )
        except Exception:  # not msgpack at all: the refusal says so
            raise refusal from None
        if not (isinstance(env, dict) and isinstance(env.get("b"), dict)):
            raise refusal from None
        version, added = env.get("v"), FIELDS_ADDED.get(env.get("t"), {})
        if type(version) is not int or version < OLDEST_READ_VERSION:
            raise refusal from None
        since = [v for v in sorted(added) if v > version]
        if not since:
            raise refusal from None
        for v in since:
            for name, value in added[v].items():
                env["b"].setdefault(name, value)
        env["v"] = SCHEMA_VERSION
        return decode(msgpack.packb(env, use_bin_type=True), expected=expected)


def _refuse_ext(code: int, data: bytes) -> Any:
    raise ValueError(f"msgpack extension type {code} is not allowed")


def _refusal(payload: Any, exc: Exception, types: tuple[type, ...]) -> ProtocolError:
    """The ProtocolError saying why msgspec refused ``payload`` (with ``exc``)."""
    try:
        envelope = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, ext_hook=_refuse_ext, **_UNPACK_LIMITS
        )
    except Exception as e:  # msgpack raises several types for truncated or garbage input
        return ProtocolError(f"payload: not a valid msgpack document ({e})")
    if not isinstance(exc, msgspec.ValidationError):
        return ProtocolError(f"payload: not a valid msgpack document ({exc})")
    try:
        return _explain_envelope(envelope, exc, types)
    except Exception as e:  # a backstop: explaining must not raise another type
        return ProtocolError(f"payload: refused ({exc}; {type(e).__name__} explaining it)")


def _explain_envelope(envelope: Any, exc: Exception, types: tuple[type, ...]) -> ProtocolError:
    if not isinstance(envelope, dict):
        return ProtocolError(f"envelope: expected a map, got {type_name(envelope)}")
    if envelope.keys() != _ENVELOPE_KEYS:
        missing = sorted(_ENVELOPE_KEYS - envelope.keys())
        extra = [k for k in envelope if k not in _ENVELOPE_KEYS]
        return ProtocolError(
            f"envelope: expected keys ['b', 't', 'v'], missing {missing}, "
            f"unknown {short_repr(extra)}"
        )
    version = envelope["v"]
    if type(version) is not int or not OLDEST_READ_VERSION <= version <= SCHEMA_VERSION:
        return ProtocolError(
            f"envelope.v: unsupported schema version {short_repr(version)}, "
            f"this side speaks {SCHEMA_VERSION}"
        )
    tag = envelope["t"]
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        return ProtocolError(f"envelope.t: unknown message type {short_repr(tag)}")
    if version not in readable_versions(tag):
        return ProtocolError(
            f"envelope.v: a {tag} of schema version {version} is not read here: its fields "
            f"changed in {BODY_CHANGED_IN[tag]} (this side speaks {SCHEMA_VERSION})"
        )
    if cls not in types:
        names = ", ".join(t.__name__ for t in types)
        return ProtocolError(f"envelope.t: expected {names}, got {cls.__name__}")
    text, steps = path_of(exc)
    if steps[:1] != ["b"]:
        return ProtocolError(f"envelope: {text}")
    return explain_at(cls, envelope["b"], steps[1:], text, cls.__name__)


# ------------------------------------------------------------------------------ refusals


class _ClaimedBody(msgspec.Struct):
    program_id: Name


class _Claimed(msgspec.Struct):
    t: str
    b: _ClaimedBody


_CLAIMED = msgspec.msgpack.Decoder(_Claimed)


def claimed_program_id(payload: bytes) -> str | None:
    """The program id a program payload that :func:`decode` refused claims, if it claims a
    valid one (so that its refusal reaches the sender under that id); None otherwise. Reads
    only the envelope's type and the body's ``program_id``."""
    try:
        claimed = _CLAIMED.decode(payload)
    except (msgspec.MsgspecError, ValueError, TypeError, RecursionError):
        return None
    return claimed.b.program_id if claimed.t == MotionProgram.TYPE else None
