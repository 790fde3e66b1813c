"""An operator site meets a work site that went and came back with new zenoh sessions (new peer
ids), its link's and its heartbeat process's alike (``protocol.session.PeerWatch``): the same
session reconnecting can be merged into the work site's stale transport after a cut link, and
then nothing of the work site reaches it (``tests/test_net_netns.py`` cuts a real link).
Checked here between real sessions on loopback: a stand-in work site that closes its session
and opens a new one on the same ports."""

from __future__ import annotations

import numpy as np
import zenoh

from operator_site.link import WorkSiteLink
from protocol import RobotState, alive_key, encode, key, make_config
from protocol.session import link_endpoints
from tests.conftest import free_port, wait_until

SITE = "renewal"


class StandIn:
    """The work site's side of the wire: its liveliness token and its robot state."""

    def __init__(self, listen: list[str]) -> None:
        self.session = zenoh.open(make_config(listen=listen))
        self.token = self.session.liveliness().declare_token(alive_key(SITE, "work_site"))
        self.state = self.session.declare_publisher(key(SITE, "robot_state"))
        self.seq = 0

    def peers(self) -> set[str]:
        return {str(z) for z in self.session.info.peers_zid()}

    def publish_state(self) -> None:
        self.seq += 1
        state = RobotState(
            seq=self.seq, stamp_s=0.0, q=np.zeros(6), X_WF=np.eye(4), gripper_opening_m=0.0,
            wrench_S=np.zeros(6),
        )  # fmt: skip
        self.state.put(encode(state))


def _alive(link: WorkSiteLink) -> bool:
    link.poll()
    return link.status.work_site_alive


def test_a_work_site_that_came_back_is_met_by_new_sessions() -> None:
    endpoints, _ = link_endpoints([f"tcp/127.0.0.1:{free_port()}"])
    site = StandIn(endpoints)
    link = WorkSiteLink(make_config(connect=endpoints), SITE)
    try:
        assert wait_until(lambda: _alive(link), 10.0)
        first_zid = str(link.session.info.zid())
        assert link._beats.wait_ready()  # the heartbeat process has its session too
        assert wait_until(lambda: len(site.peers()) == 2, 10.0), site.peers()
        old_peers = site.peers()
        assert first_zid in old_peers

        site.session.close()  # the work site went: its token with it
        assert wait_until(lambda: not _alive(link), 10.0)
        site = StandIn(endpoints)  # ... and came back on the same ports

        assert wait_until(lambda: _alive(link), 20.0)
        assert str(link.session.info.zid()) != first_zid
        # The heartbeat process opened a new session too: none of the old peers is back.
        assert wait_until(lambda: len(site.peers()) == 2, 20.0), site.peers()
        assert not site.peers() & old_peers, (site.peers(), old_peers)

        # The new session hears the work site.
        def state_heard() -> bool:
            site.publish_state()
            return link.poll()[0]

        assert wait_until(state_heard, 10.0), "no robot state on the new session"
    finally:
        link.close()
        site.session.close()
