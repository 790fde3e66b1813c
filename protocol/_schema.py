"""Field types of the wire records, and the one validation of them.

A record (a frozen dataclass deriving from :class:`Record`) declares each field once, as an
annotation: msgspec's own constrained types for scalars (``Annotated[int, Meta(...)]``,
``Annotated[float, FINITE]``, ``Annotated[str, Meta(...)]``, ``Literal[...]``),
``Annotated[np.ndarray, Array(...)]`` for arrays and ``Annotated[tuple[R, ...], Meta(...)]`` for
nested records. msgspec enforces what its types express, in C, both when a payload is decoded
(``protocol/codec.py``) and when a record is constructed (``msgspec.convert``);
:func:`array_problem` does what msgspec cannot (shape ranges, dtype, finite elements, rigid
transforms, unit normals, intrinsics), the same for both. :func:`explain` only words a refusal
msgspec has already made: it never decides whether a value is valid.
"""

from __future__ import annotations

import functools
import math
import re
import reprlib
import sys
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from .errors import ProtocolError

HOMOGENEOUS_ROW_TOL = 1e-9
"""Largest deviation of a pose's last row from ``[0, 0, 0, 1]`` (dimensionless)."""

ROTATION_ORTHONORMAL_TOL = 1e-6
"""Largest ``|RᵀR − I|`` entry accepted for a pose's rotation block (dimensionless)."""

UNIT_NORMAL_TOL = 1e-6
"""Largest ``| |n| − 1 |`` accepted for a unit normal vector (dimensionless)."""

FLOAT_MAX = sys.float_info.max
FINITE = msgspec.Meta(ge=-FLOAT_MAX, le=FLOAT_MAX)
"""A finite float: no comparison holds for NaN, and ±inf is beyond ±``FLOAT_MAX``."""
NON_NEGATIVE = msgspec.Meta(ge=0.0, le=FLOAT_MAX)
"""A finite float ≥ 0."""

FLOAT64 = np.dtype("<f8")
UINT8 = np.dtype("u1")

SMALL_ARRAY_SIZE = 64
"""Arrays of at most this many elements are checked element by element in Python, which is
faster than numpy's per-call overhead at that size (a wrench, a pose)."""


def anchored(pattern: str) -> str:
    """``pattern`` as msgspec must get it to match a whole string (msgspec searches; ``\\Z``,
    unlike ``$``, does not match before a final newline)."""
    return rf"^(?:{pattern})\Z"


_repr = reprlib.Repr()
_repr.maxstring = 40
_repr.maxother = 40
_repr.maxlist = 6


def short_repr(value: object) -> str:
    """A bounded-length repr for error messages (never echoes a whole payload)."""
    return _repr.repr(value)


def type_name(value: object) -> str:
    """The value's type name for error messages."""
    return type(value).__name__


# ------------------------------------------------------------------------------------ arrays


@dataclass(frozen=True)
class Array:
    """An array field: ``shape`` gives each axis as a size or an inclusive ``(lo, hi)`` range,
    ``dtype`` is the wire's (little-endian) and the in-memory one; ``check`` (optional) returns
    an error text for a finite array of the right shape, or ``None``."""

    shape: tuple[int | tuple[int, int], ...]
    dtype: np.dtype = FLOAT64
    check: Callable[[np.ndarray], str | None] | None = None
    ranges: tuple[tuple[int, int], ...] = field(init=False, repr=False, compare=False)
    fixed_shape: tuple[int, ...] | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ranges = tuple((n, n) if isinstance(n, int) else n for n in self.shape)
        object.__setattr__(self, "ranges", ranges)
        fixed = tuple(lo for lo, hi in ranges) if all(lo == hi for lo, hi in ranges) else None
        object.__setattr__(self, "fixed_shape", fixed)

    def shape_text(self) -> str:
        """The expected shape as text, e.g. ``(6,)`` or ``(1..16, 3)``."""
        parts = [str(lo) if lo == hi else f"{lo}..{hi}" for lo, hi in self.ranges]
        return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"

    def shape_ok(self, shape: tuple[int, ...]) -> bool:
        if shape == self.fixed_shape:
            return True
        return len(shape) == len(self.ranges) and all(
            lo <= n <= hi for n, (lo, hi) in zip(shape, self.ranges, strict=True)
        )


@dataclass(frozen=True)
class Image(Array):
    """A grey image (h, w) uint8 in memory, whose wire bytes are in the record's ``encoding``
    field's encoding (``protocol/images.py``), at its ``quality`` field's JPEG quality."""

    dtype: np.dtype = UINT8


def all_finite(arr: np.ndarray) -> bool:
    """Whether every element of a float array is finite."""
    if arr.size <= SMALL_ARRAY_SIZE:
        return all(map(math.isfinite, arr.ravel().tolist()))
    return bool(np.isfinite(arr).all())


def check_pose(X: np.ndarray) -> str | None:
    """Error text if the finite ``X`` (4, 4) is not a rigid transform, else ``None``."""
    (r00, r01, r02, _), (r10, r11, r12, _), (r20, r21, r22, _), last = X.tolist()
    if max(abs(last[0]), abs(last[1]), abs(last[2]), abs(last[3] - 1.0)) > HOMOGENEOUS_ROW_TOL:
        return f"last row must be [0, 0, 0, 1] (within {HOMOGENEOUS_ROW_TOL:g}), got {last}"
    R_max = max(map(abs, (r00, r01, r02, r10, r11, r12, r20, r21, r22)))
    if R_max > 1.0 + ROTATION_ORTHONORMAL_TOL:  # also keeps RᵀR from overflowing
        return f"rotation block is not orthonormal: max |R_ij| = {R_max:.3g} > 1"
    orth_err = max(  # the entries of RᵀR − I (symmetric: six of them)
        abs(r00 * r00 + r10 * r10 + r20 * r20 - 1.0),
        abs(r01 * r01 + r11 * r11 + r21 * r21 - 1.0),
        abs(r02 * r02 + r12 * r12 + r22 * r22 - 1.0),
        abs(r00 * r01 + r10 * r11 + r20 * r21),
        abs(r00 * r02 + r10 * r12 + r20 * r22),
        abs(r01 * r02 + r11 * r12 + r21 * r22),
    )
    if orth_err > ROTATION_ORTHONORMAL_TOL:
        return (
            f"rotation block is not orthonormal: max |RᵀR − I| = {orth_err:.3g} "
            f"> {ROTATION_ORTHONORMAL_TOL:g}"
        )
    det = (
        r00 * (r11 * r22 - r12 * r21)
        - r01 * (r10 * r22 - r12 * r20)
        + r02 * (r10 * r21 - r11 * r20)
    )
    if det <= 0.0:
        return f"rotation block has determinant {det:.6g}, expected +1 (a reflection)"
    return None


def check_unit_rows(n: np.ndarray) -> str | None:
    """Error text if some row of the finite ``n`` (k, 3) is not a unit vector, else ``None``."""
    for i, row in enumerate(n.tolist()):
        if max(map(abs, row)) > 1.0 + UNIT_NORMAL_TOL:  # also keeps the norm from overflowing
            return f"row {i} is not a unit vector (an entry exceeds 1 in magnitude)"
        err = abs(math.hypot(*row) - 1.0)
        if err > UNIT_NORMAL_TOL:
            return f"row {i} is not a unit vector (| |n| − 1 | = {err:.3g} > {UNIT_NORMAL_TOL:g})"
    return None


def check_camera_matrix(K: np.ndarray) -> str | None:
    """Error text if ``K`` (3, 3) is not ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, fx, fy > 0."""
    (fx, _, _), (k10, fy, _), (k20, k21, k22) = K.tolist()
    if k10 != 0.0 or k20 != 0.0 or k21 != 0.0 or k22 != 1.0:
        return f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
    if not (fx > 0.0 and fy > 0.0):
        return f"focal lengths fx, fy must be > 0, got {fx!r}, {fy!r}"
    return None


def array_problem(spec: Array, arr: np.ndarray) -> str | None:
    """What is wrong with ``arr`` (already of ``spec``'s dtype and shape), or ``None``: the
    checks msgspec cannot express, the same for decoded and constructed records."""
    if spec.dtype.kind == "f" and not all_finite(arr):
        return "all elements must be finite (no NaN or inf)"
    return spec.check(arr) if spec.check is not None else None


def array_from_python(spec: Array, value: Any, where: str) -> np.ndarray:
    """A read-only copy of a caller's array-like ``value`` as ``spec`` says, or ProtocolError."""
    if type(value) is np.ndarray and value.dtype == spec.dtype and value.shape == spec.fixed_shape:
        arr = value.copy()  # the common case, with fewer calls: a C-order copy
    else:
        arr = _as_array(spec, value, where)
    if (text := array_problem(spec, arr)) is not None:
        raise ProtocolError(f"{where}: {text}")
    arr.setflags(write=False)
    return arr


def _as_array(spec: Array, value: Any, where: str) -> np.ndarray:
    """A C-order copy of ``value`` of ``spec``'s shape and dtype, or ProtocolError."""
    if isinstance(value, np.ndarray):
        arr = value
    elif isinstance(value, list | tuple):
        try:
            arr = np.asarray(value)
        except (ValueError, TypeError, OverflowError):
            raise ProtocolError(f"{where}: expected a rectangular array of numbers") from None
    else:
        raise ProtocolError(f"{where}: expected array, got {type_name(value)}")
    if not spec.shape_ok(arr.shape):
        raise ProtocolError(f"{where}: expected shape {spec.shape_text()}, got {arr.shape}")
    if arr.dtype != spec.dtype:
        kind = arr.dtype.kind
        if spec.dtype == UINT8:
            if kind not in "iu":
                raise ProtocolError(f"{where}: expected uint8 array, got dtype {arr.dtype}")
            if arr.size and (arr.min() < 0 or arr.max() > 255):
                raise ProtocolError(
                    f"{where}: integer values must be in [0, 255] for a uint8 array"
                )
        elif kind not in "fiu":
            raise ProtocolError(f"{where}: expected float64 array, got dtype {arr.dtype}")
    return np.array(arr, dtype=spec.dtype, order="C")  # always a copy: never the caller's array


# ----------------------------------------------------------------------------------- records

SCALAR, ARRAY, IMAGE, RECORDS = "scalar", "array", "image", "records"


@dataclass(frozen=True)
class FieldInfo:
    """One field of a record class, as its annotation declares it."""

    name: str
    hint: Any
    kind: str
    array: Array | None = None
    item: type | None = None  # RECORDS: the nested record class

    @functools.cached_property
    def meta(self) -> msgspec.Meta:
        """The field's constraints (all of its ``Meta`` merged)."""
        merged: dict[str, Any] = {}
        if typing.get_origin(self.hint) is Annotated:
            for m in typing.get_args(self.hint)[1:]:
                if isinstance(m, msgspec.Meta):
                    merged.update(
                        {k: getattr(m, k) for k in _META_KEYS if getattr(m, k) is not None}
                    )
        return msgspec.Meta(**merged)

    @functools.cached_property
    def base(self) -> Any:
        """The annotation without ``Annotated``: ``int``, ``float``, ``str``, a ``Literal``…"""
        hint = self.hint
        return typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint


_META_KEYS = ("ge", "gt", "le", "lt", "min_length", "max_length", "pattern")


def _field_info(name: str, hint: Any) -> FieldInfo:
    if typing.get_origin(hint) is Annotated:
        base, *extras = typing.get_args(hint)
        for extra in extras:
            if isinstance(extra, Array):
                return FieldInfo(name, hint, IMAGE if isinstance(extra, Image) else ARRAY, extra)
        if typing.get_origin(base) is tuple:
            item, ellipsis = typing.get_args(base)
            assert ellipsis is Ellipsis, f"{name}: tuples are tuple[T, ...]"
            if isinstance(item, type) and issubclass(item, Record):
                return FieldInfo(name, hint, RECORDS, item=item)
            # A tuple of scalars (names): msgspec checks it whole, items' constraints too.
    return FieldInfo(name, hint, SCALAR)


class Record:
    """Base of all wire records (frozen dataclasses): validated on construction, so no site can
    build an invalid one; arrays are stored as read-only copies."""

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class Plan:
    """What validation needs of one record class, worked out once from its annotations."""

    cls: type
    fields: tuple[FieldInfo, ...]

    @functools.cached_property
    def by_name(self) -> Mapping[str, FieldInfo]:
        return {f.name: f for f in self.fields}

    @functools.cached_property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @functools.cached_property
    def values_type(self) -> type:
        """The msgspec struct of the fields msgspec checks on construction (all but arrays)."""
        return msgspec.defstruct(
            f"{self.cls.__name__}Values",
            [(f.name, f.hint) for f in self.fields if f.array is None],
        )

    @functools.cached_property
    def checked_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields if f.array is None)

    @functools.cached_property
    def texts(self) -> tuple[str, ...]:
        """The str fields (msgspec does not check that a str is encodable as UTF-8)."""
        return tuple(f.name for f in self.fields if f.kind == SCALAR and _is_str(f.base))

    @functools.cached_property
    def arrays(self) -> tuple[tuple[str, Array, str], ...]:
        """``(name, spec, where)`` of each array field."""
        name = self.cls.__name__
        return tuple(
            (f.name, f.array, f"{name}.{f.name}") for f in self.fields if f.array is not None
        )


def _is_str(base: Any) -> bool:
    return base is str or typing.get_origin(base) is Literal


@functools.cache
def plan_of(cls: type) -> Plan:
    """The :class:`Plan` of record class ``cls``."""
    hints = typing.get_type_hints(cls, include_extras=True)
    return Plan(cls, tuple(_field_info(f.name, hints[f.name]) for f in fields(cls)))


def validate(record: Any) -> None:
    """Check and normalise a freshly constructed record's fields in place (ints to floats,
    lists to tuples, array-likes to read-only arrays), or raise ProtocolError naming the
    field. Called by :meth:`Record.__post_init__`."""
    plan = plan_of(type(record))
    values = record.__dict__  # frozen: write the normalised values where __init__ put them
    try:
        checked = msgspec.convert(values, plan.values_type)
    except Exception as exc:  # ValidationError; UnicodeEncodeError quoting a lone surrogate
        checked = _convert_numpy_scalars(plan, values, exc)
    values.update(msgspec.structs.asdict(checked))
    for name in plan.texts:
        # msgspec hands a str subclass (numpy's str_, a caller's own) back as it came for a
        # str field but a plain str for a Literal one: every text field is a plain str.
        if type(values[name]) is not str:
            values[name] = str.__str__(values[name])
        if not values[name].isascii() and not _utf8(values[name]):
            where = f"{plan.cls.__name__}.{name}"
            raise ProtocolError(f"{where}: is not encodable as UTF-8 (lone surrogate)")
    for name, spec, where in plan.arrays:
        values[name] = array_from_python(spec, values[name], where)


def _convert_numpy_scalars(plan: Plan, values: dict[str, Any], exc: Exception) -> Any:
    """Retry with numpy scalars (which msgspec refuses) as the Python ones they stand for."""
    plain = {k: v.item() if isinstance(v, np.generic) else v for k, v in values.items()}
    if any(plain[k] is not values[k] for k in plan.checked_names):
        try:
            return msgspec.convert(plain, plan.values_type)
        except Exception as again:
            exc = again
    raise explain(plan.cls, values, exc, plan.cls.__name__) from None


# ------------------------------------------------------------------------------ explanations


def path_of(exc: Exception) -> tuple[str, list[str | int]]:
    """msgspec's message without its location, and the location as field names and indices
    (``"… - at `$.commands[1].X_WP`"`` → ``["commands", 1, "X_WP"]``)."""
    text, sep, path = str(exc).rpartition(" - at `")
    if not sep:
        return str(exc), []
    steps = re.findall(r"\.([A-Za-z_]\w*)|\[(\d+)\]", path.rstrip("`")[1:])
    return text, [name or int(index) for name, index in steps]


def explain(cls: type, value: Any, exc: Exception, where: str) -> ProtocolError:
    """The ProtocolError for msgspec's refusal ``exc`` of record ``value`` of class ``cls`` (a
    decoded map, or a constructor's field values): what was wrong and where, e.g.
    ``MotionProgram.commands[1].speed_mps: must be >= 0.0, got -1.0``."""
    text, steps = path_of(exc)
    return explain_at(cls, value, steps, text, where)


def explain_at(
    cls: type, value: Any, steps: list[str | int], fallback: str, where: str
) -> ProtocolError:
    """:func:`explain` for a refusal at ``steps`` below ``value``; ``fallback`` (msgspec's
    own words) if the value there shows nothing wrong."""
    record: type | None = cls
    field: FieldInfo | None = None
    for step in steps:
        if record is not None:
            if not isinstance(step, str) or _record_problem(record, value) is not None:
                break
            field = plan_of(record).by_name.get(step)
            if field is None:
                break
            value = value[step] if isinstance(value, dict) else getattr(value, step)
            where, record = f"{where}.{step}", None
            if field.kind != RECORDS:
                break
        else:
            assert field is not None
            if not isinstance(step, int) or _field_problem(field, value) is not None:
                break
            if not 0 <= step < len(value):
                break
            value, where, record, field = value[step], f"{where}[{step}]", field.item, None
    if record is not None:
        problem = _record_problem(record, value)
        if problem is None and isinstance(value, dict) and not steps:  # no place: look for one
            for f in plan_of(record).fields:
                if f.array is None and (problem := _field_problem(f, value[f.name])) is not None:
                    where = f"{where}.{f.name}"
                    break
    else:
        assert field is not None
        problem = _field_problem(field, value)
    return ProtocolError(f"{where}: {problem or fallback}")


def _record_problem(cls: type, value: Any) -> str | None:
    if isinstance(value, cls):
        return None
    if not isinstance(value, dict):
        return f"expected {cls.__name__}, got {type_name(value)}"
    names = plan_of(cls).names
    missing = [name for name in names if name not in value]
    if missing:
        return f"missing field(s) {missing}"
    extra = [key for key in value if key not in names]
    return f"unknown field(s) {short_repr(extra)}" if extra else None


def _field_problem(field: FieldInfo, value: Any) -> str | None:
    if field.kind == RECORDS:
        assert field.item is not None
        if not isinstance(value, list | tuple):
            return f"expected a sequence of {field.item.__name__}, got {type_name(value)}"
        lo, hi = field.meta.min_length or 0, field.meta.max_length
        if not lo <= len(value) <= hi:
            return f"must have {lo}..{hi} items, got {len(value)}"
        return None
    if field.array is not None:
        return _wire_array_problem(field.array, value)
    base, meta = field.base, field.meta
    if typing.get_origin(base) is Literal:
        choices = list(typing.get_args(base))
        if not isinstance(value, str):
            return f"expected str, got {type_name(value)}"
        return None if value in choices else f"must be one of {choices}, got {short_repr(value)}"
    if base is bool:
        return (
            None if isinstance(value, bool | np.bool_) else f"expected bool, got {type_name(value)}"
        )
    if base is int:
        return _int_problem(meta, value)
    if base is float:
        return _float_problem(meta, value)
    if base is str:
        return _str_problem(meta, value)
    if typing.get_origin(base) is tuple:  # a tuple of scalars (names), msgspec's to check
        if not isinstance(value, list | tuple):
            return f"expected array, got {type_name(value)}"
        if meta.max_length is not None and len(value) > meta.max_length:
            return f"must have at most {meta.max_length} items, got {len(value)}"
        item = FieldInfo(field.name, typing.get_args(base)[0], SCALAR)
        for k, v in enumerate(value):
            if (problem := _field_problem(item, v)) is not None:
                return f"item {k}: {problem}"
    return None


def _int_problem(meta: msgspec.Meta, value: Any) -> str | None:
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        return f"expected int, got {type_name(value)}"
    lo = meta.ge if meta.ge is not None else meta.gt + 1 if meta.gt is not None else None
    hi = meta.lt if meta.lt is not None else meta.le + 1 if meta.le is not None else None
    if (lo is not None and value < lo) or (hi is not None and value >= hi):
        hi_text = "2**63" if hi == 2**63 else str(hi)
        return f"must be in [{lo}, {hi_text}), got {int(value)}"
    return None


def _float_problem(meta: msgspec.Meta, value: Any) -> str | None:
    if isinstance(value, bool | np.bool_) or not isinstance(
        value, float | int | np.floating | np.integer
    ):
        return f"expected float, got {type_name(value)}"
    try:
        number = float(value)
    except OverflowError:  # an int too large for a float
        return f"must be finite, got {short_repr(value)}"
    if not math.isfinite(number):
        return f"must be finite, got {number!r}"
    if meta.ge is not None and meta.ge != -FLOAT_MAX and not number >= meta.ge:
        return f"must be >= {meta.ge!r}, got {number!r}"
    return None


def _str_problem(meta: msgspec.Meta, value: Any) -> str | None:
    if not isinstance(value, str):
        return f"expected str, got {type_name(value)}"
    if meta.max_length is not None and len(value) > meta.max_length:
        return f"must be at most {meta.max_length} characters, got {len(value)}"
    if meta.pattern is not None and re.search(meta.pattern, value) is None:
        shown = meta.pattern.removeprefix("^(?:").removesuffix(r")\Z")
        return f"must match {shown}, got {short_repr(value)}"
    return None if _utf8(value) else "is not encodable as UTF-8 (lone surrogate)"


def _utf8(text: str) -> bool:
    if text.isascii():  # an ASCII string cannot hold a lone surrogate: skip the encoding
        return True
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _wire_array_problem(spec: Array, value: Any) -> str | None:
    """What is wrong with the form of a decoded array ``[shape, data]``, or ``None``."""
    if not isinstance(value, list | tuple) or len(value) != 2:
        return f"expected array as [shape, data], got {type_name(value)}"
    shape, data = value
    if not isinstance(shape, list | tuple) or not all(type(n) is int and n >= 0 for n in shape):
        return f"array shape must be a list of non-negative ints, got {short_repr(shape)}"
    if not spec.shape_ok(tuple(shape)):
        return f"expected shape {spec.shape_text()}, got {tuple(shape)}"
    if not isinstance(data, bytes):
        return f"array data must be bytes, got {type_name(data)}"
    return None
