"""Task files: round trips, one clear line for each kind of fault, symmetry-aware goal error."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from models.transforms import R_to_rpy, make_pose, rpy_to_R, so3_exp
from operator_site.taskfile import (
    TaskFileError,
    load_task,
    parse_task,
    pose_error,
    save_task,
    task_to_json,
)

CORNER = {
    "task": 1,
    "name": "cube into the near left inside corner",
    "workpiece": "cube",
    "reference": "frame",
    "steps": [
        {"xyz_m": [-0.055, -0.055, 0.006], "rpy_deg": [0, 0, 0]},
        {"xyz_m": [-0.080, -0.080, 0.006], "rpy_deg": [0, 0, 0], "capture": [], "release": []},
    ],
    "goal": {
        "xyz_m": [-0.075, -0.075, 0.010],
        "rpy_deg": [0, 0, 0],
        "contacts": ["frame", "table"],
        "tolerance_mm": 1.5,
        "tolerance_deg": 1.5,
    },
}


def test_the_issue_example_parses() -> None:
    task = parse_task(CORNER)
    assert (task.name, task.workpiece, task.reference) == (
        "cube into the near left inside corner",
        "cube",
        "frame",
    )
    assert len(task.steps) == 2
    assert task.steps[0].capture is None and task.steps[1].capture == ()
    np.testing.assert_allclose(task.goal.X_RO[:3, 3], [-0.075, -0.075, 0.010])
    assert task.goal.contacts == ("frame", "table")
    assert task.goal.tolerance_m == pytest.approx(1.5e-3)
    assert task.goal.tolerance_rad == pytest.approx(math.radians(1.5))


def test_rpy_round_trips_including_gimbal_lock() -> None:
    rng = np.random.default_rng(0)
    for _ in range(500):
        rpy = rng.uniform([-math.pi, -math.pi / 2, -math.pi], [math.pi, math.pi / 2, math.pi])
        R = rpy_to_R(rpy)
        np.testing.assert_allclose(rpy_to_R(R_to_rpy(R)), R, atol=1e-12)
    for pitch in (math.pi / 2, -math.pi / 2):
        R = rpy_to_R([0.3, pitch, -1.1])
        rpy = R_to_rpy(R)
        assert rpy[0] == 0.0
        np.testing.assert_allclose(rpy_to_R(rpy), R, atol=1e-12)


def test_a_task_written_and_read_back_is_the_same_task(tmp_path) -> None:
    rng = np.random.default_rng(1)
    doc = copy.deepcopy(CORNER)
    doc["steps"] = [
        {
            "xyz_m": list(rng.uniform(-0.3, 0.3, 3)),
            "rpy_deg": list(rng.uniform(-179, 179, 3) * [1, 0.49, 1]),
            **({"capture": ["frame"]} if i == 3 else {}),
            **({"release": ["frame"]} if i == 7 else {}),
        }
        for i in range(10)
    ]
    task = parse_task(doc)
    save_task(task, tmp_path / "t.json")
    again = load_task(tmp_path / "t.json")
    a_doc, b_doc = task_to_json(task), task_to_json(again)
    assert [sorted(s) for s in a_doc["steps"]] == [sorted(s) for s in b_doc["steps"]]
    for a, b in zip(task.steps, again.steps, strict=True):
        np.testing.assert_allclose(a.X_RD, b.X_RD, atol=1e-12)
        assert (a.capture, a.release) == (b.capture, b.release)
    np.testing.assert_allclose(task.goal.X_RO, again.goal.X_RO, atol=1e-12)
    assert again.goal.tolerance_m == pytest.approx(task.goal.tolerance_m, rel=1e-12)
    assert not (tmp_path / "t.json.tmp").exists()


def _mutated(path: tuple, value: object) -> dict:
    doc = copy.deepcopy(CORNER)
    node = doc
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


class _Delete:
    """Marks a field to take out; its name is the same in every process (test ids)."""

    def __repr__(self) -> str:
        return "<delete>"


_DELETE = _Delete()

FAULTS = [
    (("task",), 2, "task.task: format version 2 is not supported"),
    (("task",), "1", "task.task: expected the format version 1"),
    (("task",), _DELETE, "missing field 'task'"),
    (("name",), "", "task.name: expected a non-empty string"),
    (("name",), "x" * 201, "task.name: longer than 200"),
    (("workpiece",), 7, "task.workpiece: expected a non-empty string, got a number"),
    (("reference",), None, "task.reference: expected a non-empty string, got null"),
    (("steps",), [], "task.steps: expected a non-empty list"),
    (("steps",), {}, "task.steps: expected a non-empty list, got an object"),
    (("steps", 0), [1, 2], "task.steps[0]: expected an object, got a list"),
    (("steps", 0, "xyz_m"), [0, 0], "task.steps[0].xyz_m: expected a list of 3 numbers"),
    (("steps", 0, "xyz_m"), [0, "a", 0], "task.steps[0].xyz_m[1]: expected a number, got a string"),
    (("steps", 0, "xyz_m"), [0, 0, 1e9], "task.steps[0].xyz_m[2]: 1000000000.0 is not a number in"),
    (
        ("steps", 0, "xyz_m"),
        [0, True, 0],
        "task.steps[0].xyz_m[1]: expected a number, got a boolean",
    ),
    (("steps", 1, "rpy_deg"), [0, 0, 400], "task.steps[1].rpy_deg[2]: 400 is not a number in"),
    (("steps", 1, "rpy_deg"), _DELETE, "task.steps[1]: missing field 'rpy_deg'"),
    (("steps", 1, "capture"), "frame", "task.steps[1].capture: expected a list of object names"),
    (
        ("steps", 1, "capture"),
        ["frame", "frame"],
        "task.steps[1].capture: an object is named twice",
    ),
    (("steps", 1, "release"), [""], "task.steps[1].release[0]: expected a non-empty string"),
    (("steps", 1, "xyz"), [0, 0, 0], "task.steps[1].xyz: unknown field (allowed: capture,"),
    (("goal",), [], "task.goal: expected an object, got a list"),
    (("goal", "contacts"), _DELETE, "task.goal: missing field 'contacts'"),
    (("goal", "tolerance_mm"), 0, "task.goal.tolerance_mm: 0 is outside [0.01, 100] mm"),
    (("goal", "tolerance_deg"), 1e3, "task.goal.tolerance_deg: 1000.0 is outside [0.01, 180]"),
    (("goal", "tolerance_deg"), "1", "task.goal.tolerance_deg: expected a number, got a string"),
    (("extra",), 1, "task.extra: unknown field"),
]


@pytest.mark.parametrize(("path", "value", "message"), FAULTS, ids=lambda v: str(v)[:30])
def test_each_fault_is_named_in_one_line(path: tuple, value: object, message: str) -> None:
    with pytest.raises(TaskFileError) as err:
        parse_task(_mutated(path, value))
    text = str(err.value)
    assert message in text and "\n" not in text, text


def test_a_step_that_captures_and_releases_one_object_is_refused() -> None:
    doc = _mutated(("steps", 1, "release"), ["frame"])
    doc["steps"][1]["capture"] = ["frame"]
    with pytest.raises(TaskFileError, match=r"steps\[1\]: 'frame' is both captured and released"):
        parse_task(doc)


def test_files_that_are_not_tasks_name_the_file(tmp_path) -> None:
    with pytest.raises(TaskFileError, match="no such file"):
        load_task(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"task": 1,\n "name": }')
    with pytest.raises(TaskFileError, match=rf"{bad}: not JSON: .* line 2, column 10"):
        load_task(bad)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps(_mutated(("goal", "tolerance_mm"), -1)))
    with pytest.raises(TaskFileError, match=rf"^{wrong}\.goal\.tolerance_mm: -1 is outside"):
        load_task(wrong)


def test_names_are_checked_against_the_model() -> None:
    task = parse_task(CORNER)
    movable, fixed = {"cube", "plank"}, {"frame", "table"}
    task.check_names(movable, fixed)
    with pytest.raises(TaskFileError, match="workpiece: 'cube' is not in the model"):
        task.check_names({"plank"}, fixed)
    with pytest.raises(TaskFileError, match="workpiece: 'frame' is part of the fixed"):
        parse_task(_mutated(("workpiece",), "frame")).check_names(movable, fixed)
    with pytest.raises(TaskFileError, match="'wall' is not an object of the model"):
        parse_task(_mutated(("goal", "contacts"), ["wall"])).check_names(movable, fixed)
    with pytest.raises(TaskFileError, match="cannot be its own reference"):
        parse_task(_mutated(("reference",), "cube")).check_names(movable, fixed)


def test_goal_error_is_taken_up_to_the_blocks_symmetries() -> None:
    quarter_turns_z = [rpy_to_R([0, 0, k * math.pi / 2]) for k in range(4)]
    goal = make_pose(rpy_to_R([0, 0, 0.2]), [0.1, 0.0, 0.025])
    turned = make_pose(goal[:3, :3] @ rpy_to_R([0, 0, math.pi / 2]) @ so3_exp([0, 0, 0.01]))
    turned[:3, 3] = [0.1, 0.003, 0.025]
    d, a = pose_error(goal, turned, quarter_turns_z)
    assert d == pytest.approx(0.003) and a == pytest.approx(0.01, abs=1e-12)
    _, a_plain = pose_error(goal, turned, [np.eye(3)])
    assert a_plain == pytest.approx(math.pi / 2 + 0.01, abs=1e-9)
