"""The codec's fast path: msgspec types derived from each record's ``_SPEC`` table.

The command path's own cost over bare zenoh was mostly Python run cold after each wake-up
(validation and message objects, not msgpack): msgspec decodes, checks types, ranges, lengths,
patterns and choices in one C call. Its contract with :mod:`protocol.codec`:

- :func:`fast_decode` returns a message only for a payload the reference decoder accepts, and then
  the same message; for anything else it returns ``None``, and the reference decoder decides and
  says what was wrong and where. ``tests/test_protocol_fast.py`` checks both against each other.
- :func:`fast_encode` produces the reference encoder's bytes.

Records with an image (``CameraFrame``) stay on the reference path: their cost is the image.
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from ._spec import (
    _FLOAT_MAX,
    ArrayField,
    Field,
    FloatField,
    ImageField,
    IntField,
    NestedField,
    StrField,
    TupleField,
    _all_finite,
    checker,
)
from .errors import ProtocolError
from .messages import MESSAGE_TYPES, SCHEMA_VERSION, Message


class _UnsupportedError(Exception):
    """A record this path does not handle (an image field, or arrays on a big-endian host)."""


def _accepts(check: Any, field: Field, value: Any) -> bool:
    try:
        check(field, value, "", False)
    except ProtocolError:
        return False
    return True


def _axis_type(lo: int, hi: int) -> Any:
    return Literal[lo] if lo == hi else Annotated[int, msgspec.Meta(ge=lo, le=hi)]


def _field_type(field: Field) -> Any:
    if isinstance(field, ImageField):
        raise _UnsupportedError
    if isinstance(field, IntField):
        return Annotated[int, msgspec.Meta(ge=field.lo, le=field.hi - 1)]
    if isinstance(field, FloatField):
        lo = -_FLOAT_MAX if field.lo is None else field.lo
        return Annotated[float, msgspec.Meta(ge=lo, le=_FLOAT_MAX)]
    if isinstance(field, StrField):
        if field.choices is not None:  # those the reference accepts (length, pattern) too
            check = checker(field)
            return Literal[tuple(c for c in field.choices if _accepts(check, field, c))]
        if field.pattern is None:
            return Annotated[str, msgspec.Meta(max_length=field.max_len)]
        # msgspec searches: anchored at both ends it is the reference's fullmatch (\Z, not $,
        # which would also match before a final newline).
        pattern = rf"^(?:{field.pattern})\Z"
        return Annotated[str, msgspec.Meta(max_length=field.max_len, pattern=pattern)]
    if isinstance(field, ArrayField):
        if field.dtype != field.dtype.newbyteorder("="):
            raise _UnsupportedError  # a big-endian host: the reference converts to native order
        shape = tuple[tuple(_axis_type(lo, hi) for lo, hi in field.shape)]  # type: ignore[misc]
        return tuple[shape, bytes]
    if isinstance(field, NestedField):
        return _body_type(field.cls)
    if isinstance(field, TupleField):
        items = list[_body_type(field.cls)]  # type: ignore[misc]
        return Annotated[items, msgspec.Meta(min_length=field.min_len, max_length=field.max_len)]
    raise TypeError(f"unknown field kind {field!r}")  # a bug in a spec table, not bad input


_CONVERTERS: dict[type, Any] = {}
"""For each body struct: the function that makes its record (``_converter``)."""


@functools.cache
def _body_type(cls: type) -> type:
    """The msgspec struct of record class ``cls``'s wire body (raises ``_UnsupportedError``)."""
    fields = [(name, _field_type(field)) for name, field in cls._SPEC.items()]
    body = msgspec.defstruct(f"{cls.__name__}Wire", fields, forbid_unknown_fields=True)
    _CONVERTERS[body] = _converter(cls)
    return body


def _converter(cls: type) -> Any:
    """A function from a decoded wire struct of record class ``cls`` to the record, generated
    from the spec: scalars as msgspec checked them, arrays checked by :func:`_array`, nested
    records converted in turn, and no re-validation.

    Why generated: a report's conversion, field by field in a loop, was as costly as msgspec's
    whole decode, and the command path runs it cold after each wake-up.
    """
    ns: dict[str, Any] = {
        "_cls": cls,
        "_new": object.__new__,
        "_setattr": object.__setattr__,
        "_array": _array,
        "_record": _record,
        "_tuple": tuple,
        "_map": map,
    }
    values = []
    for i, (name, field) in enumerate(cls._SPEC.items()):
        kind = type(field)
        ns[f"_field{i}"] = field
        if kind is ArrayField:
            value = f"_array(_field{i}, w.{name})"
        elif kind is NestedField:
            value = f"_record(w.{name})"
        elif kind is TupleField:
            value = f"_tuple(_map(_record, w.{name}))"
        else:
            value = f"w.{name}"
        values.append(f"{name!r}: {value}")
    source = (
        "def convert(w):\n"
        "    obj = _new(_cls)\n"
        f"    _setattr(obj, '__dict__', {{{', '.join(values)}}})\n"  # frozen: set, not assigned
        "    return obj\n"
    )
    exec(source, ns)  # generated from the spec table alone, as dataclasses do
    return ns["convert"]


@functools.cache
def _envelope_type(cls: type) -> type | None:
    """The struct of message class ``cls``'s envelope, its type tag in ``t``; ``None`` if this
    path does not handle ``cls``."""
    try:
        body = _body_type(cls)
    except _UnsupportedError:
        return None
    return msgspec.defstruct(
        f"{cls.__name__}Envelope",
        [("v", Literal[SCHEMA_VERSION]), ("b", body)],
        tag_field="t",
        tag=cls.TYPE,
        forbid_unknown_fields=True,
    )


def decoder(types: tuple[type, ...]) -> msgspec.msgpack.Decoder | None:
    """One decoder for the union of those message ``types`` this path handles, or ``None``."""
    handled = [e for e in map(_envelope_type, types) if e is not None]
    if not handled:
        return None
    return msgspec.msgpack.Decoder(functools.reduce(operator.or_, handled))


def _array(field: ArrayField, wire: tuple[tuple[int, ...], bytes]) -> np.ndarray:
    """The read-only array of ``wire`` (its shape already checked by msgspec); raises
    ``ValueError`` where the reference decoder would refuse it."""
    shape, data = wire
    if len(data) != math.prod(shape) * field.dtype.itemsize:
        raise ValueError("array data and shape disagree")
    arr = np.frombuffer(data, field.dtype)  # read-only: a view of bytes
    if len(shape) != 1:
        arr = arr.reshape(shape)
    if field.dtype.kind == "f" and not _all_finite(arr):
        raise ValueError("not finite")
    if field.check is not None and field.check(arr) is not None:
        raise ValueError("refused by the field's check")
    return arr


def _record(wire: Any) -> Any:
    """The record of a decoded wire struct, without re-validating what msgspec did."""
    return _CONVERTERS[type(wire)](wire)


def fast_decode(decoder: msgspec.msgpack.Decoder, payload: bytes) -> Message | None:
    """The message in ``payload`` if it is valid for ``decoder`` (from :func:`decoder`), else
    ``None``: the reference decoder then decides, and says what was wrong and where."""
    try:
        return _record(decoder.decode(payload).b)
    except Exception:
        return None


def _array_to_wire(arr: Any) -> Any:
    if isinstance(arr, np.ndarray):
        # A message's arrays are validated: native, and this path takes only little-endian hosts.
        return [list(arr.shape), arr.tobytes()]
    raise TypeError(f"cannot encode {type(arr).__name__}")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_array_to_wire)


_ENCODED_TYPES = frozenset(cls for cls in MESSAGE_TYPES.values() if _envelope_type(cls) is not None)


def fast_encode(msg: Any) -> bytes | None:
    """The envelope of message ``msg``, or ``None`` if ``msg`` is not a message (of exactly a
    registered class) this path handles."""
    if type(msg) not in _ENCODED_TYPES:
        return None
    # A record is a dataclass: msgspec writes its fields in order, the spec's order.
    return _ENCODER.encode({"t": msg.TYPE, "v": SCHEMA_VERSION, "b": msg})
