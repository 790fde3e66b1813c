"""What the operator is shown about the link, made from what arrives."""

from __future__ import annotations

import pytest

from operator_site.link import RATE_WINDOW_S, RateMeter


def test_rates_count_what_was_sent_not_what_the_ring_kept() -> None:
    """A page draining a 4-slot ring 20 times a second keeps 80 of 100 states a second; the
    rate shown is the work site's, from the states' sequence numbers."""
    meter = RateMeter()
    seq = 0
    for k in range(int(20 * RATE_WINDOW_S)):  # 20 drains a second, 4 of the 5 new states kept
        for _ in range(4):
            seq += 1
            meter.tick(k / 20, seq)
        seq += 1  # dropped by the ring
    assert meter.rate_hz((20 * RATE_WINDOW_S - 1) / 20) == pytest.approx(100.0, rel=0.03)
    meter.tick(10.0, 5)  # the sender restarted: counts as one
    assert meter.rate_hz(10.0) == pytest.approx(1 / RATE_WINDOW_S)
