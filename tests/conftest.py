"""Shared fixtures: free loopback ports and a real work-site process."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from models.transforms import make_pose, rpy_to_R
from protocol import MotionCommand, MotionProgram
from protocol.session import free_port_pair

REPO = Path(__file__).resolve().parents[1]

FAST_TIER = os.environ.get("TELEROBOT_TESTS") == "fast"
"""``make test-fast`` sets ``TELEROBOT_TESTS=fast``: property tests then draw a tenth of their
examples (:func:`examples`), for a quick look; ``make test`` draws them all."""


def examples(n: int) -> int:
    """The number of hypothesis examples for a property test that draws ``n`` in the full run."""
    return max(20, n // 10) if FAST_TIER else n


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, nor on the next one (a work
    site listens on both: commands on the port, camera frames on the next)."""
    return free_port_pair()


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.05) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` passes; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()


@dataclass
class WorkSiteProcess:
    proc: subprocess.Popen
    endpoint: str
    site_id: str
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


@pytest.fixture
def work_site(tmp_path: Path) -> Iterator[Callable[..., WorkSiteProcess]]:
    """Start ``python -m work_site serve`` on a free port; killed at the end of the test."""
    started: list[WorkSiteProcess] = []

    def start(*extra: str, site_id: str = "test", vision: bool = False) -> WorkSiteProcess:
        """``vision``: run recognition too (off by default: it costs a core)."""
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        if not vision and "--vision-rate" not in extra:
            extra = (*extra, "--vision-rate", "0")
        if "--journal" not in extra:  # each test its own: program ids repeat across tests
            extra = (*extra, "--journal", str(tmp_path / f"journal_{len(started)}.jsonl"))
        log_path = tmp_path / f"work_site_{len(started)}.log"
        with log_path.open("w") as log:
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "work_site",
                    "serve",
                    "--listen",
                    endpoint,
                    "--site-id",
                    site_id,
                    *extra,
                ],
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        ws = WorkSiteProcess(proc, endpoint, site_id, log_path)
        started.append(ws)
        return ws

    yield start
    for ws in started:
        if ws.proc.poll() is None:
            os.killpg(ws.proc.pid, signal.SIGKILL)
            ws.proc.wait()


@pytest.fixture(scope="session")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Test certificates from deploy/make-certs.sh (CA, work-site, operator, router, viewer, and
    an intruder of another CA); the test is skipped, saying why, without openssl."""
    if shutil.which("openssl") is None:
        print("skipping TLS tests: no openssl")
        pytest.skip("openssl is needed to make test certificates")
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(
        [str(REPO / "deploy" / "make-certs.sh"), str(out)], check=True, capture_output=True
    )
    return out


GRIPPER_DOWN = rpy_to_R(np.array([np.pi, 0.0, np.pi]))
"""A gripper orientation pointing down, as the tests' programs use."""


def one_move_program(
    program_id: str, speed_mps: float = 0.05, p_WP: tuple = (0.40, -0.1, 0.15)
) -> MotionProgram:
    """A valid, reachable one-move program: a work site that gets it runs it."""
    command = MotionCommand(
        kind="move",
        X_WP=make_pose(GRIPPER_DOWN, p_WP),
        speed_mps=speed_mps,
        force_limit_n=10.0,
        contacts=(),
    )
    return MotionProgram(program_id=program_id, X_GP=np.eye(4), commands=(command,))


PROCESS_FIXTURES = frozenset({"work_site", "link_factory", "certs"})
"""Fixtures that start OS processes or network namespaces: a test using one is an integration
test whether or not its module says so (``make test-fast`` leaves them out)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if PROCESS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.integration)
