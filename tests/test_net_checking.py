"""The control loop never waits for a program's check: a real work site process checking a
1,000-command program keeps publishing its state and acts on a stop meanwhile. How fast (the
state rate, the stop's latency): ``python -m bench safety``; this test asserts behaviour, never
wall times."""

from __future__ import annotations

import itertools
import time

import pytest

from bench.netsafety import long_check_program
from operator_site.link import WorkSiteLink
from protocol import make_config
from protocol.messages import MAX_COMMANDS
from tests.conftest import one_move_program, wait_until

pytestmark = pytest.mark.integration

STOP_AFTER_SEND_S = 0.02


def test_state_keeps_its_rate_and_a_stop_acts_while_a_long_program_is_checked(work_site):
    ws = work_site("--no-camera")
    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    states: dict[int, float] = {}

    def poll() -> None:
        if link.poll()[0]:
            states[link.robot_state.seq] = link.robot_state.stamp_s

    def reports(pid: str) -> list:
        return [r for r in link.status.reports if r.program_id == pid]

    try:
        assert wait_until(lambda: (poll(), link.status.label == "connected")[1], 20), ws.log()
        # 1. The check of a long program: robot state keeps coming at its rate meanwhile.
        sent = time.time()
        link.send_program(long_check_program("long"))
        assert wait_until(lambda: (poll(), bool(reports("long")))[1], 30, poll_s=0.002)
        answered = reports("long")[0].stamp_s
        # Its first answer (the start may come in the same poll).
        assert reports("long")[0].status == "accepted", reports("long")
        # The states the work site stamped while it checked: their rate, and the longest gap.
        during = sorted((seq, t) for seq, t in states.items() if sent <= t <= answered)
        rate_hz = (during[-1][0] - during[0][0]) / (during[-1][1] - during[0][1])
        gap_s = max(b[1] - a[1] for a, b in itertools.pairwise(during))
        check_s = answered - sent
        link.send_stop("enough")
        assert wait_until(lambda: (poll(), reports("long")[-1].status == "stopped")[1], 5)
        # 2. A stop 20 ms after a long program is sent: it acts at once, and the program,
        # still being checked, never starts.
        link.send_program(long_check_program("cancelled"))
        time.sleep(STOP_AFTER_SEND_S)
        stop_sent_s = time.time()
        link.send_stop("changed my mind")
        assert wait_until(lambda: (poll(), bool(reports("cancelled")))[1], 5, poll_s=0.002)
        answer = reports("cancelled")
        latency_s = answer[0].stamp_s - stop_sent_s
        time.sleep(0.5)
        poll()
        answer = reports("cancelled")
    finally:
        link.close()
    print(
        f"check of {MAX_COMMANDS} commands {check_s:.2f} s; state rate meanwhile "
        f"{rate_hz:.1f} Hz, longest gap {1e3 * gap_s:.0f} ms; stop during a check answered in "
        f"{1e3 * latency_s:.1f} ms"
    )
    assert check_s > 0.1  # a check long enough to matter
    # The loop kept running throughout the check: a loop that waited for it would have
    # published nothing between the program's arrival and its answer.
    assert len(during) >= 3 and gap_s < check_s / 2, (len(during), gap_s, check_s)
    # The stop was acted on while the program was still being checked: it never started.
    assert [(r.command_index, r.status) for r in answer] == [(-1, "stopped")], answer
    # Cancelled in its check, or, when the stop overtook it on the wire, on its arrival.
    assert "being checked" in answer[0].message or "arrived after it" in answer[0].message
    assert latency_s > 0, latency_s


def test_a_program_that_arrives_after_the_stop_that_cancels_it_never_starts(work_site):
    """A stop overtakes the program sent just before it (stops go at a higher priority): the
    stop names it, and the work site never runs it when it comes."""
    import zenoh

    from protocol import Stop, encode, key

    ws = work_site("--no-camera")
    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    sender = zenoh.open(make_config(connect=[ws.endpoint]))
    try:
        assert wait_until(lambda: (link.poll(), link.status.label == "connected")[1], 20), ws.log()
        stop = Stop(reason="changed my mind", stamp_s=time.time(), cancels=("late",))

        def stop_answered() -> bool:  # sent until the sender's session has its route
            sender.put(key(ws.site_id, "stop"), encode(stop))
            link.poll()
            return any(r.program_id == "stop" for r in link.status.reports)

        # The stop's own answer (no program ran), then the program it cancelled.
        assert wait_until(stop_answered, 20, poll_s=0.5), ws.log()
        link.send_program(one_move_program("late"))
        assert wait_until(
            lambda: (link.poll(), any(r.program_id == "late" for r in link.status.reports))[1], 10
        ), ws.log()
        time.sleep(0.5)
        link.poll()
        late = [r for r in link.status.reports if r.program_id == "late"]
        assert [(r.command_index, r.status) for r in late] == [(-1, "stopped")], late
        assert "arrived after it" in late[0].message and "changed my mind" in late[0].message
        # The link's own stop names what it sent and has no answer for (here a program whose
        # samples were all lost), and stops sending it again; sent later, it never runs.
        lost = one_move_program("lost")
        link._unanswered["lost"] = (encode(lost), time.monotonic(), time.monotonic())
        link.send_stop("enough")
        assert not link.pending_programs()
        time.sleep(0.5)  # the stop arrives first

        def lost_answered() -> bool:
            sender.put(key(ws.site_id, "program"), encode(lost))
            link.poll()
            return any(r.program_id == "lost" for r in link.status.reports)

        assert wait_until(lost_answered, 20, poll_s=0.5), ws.log()
        lost_reports = [r for r in link.status.reports if r.program_id == "lost"]
        assert lost_reports[0].status == "stopped" and "enough" in lost_reports[0].message
    finally:
        sender.close()
        link.close()
