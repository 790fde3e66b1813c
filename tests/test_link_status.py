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


def test_the_share_that_arrives_counts_arrivals_against_the_senders_numbers() -> None:
    """The work site numbers every frame it renders and sends one in three: the page reads the
    newest of each poll's arrivals and finds a third of them came; a restart starts anew."""
    meter = RateMeter()
    assert meter.share(0.0) is None
    for k in range(0, 30, 3):  # frames 0, 3, 6, ... arrive; one read in two polls
        meter.tick(k / 5)
        if k % 2 == 0:
            meter.read(k / 5, k)
    assert meter.share(30 / 5) == pytest.approx(1 / 3)
    assert meter.share(100.0) is None  # nothing read within the window
    meter.tick(101.0)
    meter.read(101.0, 2)  # a lower number: the work site restarted
    meter.tick(101.2)
    meter.read(101.2, 3)
    assert meter.share(101.2) == pytest.approx(1.0)
