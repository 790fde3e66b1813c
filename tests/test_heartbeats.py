"""The heartbeat process: beats while told, stops when told, when its parent goes silent for
OPERATOR_FROZEN_S, and ends with its parent. A real child and real zenoh sessions on loopback;
the test plays the work site (its liveliness token, a subscriber on the heartbeat key)."""

from __future__ import annotations

import time

import zenoh

from operator_site.heartbeats import OPERATOR_FROZEN_S, SEQ_OFFSET, HeartbeatProcess
from protocol import Heartbeat, alive_key, decode, key, make_config
from protocol.session import free_port_pair
from tests.conftest import wait_until

SITE = "beats-test"
QUIET_S = 0.5
"""No beat within this long counts as silence (five beat periods)."""


def _beats(sub) -> list[Heartbeat]:
    out = []
    while (sample := sub.try_recv()) is not None:
        out.append(decode(sample.payload.to_bytes(), expected=Heartbeat))
    return out


def test_the_child_beats_while_told_and_ends_with_its_parent() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port_pair()}"
    site = zenoh.open(make_config(listen=[endpoint]))
    token = site.liveliness().declare_token(alive_key(SITE, "work_site"))
    sub = site.declare_subscriber(key(SITE, "heartbeat"), zenoh.handlers.FifoChannel(10_000))
    beats = HeartbeatProcess(make_config(connect=[endpoint]), SITE, "alice")
    try:
        beats.start()
        assert beats.wait_ready()
        time.sleep(QUIET_S)
        assert _beats(sub) == []  # resting

        for _ in range(10):  # told every period, as the link's thread does
            beats.beat()
            time.sleep(0.1)
        got = _beats(sub)
        assert len(got) >= 5, got
        assert all(b.operator == "alice" and b.seq >= SEQ_OFFSET for b in got)
        assert all(b.role == "operator_site" and b.site_id == SITE for b in got)

        beats.rest()
        time.sleep(QUIET_S)
        _beats(sub)
        time.sleep(QUIET_S)
        assert _beats(sub) == []

        beats.beat()  # then silence from the parent: beats go on, then stop
        time.sleep(OPERATOR_FROZEN_S / 2)
        assert _beats(sub)
        time.sleep(OPERATOR_FROZEN_S / 2 + QUIET_S)
        _beats(sub)
        time.sleep(QUIET_S)
        assert _beats(sub) == []

        pid = beats.pid
        assert pid is not None
        beats.close()
        assert beats.pid is None
    finally:
        beats.close()
        token.undeclare()
        site.close()
    assert wait_until(lambda: not _alive(pid), 5)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_child_that_cannot_start_leaves_the_thread_beating() -> None:
    beats = HeartbeatProcess(make_config(connect=["tcp/127.0.0.1:1"]), SITE, "bob")
    beats._setup = "not json"  # the child refuses its set-up and ends
    beats.start()
    assert not beats.wait_ready()
    for _ in range(5):  # never raises; starts again at most MAX_STARTS times
        beats.beat()
        time.sleep(0.2)
    beats.close()
