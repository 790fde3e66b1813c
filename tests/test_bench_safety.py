"""bench/safety.py's arithmetic: the state rate over windows, when the arm is still, the summary.
(The benchmark itself runs real processes: ``python -m bench safety``.)"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench import safety
from bench.netsafety import still_since


def test_window_rates_see_a_gap_that_the_mean_over_the_check_hides() -> None:
    t0 = 1000.0
    stamps = [t0 + 0.01 * k for k in range(100)]  # 1 s at 100 Hz ...
    del stamps[40:45]  # ... but for a 60 ms gap
    rates = safety.window_rates_hz(stamps, t0, t0 + 0.99)
    assert len(rates) == round((0.99 - safety.RATE_WINDOW_S) / safety.RATE_STEP_S) + 1
    assert max(rates) == pytest.approx(100.0)
    assert min(rates) == pytest.approx(15 / 0.2, rel=0.1)  # 16 states over 0.2 s in the worst
    mean_hz = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert mean_hz > 90 > min(rates)
    # A check shorter than a window is one window.
    assert safety.window_rates_hz(stamps[:10], t0, t0 + 0.09) == [pytest.approx(100.0)]


def _states(q_rad: list[float], t0: float = 50.0) -> list[SimpleNamespace]:
    return [
        SimpleNamespace(seq=k, stamp_s=t0 + 0.01 * k, q=np.full(6, q)) for k, q in enumerate(q_rad)
    ]


def test_still_since_is_the_first_state_after_which_the_arm_never_moves() -> None:
    moving = [1e-3 * k for k in range(10)]
    states = _states([*moving, moving[-1], moving[-1] + 1e-5, moving[-1] + 1e-5])
    assert still_since(states, 50.0, 2e-4) == pytest.approx(50.10)
    # Moving again later: still only from after the last move.
    states = _states([*moving, moving[-1], moving[-1] + 1e-3, moving[-1] + 1e-3])
    assert still_since(states, 50.0, 2e-4) == pytest.approx(50.12)
    assert still_since(_states(moving), 50.0, 2e-4) is None
    # States before the event do not count, and a state missed counts per period.
    states = _states([0.0, 0.0, 0.0, 1e-3, 2e-3])
    assert still_since(states, 50.025, 2e-4) is None
    skipped = [SimpleNamespace(seq=0, stamp_s=0.0, q=np.zeros(6)),
               SimpleNamespace(seq=10, stamp_s=0.1, q=np.full(6, 1e-3))]  # fmt: skip
    assert still_since(skipped, 0.0, 2e-4) == pytest.approx(0.1)  # 1e-4 rad a period


def test_the_summary_counts_trials_failures_and_dead_man_stops_out_of_bounds() -> None:
    def row(scenario: str, latency_ms: float | str, error: str = "", **more) -> dict:
        return safety._row(scenario, 0, "p", latency_ms=latency_ms, error=error, **more)

    rows = [
        *(row("stop", v, still_ms=v + 10) for v in (1.0, 2.0, 3.0)),
        row("stop", float("nan"), "no stopped report"),
        *(row("stop_flood", v, flood_hz=11_000) for v in (1.0, 60.0)),
        row("deadman_kill", 450.0, timeout_ms=500.0),
        row("deadman_kill", 900.0, timeout_ms=500.0),  # late
        # Within its work site's timeout, 0.5 s and three round trips of 10 ms:
        row("deadman_kill", 540.0, timeout_ms=530.0),
        row("deadman_cut", 300.0, timeout_ms=500.0),  # early
        row("check", "", state_hz_min=97.5, state_gap_ms_max=14.0, check_s=0.5),
        row("check", "", state_hz_min=99.0, state_gap_ms_max=12.0, check_s=0.7),
        row("stop_during_check", 1.5),
    ]
    s = safety.summarise(rows)
    assert (s["stop_trials"], s["stop_failures"]) == (4, 1)
    assert s["stop_ms_median"] == 2.0 and s["stop_ms_max"] == 3.0
    assert s["stop_still_ms_max"] == 13.0
    assert s["stop_flood_ms_max"] == 60.0 and s["flood_hz_per_key"] == 11_000
    assert (s["deadman_kill_outside_bounds"], s["deadman_cut_outside_bounds"]) == (1, 1)
    assert (s["deadman_kill_timeout_ms_max"], s["deadman_cut_timeout_ms_max"]) == (530.0, 500.0)
    assert s["deadman_kill_ms_max"] == 900.0 and s["deadman_kill_ms_median"] == 540.0
    assert s["state_hz_min_during_check"] == 97.5 and s["state_gap_ms_max_during_check"] == 14.0
    assert s["check_trials"] == 2 and s["check_s_median"] == pytest.approx(0.6)
