"""A task saved to a file and read back: the model's poses, the workpiece, its dragged path and
the captured objects (JSON, poses as 4×4 lists in metres)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TASK_FILE_VERSION = 1
MAX_PATH_POSES = 100_000


@dataclass(frozen=True)
class TaskFile:
    """What a task file holds. ``path`` is the workpiece's pose at each simulator step."""

    scene: str
    model: dict[str, np.ndarray]
    workpiece: str | None
    path: list[np.ndarray]
    captured: list[str]


def save_task(path: Path | str, task: TaskFile) -> None:
    """Write ``task`` to ``path`` (the directory must exist)."""
    data = {
        "version": TASK_FILE_VERSION,
        "scene": task.scene,
        "model": {name: X.tolist() for name, X in task.model.items()},
        "workpiece": task.workpiece,
        "path": [X.tolist() for X in task.path],
        "captured": list(task.captured),
    }
    Path(path).write_text(json.dumps(data))


def _pose(value, where: str) -> np.ndarray:
    try:
        X = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: not a 4×4 array of numbers") from e
    if X.shape != (4, 4) or not np.all(np.isfinite(X)):
        raise ValueError(f"{where}: not a finite 4×4 pose (shape {X.shape})")
    return X


def load_task(path: Path | str) -> TaskFile:
    """Read a task file; ValueError naming the file and what is wrong with it."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e.strerror})") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a task file (not JSON: {e})") from e
    if not isinstance(data, dict) or data.get("version") != TASK_FILE_VERSION:
        raise ValueError(f"{path}: not a version-{TASK_FILE_VERSION} task file")
    try:
        model = {str(n): _pose(X, f"{path}: model[{n!r}]") for n, X in data["model"].items()}
        poses = data["path"]
        if not isinstance(poses, list) or len(poses) > MAX_PATH_POSES:
            raise ValueError(f"{path}: path must be a list of at most {MAX_PATH_POSES} poses")
        task = TaskFile(
            scene=str(data["scene"]),
            model=model,
            workpiece=None if data["workpiece"] is None else str(data["workpiece"]),
            path=[_pose(X, f"{path}: path[{i}]") for i, X in enumerate(poses)],
            captured=[str(n) for n in data["captured"]],
        )
    except (KeyError, AttributeError, TypeError) as e:
        raise ValueError(f"{path}: missing or malformed field ({e})") from e
    if task.workpiece is not None and task.workpiece not in task.model:
        raise ValueError(f"{path}: workpiece {task.workpiece!r} is not in the model")
    return task
