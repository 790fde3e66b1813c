"""What the operator is shown about the link, made from what arrives."""

from __future__ import annotations

import pytest

from operator_site.link import RATE_WINDOW_S, RateMeter


def test_rates_count_every_arrival_between_two_polls() -> None:
    """States arrive at 100 Hz into the link's arrival ring; a page drains it 20 times a
    second, and the rate shown counts them all."""
    meter = RateMeter()
    for k in range(int(100 * RATE_WINDOW_S)):
        meter.tick(k / 100)
    assert meter.rate_hz((100 * RATE_WINDOW_S - 1) / 100) == pytest.approx(100.0, rel=0.03)
    assert meter.rate_hz(100.0) == 0.0  # nothing lately
