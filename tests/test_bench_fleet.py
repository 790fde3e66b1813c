"""``python -m bench fleet`` end to end at its smallest: one cell through a real router, its
operator probe, the router's hop; the JSON summary, CSV and plot it writes. (The full sweep,
1 to 10 cells: ``make bench``.)"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]


def test_one_cell_is_measured_and_written_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    from bench import fleet

    parser = argparse.ArgumentParser()
    fleet.add_arguments(parser)
    args = parser.parse_args(["--cells", "1", "--seconds", "5", "--hop-samples", "100",
                              "--out", str(tmp_path)])  # fmt: skip
    drawn = importlib.util.find_spec("matplotlib") is not None  # only the [bench] extra has it
    if not drawn:
        print("matplotlib not installed: fleet.png not drawn, not checked")
        monkeypatch.setattr(fleet, "plot", lambda _summary, _path: None)
    assert fleet.main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (point,) = summary["points"]
    assert point["cells"] == point["operators"] == 1
    # Every refused program answered, through the router; the cell's state heard.
    assert point["commands"] >= 5 and point["lost"] == 0
    assert 0 < point["command_ms_median"] <= point["command_ms_p99"]
    assert point["state_hz_min"] > 0 and point["frame_hz_min"] > 0
    for hop in (summary["router_hop"], summary["router_hop_quiet"]):
        assert hop["samples"] == 100 and 0 < hop["direct_ms_median"] and 0 < hop["routed_ms_median"]
    assert json.loads((tmp_path / "fleet.json").read_text()) == summary
    if drawn:
        assert (tmp_path / "fleet.png").stat().st_size > 0
    assert len((tmp_path / "fleet.csv").read_text().splitlines()) == 2


def test_bad_options_are_refused_with_their_range() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "bench", "fleet", "--cells", "0"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "1..40" in done.stderr


def test_points_pool_each_cells_operators() -> None:
    from argparse import Namespace

    from bench.fleet import summarise

    def row(cells: int, site: str, rtts: list[float], hz: float, lost: int = 0) -> dict:
        return {"cells": cells, "site": site, "round_trips_ms": rtts, "lost": lost,
                "frame_hz": hz, "frame_age_ms_median": 400.0, "state_hz": 100.0 - cells,
                "machine_cpu": 0.5, "router_cpu": 0.01, "sites_cpu": 0.4, "operators_cpu": 0.02,
                "hop": {"added_ms_p99": 0.5} if cells == 1 else None}  # fmt: skip

    rows = [
        row(1, "cell-01", [5.0, 7.0], 2.0),
        row(2, "cell-01", [8.0], 1.0),
        row(2, "cell-02", [10.0, 12.0], 1.5, lost=1),
    ]
    args = Namespace(seconds=5.0, command_period_s=0.5, tls=None, no_camera=False)
    summary = summarise(rows, {"added_ms_p99": 0.2}, args)
    one, two = summary["points"]
    assert (one["cells"], one["operators"], one["commands"]) == (1, 1, 2)
    assert (two["operators"], two["commands"], two["lost"]) == (2, 3, 1)
    assert two["command_ms_median"] == 10.0 and two["frame_hz_min"] == 1.0
    assert two["frame_hz_median"] == 1.25 and two["state_hz_min"] == 98.0
    assert summary["router_hop"] == {"added_ms_p99": 0.5}
    assert summary["router_hop_quiet"] == {"added_ms_p99": 0.2}
