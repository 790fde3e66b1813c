"""Two real OS processes over zenoh on loopback: the work-site server and an operator client."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request

import msgpack
import numpy as np
import pytest
import zenoh

from models.robot import PUMA_URDF, load_robot
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R
from operator_site.link import WorkSiteLink
from operator_site.program import park_pose_W
from operator_site.ui import OperatorPage
from protocol import MotionCommand, MotionProgram, encode, key, make_config
from tests.conftest import REPO, free_port, wait_until

pytestmark = pytest.mark.integration

ROBOT = load_robot(PUMA_URDF)
STARTUP_TIMEOUT_S = 20.0  # the bound for ≥ 50 states and ≥ 1 frame
LIVELINESS_TIMEOUT_S = 5.0


@pytest.fixture
def link_to(request):
    links: list[WorkSiteLink] = []

    def connect(ws) -> WorkSiteLink:
        link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
        links.append(link)
        return link

    yield connect
    for link in links:
        link.close()


def test_client_receives_state_and_frames_then_sees_the_server_die(work_site, link_to) -> None:
    ws = work_site()
    link = link_to(ws)
    states: list = []
    frames: list = []

    def collect() -> bool:
        new_state, new_frame = link.poll()
        if new_state:
            states.append(link.robot_state)
        if new_frame:
            frames.append(link.camera_frame)
        return len(states) >= 50 and len(frames) >= 1 and link.status.work_site_alive

    assert wait_until(collect, STARTUP_TIMEOUT_S), (
        f"got {len(states)} states, {len(frames)} frames, alive={link.status.work_site_alive}; "
        f"work-site log:\n{ws.log()}"
    )
    assert link.status.label == "connected"
    assert link.status.rejected == 0
    seqs = [s.seq for s in states]
    assert seqs == sorted(seqs)
    q_home = load_scene().robot.q_home_rad
    np.testing.assert_allclose(states[-1].q, q_home, atol=1e-3)
    frame = frames[-1]
    assert frame.encoding == "jpeg"  # the default for a remote operator
    assert frame.image.shape == (480, 640) and frame.image.dtype == np.uint8
    assert frame.image.std() > 10
    np.testing.assert_allclose(frame.X_WC, load_scene().camera.X_WC)

    os.killpg(ws.proc.pid, signal.SIGKILL)
    ws.proc.wait()
    assert wait_until(
        lambda: (link.poll(), not link.status.work_site_alive)[1], LIVELINESS_TIMEOUT_S
    ), "liveliness did not go down after SIGKILL"
    assert link.status.label == "not connected"


FORGED_FRAME_TRIES = 5
"""Times a forged frame is sent until the link reads it (a real frame can displace it)."""


@pytest.mark.parametrize("encoding", ["raw", "png", "jpeg:75"])
def test_frames_arrive_in_the_encoding_the_work_site_was_given(work_site, link_to, encoding):
    ws = work_site("--camera-encoding", encoding)
    link = link_to(ws)
    assert wait_until(lambda: (link.poll(), link.camera_frame is not None)[1], STARTUP_TIMEOUT_S), (
        ws.log()
    )
    frame = link.camera_frame
    name, _, quality = encoding.partition(":")
    assert frame.encoding == name
    if quality:
        assert frame.quality == int(quality)
    assert frame.image.shape == (480, 640) and frame.image.dtype == np.uint8
    assert frame.image.std() > 10  # a real picture, not a blank
    assert link.status.rejected == 0
    # A frame whose image is not what its encoding says is refused by the link, counted, and
    # the last good frame stays; the next good one still arrives.
    env = msgpack.unpackb(encode(frame), raw=False)
    for i, wrong in enumerate(("png" if name != "png" else "jpeg", "gif")):
        env["b"]["encoding"] = wrong  # one at a time: the link reads only the newest frame,
        # so a real frame arriving in the same poll displaces the forged one unread: put again
        for _ in range(FORGED_FRAME_TRIES):
            link.session.put(key(ws.site_id, "camera"), msgpack.packb(env, use_bin_type=True))
            if wait_until(lambda i=i: (link.poll(), link.status.rejected > i)[1], 1.0):
                break
        assert link.status.rejected == i + 1
        assert link.camera_frame.image.std() > 10
    seq = link.camera_frame.seq
    assert wait_until(lambda: (link.poll(), link.camera_frame.seq > seq)[1], STARTUP_TIMEOUT_S)
    assert link.camera_frame.encoding == name
    assert ws.proc.poll() is None


def test_bad_payloads_are_refused_and_the_server_keeps_running(work_site, link_to) -> None:
    ws = work_site("--no-camera")
    link = link_to(ws)
    assert wait_until(
        lambda: (link.poll(), link.status.label == "connected")[1], STARTUP_TIMEOUT_S
    ), ws.log()
    garbage = [b"", b"\xc1", b"\x93\x01\x02", b"{not msgpack", os.urandom(1000)]
    for payload in garbage:
        link.session.put(key(ws.site_id, "program"), payload)
        link.session.put(key(ws.site_id, "stop"), payload)
    program = MotionProgram(
        program_id="p1",
        X_GP=np.eye(4),
        commands=(
            MotionCommand(
                kind="move", X_WP=np.eye(4), speed_mps=0.05, force_limit_n=10.0, contacts=()
            ),
        ),
    )
    link.send_program(program)
    # The stop after the program's answer: a stop while it is still being checked cancels it
    # ("stopped"), which is not what this test is about.
    assert wait_until(
        lambda: (link.poll(), any(r.program_id == "p1" for r in link.status.reports))[1], 10.0
    ), (link.status.reports, ws.log())
    link.send_stop("test")

    def reports_arrived() -> bool:
        link.poll()
        return len(link.status.reports) >= len(garbage) + 2

    assert wait_until(reports_arrived, 10.0), (link.status.reports, ws.log())
    # The stop found nothing running: it is answered all the same.
    replies = [r for r in link.status.reports if r.program_id == "stop"]
    assert [r.status for r in replies] == ["stopped"] and "the arm is held" in replies[0].message
    reports = [r for r in link.status.reports if r.program_id != "stop"]
    assert all(r.status == "refused" for r in reports)
    assert sum(r.program_id == "invalid" for r in reports) == len(garbage)
    # Well-formed but unsafe: the gripper would go to the robot's base.
    assert any(r.program_id == "p1" and "outside the workspace" in r.message for r in reports)
    # Still alive and publishing after all that.
    assert ws.proc.poll() is None
    before = link.robot_state.seq
    assert wait_until(lambda: (link.poll(), link.robot_state.seq > before + 10)[1], 5.0)
    assert "malformed program" in ws.log()


def test_sigterm_stops_the_server_cleanly(work_site, link_to) -> None:
    ws = work_site()
    link = link_to(ws)
    assert wait_until(
        lambda: (link.poll(), link.status.label == "connected")[1], STARTUP_TIMEOUT_S
    ), ws.log()
    ws.proc.send_signal(signal.SIGTERM)
    assert ws.proc.wait(timeout=15) == 0
    assert "stopped" in ws.log()
    assert wait_until(lambda: (link.poll(), not link.status.work_site_alive)[1], 2.0)


def test_operator_page_shows_the_live_work_site(work_site, link_to) -> None:
    ws = work_site()
    link = link_to(ws)
    port = free_port()
    page = OperatorPage(load_scene(), link, port=port)
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as response:
            assert response.status == 200
            assert b"<html" in response.read().lower()

        def shown() -> bool:
            page.update()
            return page.frames_shown >= 1 and page.states_shown >= 10

        assert wait_until(shown, STARTUP_TIMEOUT_S), ws.log()
        assert link.status.label == "connected"
        # The frame, in colour, with the model's blocks outlined on it: every pixel off the
        # outlines is the frame's grey.
        shown_rgb, grey = page.camera_image.image, link.camera_frame.image
        assert shown_rgb.shape == (*grey.shape, 3)
        assert (shown_rgb == grey[..., None]).all(axis=2).mean() > 0.9
    finally:
        page.close()


def test_page_stays_up_while_the_work_site_is_absent_and_comes_back(work_site, link_to) -> None:
    ws = work_site()
    os.killpg(ws.proc.pid, signal.SIGKILL)
    ws.proc.wait()
    link = link_to(ws)  # connects to an endpoint nobody serves: retried in the background
    page = OperatorPage(load_scene(), link, port=free_port())
    try:
        for _ in range(10):
            page.update()
        assert link.status.label == "not connected"
        # A work site appears on the same endpoint: the link comes up without a restart.
        conf = make_config(listen=[ws.endpoint])
        with zenoh.open(conf) as session:
            token = session.liveliness().declare_token(f"telerobot/{ws.site_id}/alive/work_site")
            assert wait_until(lambda: (page.update(), link.status.work_site_alive)[1], 15.0)
            token.undeclare()
        assert wait_until(lambda: (page.update(), not link.status.work_site_alive)[1], 5.0)
    finally:
        page.close()


DOWN = rpy_to_R(np.array([np.pi, 0.0, np.pi]))


def move(x: float, y: float, z: float, speed: float = 0.1) -> MotionCommand:
    return MotionCommand(
        kind="move",
        X_WP=make_pose(DOWN, (x, y, z)),
        speed_mps=speed,
        force_limit_n=10.0,
        contacts=(),
    )


def reports_of(link: WorkSiteLink, program_id: str) -> list:
    return [r for r in link.status.reports if r.program_id == program_id]


def test_a_program_runs_reports_in_order_and_a_stop_halts_it(work_site, link_to) -> None:
    ws = work_site("--no-camera")
    link = link_to(ws)
    assert wait_until(
        lambda: (link.poll(), link.status.label == "connected")[1], STARTUP_TIMEOUT_S
    ), ws.log()
    program = MotionProgram(
        program_id="two_moves",
        X_GP=np.eye(4),
        commands=(move(0.40, -0.1, 0.15), move(0.45, -0.1, 0.12)),
    )
    link.send_program(program)
    assert wait_until(
        lambda: (
            link.poll(),
            any(
                r.status == "done" and r.command_index == -1 for r in reports_of(link, "two_moves")
            ),
        )[1],
        20.0,
    ), (link.status.reports, ws.log())
    statuses = [(r.command_index, r.status) for r in reports_of(link, "two_moves")]
    assert statuses == [
        (-1, "accepted"),
        (0, "started"),
        (0, "done"),
        (1, "started"),
        (1, "done"),
        (-1, "done"),
    ]
    X_WF = link.robot_state.X_WF
    X_WG = ROBOT.tcp_pose_W(link.robot_state.q)
    assert np.linalg.norm(X_WG[:3, 3] - [0.45, -0.1, 0.12]) < 1e-3, X_WF
    # The same id again (a re-send) is not run again: its reports are replayed, and this link
    # keeps each once.
    q_done = link.robot_state.q.copy()
    link.send_program(program)
    time.sleep(1.0)
    link.poll()
    assert [(r.command_index, r.status) for r in reports_of(link, "two_moves")] == statuses
    np.testing.assert_allclose(link.robot_state.q, q_done, atol=1e-4)
    # A new operator process asking again gets the whole history, in order.
    other = link_to(ws)
    assert wait_until(lambda: (other.poll(), other.status.label == "connected")[1], 10.0)
    other.send_program(program)
    assert wait_until(
        lambda: (other.poll(), len(reports_of(other, "two_moves")) == len(statuses))[1], 10.0
    ), reports_of(other, "two_moves")
    assert [(r.command_index, r.status) for r in reports_of(other, "two_moves")] == statuses
    assert other.pending_programs() == []
    # A slow long move, stopped on the way: the arm holds short of the goal.
    slow = MotionProgram(
        program_id="slow", X_GP=np.eye(4), commands=(move(0.30, 0.1, 0.25, speed=0.02),)
    )
    link.send_program(slow)
    assert wait_until(
        lambda: (link.poll(), any(r.status == "started" for r in reports_of(link, "slow")))[1], 10.0
    )
    link.send_stop("operator pressed stop")
    assert wait_until(
        lambda: (link.poll(), any(r.status == "stopped" for r in reports_of(link, "slow")))[1], 5.0
    ), ws.log()
    q_stop = link.robot_state.q.copy()
    assert wait_until(lambda: (link.poll(), link.robot_state.seq > 0)[1], 1.0)
    time.sleep(0.5)
    link.poll()
    np.testing.assert_allclose(link.robot_state.q, q_stop, atol=2e-3)  # held, not moving on
    assert np.linalg.norm(ROBOT.tcp_pose_W(link.robot_state.q)[:3, 3] - [0.30, 0.1, 0.25]) > 0.02


def test_drag_confirm_send_and_the_robot_does_it(work_site, link_to) -> None:
    """The operator's whole loop today: pick the cube on the page, drag it 8 cm along the
    table (towards the robot), make the program, send it; the real work site grasps, carries
    and places it."""
    ws = work_site("--no-camera")
    link = link_to(ws)
    page = OperatorPage(load_scene(), link, port=free_port())
    try:
        assert wait_until(
            lambda: (page.update(), link.status.label == "connected")[1], STARTUP_TIMEOUT_S
        ), ws.log()
        page.on_select("cube")
        start = page.session.X_WO["cube"].copy()
        page.dragger.position = tuple(start[:3, 3] + [-0.08, 0.0, -0.003])
        page.on_drag()
        for _ in range(80):
            page.step_task()
        goal = page.session.X_WO["cube"].copy()
        assert goal[0, 3] == pytest.approx(start[0, 3] - 0.08, abs=1e-3)
        page.on_make_program()
        program = page.pending_program
        assert program is not None and not page.send_button.disabled
        kinds = [c.kind for c in program.commands]
        # Grasp, lift off the table (the slide was not a required contact), set it down again
        # with the table required, release, back off upwards, rise clear of the blocks, park.
        tail = ["release", "move", "move", "move"]
        assert kinds[0] == "guarded_grasp" and kinds[-4:] == tail, kinds
        assert kinds[-5] == "contact_move" and program.commands[-5].contacts[0].object == "table"
        page.on_send_program()
        assert page.send_button.disabled and page.pending_program is None

        def finished() -> bool:
            page.update()
            return any(
                r.program_id == program.program_id
                and r.command_index == -1
                and r.status in ("done", "failed", "refused")
                for r in link.status.reports
            )

        assert wait_until(finished, 60.0), (link.status.reports, ws.log())
        last = [r for r in link.status.reports if r.program_id == program.program_id][-1]
        assert last.status == "done", f"{last.message} ({ws.log()[-3000:]})"
        # The gripper ends parked, out of the way of the block it put down.
        X_WG = ROBOT.tcp_pose_W(link.robot_state.q)
        np.testing.assert_allclose(X_WG[:3, 3], park_pose_W(page.scene)[:3, 3], atol=2e-3)
    finally:
        page.close()


def test_a_work_site_restarted_mid_program_never_runs_it_twice(work_site, link_to, tmp_path):
    journal = tmp_path / "programs.jsonl"
    ws = work_site("--no-camera", "--journal", str(journal))
    link = link_to(ws)
    assert wait_until(lambda: (link.poll(), link.status.label == "connected")[1], 20.0), ws.log()
    slow = MotionProgram(
        program_id="slow", X_GP=np.eye(4), commands=(move(0.30, 0.1, 0.25, speed=0.02),)
    )
    link.send_program(slow)
    assert wait_until(
        lambda: (link.poll(), any(r.status == "started" for r in reports_of(link, "slow")))[1], 10
    )
    os.killpg(ws.proc.pid, signal.SIGKILL)  # no goodbye: a crash
    ws.proc.wait()
    assert wait_until(lambda: (link.poll(), not link.status.work_site_alive)[1], 15.0)
    assert link.pending_programs() == ["slow"]
    # The same site comes back on the same endpoint with its journal; the link asks again.
    again = work_site("--no-camera", "--journal", str(journal), "--listen", ws.endpoint)
    assert wait_until(
        lambda: (link.poll(), any(r.status == "failed" for r in reports_of(link, "slow")))[1], 30
    ), again.log()
    statuses = [(r.command_index, r.status) for r in reports_of(link, "slow")]
    assert statuses == [(-1, "accepted"), (0, "started"), (-1, "failed")], statuses
    assert "restarted during this program" in reports_of(link, "slow")[-1].message
    assert link.pending_programs() == []
    assert "program slow received again" in again.log()


def _operator_process(ws, program_id: str, *args: str) -> subprocess.Popen:
    """A real operator process (bench/operator_process.py) sending a program of moves."""
    return subprocess.Popen(
        [sys.executable, "-m", "bench.operator_process", ws.endpoint, ws.site_id, program_id,
         *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip


def _read_lines(proc: subprocess.Popen, until, timeout_s: float) -> list[dict]:
    """JSON lines of ``proc``'s output until ``until(line)`` holds (or it ends)."""
    lines: list[dict] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = proc.stdout.readline()
        if not text:
            break
        lines.append(json.loads(text))
        if until(lines[-1]):
            break
    return lines


def test_an_operator_killed_mid_program_and_restarted_loses_nothing(work_site) -> None:
    """The operator's process dies (SIGKILL) while its program runs: its heartbeats stop and
    the work site's dead-man stops the program. A new process sends the same program id: the
    work site does not run it again, and the new process gets every report in order through
    the end."""
    ws = work_site("--no-camera")
    points = ("0.40,-0.1,0.15", "0.45,-0.1,0.12", "0.45,0.0,0.12", "0.40,0.05,0.15")
    first = _operator_process(ws, "relay", *points)
    try:
        seen = _read_lines(first, lambda ln: (ln.get("i"), ln.get("status")) == (1, "started"), 60)
        assert [(ln["i"], ln["status"]) for ln in seen][-1] == (1, "started"), (seen, ws.log())
        first.kill()  # SIGKILL: no goodbye, no undeclaring
        first.wait()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        first.stdout.close()
    # The dead-man ends the program; a new process asking after that gets the replay.
    assert wait_until(lambda: "no heartbeat from the operator" in ws.log(), 5), ws.log()
    second = _operator_process(ws, "relay", *points)
    try:
        lines = _read_lines(second, lambda ln: "end" in ln or "error" in ln, 120)
    finally:
        if second.poll() is None:
            second.kill()
        second.wait()
        second.stdout.close()
    assert lines and lines[-1].get("end"), (lines, ws.log())
    expected = [[-1, "accepted"], [0, "started"], [0, "done"], [1, "started"], [-1, "stopped"]]
    assert lines[-1]["reports"] == expected, (lines, ws.log())
    assert lines[-1]["pending"] == []
    assert "no heartbeat from the operator" in lines[-2]["message"], lines[-2]
    # Every report arrived in the new process, none twice.
    received = [[ln["i"], ln["status"]] for ln in lines[:-1]]
    assert sorted(received) == sorted(expected)
    # Run once: accepted once, started once per command; the second copy was answered from
    # the reports kept.
    log = ws.log()
    assert log.count("program relay command -1: accepted") == 1, log
    assert log.count("program relay command 0: started") == 1, log
    assert "program relay received again" in log
