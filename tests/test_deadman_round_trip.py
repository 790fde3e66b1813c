"""The dead-man's timeout grows with the operator's round trip, measured by heartbeats echoing
each other (``Heartbeat.round_trip_s``, ``work_site/lease.py``): the arithmetic. Real sessions:
``tests/test_net_deadman.py``; a long, lossy link end to end: ``python -m bench latency``."""

from __future__ import annotations

import pytest

from protocol import RoundTrips
from protocol.messages import ROUND_TRIP_SAMPLES
from work_site.lease import ControlLease
from work_site.options import DEADMAN_RANGE_S
from work_site.server import DEADMAN_ROUND_TRIPS, deadman_timeout_s


def test_the_round_trip_is_the_median_of_the_last_few_each_operators_own() -> None:
    lease = ControlLease()
    assert lease.round_trip_s("a") is None
    for k, rtt in enumerate([0.5, 0.5, 2.0, 0.5, 0.6]):  # one beat held up by a resend
        lease.heard("a", float(k), rtt, stamp_s=100.0 + k, echo_stamp_s=1000.0 + k)
    assert lease.round_trip_s("a") == pytest.approx(0.5)
    lease.heard("a", 5.0)  # a beat without an echo (the heartbeat process's) changes nothing
    # Later beats echoing the same beat of ours (held up behind a resend, all of them) do not
    # count: one measurement per beat of ours.
    for k in range(3 * ROUND_TRIP_SAMPLES):
        lease.heard("a", 5.0 + 0.1 * k, 3.0 - 0.1 * k, echo_stamp_s=1004.0)
    assert lease.round_trip_s("a") == pytest.approx(0.5)
    for k in range(ROUND_TRIP_SAMPLES):  # the link got slower: the old samples age out
        lease.heard("a", 6.0 + k, 1.0, echo_stamp_s=1010.0 + k)
    assert lease.round_trip_s("a") == pytest.approx(1.0)
    assert lease.round_trip_s("b") is None
    lease.heard("", 1.0, 0.1, echo_stamp_s=1.0)  # anonymous: nothing kept
    assert lease.round_trip_s("") is None


def test_the_echo_is_the_operators_latest_stamp_and_how_long_ago_it_was_heard() -> None:
    lease = ControlLease()
    assert lease.echo(10.0) == ("", 0.0, 0.0)
    lease.heard("a", 10.0, stamp_s=1234.5)
    assert lease.echo(10.25) == ("a", 1234.5, pytest.approx(0.25))
    lease.heard("", 10.5, stamp_s=99.0)  # anonymous: never echoed
    assert lease.echo(10.75) == ("a", 1234.5, pytest.approx(0.75))


def test_the_operators_heard_lately_take_turns_in_the_echo() -> None:
    lease = ControlLease(idle_s=5.0)
    for name, stamp_s in (("carol", 3.0), ("alice", 1.0), ("bob", 2.0)):
        lease.heard(name, 10.0, stamp_s=stamp_s)
    lease.take("carol", 10.0)  # the holder gets its turn like the watchers
    echoed = [lease.echo(10.5 + 0.01 * k)[:2] for k in range(6)]
    assert echoed == [("alice", 1.0), ("bob", 2.0), ("carol", 3.0)] * 2
    lease.heard("alice", 14.0, stamp_s=5.0)
    lease.heard("dave", 14.0)  # no stamp: nothing to echo
    assert [lease.echo(15.5)[0] for _ in range(3)] == ["alice"] * 3  # bob, carol gone quiet
    assert lease.echo(30.0) == ("", 0.0, 0.0)


def test_the_timeout_adds_round_trips_up_to_the_top_of_the_range() -> None:
    assert deadman_timeout_s(0.5, None) == 0.5
    assert deadman_timeout_s(0.5, 0.0) == 0.5
    assert deadman_timeout_s(0.5, 0.5) == pytest.approx(0.5 + DEADMAN_ROUND_TRIPS * 0.5)
    assert deadman_timeout_s(0.5, 10.0) == DEADMAN_RANGE_S[1]  # a forged echo buys no more
    assert deadman_timeout_s(DEADMAN_RANGE_S[1], 1.0) == DEADMAN_RANGE_S[1]


def test_round_trips_count_each_echoed_beat_once() -> None:
    round_trips = RoundTrips(samples=3)
    assert round_trips.median_s() is None
    round_trips.add(None, 0.0)  # a beat that echoed nothing
    assert round_trips.median_s() is None
    for rtt in (0.2, 0.9, 1.6):  # one echo, read three times as the wait for our next grows
        round_trips.add(rtt, 1000.0)
    assert round_trips.median_s() == pytest.approx(0.2)
    for k, rtt in enumerate((0.3, 0.4, 0.5)):  # the oldest ages out
        round_trips.add(rtt, 1001.0 + k)
    assert round_trips.median_s() == pytest.approx(0.4)
    with pytest.raises(ValueError, match="samples = 0"):
        RoundTrips(samples=0)
