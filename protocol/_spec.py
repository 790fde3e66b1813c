"""Declarative field specifications and the one validator used by constructors and the decoder.

Each record class (message or nested value) carries ``_SPEC``: an ordered mapping from field name
to one of the field kinds below. ``check_field`` checks and normalises one field's value
against it; the codec derives the wire format from the same table.
"""

from __future__ import annotations

import functools
import math
import re
import reprlib
import sys
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar

import numpy as np

from .errors import ProtocolError

HOMOGENEOUS_ROW_TOL = 1e-9
"""Largest deviation of a pose's last row from ``[0, 0, 0, 1]`` (dimensionless)."""

ROTATION_ORTHONORMAL_TOL = 1e-6
"""Largest ``|RᵀR − I|`` entry accepted for a pose's rotation block (dimensionless)."""

UNIT_NORMAL_TOL = 1e-6
"""Largest ``| |n| − 1 |`` accepted for a unit normal vector (dimensionless)."""

SMALL_ARRAY_SIZE = 64
"""Arrays of at most this many elements are checked element by element in Python, which is
faster than numpy's per-call overhead at that size (a wrench, a pose)."""

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


# ----------------------------------------------------------------------------------- field kinds


@dataclass(frozen=True)
class IntField:
    """An ``int`` (never ``bool``) in ``[lo, hi)``."""

    lo: int
    hi: int


@dataclass(frozen=True)
class FloatField:
    """A finite ``float`` (``int`` accepted and converted), optionally ``>= lo``."""

    lo: float | None = None


@dataclass(frozen=True)
class StrField:
    """A ``str`` of at most ``max_len`` characters, optionally matching ``pattern`` (whole string)
    or one of ``choices``."""

    max_len: int
    pattern: str | None = None
    choices: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        compiled = re.compile(self.pattern) if self.pattern is not None else None
        object.__setattr__(self, "_compiled", compiled)


@dataclass(frozen=True)
class ArrayField:
    """A numpy array of ``dtype`` whose shape matches ``shape``: one ``(lo, hi)`` range per axis.

    ``check`` (optional) validates the converted array and returns an error text or ``None``.
    """

    shape: tuple[tuple[int, int], ...]
    dtype: np.dtype
    check: Callable[[np.ndarray], str | None] | None = None

    def __post_init__(self) -> None:
        fixed = all(lo == hi for lo, hi in self.shape)
        object.__setattr__(
            self, "_fixed_shape", tuple(lo for lo, _ in self.shape) if fixed else None
        )
        object.__setattr__(self, "_native", self.dtype.newbyteorder("="))

    def shape_text(self) -> str:
        """The expected shape as text, e.g. ``(6,)`` or ``(1..16, 3)``."""
        parts = [str(lo) if lo == hi else f"{lo}..{hi}" for lo, hi in self.shape]
        return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"

    def shape_ok(self, shape: tuple[int, ...]) -> bool:
        """Whether ``shape`` matches this field's shape ranges."""
        if self._fixed_shape is not None:  # type: ignore[attr-defined]
            return shape == self._fixed_shape  # type: ignore[attr-defined]
        return len(shape) == len(self.shape) and all(
            lo <= n <= hi for n, (lo, hi) in zip(shape, self.shape, strict=True)
        )


@dataclass(frozen=True)
class ImageField(ArrayField):
    """A grey image, an :class:`ArrayField` of uint8 (h, w) in memory, whose wire form is the
    image in the encoding named by the record's ``encoding_field`` (``protocol/images.py``),
    with the JPEG quality in its ``quality_field``."""

    encoding_field: str = "encoding"
    quality_field: str = "quality"


@dataclass(frozen=True)
class NestedField:
    """One nested record of class ``cls``."""

    cls: type


@dataclass(frozen=True)
class TupleField:
    """A tuple of ``min_len..max_len`` nested records of class ``cls``."""

    cls: type
    min_len: int
    max_len: int


Field = IntField | FloatField | StrField | ArrayField | ImageField | NestedField | TupleField

FLOAT64 = np.dtype("<f8")
UINT8 = np.dtype("u1")

# ------------------------------------------------------------------------------- array checks


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


# --------------------------------------------------------------------------------- validation


def _fail(where: str, text: str) -> ProtocolError:
    return ProtocolError(f"{where}: {text}")


def _check_int(spec: IntField, value: Any, where: str, owned: bool = False) -> int:
    if type(value) is int and spec.lo <= value < spec.hi:  # the common case, cheaply
        return value
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise _fail(where, f"expected int, got {type_name(value)}")
    value = int(value)
    if not spec.lo <= value < spec.hi:
        hi = "2**63" if spec.hi == 2**63 else str(spec.hi)
        raise _fail(where, f"must be in [{spec.lo}, {hi}), got {value}")
    return value


def _check_float(spec: FloatField, value: Any, where: str, owned: bool = False) -> float:
    if (
        type(value) is float and math.isfinite(value) and (spec.lo is None or value >= spec.lo)
    ):  # the common case, cheaply
        return value
    if isinstance(value, bool) or not isinstance(value, float | int | np.floating | np.integer):
        raise _fail(where, f"expected float, got {type_name(value)}")
    try:
        value = float(value)
    except OverflowError:  # an int too large for a float
        raise _fail(where, f"must be finite, got {short_repr(value)}") from None
    if not math.isfinite(value):
        raise _fail(where, f"must be finite, got {value!r}")
    if spec.lo is not None and not value >= spec.lo:
        raise _fail(where, f"must be >= {spec.lo!r}, got {value!r}")
    return value


def _check_str(spec: StrField, value: Any, where: str, owned: bool = False) -> str:
    if not isinstance(value, str):
        raise _fail(where, f"expected str, got {type_name(value)}")
    if len(value) > spec.max_len:
        raise _fail(where, f"must be at most {spec.max_len} characters, got {len(value)}")
    if spec.choices is not None and value not in spec.choices:
        raise _fail(where, f"must be one of {list(spec.choices)}, got {short_repr(value)}")
    compiled: re.Pattern[str] | None = spec._compiled  # type: ignore[attr-defined]
    if compiled is not None and compiled.fullmatch(value) is None:
        raise _fail(where, f"must match {spec.pattern}, got {short_repr(value)}")
    if not value.isascii():  # an ASCII string cannot hold a lone surrogate: skip the encoding
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise _fail(where, "is not encodable as UTF-8 (lone surrogate)") from None
    return value


def _all_finite(arr: np.ndarray) -> bool:
    if arr.size <= SMALL_ARRAY_SIZE:
        return all(map(math.isfinite, arr.ravel().tolist()))
    return bool(np.isfinite(arr).all())


def _check_array(spec: ArrayField, value: Any, where: str, owned: bool = False) -> np.ndarray:
    if isinstance(value, np.ndarray):
        arr = value
    elif isinstance(value, list | tuple):
        try:
            arr = np.asarray(value)
        except (ValueError, TypeError, OverflowError):
            raise _fail(where, "expected a rectangular array of numbers") from None
    else:
        raise _fail(where, f"expected array, got {type_name(value)}")
    if not spec.shape_ok(arr.shape):
        raise _fail(where, f"expected shape {spec.shape_text()}, got {tuple(arr.shape)}")
    native: np.dtype = spec._native  # type: ignore[attr-defined]
    if arr.dtype != native:
        kind = arr.dtype.kind
        if native == UINT8:
            if kind not in "iu":
                raise _fail(where, f"expected uint8 array, got dtype {arr.dtype}")
            if arr.size and (arr.min() < 0 or arr.max() > 255):
                raise _fail(where, "integer values must be in [0, 255] for a uint8 array")
        elif kind not in "fiu":
            raise _fail(where, f"expected float64 array, got dtype {arr.dtype}")
        arr = np.array(arr, dtype=native, order="C", copy=True)
    elif not owned or not arr.flags.c_contiguous:
        arr = np.array(arr, order="C", copy=True)
    if native.kind == "f" and not _all_finite(arr):
        raise _fail(where, "all elements must be finite (no NaN or inf)")
    if spec.check is not None:
        text = spec.check(arr)
        if text is not None:
            raise _fail(where, text)
    arr.setflags(write=False)
    return arr


def _check_nested(spec: NestedField, value: Any, where: str, owned: bool = False) -> Any:
    if not isinstance(value, spec.cls):
        raise _fail(where, f"expected {spec.cls.__name__}, got {type_name(value)}")
    return value


def _check_tuple(spec: TupleField, value: Any, where: str, owned: bool = False) -> tuple[Any, ...]:
    if not isinstance(value, tuple | list):
        raise _fail(where, f"expected tuple of {spec.cls.__name__}, got {type_name(value)}")
    if not spec.min_len <= len(value) <= spec.max_len:
        raise _fail(where, f"must have {spec.min_len}..{spec.max_len} items, got {len(value)}")
    for i, item in enumerate(value):
        if not isinstance(item, spec.cls):
            raise _fail(f"{where}[{i}]", f"expected {spec.cls.__name__}, got {type_name(item)}")
    return tuple(value)


Checker = Callable[[Any, Any, str, bool], Any]
"""``(spec, value, where, owned) -> normalised value``; raises :class:`ProtocolError` naming
``where``. ``owned``: an array value is ours (fresh from the decoder), so need not be copied."""

_CHECKS: dict[type, Checker] = {
    IntField: _check_int,
    FloatField: _check_float,
    StrField: _check_str,
    ArrayField: _check_array,
    ImageField: _check_array,
    NestedField: _check_nested,
    TupleField: _check_tuple,
}
"""The validator of each field kind, looked up by the spec's exact type."""


def checker(spec: Field) -> Checker:
    """The validator of field ``spec`` (look it up once per field: validation runs for every
    field of every message, on the command path, where each layer of calls showed)."""
    check = _CHECKS.get(type(spec))
    if check is None:
        raise TypeError(f"unknown field kind {spec!r}")  # a bug in a spec table, not bad input
    return check


def check_field(spec: Field, value: Any, where: str, owned: bool = False) -> Any:
    """Validate one field value and return its normalised form (read-only arrays, tuples).

    ``owned``: the array is ours (fresh from the decoder), so it need not be copied.
    """
    return checker(spec)(spec, value, where, owned)


@functools.cache
def _field_checks(cls: type) -> tuple[tuple[str, Field, Checker, str], ...]:
    """``(name, spec, checker, where)`` of each field of record class ``cls``."""
    return tuple(
        (name, spec, checker(spec), f"{cls.__name__}.{name}") for name, spec in cls._SPEC.items()
    )


class Record:
    """Base of all wire records: validates and normalises its fields after construction."""

    _SPEC: ClassVar[Mapping[str, Field]]

    def __post_init__(self) -> None:
        # The reference validation: the message classes get a generated __init__ that does the
        # same in one function (install_validating_init); this runs for any other record.
        values = self.__dict__  # frozen: write the normalised values where __init__ put them
        for name, spec, check, where in _field_checks(type(self)):
            values[name] = check(spec, values[name], where, False)

    @classmethod
    def _from_validated(cls, values: Mapping[str, Any]) -> Any:
        """Build an instance from already validated values (used by the decoder)."""
        obj = object.__new__(cls)
        for name, value in values.items():
            object.__setattr__(obj, name, value)
        return obj


def check_spec_matches_fields(cls: type) -> None:
    """Assert at import time that a record's spec names exactly its dataclass fields, in order."""
    names = tuple(f.name for f in fields(cls))
    spec_names = tuple(cls._SPEC)  # type: ignore[attr-defined]
    if names != spec_names:
        raise TypeError(f"{cls.__name__}: spec fields {spec_names} != dataclass fields {names}")


_FLOAT_MAX = sys.float_info.max
"""Bounds every float field with ±this (the generated constructors, msgspec's types), which is
what refuses NaN (no comparison holds) and ±inf: the reference accepts finite floats only."""

REFERENCE_INITS: dict[type, Callable[..., None]] = {}
"""Each record class's dataclass ``__init__`` (which runs ``Record.__post_init__``), kept when
:func:`install_validating_init` replaces it: the reference the tests hold the generated one to."""


def _common_case(spec: Field, name: str, i: int, ns: dict[str, Any]) -> str | None:
    """A Python condition, true unless ``name``'s value is a common valid one that its checker
    would return unchanged; ``None`` where there is no such shortcut. Names the condition needs
    go into ``ns``, suffixed with ``i``."""
    kind = type(spec)
    if kind is IntField:
        return f"type({name}) is not int or not {spec.lo} <= {name} < {spec.hi}"
    if kind is FloatField:
        # Comparisons with ±max float refuse NaN and ±inf, as the checker does.
        ns[f"_lo{i}"] = -_FLOAT_MAX if spec.lo is None else spec.lo
        return f"type({name}) is not float or not _lo{i} <= {name} <= _FLOAT_MAX"
    if kind is StrField:
        # An ASCII string is UTF-8 encodable; any other goes to the checker, which tests that.
        cond = f"type({name}) is not str or len({name}) > {spec.max_len} or not {name}.isascii()"
        if spec.choices is not None:
            ns[f"_choices{i}"] = frozenset(spec.choices)
            cond += f" or {name} not in _choices{i}"
        if spec._compiled is not None:  # type: ignore[attr-defined]
            ns[f"_match{i}"] = spec._compiled.fullmatch  # type: ignore[attr-defined]
            cond += f" or _match{i}({name}) is None"
        return cond
    if kind is NestedField:
        ns[f"_cls{i}"] = spec.cls
        return f"type({name}) is not _cls{i}"
    return None


def _field_lines(spec: Field, name: str, i: int, ns: dict[str, Any], where: str) -> str:
    """The generated ``__init__``'s lines that validate argument ``name`` in place."""
    ns[f"_spec{i}"], ns[f"_check{i}"] = spec, checker(spec)
    check = f"{name} = _check{i}(_spec{i}, {name}, {where!r}, False)"
    fixed = getattr(spec, "_fixed_shape", None)
    if (
        type(spec) is ArrayField
        and fixed is not None
        and spec._native.kind == "f"  # type: ignore[attr-defined]
        and math.prod(fixed) <= SMALL_ARRAY_SIZE
    ):
        # A native float array of the fixed shape: copied, checked finite (and by the field's
        # own check) here; the checker runs only to say what is wrong.
        ns[f"_dtype{i}"], ns[f"_shape{i}"] = spec._native, fixed  # type: ignore[attr-defined]
        invalid = f"not _all(_map(_isfinite, {name}.ravel().tolist()))"
        if spec.check is not None:
            ns[f"_valid{i}"] = spec.check
            invalid += f" or _valid{i}({name}) is not None"
        return (
            f"    if type({name}) is _ndarray and {name}.dtype == _dtype{i}"
            f" and {name}.shape == _shape{i}:\n"
            f"        {name} = {name}.copy()\n"
            f"        if {invalid}:\n"
            f"            {check}\n"
            f"        {name}.setflags(write=False)\n"
            f"    else:\n"
            f"        {check}"
        )
    cond = _common_case(spec, name, i, ns)
    return f"    if {cond}:\n        {check}" if cond else f"    {check}"


def install_validating_init(cls: type) -> None:
    """Give record class ``cls`` a generated ``__init__`` that validates as ``__post_init__``
    does, with the same errors, in one function: the common valid values of scalars and nested
    records are recognised inline, every other value goes to its field's checker.

    Why: constructing a report took ~4 µs warm and ~18 µs on the command path, run cold after
    each wake-up, where most of it was the calls of the dataclass's ``__init__``, the loop of
    ``__post_init__`` and the checkers' own calls.
    """
    check_spec_matches_fields(cls)
    spec_table: Mapping[str, Field] = cls._SPEC  # type: ignore[attr-defined]
    ns: dict[str, Any] = {
        "_FLOAT_MAX": _FLOAT_MAX,
        "_setattr": object.__setattr__,
        "_ndarray": np.ndarray,
        "_all": all,
        "_map": map,
        "_isfinite": math.isfinite,
    }
    params, lines = [], []
    for i, field in enumerate(fields(cls)):
        if field.default is not MISSING:
            ns[f"_default{i}"] = field.default
            params.append(f"{field.name}=_default{i}")
        elif field.default_factory is not MISSING:
            raise TypeError(f"{cls.__name__}.{field.name}: default_factory is not supported")
        else:
            params.append(field.name)
    for i, (name, spec) in enumerate(spec_table.items()):
        lines.append(_field_lines(spec, name, i, ns, f"{cls.__name__}.{name}"))
    values = ", ".join(f"{name!r}: {name}" for name in spec_table)
    source = (
        f"def __init__(self, {', '.join(params)}):\n"
        + "\n".join(lines)
        + f"\n    _setattr(self, '__dict__', {{{values}}})\n"  # frozen: as the decoder does
    )
    exec(source, ns)  # generated from the spec table alone, as dataclasses do
    init = ns["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    REFERENCE_INITS[cls] = cls.__init__  # type: ignore[misc]
    init.__doc__ = cls.__init__.__doc__
    cls.__init__ = init  # type: ignore[misc]
