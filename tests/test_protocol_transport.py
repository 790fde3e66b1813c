"""Key expressions, zenoh configs (including one real loopback session pair) and the exports."""

from __future__ import annotations

import json
import queue
import socket
import time
import types

import numpy as np
import pytest
import zenoh

import protocol
from protocol import (
    DEFAULT_SITE_ID,
    DEFAULT_WORK_SITE_ENDPOINT,
    TOPIC_MESSAGE_TYPES,
    TOPICS,
    ProtocolError,
    RobotState,
    alive_key,
    decode,
    encode,
    key,
    make_config,
    operator_site_config,
    work_site_config,
)

# ------------------------------------------------------------------------------------- keys


def test_keys() -> None:
    assert key("site1", "robot_state") == "telerobot/site1/robot_state"
    assert key(DEFAULT_SITE_ID, "camera") == "telerobot/site1/camera"
    assert alive_key("lab-2_b", "operator_site") == "telerobot/lab-2_b/alive/operator_site"
    assert set(TOPICS) == {
        "camera",
        "recognitions",
        "robot_state",
        "program",
        "report",
        "stop",
        "heartbeat",
        "truth",
    }
    assert {key("s", t).rsplit("/", 1)[1] for t in TOPICS} == set(TOPICS)
    assert set(TOPIC_MESSAGE_TYPES.values()) == set(protocol.MESSAGE_TYPES.values())


@pytest.mark.parametrize("site_id", ["", "a/b", "a*", "a.b", "$x", "a b", "**", "é", "x" * 257, 1])
def test_key_rejects_bad_site_ids(site_id: object) -> None:
    with pytest.raises(ProtocolError, match="site_id"):
        key(site_id, "camera")  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match="site_id"):
        alive_key(site_id, "work_site")  # type: ignore[arg-type]


def test_key_rejects_bad_topics_and_roles() -> None:
    with pytest.raises(ProtocolError, match="topic: must be one of"):
        key("site1", "alive")
    with pytest.raises(ProtocolError, match="role: must be one of"):
        alive_key("site1", "robot")


def test_keys_are_valid_zenoh_key_expressions() -> None:
    for topic in TOPICS:
        assert str(zenoh.KeyExpr(key("a-b_1", topic))) == key("a-b_1", topic)
    assert zenoh.KeyExpr(alive_key("site1", "work_site"))


# ---------------------------------------------------------------------------------- configs


def test_make_config_sets_exactly_what_it_is_given() -> None:
    conf = make_config(
        mode="client",
        listen=("tcp/127.0.0.1:7000",),
        connect=["tcp/10.0.0.1:7447", "udp/10.0.0.1:7447"],
        multicast_scouting=True,
        shared_memory=True,
    )
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]
    assert json.loads(conf.get_json("connect/endpoints")) == [
        "tcp/10.0.0.1:7447",
        "udp/10.0.0.1:7447",
    ]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is True


def test_default_configs_are_the_loopback_demo() -> None:
    conf = make_config()
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("connect/endpoints")) == []
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    assert DEFAULT_WORK_SITE_ENDPOINT == "tcp/127.0.0.1:7447"
    # Two links: priorities 0-3 on the default port, robot state's and camera frames' 4-7 on
    # the next one.
    split = ["tcp/127.0.0.1:7447?prio=0-3", "tcp/127.0.0.1:7448?prio=4-7"]
    work = work_site_config()
    assert json.loads(work.get_json("listen/endpoints")) == split
    operator = operator_site_config()
    assert json.loads(operator.get_json("connect/endpoints")) == split
    assert json.loads(operator.get_json("listen/endpoints")) == []
    single = work_site_config(single_link=True)
    assert json.loads(single.get_json("listen/endpoints")) == [DEFAULT_WORK_SITE_ENDPOINT]


def test_make_config_rejects_bad_arguments() -> None:
    with pytest.raises(ProtocolError, match="mode: must be one of"):
        make_config(mode="server")
    with pytest.raises(ProtocolError, match="listen: expected a sequence of endpoints"):
        make_config(listen="tcp/127.0.0.1:7447")  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match="connect: endpoint must look like"):
        make_config(connect=("127.0.0.1:7447",))


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_sessions_exchange_a_message_on_loopback() -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    received: queue.Queue[bytes] = queue.Queue()
    alive: queue.Queue[str] = queue.Queue()
    work = zenoh.open(work_site_config(endpoint))
    try:
        operator = zenoh.open(operator_site_config(endpoint))
        try:
            # Callbacks only hand data over to a queue: never block or call zenoh inside one.
            operator.declare_subscriber(
                key("site1", "robot_state"),
                lambda sample: received.put_nowait(sample.payload.to_bytes()),
            )
            operator.liveliness().declare_subscriber(
                alive_key("site1", "work_site"),
                lambda sample: alive.put_nowait(str(sample.key_expr)),
                history=True,
            )
            token = work.liveliness().declare_token(alive_key("site1", "work_site"))
            assert alive.get(timeout=10.0) == "telerobot/site1/alive/work_site"
            state = RobotState(7, 1.5, np.arange(6.0), np.eye(4), 0.03, np.ones(6))
            deadline = time.monotonic() + 10.0
            payload = None
            while payload is None:  # the subscription may take a moment to reach the work site
                assert time.monotonic() < deadline, "no sample within 10 s"
                work.put(key("site1", "robot_state"), encode(state))
                try:
                    payload = received.get(timeout=0.1)
                except queue.Empty:
                    pass
            got = decode(payload, expected=RobotState)
            assert got.seq == 7 and np.array_equal(got.q, np.arange(6.0))
            token.undeclare()
        finally:
            operator.close()
    finally:
        work.close()
    assert work.is_closed() and operator.is_closed()


# ---------------------------------------------------------------------------------- exports


def test_all_matches_the_exported_names() -> None:
    public = {
        name
        for name, value in vars(protocol).items()
        if not name.startswith("_") and not isinstance(value, types.ModuleType)
    }
    assert set(protocol.__all__) == public
    assert len(protocol.__all__) == len(set(protocol.__all__))
    for name in protocol.__all__:
        assert getattr(protocol, name) is not None
