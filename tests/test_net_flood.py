"""A STOP that always arrives: a real work site process, a real operator link, and an attacker
flooding garbage on every key the work site reads, over zenoh on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from bench.netsafety import FLOOD_KEYS, Flood
from operator_site.link import WorkSiteLink
from protocol import make_config
from tests.conftest import one_move_program, wait_until

pytestmark = pytest.mark.integration

TRIALS = 20
CONTROL_PERIOD_S = 0.01
FLOOD_BEFORE_STOP_S = 0.2
STILL_RAD = 2e-4
"""Joint motion between two states a control period apart that counts as still (rad)."""
TARGETS = ((0.30, 0.10, 0.25), (0.45, -0.10, 0.15))


def test_every_stop_acts_through_a_garbage_flood_on_every_key(work_site) -> None:
    """Each STOP ends its program (a 5 s move, stopped rather than done) and the arm is still a
    control period after the work site's "stopped" report. How soon: ``python -m bench
    safety`` (this test asserts behaviour, never wall times)."""
    ws = work_site("--no-camera")
    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    flood = Flood(ws.endpoint, ws.site_id)
    states = []

    def poll() -> None:
        if link.poll()[0]:
            states.append(link.robot_state)

    latencies_s, stills = [], []
    try:
        assert wait_until(lambda: (poll(), link.status.label == "connected")[1], 20), ws.log()
        for trial in range(TRIALS):
            pid = f"flood{trial}"
            link.send_program(one_move_program(pid, 0.05, TARGETS[trial % 2]))
            assert wait_until(
                lambda pid=pid: (
                    poll(),
                    any(r.program_id == pid and r.status == "started" for r in link.status.reports),
                )[1],
                10,
            ), (link.status.reports[-5:], ws.log()[-3000:])
            flood.on.set()
            time.sleep(FLOOD_BEFORE_STOP_S)
            sent_s = time.time()
            link.send_stop(f"trial {trial}")
            assert wait_until(
                lambda pid=pid: (
                    poll(),
                    any(r.program_id == pid and r.status == "stopped" for r in link.status.reports),
                )[1],
                5,
                poll_s=0.005,
            ), (trial, link.status.reports[-5:], ws.log()[-3000:])
            stopped = next(
                r for r in link.status.reports if r.program_id == pid and r.status == "stopped"
            )
            latencies_s.append(stopped.stamp_s - sent_s)

            # The arm is still from a control period after the work site stopped it on.
            def later(at_s=stopped.stamp_s + CONTROL_PERIOD_S) -> list:
                return [s for s in states if s.stamp_s >= at_s]

            assert wait_until(lambda: (poll(), len(later()) >= 3)[1], 2, poll_s=0.005)
            flood.on.clear()
            a, b = later()[0], later()[-1]
            stills.append(float(np.max(np.abs(b.q - a.q))) / (b.seq - a.seq))
        rate_hz = flood.rate_achieved_hz
    finally:
        flood.close()
        link.close()
    print(
        f"flood {rate_hz:.0f} msg/s on each of {FLOOD_KEYS}; stop latency ms: "
        f"median {1e3 * np.median(latencies_s):.1f}, max {1e3 * max(latencies_s):.1f}; "
        f"joint motion after it: max {max(stills):.2e} rad a period"
    )
    assert rate_hz >= 10_000, rate_hz  # it really flooded
    assert len(latencies_s) == TRIALS  # every STOP acted (the work site's stamps are after it)
    assert min(latencies_s) > 0, latencies_s
    assert max(stills) <= STILL_RAD, stills
    log = ws.log()
    assert "dropped" in log and "malformed stop" in log  # counted and summed up ...
    assert log.count("malformed stop") < 50, log.count("malformed stop")  # ... not one a line
