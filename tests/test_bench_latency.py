"""bench/latency.py's arithmetic: the points from the runs, the grid's option parsing; and a
run stopped by SIGTERM leaves nothing behind. (The benchmark itself runs real processes across
network namespaces: ``python -m bench latency``.)"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from bench import latency
from deploy import netns
from tests.conftest import REPO, wait_until


def _row(rtt_ms: float, loss: float, seed: int, success: bool, task_s: float | None) -> dict:
    failure = None if success else {"kind": "execution_failed", "message": "stopped"}
    first_report_s = None if task_s is None else 0.2 + rtt_ms / 1e3
    return {"rtt_ms": rtt_ms, "loss": loss, "seed": seed, "success": success,
            "failure": failure, "task_s": task_s, "execute_s": task_s,
            "first_report_s": first_report_s, "frame_age_s": None,
            "frame_rate_hz": 2.5}  # fmt: skip


def test_points_count_successes_and_time_successful_runs_against_the_same_seed_at_0_ms() -> None:
    rows = [
        _row(0, 0.0, 0, True, 40.0), _row(0, 0.0, 1, True, 42.0),
        _row(500, 0.0, 0, True, 43.0), _row(500, 0.0, 1, False, 90.0),
        _row(500, 0.01, 0, True, 45.0),  # no 0 ms point at this loss: against loss 0's
    ]  # fmt: skip
    points = {(p["rtt_ms"], p["loss"]): p for p in latency.summarise(rows)}
    assert points[(0, 0.0)]["runs"] == 2 and points[(0, 0.0)]["successes"] == 2
    assert points[(0, 0.0)]["task_s_median"] == pytest.approx(41.0)
    assert points[(0, 0.0)]["overhead_s_median"] == pytest.approx(0.0)
    slow = points[(500, 0.0)]
    assert (slow["runs"], slow["successes"], slow["failures"]) == (2, 1, ["execution_failed"])
    assert slow["task_s_median"] == pytest.approx(43.0)  # the failed run's time is not a task's
    assert slow["overhead_s_median"] == pytest.approx(3.0)  # seed 0's 40 s, not the median
    assert points[(500, 0.01)]["overhead_s_median"] == pytest.approx(5.0)
    # The waits are the link's: a failed run's count too, a run that measured none does not.
    assert slow["first_report_s_median"] == pytest.approx(0.7)
    assert slow["frame_rate_hz_median"] == pytest.approx(2.5)
    assert slow["frame_age_s_median"] is None


def test_a_point_without_successes_or_a_baseline_has_no_time() -> None:
    points = latency.summarise([_row(1000, 0.05, 0, False, None), _row(250, 0.0, 0, True, 50.0)])
    assert all(p["overhead_s_median"] is None for p in points)
    assert points[0]["task_s_median"] is None


@pytest.mark.parametrize(
    ("text", "why"),
    [("", "expected|each value"), ("1,x", "expected numbers"), ("-5", r"\[0, 5000\]"),
     ("6000", r"\[0, 5000\]")],
)  # fmt: skip
def test_the_grid_options_name_their_range(text: str, why: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=why):
        latency._floats(text, 0.0, 5000.0, "--rtt-ms")
    assert latency._floats("0, 250,1000", 0.0, 5000.0, "--rtt-ms") == [0.0, 250.0, 1000.0]


def test_recorded_runs_are_read_back_and_a_later_run_replaces_an_earlier(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pathlib import Path

    # matplotlib comes with the [bench] extra only; the rows are what is checked here.
    monkeypatch.setattr(latency, "plot", lambda _points, _path: None)

    first, second = tmp_path / "first", tmp_path / "second"
    rows = [_row(0, 0.01, 0, True, 40.0), _row(0, 0.01, 1, False, None),
            _row(500, 0.01, 0, True, 41.0)]  # fmt: skip
    for out, written in ((first, rows), (second, [_row(0, 0.01, 1, True, 39.0)])):
        out.mkdir()
        args = argparse.Namespace(task=Path("cube-corner.json"), jitter=0.1, time_scale=1.0,
                                  out=out)  # fmt: skip
        latency.write_outputs(written, args)
    assert latency.read_rows([first / "latency.csv"]) == rows
    merged = latency.read_rows([first / "latency.csv", second / "latency.csv"])
    assert [(r["rtt_ms"], r["seed"], r["success"]) for r in merged] == [
        (0, 0, True), (0, 1, True), (500, 0, True)
    ]  # fmt: skip
    older = tmp_path / "older.csv"  # recorded before the waits were measured
    older.write_text("rtt_ms,loss,seed,success,task_s,execute_s,failure\n0,0,0,True,1,1,\n")
    (row,) = latency.read_rows([older])
    assert row["task_s"] == 1.0 and row["first_report_s"] is None
    bad = tmp_path / "bad.csv"
    bad.write_text("rtt_ms,loss,seed,success,task_s,execute_s,failure\nfast,0,0,True,1,1,\n")
    with pytest.raises(ValueError, match=r"bad.csv:2: not a latency run"):
        latency.read_rows([bad])


def _namespaces() -> set[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True)
    return {line.split()[0] for line in out.stdout.splitlines() if line.strip()}


def _work_sites(logs: Path) -> list[str]:
    """The pids of work sites journalling into ``logs``."""
    out = subprocess.run(
        ["pgrep", "-f", "--", f"work_site serve .*--journal {logs}"], capture_output=True, text=True
    )
    return out.stdout.split()


@pytest.mark.integration
def test_a_run_stopped_by_sigterm_takes_its_work_site_and_namespaces_down(tmp_path) -> None:
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"skipping network-namespace test: {reason}")
        pytest.skip(f"network namespaces unavailable: {reason}")
    logs = tmp_path / "logs"
    before = _namespaces()
    bench = subprocess.Popen(
        [sys.executable, "-m", "bench", "latency", "--rtt-ms", "0", "--loss", "0", "--runs", "1",
         "--out", str(tmp_path), "--logs", str(logs)],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        # Its link's two namespaces and its work site (whose journal is under ``logs``) up.
        assert wait_until(lambda: len(_namespaces() - before) == 2 and _work_sites(logs), 60)
        bench.send_signal(signal.SIGTERM)
        assert bench.wait(timeout=30) == 128 + signal.SIGTERM
        assert wait_until(lambda: not _work_sites(logs), 10), _work_sites(logs)
        assert _namespaces() - before == set()
    finally:
        bench.kill()
        bench.wait()
