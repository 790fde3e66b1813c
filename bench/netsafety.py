"""Real processes and link faults for the safety measurements: a ``work-site serve`` process,
a garbage flood on the keys it reads, a TCP relay that can be cut, and an observer of its
reports and robot state. Shared by ``python -m bench safety`` and the net tests
(``tests/test_net_flood.py``, ``tests/test_net_deadman.py``, ``tests/test_net_checking.py``),
so that the benchmark measures what the tests assert on.
"""

from __future__ import annotations

import itertools
import os
import queue
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from models.transforms import make_pose, rpy_to_R
from operator_site.link import WorkSiteLink
from protocol import (
    MotionCommand,
    MotionProgram,
    ProtocolError,
    RobotState,
    Stop,
    decode,
    encode,
    key,
    make_config,
)
from protocol.messages import MAX_COMMANDS
from protocol.session import free_port_pair

REPO = Path(__file__).resolve().parents[1]

GRIPPER_DOWN = rpy_to_R(np.array([np.pi, 0.0, np.pi]))
"""A gripper orientation pointing down, as the tests' and benchmarks' programs use."""

FLOOD_KEYS = ("stop", "program", "heartbeat")
"""Every key the work site reads."""
FLOOD_RATE_HZ = 12_000.0
"""Garbage messages a second on each key (the goal is ≥ 10,000; pacing loses a little)."""


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.05) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` passes; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()


# ------------------------------------------------------------------------ the work site


@dataclass
class WorkSiteProcess:
    """A running ``python -m work_site serve`` (its own process group) and its log file."""

    proc: subprocess.Popen
    endpoint: str
    site_id: str
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def kill(self) -> None:
        """SIGKILL its process group (vision runs in a child) and reap it."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()


def start_work_site(
    run_dir: Path, index: int, *extra: str, site_id: str = "test", vision: bool = False
) -> WorkSiteProcess:
    """Start ``python -m work_site serve`` on a free loopback port, its log and journal
    (``work_site_INDEX.log``, ``journal_INDEX.jsonl``) in ``run_dir``. ``vision``: run
    recognition too (off by default: it costs a core)."""
    endpoint = f"tcp/127.0.0.1:{free_port_pair()}"
    if not vision and "--vision-rate" not in extra:
        extra = (*extra, "--vision-rate", "0")
    if "--journal" not in extra:  # each its own: program ids repeat across runs
        extra = (*extra, "--journal", str(run_dir / f"journal_{index}.jsonl"))
    log_path = run_dir / f"work_site_{index}.log"
    argv = [sys.executable, "-m", "work_site", "serve", "--listen", endpoint,
            "--site-id", site_id, *extra]  # fmt: skip
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            argv,
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    return WorkSiteProcess(proc, endpoint, site_id, log_path)


# ------------------------------------------------------------------------ programs


def moves_program(
    program_id: str, points: Sequence[Sequence[float]], speed_mps: float = 0.05
) -> MotionProgram:
    """Straight free moves of the gripper (pointing down) through ``points`` (m, in W)."""
    commands = tuple(
        MotionCommand(
            kind="move",
            X_WP=make_pose(GRIPPER_DOWN, [float(v) for v in p]),
            speed_mps=speed_mps,
            force_limit_n=10.0,
            contacts=(),
        )
        for p in points
    )
    return MotionProgram(program_id=program_id, X_GP=np.eye(4), commands=commands)


def long_check_program(program_id: str) -> MotionProgram:
    """MAX_COMMANDS valid moves back and forth: checked whole, each target through the IK."""
    points = [(0.40, -0.1, 0.15), (0.41, -0.1, 0.15)]
    return moves_program(program_id, [points[i % 2] for i in range(MAX_COMMANDS)], 0.1)


# ------------------------------------------------------------------------ faults


class Flood:
    """A publisher thread (its own zenoh session: another peer) putting garbage on ``keys``
    at ``rate_hz`` each while :attr:`on` is set; counts what it put and for how long."""

    def __init__(
        self,
        endpoint: str,
        site_id: str,
        keys: Sequence[str] = FLOOD_KEYS,
        rate_hz: float = FLOOD_RATE_HZ,
    ) -> None:
        self.session = zenoh.open(make_config(connect=[endpoint]))
        self.pubs = [self.session.declare_publisher(key(site_id, k)) for k in keys]
        self.rate_hz = rate_hz
        self.on, self.done = threading.Event(), threading.Event()
        self.sent, self.flood_s = 0, 0.0
        rng = np.random.default_rng(7)
        valid = bytearray(encode(Stop(reason="x" * 40, stamp_s=1.0)))
        self.garbage = [rng.bytes(int(n)) for n in rng.integers(1, 300, 64)]
        for _ in range(64):  # near misses too: a stop with one byte changed, no longer valid
            corrupt = bytearray(valid)
            corrupt[int(rng.integers(0, len(corrupt)))] ^= 0xFF
            try:
                decode(bytes(corrupt), expected=Stop)
            except ProtocolError:
                self.garbage.append(bytes(corrupt))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    @property
    def rate_achieved_hz(self) -> float:
        """Messages a second put on each key while on, so far."""
        return self.sent / self.flood_s if self.flood_s > 0 else 0.0

    def _run(self) -> None:
        burst = 50
        i = 0
        while not self.done.is_set():
            if not self.on.wait(0.05):
                continue
            t0 = time.monotonic()
            n = 0
            while self.on.is_set() and not self.done.is_set():
                for _ in range(burst):
                    g = self.garbage[i % len(self.garbage)]
                    i += 1
                    for pub in self.pubs:
                        pub.put(g)
                n += burst
                ahead_s = t0 + n / self.rate_hz - time.monotonic()
                if ahead_s > 0:
                    time.sleep(ahead_s)
            self.sent += n
            self.flood_s += time.monotonic() - t0

    def close(self) -> None:
        self.done.set()
        self.on.clear()
        self.thread.join(5)
        self.session.close()


class Relay:
    """A TCP relay on 127.0.0.1:``port`` to ``target``; :meth:`cut` stops forwarding in both
    directions and keeps the connections open (a partition: nothing is closed or reset)."""

    def __init__(self, port: int, target: tuple[str, int]) -> None:
        self.target = target
        self.server = socket.create_server(("127.0.0.1", port))
        self.cut_event, self.done = threading.Event(), threading.Event()
        self._forwarding = threading.Lock()
        self.threads = [threading.Thread(target=self._accept, daemon=True)]
        self.threads[0].start()

    @classmethod
    def to(cls, endpoint: str) -> Relay:
        """A relay on a free port to a ``tcp/HOST:PORT`` endpoint."""
        host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
        return cls(free_port_pair(), (host, int(port)))

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.server.getsockname()[1]}"

    def cut(self) -> float:
        """Stop forwarding; the time (``time.time()``) after which nothing more got through:
        bytes being forwarded as the cut comes are through before it counts."""
        with self._forwarding:
            self.cut_event.set()
            return time.time()

    def _accept(self) -> None:
        self.server.settimeout(0.1)
        while not self.done.is_set():
            try:
                client, _ = self.server.accept()
            except TimeoutError:
                continue
            upstream = socket.create_connection(self.target)
            t = threading.Thread(target=self._pump, args=(client, upstream), daemon=True)
            t.start()
            self.threads.append(t)

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        peer = {a: b, b: a}
        with a, b:
            while not self.done.is_set():
                ready, _, _ = select.select([a, b], [], [], 0.1)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    with self._forwarding:
                        if not self.cut_event.is_set():
                            peer[s].sendall(data)

    def close(self) -> None:
        self.done.set()
        for t in self.threads:
            t.join(2)
        self.server.close()


# ------------------------------------------------------------------------ observing


class Observer:
    """A second operator site that sends nothing (so it never beats): it sees the reports and
    every robot state (a FIFO of its own, not the link's newest-few ring) directly from the
    work site ``ws`` (anything with ``endpoint`` and ``site_id``)."""

    def __init__(self, ws, timeout_s: float = 20.0) -> None:
        self.link = WorkSiteLink(
            make_config(connect=[ws.endpoint]), ws.site_id, heartbeat_process=False
        )
        # Every state, on zenoh's thread, into a queue this thread drains (also after the link
        # renewed its session).
        self._states_in: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self.link.follow("robot_state", lambda s: self._states_in.put(s.payload.to_bytes()))
        self.states: list[RobotState] = []
        self.also_poll: list[WorkSiteLink] = []
        """Operator links polled with this one (their re-sends of unanswered programs)."""
        if not wait_until(lambda: (self.poll(), self.link.status.label == "connected")[1],
                          timeout_s):  # fmt: skip
            self.close()
            raise TimeoutError(f"no robot state from {ws.endpoint} in {timeout_s} s")

    def poll(self) -> None:
        for link in self.also_poll:
            link.poll()
        self.link.poll()
        while not self._states_in.empty():
            try:
                self.states.append(decode(self._states_in.get(), expected=RobotState))
            except ProtocolError:
                pass

    def report(self, pid: str, index: int, status: str):
        for r in self.link.status.reports:
            if (r.program_id, r.command_index, r.status) == (pid, index, status):
                return r
        return None

    def wait_report(self, pid: str, index: int, status: str, timeout_s: float):
        """The report (``pid``, ``index``, ``status``) once it came; TimeoutError if not."""
        if not wait_until(
            lambda: (self.poll(), self.report(pid, index, status) is not None)[1],
            timeout_s,
            poll_s=0.002,
        ):
            raise TimeoutError((pid, index, status, self.link.status.reports[-6:]))
        return self.report(pid, index, status)

    def wait_states_until(self, stamp_s: float, timeout_s: float = 2.0) -> None:
        """Wait until a state stamped at or after ``stamp_s`` (work site's clock) came."""
        if not wait_until(
            lambda: (self.poll(), bool(self.states) and self.states[-1].stamp_s >= stamp_s)[1],
            timeout_s,
            poll_s=0.005,
        ):
            raise TimeoutError(f"no robot state stamped after {stamp_s}")

    def motion_after(self, stamp_s: float, periods: int = 0, count: int = 5) -> float:
        """Largest joint motion a control period (rad) in the states from ``periods`` control
        periods after the first one stamped at or after ``stamp_s`` on (waits for ``count`` of
        them). Periods are counted on the states' own clock, their ``seq``: a loaded work site
        falls behind the wall clock but runs every period's physics all the same."""

        def later() -> list[RobotState]:
            first = next((s.seq for s in self.states if s.stamp_s >= stamp_s), None)
            return [] if first is None else [s for s in self.states if s.seq >= first + periods]

        if not wait_until(lambda: (self.poll(), len(later()) >= count)[1], 2 + 0.1 * periods):
            raise TimeoutError(f"fewer than {count} robot states {periods} periods after {stamp_s}")
        return max(motion_per_period(a, b) for a, b in itertools.pairwise(later()))

    def close(self) -> None:
        self.link.close()


def motion_per_period(a: RobotState, b: RobotState) -> float:
    """Largest joint motion (rad) a state period between states ``a`` and ``b``."""
    return float(np.max(np.abs(b.q - a.q))) / max(1, b.seq - a.seq)


def still_since(states: Sequence[RobotState], from_s: float, still_rad: float) -> float | None:
    """The stamp of the first state from ``from_s`` on after which the arm never moved more
    than ``still_rad`` a period among ``states`` (None: it was moving at the last one)."""
    later = [s for s in states if s.stamp_s >= from_s]
    still = None
    for a, b in itertools.pairwise(later):
        if motion_per_period(a, b) >= still_rad:
            still = None
        elif still is None:
            still = b.stamp_s
    return still
