"""The whole chain, as `operator-site demo --scripted TASK --seed N --json` runs it: a seeded work
site on loopback, vision, the model editor, a scripted operator, the program generator, the robot
with its execution monitor; judged by the simulated work site's ground truth (issue 9)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

pytestmark = pytest.mark.integration

SEEDS = {"around-corner": (6,)}
"""A fixed seed; the benchmark runs a hundred a task. The corner task on seed 3 runs end to end in
tests/test_runner.py (as a task file, the same chain), so the suite runs it once. around-corner's
outcome on
a seed varies from run to run (the execution is chaotic: a start a few control periods later
moves the final error by millimetres), so only a seed that passed every time is here: seed 6,
4 of 4 real runs at --time-scale 3 (0.26-1.04 mm) and 7 of 7 in-process replays started at
seven phases (0.16-0.79 mm), 2026-11-25."""
TIME_SCALE = 3.0
"""The work site simulates this much faster than real time where the machine keeps up: the
physics is stepped alike per control period at any scale, and the suite is shorter."""


@pytest.mark.parametrize(
    ("task", "seed"), [(task, seed) for task, seeds in SEEDS.items() for seed in seeds]
)
def test_a_scripted_task_succeeds_end_to_end(task: str, seed: int) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "operator_site", "demo", "--scripted", task, "--seed", str(seed),
         "--time-scale", str(TIME_SCALE), "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["task"] == task and result["seed"] == seed
    # The failure first: pytest cuts a long message short, and it says what went wrong.
    assert result["success"], (result["failure"], proc.stderr[-2000:], result)
    assert proc.returncode == 0
    assert result["final_error_mm"] <= 1.5 and result["final_error_deg"] <= 1.5
    assert result["contacts_verified"] >= result["contacts_required"] > 0
    assert result["time_scale"] == TIME_SCALE and result["time_scale_achieved"] > 0.0
    # Vision looked at the block once the program was done: where the program put it.
    assert result["vision_check"]["verdict"] == "placed", result["vision_check"]
