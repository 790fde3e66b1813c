"""Several sites through one zenoh router (deploy/router.py, deploy/zenoh/router.json5): two
work sites under their own site ids and one operator, all connected only to the router, with
split links (the default) and with one link. The operator is a zenoh client, so that everything
it sends and receives really goes through the router: a peer would connect directly to a work
site that the router introduced, once it can reach it. Also keeps the example configs in
deploy/zenoh/ loadable by zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh

from operator_site.link import FINAL_STATUSES, WorkSiteLink
from protocol import RobotState, decode, encode, key, make_config
from protocol.session import TlsFiles, free_port_pair, link_endpoints
from tests.conftest import one_move_program, wait_until

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "deploy" / "zenoh").glob("*.json5"))
PROGRAM_TIMEOUT_S = 120.0
"""A one-move program's end is waited for this long: it bounds a hang, not the run (a loaded
machine simulates slower than real time)."""
ROUTED_DEADMAN_S = 2.0
"""The routed work sites' dead-man time: what is tested here is where messages go, and on a
loaded machine the operator's beats through the router have come further apart than the
default (the dead-man has tests of its own)."""


def _ended(report, program_id: str) -> bool:
    return (
        report.program_id == program_id
        and report.command_index == -1
        and report.status in FINAL_STATUSES
    )


@dataclass
class _Spawned:
    """Processes started by a test, each logging to its own file; all stopped afterwards."""

    tmp_path: Path
    procs: list[subprocess.Popen] = field(default_factory=list)
    logs: list[Path] = field(default_factory=list)

    def __call__(self, name: str, argv: list[str]) -> Path:
        log_path = self.tmp_path / f"{name}.log"
        self.logs.append(log_path)
        with log_path.open("w") as log:
            self.procs.append(
                subprocess.Popen(
                    argv, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                    env={**os.environ, "PYTHONUNBUFFERED": "1"},
                )
            )  # fmt: skip
        return log_path

    def texts(self) -> list[str]:
        return [p.read_text(errors="replace") for p in self.logs]

    def stop(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[_Spawned]:
    spawned = _Spawned(tmp_path)
    try:
        yield spawned
    finally:
        spawned.stop()


@pytest.fixture
def links() -> Iterator[list[WorkSiteLink]]:
    """Links a test opens; closed (before its processes stop) afterwards."""
    opened: list[WorkSiteLink] = []
    yield opened
    for link in opened:
        link.close()


ROUTER = [
    sys.executable,
    str(REPO / "deploy" / "router.py"),
    str(REPO / "deploy" / "zenoh" / "router.json5"),
]


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_example_configs_are_valid_zenoh_configs(path: Path) -> None:
    conf = zenoh.Config.from_file(str(path))
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("transport/shared_memory/enabled") == "false"


@pytest.mark.parametrize("single_link", [False, True], ids=["split-links", "single-link"])
def test_two_work_sites_and_an_operator_through_a_router(spawn, links, single_link) -> None:
    router_ep = f"tcp/127.0.0.1:{free_port_pair()}"
    one = ["--single-link"] if single_link else []
    router_log = spawn("router", [*ROUTER, "--listen", router_ep, *one])
    # Vision off, as in every other process test: its start-up takes the cores for seconds.
    for site in ("cell-a", "cell-b"):
        spawn(
            site,
            [sys.executable, "-m", "work_site", "serve", "--site-id", site,
             "--listen", f"tcp/127.0.0.1:{free_port_pair()}", "--connect", router_ep, *one,
             "--journal", str(spawn.tmp_path / f"{site}.jsonl"), "--vision-rate", "0",
             "--deadman-s", str(ROUTED_DEADMAN_S)],
        )  # fmt: skip
    # A client's zenoh.open fails rather than retries while its router is not up yet.
    assert wait_until(lambda: "router: up" in router_log.read_text(), 30.0), spawn.texts()
    # The operator knows only the router, and as a client talks to nobody else.
    connect = link_endpoints([router_ep], single_link)[0]
    assert len(connect) == (1 if single_link else 2)
    for site in ("cell-a", "cell-b"):
        links.append(WorkSiteLink(make_config(mode="client", connect=connect), site))
    a, b = links

    def both_connected() -> bool:
        a.poll(), b.poll()
        return all(
            link.status.label == "connected" and link.camera_frame is not None for link in links
        )

    assert wait_until(both_connected, 60.0), spawn.texts()
    for link in links:
        info = link.session.info
        assert len(list(info.routers_zid())) == 1 and not list(info.peers_zid())
    q_b = b.robot_state.q.copy()
    a.send_program(one_move_program("to-a", speed_mps=0.1))

    def a_done() -> bool:
        a.poll(), b.poll()
        return any(_ended(r, "to-a") for r in a.status.reports)

    assert wait_until(a_done, PROGRAM_TIMEOUT_S), (a.status.reports, spawn.texts())
    ends = [r for r in a.status.reports if _ended(r, "to-a")]
    assert [r.status for r in ends] == ["done"], ([r.message for r in ends], spawn.texts())
    # Site b heard nothing of it and did not move; site a did.
    assert b.status.reports == []
    np.testing.assert_allclose(b.robot_state.q, q_b, atol=1e-4)
    assert np.linalg.norm(a.robot_state.q - q_b) > 0.05

    # Holding site a's control or only watching site b, the operator measures its round trip
    # through the router by the work site's heartbeats echoing its own, and with it how old a
    # camera frame is when it arrives (rendering, encoding, the wire: one clock here, so never
    # negative).
    def measured() -> bool:
        a.poll(), b.poll()
        return all(
            link.status.round_trip_s is not None and link.status.frame_age_s is not None
            for link in links
        )

    assert wait_until(measured, 10.0)
    assert a.status.holder == a.operator_id and b.status.holder == ""
    for link in links:
        assert 0.0 <= link.status.round_trip_s < 1.0
        assert 0.0 <= link.status.frame_age_s < 5.0


# ------------------------------------------------------------ a secured router (mutual TLS, ACL)


def _tls(certs: Path, name: str, ca: str = "ca.pem") -> TlsFiles:
    return TlsFiles.in_dir(certs, name, ca)


def test_a_secured_router_admits_each_cells_operator_only(spawn, links, certs: Path) -> None:
    """Router with mutual TLS and --cell rules: cell-a is commanded by "operator" and watched
    by "viewer", cell-b commanded by "viewer". The operator's program reaches cell-a only, and
    it sees nothing of cell-b; the viewer cannot command cell-a nor fake cell-a's robot state;
    a certificate of another CA gets no session."""
    router_ep = f"tls/localhost:{free_port_pair()}"

    def link(name: str, site: str, ca: str = "ca.pem") -> WorkSiteLink:
        config = make_config(
            mode="client", connect=link_endpoints([router_ep])[0], tls=_tls(certs, name, ca)
        )
        links.append(WorkSiteLink(config, site))
        return links[-1]

    router_log = spawn(
        "router",
        [*ROUTER, "--listen", router_ep, "--certs", str(certs),
         "--cell", "cell-a=work-site:operator:viewer", "--cell", "cell-b=work-site:viewer"],
    )  # fmt: skip
    for site in ("cell-a", "cell-b"):
        # The router has checked who sent a command: the work site admits the router's.
        spawn(
            site,
            [sys.executable, "-m", "work_site", "serve", "--site-id", site, "--no-camera",
             "--listen", f"tcp/127.0.0.1:{free_port_pair()}", "--connect", router_ep,
             "--certs", str(certs), "--operators", "router",
             "--journal", str(spawn.tmp_path / f"{site}.jsonl")],
        )  # fmt: skip
    assert wait_until(lambda: "router: up" in router_log.read_text(), 30.0), spawn.texts()
    assert "mutual TLS; cells cell-a, cell-b" in router_log.read_text()
    op_a, op_b, viewer_a = (
        link("operator", "cell-a"),
        link("operator", "cell-b"),
        link("viewer", "cell-a"),
    )

    viewer_b = link("viewer", "cell-b")
    # Whatever the operator's session declares, the router forwards it nothing of cell-b.
    keys_heard: set[str] = set()
    wide = op_a.session.declare_subscriber(
        "telerobot/**", lambda s: keys_heard.add(str(s.key_expr))
    )

    def all_see_state() -> bool:
        for each in (op_a, op_b, viewer_a, viewer_b):
            each.poll()
        return all(each.robot_state is not None for each in (op_a, viewer_a, viewer_b))

    assert wait_until(all_see_state, 60.0), spawn.texts()
    q_a, q_b = op_a.robot_state.q.copy(), viewer_b.robot_state.q.copy()
    with pytest.raises(zenoh.ZError):  # another CA's certificate: no session at all
        link("intruder", "cell-a")

    # Refused at the router: the operator commanding cell-b, the viewer commanding cell-a,
    # the viewer publishing a robot state for cell-a.
    fake = RobotState(
        seq=10**9, stamp_s=0.0, q=np.zeros(6), X_WF=np.eye(4), gripper_opening_m=0.0,
        wrench_S=np.zeros(6),
    )  # fmt: skip
    seqs: list[int] = []  # every robot state of cell-a the operator receives
    spy = op_a.session.declare_subscriber(
        key("cell-a", "robot_state"), lambda s: seqs.append(decode(s.payload.to_bytes()).seq)
    )
    for _ in range(15):
        op_b.send_program(one_move_program("op-to-b", speed_mps=0.1))
        viewer_a.send_program(one_move_program("viewer-to-a", speed_mps=0.1))
        viewer_a.send_stop("viewer")
        viewer_a.session.put(key("cell-a", "robot_state"), encode(fake))
        op_a.poll(), op_b.poll()
        time.sleep(0.2)
    spy.undeclare()
    wide.undeclare()
    assert seqs and max(seqs) < 10**9, "a forged robot state got through"
    assert op_a.status.reports == [] and op_b.status.reports == []
    np.testing.assert_allclose(viewer_b.robot_state.q, q_b, atol=1e-4)
    # Its own cell's traffic reached the operator; of cell-b, not even liveliness.
    assert op_b.robot_state is None and op_b.camera_frame is None, spawn.texts()
    assert op_b.status.label == "not connected" and viewer_b.status.label == "connected"
    assert "telerobot/cell-a/robot_state" in keys_heard, keys_heard
    assert not [k for k in keys_heard if not k.startswith("telerobot/cell-a/")], keys_heard
    np.testing.assert_allclose(op_a.robot_state.q, q_a, atol=1e-4)

    # The operator's program to its own cell runs.
    op_a.send_program(one_move_program("op-to-a", speed_mps=0.1))

    def a_done() -> bool:
        op_a.poll(), op_b.poll()
        return any(_ended(r, "op-to-a") for r in op_a.status.reports)

    assert wait_until(a_done, PROGRAM_TIMEOUT_S), (op_a.status.reports, spawn.texts())
    ended = [r.status for r in op_a.status.reports if _ended(r, "op-to-a")]
    assert ended == ["done"], (ended, spawn.texts())
    assert np.linalg.norm(op_a.robot_state.q - q_a) > 0.05
    assert op_b.status.reports == []


def test_the_router_refuses_a_plain_listener_on_the_network_and_bad_cells() -> None:
    done = subprocess.run(
        [*ROUTER, "--listen", f"tcp/0.0.0.0:{free_port_pair()}"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "without TLS" in done.stderr and "--insecure" in done.stderr
    done = subprocess.run(
        [*ROUTER, "--listen", "tcp/127.0.0.1:7", "--cell", "a=ws:op"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "--cell needs --certs" in done.stderr
    done = subprocess.run(
        [*ROUTER, "--cell", "no-operators=ws"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2 and "SITE=WORK_SITE_CN:OPERATOR_CN" in done.stderr
