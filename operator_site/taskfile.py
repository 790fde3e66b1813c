"""Task files: a contact task as data, loadable by the page, the command line and the tests.

A task names the workpiece, the reference object its poses are expressed in, the operator's drag
targets in order (with the captures and releases made at each), and the goal the work site must
reach. Poses are the workpiece's model frame O in the reference's model frame R, written as a
position in metres and URDF roll-pitch-yaw in degrees. The format is documented in
``docs/tasks.md``; this module is its only reader and writer.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.transforms import R_to_rpy, make_pose, rpy_to_R, so3_log

TASK_FORMAT_VERSION = 1
"""The ``"task"`` field of files this module reads and writes."""

MAX_STEPS = 10_000
"""Drag targets a task may hold: far beyond any demonstration, small enough to load at once."""

MAX_COORDINATE_M = 10.0
"""Largest |coordinate| of a pose relative to its reference: the work cell is about 1 m across."""

MAX_NAME_CHARS = 200
"""Longest task or object name accepted."""

TOLERANCE_MM_RANGE = (0.01, 100.0)
TOLERANCE_DEG_RANGE = (0.01, 180.0)


class TaskFileError(ValueError):
    """A task file that cannot be used: the message names the file, the field and the fault."""


@dataclass(frozen=True)
class TaskStep:
    """One drag target: ``X_RD`` (4×4, the dragger in the reference's frame R) and the objects
    captured and released when the workpiece reaches it (None: the file did not say)."""

    X_RD: np.ndarray
    capture: tuple[str, ...] | None = None
    release: tuple[str, ...] | None = None


@dataclass(frozen=True)
class TaskGoal:
    """Where the workpiece must end at the work site (``X_RO``, 4×4 in the reference's frame),
    the contacts the execution monitor must verify there, and how close is close enough."""

    X_RO: np.ndarray
    contacts: tuple[str, ...]
    tolerance_m: float
    tolerance_rad: float


@dataclass(frozen=True)
class Task:
    """A contact task as the operator demonstrated it (see the module docstring)."""

    name: str
    workpiece: str
    reference: str
    steps: tuple[TaskStep, ...]
    goal: TaskGoal

    def objects_named(self) -> set[str]:
        """Every object the task names: workpiece, reference, captures, releases, contacts."""
        names = {self.workpiece, self.reference, *self.goal.contacts}
        for step in self.steps:
            names.update(step.capture or ())
            names.update(step.release or ())
        return names

    def check_names(self, movable: set[str], fixed: set[str], where: str = "task") -> None:
        """Raise :class:`TaskFileError` unless every name the task uses is an object of the
        model (``movable`` blocks and ``fixed`` environment), the workpiece is movable and it
        is not its own reference or contact."""
        known = movable | fixed
        if self.workpiece not in movable:
            what = (
                "part of the fixed environment" if self.workpiece in fixed else "not in the model"
            )
            raise TaskFileError(f"{where}: workpiece: {self.workpiece!r} is {what}")
        unknown = sorted(self.objects_named() - known)
        if unknown:
            have = ", ".join(sorted(known))
            raise TaskFileError(f"{where}: {unknown[0]!r} is not an object of the model ({have})")
        if self.reference == self.workpiece:
            raise TaskFileError(f"{where}: reference: the workpiece cannot be its own reference")
        if self.workpiece in self.goal.contacts:
            raise TaskFileError(f"{where}: goal.contacts: the workpiece cannot touch itself")


def pose_from_fields(xyz_m: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    """The 4×4 pose of a position (m) and URDF roll-pitch-yaw (degrees)."""
    return make_pose(rpy_to_R(np.radians(rpy_deg)), np.asarray(xyz_m, dtype=np.float64))


def pose_to_fields(X: np.ndarray) -> tuple[list[float], list[float]]:
    """``(xyz_m, rpy_deg)`` of a 4×4 pose, for writing a file."""
    return [float(v) for v in X[:3, 3]], [float(v) for v in np.degrees(R_to_rpy(X[:3, :3]))]


def symmetric_nearest(
    R_goal: np.ndarray, R_now: np.ndarray, symmetries: Sequence[np.ndarray]
) -> np.ndarray:
    """Of the rotations ``R_goal · S`` that look the same as ``R_goal`` (``S`` in
    ``symmetries``, the shape's symmetry rotations in its own frame, identity included), the
    one nearest to ``R_now``."""
    candidates = [R_goal @ S for S in symmetries] or [R_goal]
    return min(candidates, key=lambda R: float(np.linalg.norm(so3_log(R_now.T @ R))))


def pose_error(
    X_goal: np.ndarray, X_now: np.ndarray, symmetries: Sequence[np.ndarray]
) -> tuple[float, float]:
    """``(distance_m, angle_rad)`` between two poses of one block, up to its symmetries."""
    R = symmetric_nearest(X_goal[:3, :3], X_now[:3, :3], symmetries)
    angle = float(np.linalg.norm(so3_log(X_now[:3, :3].T @ R)))
    return float(np.linalg.norm(X_now[:3, 3] - X_goal[:3, 3])), angle


# Reading ---------------------------------------------------------------------------------


def _fields(doc: object, where: str, required: set[str], optional: set[str]) -> dict:
    if not isinstance(doc, dict):
        raise TaskFileError(f"{where}: expected an object, got {_kind(doc)}")
    unknown = sorted(set(doc) - required - optional)
    if unknown:
        allowed = ", ".join(sorted(required | optional))
        raise TaskFileError(f"{where}.{unknown[0]}: unknown field (allowed: {allowed})")
    missing = sorted(required - set(doc))
    if missing:
        raise TaskFileError(f"{where}: missing field {missing[0]!r}")
    return doc


def _kind(value: object) -> str:
    if value is None:
        return "null"
    return {bool: "a boolean", str: "a string", list: "a list", dict: "an object"}.get(
        type(value), "a number" if isinstance(value, int | float) else type(value).__name__
    )


def _name(value: object, where: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise TaskFileError(f"{where}: expected a non-empty string, got {_kind(value)}")
    if len(value) > MAX_NAME_CHARS:
        raise TaskFileError(f"{where}: longer than {MAX_NAME_CHARS} characters")
    return value


def _names(value: object, where: str) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise TaskFileError(f"{where}: expected a list of object names, got {_kind(value)}")
    names = tuple(_name(v, f"{where}[{i}]") for i, v in enumerate(value))
    if len(set(names)) != len(names):
        raise TaskFileError(f"{where}: an object is named twice")
    return names


def _vector3(value: object, where: str, bound: float, unit: str) -> list[float]:
    if not isinstance(value, list) or len(value) != 3:
        raise TaskFileError(f"{where}: expected a list of 3 numbers, got {_kind(value)}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise TaskFileError(f"{where}[{i}]: expected a number, got {_kind(v)}")
        if not math.isfinite(v) or abs(v) > bound:
            raise TaskFileError(
                f"{where}[{i}]: {v} is not a number in [-{bound:g}, {bound:g}] {unit}"
            )
        out.append(float(v))
    return out


def _pose(doc: dict, where: str) -> np.ndarray:
    xyz = _vector3(doc["xyz_m"], f"{where}.xyz_m", MAX_COORDINATE_M, "m")
    rpy = _vector3(doc["rpy_deg"], f"{where}.rpy_deg", 360.0, "degrees")
    return pose_from_fields(xyz, rpy)


def _in_range(value: object, where: str, lo_hi: tuple[float, float], unit: str) -> float:
    lo, hi = lo_hi
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise TaskFileError(f"{where}: expected a number, got {_kind(value)}")
    if not lo <= value <= hi:
        raise TaskFileError(f"{where}: {value} is outside [{lo:g}, {hi:g}] {unit}")
    return float(value)


def parse_task(doc: object, where: str = "task") -> Task:
    """The :class:`Task` of a decoded JSON document; :class:`TaskFileError` naming ``where``
    and the field at the first fault."""
    doc = _fields(doc, where, {"task", "name", "workpiece", "reference", "steps", "goal"}, set())
    version = doc["task"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise TaskFileError(f"{where}.task: expected the format version {TASK_FORMAT_VERSION}")
    if version != TASK_FORMAT_VERSION:
        raise TaskFileError(
            f"{where}.task: format version {version} is not supported (this reads version "
            f"{TASK_FORMAT_VERSION})"
        )
    steps_doc = doc["steps"]
    if not isinstance(steps_doc, list) or not steps_doc:
        raise TaskFileError(f"{where}.steps: expected a non-empty list, got {_kind(steps_doc)}")
    if len(steps_doc) > MAX_STEPS:
        raise TaskFileError(f"{where}.steps: {len(steps_doc)} steps, at most {MAX_STEPS}")
    steps = []
    for i, s in enumerate(steps_doc):
        at = f"{where}.steps[{i}]"
        s = _fields(s, at, {"xyz_m", "rpy_deg"}, {"capture", "release"})
        capture = _names(s["capture"], f"{at}.capture") if "capture" in s else None
        release = _names(s["release"], f"{at}.release") if "release" in s else None
        both = set(capture or ()) & set(release or ())
        if both:
            raise TaskFileError(f"{at}: {sorted(both)[0]!r} is both captured and released")
        steps.append(TaskStep(_pose(s, at), capture, release))
    at = f"{where}.goal"
    g = _fields(
        doc["goal"], at, {"xyz_m", "rpy_deg", "contacts"}, {"tolerance_mm", "tolerance_deg"}
    )
    goal = TaskGoal(
        X_RO=_pose(g, at),
        contacts=_names(g["contacts"], f"{at}.contacts"),
        tolerance_m=_in_range(
            g.get("tolerance_mm", 1.5), f"{at}.tolerance_mm", TOLERANCE_MM_RANGE, "mm"
        )
        / 1000.0,
        tolerance_rad=math.radians(
            _in_range(
                g.get("tolerance_deg", 1.5), f"{at}.tolerance_deg", TOLERANCE_DEG_RANGE, "degrees"
            )
        ),
    )
    return Task(
        name=_name(doc["name"], f"{where}.name"),
        workpiece=_name(doc["workpiece"], f"{where}.workpiece"),
        reference=_name(doc["reference"], f"{where}.reference"),
        steps=tuple(steps),
        goal=goal,
    )


def load_task(path: Path | str) -> Task:
    """Read and check a task file; :class:`TaskFileError` says which file, field and fault."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TaskFileError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TaskFileError(f"{path}: cannot be read ({exc})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TaskFileError(
            f"{path}: not JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
        ) from None
    return parse_task(doc, where=str(path))


# Writing ---------------------------------------------------------------------------------


def task_to_json(task: Task) -> dict:
    """The JSON document of ``task`` (what :func:`parse_task` reads back)."""
    steps = []
    for step in task.steps:
        xyz, rpy = pose_to_fields(step.X_RD)
        entry: dict = {"xyz_m": xyz, "rpy_deg": rpy}
        if step.capture is not None:
            entry["capture"] = list(step.capture)
        if step.release is not None:
            entry["release"] = list(step.release)
        steps.append(entry)
    xyz, rpy = pose_to_fields(task.goal.X_RO)
    return {
        "task": TASK_FORMAT_VERSION,
        "name": task.name,
        "workpiece": task.workpiece,
        "reference": task.reference,
        "steps": steps,
        "goal": {
            "xyz_m": xyz,
            "rpy_deg": rpy,
            "contacts": list(task.goal.contacts),
            "tolerance_mm": task.goal.tolerance_m * 1000.0,
            "tolerance_deg": math.degrees(task.goal.tolerance_rad),
        },
    }


def save_task(task: Task, path: Path | str) -> None:
    """Write ``task`` to ``path`` (through a temporary file, so a failed write loses nothing)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(task_to_json(task), indent=1) + "\n", encoding="utf-8")
    tmp.replace(path)
