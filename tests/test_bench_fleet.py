"""``python -m bench fleet`` end to end at its smallest: one cell through a real router, its
operator probe, the router's hop; the JSON summary, CSV and plot it writes. (The full sweep,
1 to 10 cells: ``make bench``.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]


def test_one_cell_is_measured_and_written_down(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "bench", "fleet", "--cells", "1", "--seconds", "5",
         "--hop-samples", "100", "--out", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    (point,) = summary["points"]
    assert point["cells"] == point["operators"] == 1
    # Every refused program answered, through the router; the cell's state heard.
    assert point["commands"] >= 5 and point["lost"] == 0
    assert 0 < point["command_ms_median"] <= point["command_ms_p99"]
    assert point["state_hz_min"] > 0 and point["frame_hz_min"] > 0
    for hop in (summary["router_hop"], summary["router_hop_quiet"]):
        assert hop["samples"] == 100 and 0 < hop["direct_ms_median"] and 0 < hop["routed_ms_median"]
    assert json.loads((tmp_path / "fleet.json").read_text()) == summary
    assert (tmp_path / "fleet.png").stat().st_size > 0
    assert len((tmp_path / "fleet.csv").read_text().splitlines()) == 2


def test_bad_options_are_refused_with_their_range() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "bench", "fleet", "--cells", "0"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "1..40" in done.stderr
