"""Shared fixtures: free loopback ports and a real work-site process."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from bench.netsafety import GRIPPER_DOWN, WorkSiteProcess, start_work_site
from bench.netsafety import wait_until as wait_until  # re-exported: the tests import it here
from models.transforms import make_pose
from protocol import MotionCommand, MotionProgram
from protocol.session import free_port_pair

REPO = Path(__file__).resolve().parents[1]

# Work sites started by the tests keep their program journals (``work_site.cli.default_journal``)
# here, not in the user's state directory: two runs of the suite, or a test and a demo, never
# share a site's journal and the ids it remembers.
_STATE_HOME = tempfile.TemporaryDirectory(prefix="telerobot-tests-state-")
os.environ["XDG_STATE_HOME"] = _STATE_HOME.name

FAST_TIER = os.environ.get("TELEROBOT_TESTS") == "fast"
"""``make test-fast`` sets ``TELEROBOT_TESTS=fast``: property tests then draw a tenth of their
examples (:func:`examples`), for a quick look; ``make test`` draws them all."""
EXTREMES_TIER = os.environ.get("TELEROBOT_TESTS") == "extremes"
"""``make test-extremes`` sets ``TELEROBOT_TESTS=extremes``: property tests draw 25 times their
examples (5,000 for the 200 of the extremes tests), a nightly-sized run."""


def stop_like_ctrl_c(
    proc: subprocess.Popen, timeout_s: float = 30.0, log_path: Path | None = None
) -> tuple[str, str]:
    """SIGINT to ``proc``'s process group (what Ctrl-C in its terminal does; it was started
    with ``start_new_session``) and wait for it to end; its (stdout, stderr) where they were
    pipes ("" where not). One that lingers past ``timeout_s`` is asked for its threads' stacks
    (SIGUSR1: the sites' faulthandler), killed, and fails the test with what it printed (the
    end of ``log_path`` if its output went there)."""
    os.killpg(proc.pid, signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        ended = proc.poll() is not None
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGUSR1)
            time.sleep(STACK_DUMP_WAIT_S)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        try:
            out, err = proc.communicate(timeout=STACK_DUMP_WAIT_S)
        except subprocess.TimeoutExpired as e:  # a child in its own group holds its pipes
            proc.wait()
            for pipe in (proc.stdout, proc.stderr):
                if pipe is not None:
                    pipe.close()
            out, err = (x.decode(errors="replace") if x else "" for x in (e.stdout, e.stderr))
        logged = "" if log_path is None else log_path.read_text()[-LOG_TAIL_CHARS:]
        what = "ended, but a child of its held its output open" if ended else "did not end"
        pytest.fail(
            f"{proc.args} {what} within {timeout_s} s of SIGINT; it printed (its stacks "
            f"last):\n{out or ''}\n{err or ''}\n{logged}"
        )
    return out or "", err or ""


STACK_DUMP_WAIT_S = 1.0
"""How long a process that did not stop is given to print its stacks before it is killed."""
LOG_TAIL_CHARS = 6000
"""How much of a process's log a failing test shows."""


def examples(n: int) -> int:
    """The number of hypothesis examples for a property test that draws ``n`` in the full run."""
    if FAST_TIER:
        return max(20, n // 10)
    return 25 * n if EXTREMES_TIER else n


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, nor on the next one (a work
    site listens on both: commands on the port, robot state and camera frames on the next)."""
    return free_port_pair()


@pytest.fixture
def work_site(tmp_path: Path) -> Iterator[Callable[..., WorkSiteProcess]]:
    """Start ``python -m work_site serve`` on a free port (:func:`bench.netsafety.start_work_site`:
    ``vision=True`` runs recognition too); killed at the end of the test."""
    started: list[WorkSiteProcess] = []

    def start(*extra: str, site_id: str = "test", vision: bool = False) -> WorkSiteProcess:
        ws = start_work_site(tmp_path, len(started), *extra, site_id=site_id, vision=vision)
        started.append(ws)
        return ws

    yield start
    for ws in started:
        ws.kill()


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


def yielded_niceness() -> int:
    """The niceness a work-site child that yields to the control loop has, started from this
    process (capped at Linux's least priority)."""
    from work_site.child import CHILD_NICENESS

    return min(os.getpriority(os.PRIO_PROCESS, 0) + CHILD_NICENESS, 19)


PROCESS_FIXTURES = frozenset({"work_site", "link_factory", "certs"})
"""Fixtures that start OS processes or network namespaces: a test using one is an integration
test whether or not its module says so (``make test-fast`` leaves them out)."""


ONE_AT_A_TIME = frozenset(
    {
        "tests/test_browser_injection.py",
        "tests/test_browser_ui.py",
        "tests/test_e2e.py",
        "tests/test_runner.py",
        "tests/test_session.py",
    }
)
"""Test files that run a whole chain (work site, vision, operator) beside a heavy load of their
own: Chromium drawing the page in software, or the simulation at three times real time. Two of
them at once overload a two-core machine: the work site's network threads then wait for a CPU
so long that its dead-man stops the robot for heartbeats that were sent on time (a right stop
on a machine that slow, and a wrong test result). ``make test`` runs these files one after
another on one worker, the rest on the other meanwhile."""


def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadfile``, with the :data:`ONE_AT_A_TIME` files one unit of work."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class OneAtATime(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "one-at-a-time" if path in ONE_AT_A_TIME else path

    return OneAtATime(config, log)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if PROCESS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.integration)
