"""The dead-man: a work site stops the robot when the heartbeats of the operator whose program
runs stop coming (its process killed, its link cut), and says why. Real processes over zenoh on
loopback; the link is cut by a TCP relay that stops forwarding (no FIN, no RST: a partition)."""

from __future__ import annotations

import itertools
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from bench.control import corner_program
from models.scene import load_scene
from operator_site.link import HEARTBEAT_PERIOD_S, WorkSiteLink
from protocol import make_config
from tests.conftest import REPO, free_port, wait_until
from work_site.control.controller import EASE_S

pytestmark = pytest.mark.integration

DEADMAN_S = 0.5
CONTROL_PERIOD_S = 0.01
TRANSPORT_ALLOWANCE_S = 0.005
"""Loopback delivery of the last beat, on top of the work site's bound."""
STILL_RAD = 2e-4
"""Joint motion in a control period that counts as still (rad)."""
PRESSING_N = 3.0
"""The link is cut once the contact move presses this hard (N)."""
HOLD_FORCE_N = 1.0
"""After a stop in contact, the hold presses no more than this (N): the wrist reads within it
of what it read carrying the block in free air."""


class Observer:
    """A second operator site that sends nothing (so it never beats): it sees the reports and
    the robot state directly from the work site."""

    def __init__(self, ws) -> None:
        self.link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
        self.states: list = []
        assert wait_until(lambda: (self.poll(), self.link.status.label == "connected")[1], 20), (
            ws.log()
        )

    def poll(self) -> None:
        if self.link.poll()[0]:
            self.states.append(self.link.robot_state)

    def report(self, pid: str, index: int, status: str):
        for r in self.link.status.reports:
            if (r.program_id, r.command_index, r.status) == (pid, index, status):
                return r
        return None

    def wait_report(self, pid: str, index: int, status: str, timeout_s: float):
        assert wait_until(
            lambda: (self.poll(), self.report(pid, index, status) is not None)[1],
            timeout_s,
            poll_s=0.005,
        ), (pid, index, status, self.link.status.reports[-6:])
        return self.report(pid, index, status)

    def motion_after(self, stamp_s: float) -> float:
        """Largest joint motion a control period (rad) in the states stamped from ``stamp_s``
        on (waits for a few)."""
        assert wait_until(
            lambda: (self.poll(), sum(s.stamp_s >= stamp_s for s in self.states) >= 5)[1], 2
        )
        later = [s for s in self.states if s.stamp_s >= stamp_s]
        return max(
            float(np.max(np.abs(b.q - a.q))) / (b.seq - a.seq) for a, b in itertools.pairwise(later)
        )

    def close(self) -> None:
        self.link.close()


def check_deadman_stop(
    observer: Observer, pid: str, silent_s: float, still_after_s: float = CONTROL_PERIOD_S
) -> float:
    """The program was stopped for want of heartbeats within DEADMAN_S and a control period
    of ``silent_s`` (time.time() when the operator fell silent: its last beat was no later), and
    not before a beat can have been missed; the arm is still from ``still_after_s`` after the
    stop on. Returns the delay from ``silent_s`` (s)."""
    stopped = observer.wait_report(pid, -1, "stopped", 5)
    assert stopped.message == f"no heartbeat from the operator for {DEADMAN_S:g} s", stopped
    delay_s = stopped.stamp_s - silent_s
    low_s = DEADMAN_S - HEARTBEAT_PERIOD_S - CONTROL_PERIOD_S
    assert low_s <= delay_s <= DEADMAN_S + CONTROL_PERIOD_S + TRANSPORT_ALLOWANCE_S, delay_s
    assert observer.motion_after(stopped.stamp_s + still_after_s) <= STILL_RAD
    return delay_s


def test_an_operator_killed_mid_program_stops_the_arm_within_the_deadman(work_site) -> None:
    ws = work_site("--no-camera", "--deadman-s", str(DEADMAN_S))
    observer = Observer(ws)
    points = ("0.40,-0.1,0.15", "0.45,-0.1,0.12", "0.45,0.0,0.12", "0.40,0.05,0.15")
    operator = subprocess.Popen(
        [sys.executable, "-m", "tests.operator_process", ws.endpoint, ws.site_id, "killed",
         *points],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    try:
        observer.wait_report("killed", 1, "started", 60)
        time.sleep(0.3)  # the program ran well past a dead-man's timeout: the operator beats
        assert observer.report("killed", -1, "stopped") is None
        silent_s = time.time()
        operator.send_signal(signal.SIGKILL)
        operator.wait()
        delay_s = check_deadman_stop(observer, "killed", silent_s)
    finally:
        if operator.poll() is None:
            operator.kill()
            operator.wait()
        observer.close()
    print(f"SIGKILL: stopped {1e3 * delay_s:.1f} ms after the kill")
    assert "no heartbeat from the operator" in ws.log()


class Relay:
    """A TCP relay on 127.0.0.1:``port`` to ``target``; :meth:`cut` stops forwarding in both
    directions and keeps the connections open (a partition: nothing is closed or reset)."""

    def __init__(self, port: int, target: tuple[str, int]) -> None:
        self.target = target
        self.server = socket.create_server(("127.0.0.1", port))
        self.cut_event, self.done = threading.Event(), threading.Event()
        self.threads = [threading.Thread(target=self._accept, daemon=True)]
        self.threads[0].start()

    def cut(self) -> None:
        self.cut_event.set()

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
                    if not self.cut_event.is_set():
                        peer[s].sendall(data)

    def close(self) -> None:
        self.done.set()
        for t in self.threads:
            t.join(2)
        self.server.close()


def test_a_link_cut_during_a_contact_move_stops_and_eases_the_press(work_site) -> None:
    ws = work_site("--no-camera", "--deadman-s", str(DEADMAN_S))
    observer = Observer(ws)
    host_port = ws.endpoint.removeprefix("tcp/").rsplit(":", 1)
    relay = Relay(free_port(), (host_port[0], int(host_port[1])))
    operator = WorkSiteLink(
        make_config(connect=[f"tcp/127.0.0.1:{relay.server.getsockname()[1]}"]), ws.site_id
    )
    try:
        assert wait_until(lambda: (operator.poll(), operator.status.label == "connected")[1], 20)
        cube = next(o for o in load_scene().objects if o.name == "cube")
        program, _ = corner_program(cube.X_WO)
        contact = [c.kind for c in program.commands].index("contact_move")
        set_down = contact - 1  # a guarded move onto the table, after the carry
        operator.send_program(program)
        free_S = None
        for _ in range(3000):  # the operator polls as a page would, until the contact move
            operator.poll()
            observer.poll()
            if free_S is None and observer.report("corner", set_down, "started") is not None:
                free_S = observer.link.robot_state.wrench_S[:3].copy()  # carried, no contact
            if observer.report("corner", contact, "started") is not None:
                break
            time.sleep(0.01)
        observer.wait_report("corner", contact, "started", 1)
        pressing, above = 0.0, 0
        for _ in range(1000):  # until it presses into the corner (past the start's transient)
            operator.poll()
            if observer.link.poll()[0]:
                observer.states.append(observer.link.robot_state)
                pressing = float(np.linalg.norm(observer.link.robot_state.wrench_S[:3] - free_S))
                above = above + 1 if pressing >= PRESSING_N else 0
                if above >= 5:
                    break
            time.sleep(0.005)
        assert observer.report("corner", contact, "contact_verified") is None  # still moving
        silent_s = time.time()
        relay.cut()
        # In contact the hand first eases off the press (EASE_S), then holds still.
        delay_s = check_deadman_stop(observer, "corner", silent_s, EASE_S + CONTROL_PERIOD_S)
        stopped = observer.report("corner", -1, "stopped")
        for _ in range(100):
            observer.poll()
            time.sleep(0.005)
        held = [s for s in observer.states if s.stamp_s >= stopped.stamp_s + 0.2]
        hold_n = max(np.linalg.norm(s.wrench_S[:3] - free_S) for s in held)
        easing = [s for s in observer.states if s.stamp_s >= stopped.stamp_s]
        easing_n = max(np.linalg.norm(s.wrench_S[:3] - free_S) for s in easing)
    finally:
        operator.close()
        relay.close()
        observer.close()
    print(
        f"link cut in contact: stopped {1e3 * delay_s:.1f} ms after the cut; contact force "
        f"pressing {pressing:.2f} N, easing off at most {easing_n:.2f} N, held {hold_n:.2f} N"
    )
    assert easing_n <= pressing + HOLD_FORCE_N  # easing off does not jolt the hand
    assert pressing >= PRESSING_N  # it was pressing when the link was cut ...
    assert hold_n <= HOLD_FORCE_N, (pressing, hold_n)  # ... and is no longer
