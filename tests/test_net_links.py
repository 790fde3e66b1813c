"""One zenoh link per priority range: commands, programs, reports and state on one TCP connection,
camera frames on another (``protocol.session.link_endpoints``), so that image bytes queued in a
connection never hold a command back. Checked between real sessions: a real work-site process and
the operator's :class:`~operator_site.link.WorkSiteLink`."""

from __future__ import annotations

import json
import queue
import socket

import numpy as np
import pytest
import zenoh

from operator_site.link import WorkSiteLink
from protocol import (
    Heartbeat,
    MotionCommand,
    MotionProgram,
    ProtocolError,
    decode,
    key,
    make_config,
)
from protocol.session import (
    EPHEMERAL_RANGE_FILE,
    LISTEN_PORTS_LOWEST,
    derive_split,
    free_port_pair,
    link_endpoints,
    operator_site_config,
    split_endpoints,
    work_site_config,
)
from tests.conftest import REPO, free_port, wait_until

COMMAND_PRIORITIES = (
    zenoh.Priority.REAL_TIME,
    zenoh.Priority.INTERACTIVE_HIGH,
    zenoh.Priority.INTERACTIVE_LOW,
)
STATE_PRIORITIES = (zenoh.Priority.DATA_HIGH, zenoh.Priority.DATA)
IMAGE_PRIORITIES = (zenoh.Priority.DATA_LOW, zenoh.Priority.BACKGROUND)


def _ranges(session: zenoh.Session) -> list[tuple[int, int] | None]:
    return sorted((link.priorities for link in session.info.links()), key=str)


# ------------------------------------------------------------------------ deriving endpoints


def test_one_tcp_or_tls_endpoint_becomes_two_links_on_port_and_port_plus_one() -> None:
    assert link_endpoints(["tcp/127.0.0.1:7447"])[0] == [
        "tcp/127.0.0.1:7447?prio=0-3",
        "tcp/127.0.0.1:7448?prio=4-7",
    ]
    assert link_endpoints(["tls/robot.example.org:9000"])[0] == [
        "tls/robot.example.org:9000?prio=0-3",
        "tls/robot.example.org:9001?prio=4-7",
    ]
    assert derive_split("tcp/[::1]:7447") == ["tcp/[::1]:7447?prio=0-3", "tcp/[::1]:7448?prio=4-7"]
    assert split_endpoints("h", (1, 5)) == ["tcp/h:1?prio=0-3", "tcp/h:5?prio=4-7"]
    assert split_endpoints("h", (1, 5), split=False) == ["tcp/h:1"]


@pytest.mark.parametrize(
    ("endpoint", "why"),
    [
        ("tcp/127.0.0.1:0", "port 0 has no next port"),
        ("tcp/127.0.0.1:65535", "port 65535 has no next port"),
        ("udp/127.0.0.1:7447", "only tcp/tls endpoints are split"),
        ("tcp/127.0.0.1:7447?prio=0-7", "has its own metadata"),
        ("tcp/127.0.0.1:7447#iface=lo", "has its own metadata"),
        ("tcp/127.0.0.1", "expected tcp/host:port"),
    ],
)
def test_an_endpoint_that_cannot_be_split_is_used_as_given_and_the_note_says_why(
    endpoint: str, why: str
) -> None:
    with pytest.raises(ProtocolError, match=why):
        derive_split(endpoint)
    used, note = link_endpoints([endpoint])
    assert used == [endpoint]
    assert note.startswith("one link for all priorities") and why in note


def test_several_endpoints_are_each_split_and_single_link_uses_them_as_given() -> None:
    two = ["tcp/127.0.0.1:7447", "tls/127.0.0.1:7449"]  # e.g. two meshed routers
    assert link_endpoints(two)[0] == [
        "tcp/127.0.0.1:7447?prio=0-3", "tcp/127.0.0.1:7448?prio=4-7",
        "tls/127.0.0.1:7449?prio=0-3", "tls/127.0.0.1:7450?prio=4-7",
    ]  # fmt: skip
    assert link_endpoints(two, single_link=True) == (
        two, "one link for all priorities (--single-link)"
    )  # fmt: skip
    mixed, note = link_endpoints(["tcp/127.0.0.1:7447", "udp/127.0.0.1:7460"])
    assert mixed == ["tcp/127.0.0.1:7447?prio=0-3", "tcp/127.0.0.1:7448?prio=4-7",
                     "udp/127.0.0.1:7460"]  # fmt: skip
    assert note.startswith("split where possible") and "udp/127.0.0.1:7460" in note
    assert link_endpoints(["tcp/127.0.0.1:7447"], single_link=True)[0] == ["tcp/127.0.0.1:7447"]
    with pytest.raises(ProtocolError, match="expected a sequence"):
        link_endpoints("tcp/127.0.0.1:7447")  # type: ignore[arg-type]


def test_a_port_pair_for_listening_is_free_and_below_the_ephemeral_range() -> None:
    """Drawn where no other process's outgoing connection is given a port: one found free
    in the ephemeral range can be taken before the listener binds it (seen in the suite)."""
    import socket

    if not EPHEMERAL_RANGE_FILE.exists():
        pytest.skip(f"no {EPHEMERAL_RANGE_FILE}: the kernel chooses the ports")
    first_ephemeral = int(EPHEMERAL_RANGE_FILE.read_text().split()[0])
    for _ in range(20):
        port = free_port_pair()
        assert LISTEN_PORTS_LOWEST <= port and port + 1 < first_ephemeral
        for p in (port, port + 1):
            with socket.socket() as s:
                s.bind(("127.0.0.1", p))  # free: binds


def test_max_links_is_raised_only_for_prio_endpoints() -> None:
    split = make_config(listen=link_endpoints(["tcp/127.0.0.1:7447"])[0])
    assert json.loads(split.get_json("transport/unicast/max_links")) == 2
    plain = make_config(listen=["tcp/127.0.0.1:7447"])
    assert json.loads(plain.get_json("transport/unicast/max_links")) == 1  # zenoh's default
    demo = operator_site_config()
    assert json.loads(demo.get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:7447?prio=0-3",
        "tcp/127.0.0.1:7448?prio=4-7",
    ]
    assert json.loads(demo.get_json("transport/unicast/max_links")) == 2


# ------------------------------------------------------------------------ real sessions


def _free_pair() -> int:
    """A port p with p and p + 1 both free right now."""
    for _ in range(50):
        port = free_port()
        if port < 65535:
            try:
                with socket.socket() as s:
                    s.bind(("127.0.0.1", port + 1))
                return port
            except OSError:
                continue
    raise RuntimeError("no two consecutive free ports")


def test_operator_commands_travel_at_command_priorities_on_the_first_link() -> None:
    endpoint = f"tcp/127.0.0.1:{_free_pair()}"
    with zenoh.open(work_site_config(endpoint)) as work:
        inbox: queue.Queue[tuple[str, zenoh.Priority]] = queue.Queue()
        for topic in ("program", "stop"):
            work.declare_subscriber(
                key("links", topic),
                lambda s: inbox.put_nowait((str(s.key_expr).rsplit("/", 1)[1], s.priority)),
            )
        link = WorkSiteLink(operator_site_config(endpoint), "links")
        try:
            assert wait_until(lambda: len(_ranges(link.session)) == 2, 10.0)
            assert _ranges(link.session) == [(0, 3), (4, 7)]
            command = MotionCommand(
                kind="move", X_WP=np.eye(4), speed_mps=0.05, force_limit_n=10.0, contacts=()
            )
            got: dict[str, zenoh.Priority] = {}
            deadline_ok = wait_until(
                lambda: (
                    link.send_program(MotionProgram("p1", np.eye(4), (command,))),
                    link.send_stop("test"),
                    got.update(dict(_drain(inbox))),
                    {"program", "stop"} <= set(got),
                )[-1],
                10.0,
                poll_s=0.2,
            )
            assert deadline_ok, got
            assert got["stop"] == zenoh.Priority.REAL_TIME
            assert got["program"] in COMMAND_PRIORITIES
        finally:
            link.close()


def _drain(q: queue.Queue) -> list:
    items = []
    while not q.empty():
        items.append(q.get_nowait())
    return items


@pytest.mark.integration
def test_real_work_site_listens_on_two_links_with_the_streams_on_the_low_one(work_site) -> None:
    # `work-site serve --listen tcp/127.0.0.1:PORT`: PORT and PORT+1; vision on, for recognitions.
    ws = work_site(vision=True)
    link = WorkSiteLink(make_config(connect=link_endpoints([ws.endpoint])[0]), ws.site_id)
    try:
        seen: queue.Queue[tuple[str, zenoh.Priority]] = queue.Queue()

        def on_sample(s: zenoh.Sample) -> None:
            topic = str(s.key_expr).rsplit("/", 1)[1]
            # The operator's own heartbeats (its dead-man signal, at command priority) go the
            # other way: only the work site's are telemetry.
            if topic == "heartbeat" and decode(s.payload.to_bytes(), Heartbeat).role != "work_site":
                return
            seen.put_nowait((topic, s.priority))

        for topic in ("camera", "robot_state", "report", "heartbeat", "recognitions"):
            link.session.declare_subscriber(key(ws.site_id, topic), on_sample)

        def connected() -> bool:
            link.poll()
            return link.status.label == "connected"

        assert wait_until(connected, 30.0), ws.log()
        assert _ranges(link.session) == [(0, 3), (4, 7)], ws.log()
        port = int(ws.endpoint.rsplit(":", 1)[1])
        dst_ports = sorted(int(str(lk.dst).split("?")[0].rsplit(":", 1)[1])
                           for lk in link.session.info.links())  # fmt: skip
        assert dst_ports == [port, port + 1]
        # Unsafe (the gripper at the robot's base): refused with a report, never run.
        command = MotionCommand(
            kind="move", X_WP=np.eye(4), speed_mps=0.05, force_limit_n=10.0, contacts=()
        )
        link.send_program(MotionProgram("refused-1", np.eye(4), (command,)))
        priorities: dict[str, set] = {}

        def all_kinds() -> bool:
            link.poll()
            for topic, priority in _drain(seen):
                priorities.setdefault(topic, set()).add(int(priority))
            return {"camera", "robot_state", "report", "heartbeat", "recognitions"} <= set(
                priorities
            )

        assert wait_until(all_kinds, 60.0), (priorities, ws.log())
        # Reports, heartbeats (whose echo measures the commands' round trip) and recognitions
        # on the commands' link; robot states and camera frames, the streams, on the other.
        for topic in ("report", "heartbeat", "recognitions"):
            assert priorities[topic] <= {int(p) for p in COMMAND_PRIORITIES}, topic
        assert priorities["robot_state"] <= {int(p) for p in STATE_PRIORITIES}
        assert priorities["camera"] <= {int(p) for p in IMAGE_PRIORITIES}
        assert "robot state and camera frames on 4-7 (port + 1)" in ws.log()
    finally:
        link.close()


def test_the_loopback_config_file_is_what_work_site_serve_builds() -> None:
    path = REPO / "deploy" / "zenoh" / "work-site-loopback.json5"
    from_file, built = zenoh.Config.from_file(str(path)), work_site_config()
    for k in (
        "mode",
        "listen/endpoints",
        "connect/endpoints",
        "transport/unicast/max_links",
        "scouting/multicast/enabled",
        "transport/shared_memory/enabled",
    ):
        assert json.loads(from_file.get_json(k)) == json.loads(built.get_json(k)), k
