"""A work site behind mutual TLS and zenoh access control: only the authenticated operator can
make it move. The work site is a real process (deploy/serve_work_site.py: the server of
``work-site serve`` with TLS certificates and access control)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from operator_site.link import WorkSiteLink
from protocol import ProtocolError, make_config
from protocol.session import (
    TlsFiles,
    check_listeners,
    is_loopback_endpoint,
    operator_only_access_control,
)
from tests.conftest import free_port, one_move_program, wait_until

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
SITE = "secure"
STARTUP_TIMEOUT_S = 20.0
REFUSED_WINDOW_S = 3.0
"""How long an intruder is given to get through (its attempts are repeated meanwhile)."""


@pytest.fixture
def secure_work_site(certs: Path, tmp_path: Path) -> Iterator[str]:
    """A work site on ``tls/localhost:<port>`` with mutual TLS and operator-only commands."""
    endpoint = f"tls/localhost:{free_port()}"
    log_path = tmp_path / "work_site.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                str(REPO / "deploy" / "serve_work_site.py"),
                "--listen",
                endpoint,
                "--site-id",
                SITE,
                "--no-camera",
                "--certs",
                str(certs),
                "--operators",
                "operator",
            ],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    try:
        yield endpoint
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        print(log_path.read_text(errors="replace")[-3000:])


@pytest.fixture
def links() -> Iterator[Callable[..., WorkSiteLink]]:
    opened: list[WorkSiteLink] = []

    def open_link(config) -> WorkSiteLink:
        link = WorkSiteLink(config, SITE)
        opened.append(link)
        return link

    yield open_link
    for link in opened:
        link.close()


def tls_config(endpoint: str, certs: Path, name: str, ca: str = "ca.pem"):
    return make_config(
        connect=[endpoint],
        tls=TlsFiles.in_dir(certs, name, ca),
    )


def connected(link: WorkSiteLink, timeout_s: float) -> bool:
    return wait_until(lambda: (link.poll(), link.status.label == "connected")[1], timeout_s)


def reports_of(link: WorkSiteLink, program_id: str) -> list[str]:
    link.poll()
    return [r.status for r in link.status.reports if r.program_id == program_id]


def try_to_command(link: WorkSiteLink, program_id: str) -> None:
    """Keep sending a valid program and a stop for :data:`REFUSED_WINDOW_S`."""
    deadline = time.monotonic() + REFUSED_WINDOW_S
    while time.monotonic() < deadline:
        link.send_program(one_move_program(program_id))
        link.send_stop("intruder")
        link.poll()
        time.sleep(0.2)


def test_access_control_config_is_accepted_by_zenoh() -> None:
    conf = make_config(access_control=operator_only_access_control("site1", ["op-a", "op-b"]))
    assert '"cert_common_names":["op-a","op-b"]' in conf.get_json("access_control")


def test_unauthenticated_peers_cannot_connect_or_command(
    secure_work_site: str, certs: Path, links
) -> None:
    endpoint = secure_work_site
    operator = links(tls_config(endpoint, certs, "operator"))
    assert connected(operator, STARTUP_TIMEOUT_S), "the operator could not connect"
    q_home = operator.robot_state.q.copy()

    tcp_port = endpoint.rsplit(":", 1)[1]
    no_client_cert = make_config(connect=[endpoint])
    no_client_cert.insert_json5(
        "transport/link/tls/root_ca_certificate", f'"{certs / "ca.pem"}"'
    )  # server verified, but no certificate of its own: not authenticated
    intruders = {
        "plain-tcp": make_config(connect=[f"tcp/localhost:{tcp_port}"]),
        "no-client-cert": no_client_cert,
        "other-ca": tls_config(endpoint, certs, "intruder"),  # CN=operator from a rogue CA
    }
    for name, config in intruders.items():
        intruder = links(config)
        try_to_command(intruder, f"from-{name}")
        assert not intruder.status.work_site_alive, f"{name} got a session"
        assert intruder.robot_state is None, f"{name} received robot state"
        assert reports_of(operator, f"from-{name}") == [], name
    # Nothing ran: no report of any kind, and the arm is where it was.
    operator.poll()
    assert operator.status.reports == []
    np.testing.assert_allclose(operator.robot_state.q, q_home, atol=1e-4)


def test_only_the_operator_may_command(secure_work_site: str, certs: Path, links) -> None:
    endpoint = secure_work_site
    operator = links(tls_config(endpoint, certs, "operator"))
    viewer = links(tls_config(endpoint, certs, "viewer"))
    assert connected(operator, STARTUP_TIMEOUT_S)
    # The viewer is authenticated and may watch: it gets the robot's state...
    assert connected(viewer, STARTUP_TIMEOUT_S)
    q_home = operator.robot_state.q.copy()
    # ...but its programs and stops are dropped by access control before the work site sees them.
    try_to_command(viewer, "from-viewer")
    assert reports_of(operator, "from-viewer") == []
    np.testing.assert_allclose(operator.robot_state.q, q_home, atol=1e-4)

    # The operator's program runs, and the viewer's stop cannot interrupt it.
    operator.send_program(one_move_program("from-operator", speed_mps=0.05))
    assert wait_until(lambda: "started" in reports_of(operator, "from-operator"), 10.0)
    for _ in range(5):
        viewer.send_stop("viewer tries to stop")
        time.sleep(0.1)
    assert wait_until(lambda: "done" in reports_of(operator, "from-operator"), 30.0), reports_of(
        operator, "from-operator"
    )
    statuses = reports_of(operator, "from-operator")
    assert "stopped" not in statuses and statuses[0] == "accepted"
    assert np.linalg.norm(operator.robot_state.q - q_home) > 0.05  # it really moved
    # And the operator's own stop is obeyed.
    operator.send_program(one_move_program("slow", speed_mps=0.01, p_WP=(0.30, 0.1, 0.25)))
    assert wait_until(lambda: "started" in reports_of(operator, "slow"), 10.0)
    operator.send_stop("operator stops")
    assert wait_until(lambda: "stopped" in reports_of(operator, "slow"), 5.0)


# ------------------------------------------------- listeners reachable from the network need TLS


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/127.0.0.1:7447",
        "tcp/127.3.2.1:7447?prio=0-3",
        "tcp/[::1]:7447",
        "tcp/localhost:7447",
        "udp/127.0.0.1:7447",
        "unixsock-stream//tmp/work-site.sock",
    ],
)
def test_loopback_listeners_stay_unauthenticated(endpoint: str) -> None:
    assert is_loopback_endpoint(endpoint)
    check_listeners([endpoint], tls=None)


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/0.0.0.0:7447",
        "tcp/[::]:7447",
        "tcp/10.77.0.2:7447",
        "tcp/robot.example.org:7447?prio=4-7",
        "udp/0.0.0.0:7447",
        "tls/0.0.0.0:7447",  # TLS without certificates is refused too
    ],
)
def test_a_plain_listener_on_the_network_is_refused_unless_insecure(endpoint: str) -> None:
    assert not is_loopback_endpoint(endpoint)
    with pytest.raises(ProtocolError, match="--certs DIR") as e:
        check_listeners(["tcp/127.0.0.1:7447", endpoint], tls=None)
    assert "\n" not in str(e.value) and "--insecure" in str(e.value)
    check_listeners([endpoint], tls=None, insecure=True)


def test_a_tls_listener_with_certificates_is_accepted(certs: Path) -> None:
    tls = TlsFiles.in_dir(certs, "work-site")
    check_listeners(["tls/0.0.0.0:7447?prio=0-3", "tls/0.0.0.0:7448?prio=4-7"], tls)
    with pytest.raises(ProtocolError, match=r"tcp/0\.0\.0\.0:7449 without TLS"):
        check_listeners(["tls/0.0.0.0:7447", "tcp/0.0.0.0:7449"], tls)  # certs, but plain TCP


def _serve(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "work_site", "serve", "--no-camera", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def test_work_site_serve_refuses_a_plain_listener_on_every_interface(certs: Path) -> None:
    port = free_port()
    done = _serve("--listen", f"tcp/0.0.0.0:{port}")
    assert done.returncode == 2
    lines = [line for line in done.stderr.splitlines() if line.startswith("work-site")]
    assert len(lines) == 1, done.stderr  # one line (pybullet prints its build time first)
    assert f"on tcp/0.0.0.0:{port} without TLS" in lines[0]
    assert f"--listen tls/0.0.0.0:{port} --certs DIR" in lines[0]
    assert "--insecure" in lines[0] and "serving" not in done.stdout
    # Certificates do not make a tcp/ listener secure; --operators needs certificates.
    done = _serve("--listen", f"tcp/0.0.0.0:{port}", "--certs", str(certs))
    assert done.returncode == 2 and "without TLS" in done.stderr
    done = _serve("--listen", f"tcp/127.0.0.1:{port}", "--operators", "operator")
    assert done.returncode == 2 and "--operators needs --certs" in done.stderr


def test_insecure_allows_a_plain_listener_for_a_lab(links) -> None:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "work_site", "serve", "--no-camera", "--insecure",
         "--single-link", "--listen", f"tcp/0.0.0.0:{port}", "--site-id", SITE],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        link = links(make_config(connect=[f"tcp/127.0.0.1:{port}"]))
        assert connected(link, STARTUP_TIMEOUT_S)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=15)
    serving = [line for line in out.splitlines() if line.startswith("work-site: serving")]
    assert serving and serving[0].endswith("; --insecure"), out  # said on the start-up line
