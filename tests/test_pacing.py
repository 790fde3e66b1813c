"""The work site's stream pacing (``work_site/pacing.py``): the decisions on given echoes, and
the closed loop against a fluid model of a bottleneck link. Real sessions across a thin
emulated link: ``tests/test_net_netns.py``."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from protocol.messages import Heartbeat
from work_site import pacing
from work_site.pacing import (
    DRAIN_GAIN,
    FEEDBACK_STALE_S,
    INCREASE_FACTOR,
    MIN_SCALE,
    QUEUE_TARGET_S,
    StreamPacer,
)

BASE_S = 0.5


def feed(pacer: StreamPacer, operator: str, t0_s: float, seconds: float, queue_s: float,
         beat_s: float = 0.1) -> float:  # fmt: skip
    """Echoes every ``beat_s`` for ``seconds`` from ``t0_s``, each ``queue_s`` over the base;
    returns the time after the last."""
    t = t0_s
    for _ in range(round(seconds / beat_s)):
        pacer.heard(operator, t, BASE_S + queue_s)
        t += beat_s
    return t


def test_a_link_without_queue_keeps_the_full_rate() -> None:
    pacer = StreamPacer()
    t = feed(pacer, "a", 0.0, 30.0, 0.0)
    assert pacer.scale(t, "a") == 1.0


def test_a_lasting_queue_cuts_the_rate_once_per_decision_down_to_the_floor() -> None:
    pacer = StreamPacer()
    t = feed(pacer, "a", 0.0, 5.0, 0.0)  # the base: an empty link
    scales = [1.0]
    for i in range(60):  # a queue that keeps growing
        t = feed(pacer, "a", t, 0.2, 2 * QUEUE_TARGET_S + 0.01 * i)
        scales.append(pacer.scale(t, "a"))
    cuts = [(a, b) for a, b in itertools.pairwise(scales) if b != a]
    assert cuts and all(b <= DRAIN_GAIN * a + 1e-12 or b == MIN_SCALE for a, b in cuts), cuts
    assert scales[-1] == MIN_SCALE


def test_a_cut_goes_below_what_the_link_carried() -> None:
    """States sent 0.1 s apart begin to arrive 0.4 s apart: the link carries a quarter of
    them, and the first cut goes further than a blind one."""
    pacer = StreamPacer()
    t = 0.0
    for i in range(30):  # an empty link first: states arrive as sent
        t = 0.1 * i
        pacer.heard("a", t + BASE_S, BASE_S, sent_s=t, arrived_s=t + BASE_S / 2)
    sent0_s, queue_s, scale = t, 0.0, 1.0
    for i in range(1, 40):
        sent_s = sent0_s + 0.1 * i
        queue_s += 0.3
        pacer.heard("a", sent_s + BASE_S + queue_s, BASE_S + queue_s,
                    sent_s=sent_s, arrived_s=sent_s + BASE_S / 2 + queue_s)  # fmt: skip
        if (scale := pacer.scale(sent_s + BASE_S + queue_s, "a")) < 1.0:
            break
    assert DRAIN_GAIN * 0.25 <= scale < DRAIN_GAIN


def test_one_late_echo_alone_does_not_thin_the_streams() -> None:
    pacer = StreamPacer()
    t = feed(pacer, "a", 0.0, 5.0, 0.0)
    for _ in range(20):  # a stall of the reader: one late sample among timely ones
        pacer.heard("a", t, BASE_S + 5.0)
        t = feed(pacer, "a", t + 0.1, 1.0, 0.0)
    assert pacer.scale(t, "a") == 1.0


def test_rates_recover_step_by_step_once_the_queue_drains() -> None:
    pacer = StreamPacer()
    t = feed(pacer, "a", 0.0, 5.0, 0.0)
    t = feed(pacer, "a", t, 20.0, 1.0)
    assert pacer.scale(t, "a") == MIN_SCALE
    scales = []
    for _ in range(300):
        t = feed(pacer, "a", t, 0.1, 0.0)
        scales.append(pacer.scale(t, "a"))
    steps = [b / a for a, b in itertools.pairwise(scales) if b != a]
    assert all(1.0 < step <= INCREASE_FACTOR for step in steps), steps
    assert scales[-1] == 1.0


def test_the_holder_paces_else_the_slowest_and_silence_restores_the_full_rate() -> None:
    pacer = StreamPacer()
    t = feed(pacer, "slow", 0.0, 5.0, 0.0)
    feed(pacer, "fast", 0.0, 5.0, 0.0)
    t = feed(pacer, "slow", t, 20.0, 1.0)
    t = feed(pacer, "fast", t - 20.0, 20.0, 0.0)
    assert pacer.scale(t, "fast") == 1.0  # the holder's own link is fine
    assert pacer.scale(t, "") == MIN_SCALE  # nobody holds: the slowest watcher's
    assert pacer.scale(t, "nobody-heard") == MIN_SCALE
    assert pacer.scale(t + FEEDBACK_STALE_S + 1.0, "") == 1.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_nonsense_echoes_are_ignored(bad: float) -> None:
    pacer = StreamPacer()
    for i in range(50):
        pacer.heard("a", i * 0.1, bad)
        pacer.heard("", i * 0.1, 10.0)
    assert pacer.scale(5.0) == 1.0


@pytest.mark.parametrize(
    ("capacity_bps", "base_s"),
    [(20e3, 1.0), (50e3, 0.5), (200e3, 0.1), (1e6, 0.05)],
)
def test_against_a_bottleneck_the_queue_stays_near_the_target_and_the_link_busy(
    capacity_bps: float, base_s: float
) -> None:
    """A fluid queue of bytes at a link of ``capacity_bps`` (bytes/s) that the streams (90 kB/s
    at full rate) overfill; echoes every 0.1 s measure base + queue + a reader's jitter."""
    demand_bps, dt_s = 90e3, 0.01
    rng = np.random.default_rng(7)
    pacer = StreamPacer()
    queue_bytes, arrivals, arrived = 0.0, [], -1  # when what was sent at each step arrives
    delays, used = [], []
    steps = round(120.0 / dt_s)
    for i in range(steps):
        t = i * dt_s
        rate = demand_bps * pacer.scale(t, "a")
        queue_bytes = max(0.0, queue_bytes + (rate - capacity_bps) * dt_s)
        delay_s = queue_bytes / capacity_bps
        arrivals.append((t + base_s / 2 + delay_s, delay_s, t))
        while arrived + 1 < len(arrivals) and arrivals[arrived + 1][0] <= t:
            arrived += 1  # first in, first out: arrivals come in the order sent
        if i % 10 == 0 and arrived >= 0:  # an echo of the newest arrived; back in base / 2
            arrived_s, queued_s, sent_s = arrivals[arrived]
            pacer.heard(
                "a", t + base_s / 2, base_s + queued_s + rng.exponential(0.02), sent_s, arrived_s
            )
        if t > 60.0:
            delays.append(delay_s)
            used.append(min(rate, capacity_bps) / min(demand_bps, capacity_bps))
    print(f"queue median {np.median(delays):.3f} s, p99 {np.percentile(delays, 99):.3f} s, "
          f"link use {np.mean(used):.2f}")  # fmt: skip
    assert np.median(delays) <= 2 * QUEUE_TARGET_S, np.median(delays)
    assert np.percentile(delays, 99) <= base_s + 4 * QUEUE_TARGET_S
    if demand_bps * MIN_SCALE < capacity_bps:  # the floor itself may overfill a thin link
        assert np.mean(used) >= 0.3, np.mean(used)


def test_heartbeats_measure_the_streams_round_trip_on_the_work_sites_clock() -> None:
    beat = Heartbeat(site_id="s", role="operator_site", seq=1, stamp_s=100.0,
                     state_echo_s=99.0, state_echo_held_s=0.25)  # fmt: skip
    assert beat.state_round_trip_s(100.0) == pytest.approx(0.75)
    assert beat.state_round_trip_s(98.0) is None  # before the state was sent: a clock step
    old = Heartbeat(site_id="s", role="operator_site", seq=1, stamp_s=100.0)
    assert old.state_round_trip_s(100.0) is None


def test_stalls_of_a_lossy_link_that_carries_everything_do_not_thin_the_streams() -> None:
    """TCP on a lossy link: a lost packet holds everything behind it for a round trip
    (retransmission), then it all arrives at once; the link carries all that is sent."""
    rng = np.random.default_rng(3)
    pacer = StreamPacer()
    base_s, period_s, loss = 1.0, 0.01, 0.01
    held_until_s, arrived = 0.0, []  # (sent, arrived) of each state, in order
    scales = []
    for i in range(round(60.0 / period_s)):
        sent_s = i * period_s
        if rng.random() < loss:  # this one is resent a round trip later, the rest wait
            held_until_s = max(held_until_s, sent_s + base_s)
        arrived.append((sent_s, max(sent_s + base_s / 2, held_until_s + base_s / 2)))
        if i % 10 == 0:  # an echo every 0.1 s of the newest state arrived by now
            newest = [(s, a) for s, a in arrived[-300:] if a <= sent_s]
            if newest:
                s, a = newest[-1]
                now_s = sent_s + base_s / 2
                pacer.heard("a", now_s, now_s - s - (sent_s - a), sent_s=s, arrived_s=a)
            scales.append(pacer.scale(sent_s, "a"))
    assert min(scales[100:]) >= 0.5, min(scales[100:])


def test_frames_get_smaller_as_the_streams_thin_never_better_than_asked() -> None:
    scales = np.linspace(pacing.MIN_SCALE, 1.0, 40)
    qualities = [pacing.jpeg_quality(s, 80) for s in scales]
    assert qualities[-1] == 80 and qualities[0] == pacing.PACED_JPEG_QUALITY
    assert all(a <= b for a, b in itertools.pairwise(qualities))  # monotonic
    assert pacing.jpeg_quality(pacing.QUALITY_FLOOR_SCALE, 80) == pacing.PACED_JPEG_QUALITY
    assert pacing.jpeg_quality(0.75, 80) == 65
    assert pacing.jpeg_quality(0.1, 30) == 30  # the user's lower quality stands
    for bad in (0.0, -0.5, 1.5, math.nan):
        with pytest.raises(ValueError, match=r"outside \(0, 1\]"):
            pacing.jpeg_quality(bad, 80)
