"""The control lease: one operator drives the robot at a time, the others watch; a STOP acts from
anyone; the holder's program lives on the holder's heartbeats alone; a closed page frees the
robot. A real work site and real operator links over zenoh."""

from __future__ import annotations

import time

import pytest

from operator_site.link import WorkSiteLink
from protocol import make_config
from tests.conftest import one_move_program, wait_until
from work_site.lease import LEASE_IDLE_S

pytestmark = pytest.mark.integration

SLOW_MPS = 0.005
"""A move this slow runs for tens of seconds: long enough to act on while it runs."""
DEADMAN_S = 0.5


FINAL = ("done", "failed", "refused", "stopped")


def _final(link: WorkSiteLink, pid: str, statuses: tuple[str, ...] = FINAL):
    """``pid``'s whole-program report with one of ``statuses``, if it came."""
    link.poll()
    return next(
        (r for r in link.status.reports if r.program_id == pid and r.command_index == -1
         and r.status in statuses),
        None,
    )  # fmt: skip


def _end(link: WorkSiteLink, pid: str):
    """``pid``'s first answer: accepted, or its end."""
    return _final(link, pid, ("accepted", *FINAL))


def test_one_operator_drives_the_others_watch_and_may_stop(work_site) -> None:
    ws = work_site("--no-camera", "--deadman-s", str(DEADMAN_S))
    alice = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id, operator_id="alice")
    bob = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id, operator_id="bob")
    try:
        for link in (alice, bob):
            assert wait_until(lambda link=link: (link.poll(), link.robot_state)[1] is not None, 30)
        alice.send_program(one_move_program("alice-1", speed_mps=SLOW_MPS))
        assert wait_until(lambda: _end(alice, "alice-1") is not None, 20), ws.log()
        assert _end(alice, "alice-1").status == "accepted"
        # The work site's heartbeat says who holds the robot: Bob watches.
        assert wait_until(lambda: (bob.poll(), bob.watching)[1], 5), bob.status.holder
        assert wait_until(lambda: (alice.poll(), alice.holds_control)[1], 5)
        bob.send_program(one_move_program("bob-1", p_WP=(0.45, 0.1, 0.15)))
        assert wait_until(lambda: _final(bob, "bob-1") is not None, 20)
        refusal = _final(bob, "bob-1")
        assert refusal.status == "refused" and "controlled by operator alice" in refusal.message
        # Bob's beats do not keep Alice's program alive: Alice falls silent, it stops.
        silent_s = time.time()
        alice._closing.set()  # her heartbeat thread ends; her session stays to hear the reports
        # Bob beats on until the stop's report arrives, for up to 20 s (the dead-man time grows
        # with the round trips the work site measures, long on a loaded machine): had his beats
        # counted, the slow program would have run on all that while.
        wait_until(lambda: (bob._send_heartbeat(), _final(alice, "alice-1"))[1] is not None, 20)
        stopped = _final(alice, "alice-1")
        assert stopped is not None and stopped.status == "stopped", stopped
        assert "no heartbeat" in stopped.message and stopped.stamp_s > silent_s
        # Her page closed: once the lease lapses, Bob may drive.
        time.sleep(LEASE_IDLE_S + 1.5)
        bob.send_program(one_move_program("bob-2", p_WP=(0.45, 0.1, 0.15)))
        assert wait_until(lambda: _end(bob, "bob-2") is not None, 20)
        assert _end(bob, "bob-2").status == "accepted", _end(bob, "bob-2")
        assert wait_until(lambda: (bob.poll(), bob.holds_control)[1], 5)
        # A STOP from the watcher acts on the holder's program.
        alice_stop = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id, "alice")
        try:
            assert wait_until(lambda: (alice_stop.poll(), alice_stop.watching)[1], 10)
            alice_stop.send_stop("watcher pressed stop")
            assert wait_until(lambda: _final(bob, "bob-2") is not None, 10)
            assert _final(bob, "bob-2").status == "stopped"
        finally:
            alice_stop.close()
    finally:
        alice.close()
        bob.close()
