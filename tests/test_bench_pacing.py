"""bench/pacing.py's arithmetic: the points from the runs, the profile option. (The benchmark
itself runs real processes across network namespaces: ``python -m bench pacing``.)"""

from __future__ import annotations

import argparse

import pytest

from bench import pacing
from bench.report import _paced


def _row(profile: str, mode: str, run: int, age_s: float | None, error: str = "") -> dict:
    return {"profile": profile, "mode": mode, "run": run, "frames": None if error else 30,
            "frame_age_s_median": age_s, "frame_age_s_p90": None if age_s is None else 2 * age_s,
            "frame_rate_hz": 1.0, "state_rate_hz": 40.0, "error": error}  # fmt: skip


def test_points_take_medians_over_the_runs_that_measured_and_count_the_rest() -> None:
    rows = [
        _row("thin", "paced", 0, 1.0), _row("thin", "paced", 1, 2.0),
        _row("thin", "unpaced", 0, 15.0), _row("thin", "unpaced", 1, None, "no camera frame"),
    ]  # fmt: skip
    points = {(p["profile"], p["mode"]): p for p in pacing.summarise(rows)}
    paced, unpaced = points[("thin", "paced")], points[("thin", "unpaced")]
    assert (paced["runs"], paced["failed_runs"]) == (2, 0)
    assert paced["frame_age_s_median"] == pytest.approx(1.5)
    assert paced["rate_mbit"] == pytest.approx(0.3)  # the profile's link travels with it
    assert (unpaced["runs"], unpaced["failed_runs"]) == (2, 1)
    assert unpaced["frame_age_s_median"] == pytest.approx(15.0)
    summary = {"points": list(points.values())}
    assert _paced(summary, "thin", "unpaced") == pytest.approx(15.0)
    with pytest.raises(StopIteration):
        _paced(summary, "far-lossy", "paced")  # not measured: the report says so


def test_a_point_whose_runs_all_failed_has_no_age() -> None:
    (point,) = pacing.summarise([_row("clear", "paced", 0, None, "work site not connected")])
    assert point["frame_age_s_median"] is None and point["failed_runs"] == 1
    with pytest.raises(KeyError):
        _paced({"points": [point]}, "clear", "paced")


def test_an_unknown_profile_is_refused_naming_the_known_ones() -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="known: clear, thin"):
        pacing._profile("dialup")
