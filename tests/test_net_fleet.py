"""A fleet through routers (deploy/fleet.py): per-cell certificates keep each operator to its
own cell; a lone router that crashes mid-program stops the program (the dead-man) and, once
restarted, carries the operator's re-send to the work site, which replays the program's
reports instead of running it again; with two meshed routers the program goes on through the
other. Real processes, real zenoh, loopback."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from deploy.fleet import Fleet, FleetSpec
from operator_site.link import FINAL_STATUSES, WorkSiteLink
from tests.conftest import one_move_program, wait_until

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
PROGRAM_TIMEOUT_S = 120.0
"""A short program's end is waited for this long: it bounds a hang, not the run."""
DEADMAN_S = 0.5


def _started(link: WorkSiteLink, pid: str) -> bool:
    link.poll()
    return any(r.program_id == pid and r.status == "started" for r in link.status.reports)


def _final(link: WorkSiteLink, pid: str) -> list[str]:
    """How program ``pid`` ended, as the link has heard so far (polled)."""
    link.poll()
    return [
        r.status
        for r in link.status.reports
        if r.program_id == pid and r.command_index == -1 and r.status in FINAL_STATUSES
    ]


def _journaled_ids(fleet: Fleet, site: str) -> set[str]:
    """The program ids ``site``'s journal holds reports of."""
    path = fleet.log_dir / f"{site}.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    return {json.loads(line).get("program_id") for line in lines if line.strip()} - {None}


def _seen(link: WorkSiteLink) -> bool:
    link.poll()
    return link.robot_state is not None


@pytest.mark.parametrize("site_routers", [False, True], ids=["one-router", "site-routers"])
def test_each_operator_reaches_its_own_cell_only(
    tmp_path: Path, certs: Path, site_routers: bool
) -> None:
    """Through one router, or through a cloud router and a router per site (each checking
    certificates against its own cells' rules)."""
    del certs  # (needs openssl, as the fixture checks; the fleet makes its own certificates)
    spec = FleetSpec(sites=2, tls=tmp_path / "certs", camera=False, site_routers=site_routers)
    links: list[WorkSiteLink] = []
    with Fleet(spec, tmp_path / "logs") as fleet:
        try:
            for config_site, site in (("cell-01", "cell-01"), ("cell-02", "cell-02"),
                                      ("cell-01", "cell-02")):  # fmt: skip
                links.append(WorkSiteLink(fleet.operator_config(config_site), site))
            own_1, own_2, other = links

            def own_see_state() -> bool:
                for link in links:
                    link.poll()
                return own_1.robot_state is not None and own_2.robot_state is not None

            assert wait_until(own_see_state, 60.0), fleet.tail("router")

            # Each operator's list of work sites holds its own cell only. (The link of
            # cell-01's operator to cell-02 lists nothing at all: the router's access control
            # answers none of its liveliness, cell-01's included.)
            def listed() -> list[list[str]]:
                own_see_state()
                return [link.status.sites for link in links]

            expected = [["cell-01"], ["cell-02"]]
            assert wait_until(lambda: listed()[:2] == expected, 15.0), listed()
            assert "cell-02" not in other.status.sites
            q_2 = own_2.robot_state.q.copy()
            other.send_program(one_move_program("one-to-two", speed_mps=0.1))
            own_1.send_program(one_move_program("one-to-one", speed_mps=0.1))

            def done() -> bool:
                for link in links:
                    link.poll()
                return bool(_final(own_1, "one-to-one"))

            assert wait_until(done, PROGRAM_TIMEOUT_S), own_1.status.reports
            assert _final(own_1, "one-to-one") == ["done"]
            time.sleep(1.0)  # cell-02's reports, had the program got through, are on the way
            for link in links:
                link.poll()
            # cell-01's operator certificate: nothing of cell-02 seen, its program dropped.
            assert other.robot_state is None and other.status.reports == []
            assert other.status.label == "not connected"
            assert own_2.status.reports == []
            np.testing.assert_allclose(own_2.robot_state.q, q_2, atol=1e-4)
            assert _journaled_ids(fleet, "cell-02") == set()
            assert "one-to-one" in _journaled_ids(fleet, "cell-01")
        finally:
            for link in links:
                link.close()


def test_a_router_crash_stops_the_program_and_a_restart_replays_it(tmp_path: Path) -> None:
    spec = FleetSpec(sites=1, camera=False, site_args=("--deadman-s", str(DEADMAN_S)))
    with Fleet(spec, tmp_path) as fleet:
        link = WorkSiteLink(fleet.operator_config("cell-01"), "cell-01")
        try:
            assert wait_until(lambda: _seen(link), 60.0), fleet.tail("cell-01")
            link.send_program(one_move_program("crossing", speed_mps=0.02))

            assert wait_until(lambda: _started(link, "crossing"), PROGRAM_TIMEOUT_S), (
                link.status.reports
            )
            fleet.kill_router()
            time.sleep(2.0)  # the operator's heartbeats cannot reach the work site
            fleet.start_router()

            # The link re-sends the unfinished program when the work site is back; the work
            # site replays its reports, the dead-man's stop among them.
            assert wait_until(lambda: _final(link, "crossing"), 60.0), (
                link.status.reports,
                fleet.tail("cell-01"),
            )
            crossing = [r for r in link.status.reports if r.program_id == "crossing"]
            assert _final(link, "crossing") == ["stopped"]
            assert "no heartbeat from the operator" in crossing[-1].message
            assert [r.seq for r in crossing] == sorted(r.seq for r in crossing)
            log = fleet.log("cell-01").read_text()
            assert "received again" in log and "replayed" in log
            # Run once: a second run would have been accepted and started again, with reports
            # of its own (replays repeat the first run's, stamps and all, and count once).
            statuses = [(r.command_index, r.status) for r in crossing]
            assert statuses.count((-1, "accepted")) == 1, statuses
            assert statuses.count((0, "started")) == 1, statuses
            # And the cell is commanded again through the restarted router.
            link.send_program(one_move_program("after", p_WP=(0.42, -0.05, 0.16)))

            assert wait_until(lambda: _final(link, "after"), PROGRAM_TIMEOUT_S), link.status.reports
            assert _final(link, "after") == ["done"]
        finally:
            link.close()


def test_with_two_meshed_routers_a_program_goes_on_when_one_fails(tmp_path: Path) -> None:
    """The work site is connected to both routers, the operator (a client) to the first: when
    that one crashes, the operator's sessions go on through the second soon enough that the
    dead-man does not stop the program."""
    spec = FleetSpec(sites=1, routers=2, camera=False, site_args=("--deadman-s", str(DEADMAN_S)))
    with Fleet(spec, tmp_path) as fleet:
        link = WorkSiteLink(fleet.operator_config("cell-01"), "cell-01")
        try:
            assert wait_until(lambda: _seen(link), 60.0), fleet.tail("cell-01")
            first_router = list(link.session.info.routers_zid())
            assert len(first_router) == 1 and not list(link.session.info.peers_zid())
            link.send_program(one_move_program("failover", speed_mps=0.02))

            assert wait_until(lambda: _started(link, "failover"), PROGRAM_TIMEOUT_S), (
                link.status.reports
            )
            fleet.kill_router("router")

            assert wait_until(lambda: _final(link, "failover"), PROGRAM_TIMEOUT_S), (
                link.status.reports,
                fleet.tail("cell-01"),
            )
            failover = [r for r in link.status.reports if r.program_id == "failover"]
            assert _final(link, "failover") == ["done"], failover[-1].message
            assert [r.seq for r in failover] == sorted(r.seq for r in failover)
            assert list(link.session.info.routers_zid()) not in ([], first_router)
        finally:
            link.close()


def test_the_fleet_refuses_what_it_cannot_start(tmp_path: Path) -> None:
    cases = (
        (["--sites", "0"], "sites = 0: must be 1..40"),
        (["--sites", "2", "--pages", "3"], "pages = 3: must be 0..sites"),
        (["--sites", "1", "--routers", "3"], "routers = 3: must be 1..2"),
    )
    for argv, says in cases:
        done = subprocess.run(
            [sys.executable, str(REPO / "deploy" / "fleet.py"), *argv, "--logs", str(tmp_path)],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 2 and says in done.stderr, done.stderr
