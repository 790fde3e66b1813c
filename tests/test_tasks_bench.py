"""bench/tasks.py: the per-task summary counts and the refusal of a malformed task file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from bench import tasks


def _row(seed: int, ok: bool, kind: str | None = None, mm: float = 0.2) -> dict:
    return {
        "task": "cube into the corner",
        "file": "cube-corner.json",
        "workpiece": "cube",
        "seed": seed,
        "success": ok,
        "failure": None if ok else {"kind": kind, "message": f"why {seed}"},
        "final_error_mm": mm,
        "final_error_deg": 0.1,
        "stage_s": {"computation": 0.2 + seed / 10},
        "tree": "abc",
    }


def test_summary_counts_successes_and_failure_kinds() -> None:
    rows = [_row(0, True, mm=0.1), _row(1, True, mm=0.3), _row(2, False, "not_recognised", 9.0),
            _row(3, False, "infeasible"), _row(4, False, "not_recognised")]  # fmt: skip
    s = tasks.summarise("cube-corner.json", "cube", rows)
    assert (s["runs"], s["successes"]) == (5, 2)
    assert s["failures"] == {"not_recognised": 2, "infeasible": 1}
    assert s["failed_seeds"] == {2: "why 2", 3: "why 3", 4: "why 4"}
    # Errors are the successes' only: a failed run's 9 mm is not among them.
    assert s["final_error_mm_median"] == pytest.approx(0.2)
    assert s["final_error_mm_max"] == pytest.approx(0.3)
    assert s["computation_s_max"] == pytest.approx(0.6)
    assert s["vision_checks"] == {}


def test_summary_counts_visions_verdicts_after_the_runs_called_done() -> None:
    def check(verdict: str) -> dict:
        return {"vision_check": {"block": "cube", "verdict": verdict, "frames": 1}}

    rows = [_row(0, True) | check("placed"), _row(1, False, "goal_missed") | check("moved"),
            _row(2, True) | check("placed"), _row(3, False, "execution_failed")]  # fmt: skip
    assert tasks.summarise("cube-corner.json", "cube", rows)["vision_checks"] == {
        "placed": 2,
        "moved": 1,
    }


def test_a_malformed_task_file_is_refused_before_any_run(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"task": 1}')
    args = argparse.Namespace(
        seeds=1, first_seed=0, time_scale=1.0, tasks=[bad], keep=False, out=tmp_path / "out"
    )
    assert tasks.main(args) == 2
    assert "bad.json: missing field" in capsys.readouterr().err
    assert not (tmp_path / "out" / "tasks.jsonl").exists()


def test_runs_go_seed_by_seed_and_the_summary_is_written_after_each(
    tmp_path: Path, monkeypatch
) -> None:
    """Every task at seed 0, then every task at seed 1: a bench stopped early has as many
    layouts of each task, and its tasks.json already counts the finished seeds."""
    files = [tasks.TASKS_DIR / "cube-corner.json", tasks.TASKS_DIR / "cube-wall.json"]
    out = tmp_path / "out"
    calls: list[tuple[str, int]] = []
    seen_runs: list[dict[str, int]] = []

    def fake_run_task(task, seed, **_kwargs) -> dict:
        if len(calls) == len(files):  # the first seed done: its summary is on disk
            summary = json.loads((out / "tasks.json").read_text())
            seen_runs.append({s["file"]: s["runs"] for s in summary})
        calls.append((task.name, seed))
        return {"task": task.name, "seed": seed, "success": True, "failure": None,
                "final_error_mm": 0.1, "final_error_deg": 0.1, "stage_s": {}}  # fmt: skip

    monkeypatch.setattr(tasks, "run_task", fake_run_task)
    monkeypatch.setattr(tasks, "_plot", lambda *_args: None)
    summaries = tasks.run(out, 2, files)
    names = [tasks.load_task(f).name for f in files]
    assert calls == [(names[0], 0), (names[1], 0), (names[0], 1), (names[1], 1)]
    assert seen_runs == [{"cube-corner.json": 1, "cube-wall.json": 1}]
    assert [s["runs"] for s in summaries] == [2, 2]


def test_a_task_runs_on_the_first_layouts_that_leave_it_room(tmp_path: Path, monkeypatch) -> None:
    """Seeds whose layouts put a block in the task's way are passed over, with the reason, in
    tasks.json; the task still runs on as many layouts as asked."""
    blocked = {1, 3}
    monkeypatch.setattr(
        tasks,
        "room_for_task",
        lambda _t, _s, X_WO: "in the way" if X_WO["seed"] in blocked else None,
    )
    monkeypatch.setattr(tasks, "random_layout", lambda _scene, seed: {"seed": seed})
    monkeypatch.setattr(tasks, "_plot", lambda *_args: None)
    ran: list[int] = []

    def fake_run_task(task, seed, **_kwargs) -> dict:
        ran.append(seed)
        return {"task": task.name, "seed": seed, "success": True, "failure": None,
                "final_error_mm": 0.1, "final_error_deg": 0.1, "stage_s": {}}  # fmt: skip

    monkeypatch.setattr(tasks, "run_task", fake_run_task)
    (summary,) = tasks.run(tmp_path, 3, [tasks.TASKS_DIR / "cube-corner.json"])
    assert ran == [0, 2, 4]
    assert summary["runs"] == 3
    assert summary["passed_over_seeds"] == {"1": "in the way", "3": "in the way"}
    # Extended with --keep, the layouts passed over before are still listed.
    blocked.add(6)
    (summary,) = tasks.run(tmp_path, 2, [tasks.TASKS_DIR / "cube-corner.json"], 5, keep=True)
    assert ran[3:] == [5, 7]
    assert summary["runs"] == 5
    assert summary["passed_over_seeds"] == {"1": "in the way", "3": "in the way", "6": "in the way"}


def test_too_few_layouts_with_room_is_a_clear_error(monkeypatch) -> None:
    monkeypatch.setattr(tasks, "room_for_task", lambda *_args: "in the way")
    monkeypatch.setattr(tasks, "random_layout", lambda _scene, seed: {})
    task = tasks.load_task(tasks.TASKS_DIR / "cube-corner.json")
    with pytest.raises(ValueError, match="only 0 of 22 layouts from seed 0 leave it room"):
        tasks.seeds_with_room(task, None, 0, 2)
