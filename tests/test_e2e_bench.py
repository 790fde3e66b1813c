"""The e2e benchmark's bookkeeping: rows written as each run ends, runs made in parts and
merged (``--first-seed``, ``--keep``). ``run_scripted`` is replaced by a stub here: the real
chain is tests/test_e2e.py's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import e2e as e2e_bench


def _fake_run(task: str, seed: int, **_kwargs) -> dict:
    ok = seed % 3 != 0
    return {
        "task": task,
        "seed": seed,
        "success": ok,
        "final_error_mm": 0.2 + 0.01 * seed,
        "final_error_deg": 0.1,
        "stage_s": {"vision": 0.1, "model": 0.01, "program": 0.5, "computation": 0.61},
        "execution": "done: program complete" if ok else "failed: a contact was not felt",
    }


@pytest.fixture
def fake_chain(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int]]:
    calls: list[tuple[str, int]] = []

    def run(task: str, seed: int, **kwargs) -> dict:
        calls.append((task, seed))
        return _fake_run(task, seed, **kwargs)

    monkeypatch.setattr(e2e_bench, "run_scripted", run)
    # matplotlib comes with the [bench] extra only (CI installs [test]); the plot's input, the
    # rows by task, is what the summary is checked on here.
    monkeypatch.setattr(e2e_bench, "_plot", lambda _out, _by_task: None)
    return calls


def _rows(out: Path) -> list[tuple[str, int]]:
    return [
        (r["task"], r["seed"])
        for r in map(json.loads, (out / "e2e.jsonl").read_text().splitlines())
    ]


def test_a_run_in_parts_summarises_every_kept_row(
    tmp_path: Path, fake_chain: list[tuple[str, int]]
) -> None:
    e2e_bench.run(tmp_path, 3, ("corner",))
    e2e_bench.run(tmp_path, 3, ("corner",), first_seed=3, keep=True)
    summary = e2e_bench.run(tmp_path, 2, ("around-corner",), keep=True)
    assert fake_chain == [("corner", s) for s in range(6)] + [
        ("around-corner", 0),
        ("around-corner", 1),
    ]
    assert summary["corner"]["runs"] == 6 and summary["corner"]["success"] == 4
    assert summary["around-corner"]["runs"] == 2
    assert set(summary["corner"]["failures"]) == {0, 3}
    assert len((tmp_path / "e2e.csv").read_text().splitlines()) == 1 + 8
    assert summary["corner"]["trees"] and "tree" in json.loads(
        (tmp_path / "e2e.jsonl").read_text().splitlines()[0]
    )


def test_a_rerun_replaces_its_seeds_and_without_keep_starts_afresh(
    tmp_path: Path, fake_chain: list[tuple[str, int]]
) -> None:
    e2e_bench.run(tmp_path, 4, ("corner",))
    e2e_bench.run(tmp_path, 2, ("corner",), first_seed=1, keep=True)
    assert sorted(_rows(tmp_path)) == [("corner", s) for s in range(4)]
    summary = e2e_bench.run(tmp_path, 1, ("corner",))
    assert _rows(tmp_path) == [("corner", 0)] and summary["corner"]["runs"] == 1


def test_a_row_cut_by_a_killed_run_is_skipped_with_a_message(
    tmp_path: Path, fake_chain: list[tuple[str, int]], capsys: pytest.CaptureFixture[str]
) -> None:
    e2e_bench.run(tmp_path, 2, ("corner",))
    with (tmp_path / "e2e.jsonl").open("a") as f:
        f.write('{"task": "corner", "se')
    summary = e2e_bench.run(tmp_path, 1, ("corner",), first_seed=2, keep=True)
    assert summary["corner"]["runs"] == 3
    assert "e2e.jsonl:3: skipped, not a JSON row" in capsys.readouterr().err
