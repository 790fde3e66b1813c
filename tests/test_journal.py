"""Exactly once for every program id ever received, with a journal that stays small: the real
WorkSiteServer's program handling in-process (a real world, a stand-in report publisher)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from models.robot import load_robot
from models.scene import load_scene
from protocol import (
    RESERVED_PROGRAM_IDS,
    ExecutionReport,
    MotionCommand,
    MotionProgram,
    decode,
    encode,
)
from tests.conftest import one_move_program
from work_site import journal
from work_site.control.controller import TaskController
from work_site.intake import REMEMBERED_PROGRAMS
from work_site.journal import load_journal, write_journal
from work_site.options import ServerOptions
from work_site.server import WorkSiteServer
from work_site.world import World

COMPACT_AFTER = 1_000
OTHERS = 10_000
STARTUP_IDS = 1_000_000


class _Publisher:
    def __init__(self) -> None:
        self.reports: list[ExecutionReport] = []

    def put(self, payload: bytes) -> None:
        self.reports.append(decode(payload, ExecutionReport))


@pytest.fixture(scope="module")
def world():
    w = World(load_scene())
    yield w
    w.close()


def server_on(path, world) -> WorkSiteServer:
    server = WorkSiteServer(world.scene, zenoh.Config(), ServerOptions(camera=False, journal=path))
    server._controller = TaskController(world, load_robot(world.scene.robot.urdf_path))
    server._pub_report = _Publisher()
    return server


def send(server: WorkSiteServer, program: MotionProgram) -> list[tuple]:
    """Hand ``program`` to the server as the checking thread and the control loop would; the
    reports it sent for it."""
    before = len(server._pub_report.reports)
    server._take_program(program)
    server._start_ready()
    assert server._journal.sync(10.0)  # reports go out once they are on file
    return [
        (r.program_id, r.command_index, r.status, r.message)
        for r in server._pub_report.reports[before:]
    ]


@pytest.mark.slow
def test_an_id_resent_after_10000_others_never_runs(tmp_path, world, monkeypatch) -> None:
    monkeypatch.setattr(journal, "COMPACT_AFTER_LINES", COMPACT_AFTER)
    path = tmp_path / "programs.jsonl"
    server = server_on(path, world)
    try:
        assert [r[2] for r in send(server, one_move_program("first"))] == ["accepted"]
        assert server._execution is not None  # it runs
        server._execution.stop("done with it")
        server._release_finished()
        server._execution = None
        assert server._journal.sync(10.0)  # its "stopped" sent before the next program's
        unsafe = MotionCommand(
            kind="move", X_WP=np.eye(4), speed_mps=0.05, force_limit_n=10.0, contacts=()
        )
        for i in range(OTHERS):  # refused (outside the workspace), each remembered
            reports = send(server, MotionProgram(f"other{i}", np.eye(4), (unsafe,)))
            assert [r[2] for r in reports] == ["refused"]
        again = send(server, one_move_program("first"))
        assert server._execution is None and not server._ready  # not run
        assert [r[:3] for r in again] == [("first", -1, "refused")], again
        assert "runs at most once" in again[0][3]
    finally:
        server._journal.close()
    assert server._journal.rewrites >= 1
    lines = path.read_text().splitlines()
    assert len(lines) <= COMPACT_AFTER + REMEMBERED_PROGRAMS + OTHERS // journal.IDS_PER_LINE + 2
    # After a restart from the journal: still never run; a recent one's reports replayed.
    restarted = server_on(path, world)
    try:
        again = send(restarted, one_move_program("first"))
        assert restarted._execution is None and not restarted._ready
        assert [r[:3] for r in again] == [("first", -1, "refused")], again
        recent = send(restarted, MotionProgram(f"other{OTHERS - 1}", np.eye(4), (unsafe,)))
        assert [r[:3] for r in recent] == [(f"other{OTHERS - 1}", -1, "refused")]
        assert "outside the workspace" in recent[0][3]  # the original answer, replayed
        assert len(restarted._seen) == OTHERS + 1
    finally:
        restarted._journal.close()


@pytest.mark.slow
def test_a_journal_of_a_million_ids_is_read_whole_at_start(tmp_path, world) -> None:
    # How long it takes is printed, not asserted: a test asserts behaviour, never wall time.
    path = tmp_path / "programs.jsonl"
    ids = [f"program-{i:07d}" for i in range(STARTUP_IDS)]
    last = encode(
        ExecutionReport(
            program_id=ids[-1],
            command_index=-1,
            status="done",
            wrench_S=np.zeros(6),
            message="",
            stamp_s=1.0,
        )
    )
    write_journal(path, ids, [(ids[-1], [last])])
    t0 = time.perf_counter()
    server = server_on(path, world)
    startup_s = time.perf_counter() - t0
    server._journal.close()
    print(
        f"start-up with {STARTUP_IDS} ids ({path.stat().st_size / 1e6:.1f} MB): {startup_s:.2f} s"
    )
    assert len(server._seen) == STARTUP_IDS and ids[0] in server._seen
    assert list(server._reports) == [ids[-1]]


def test_a_rewrite_keeps_every_report_once(tmp_path) -> None:
    """Reports queued while the journal rewrites itself are neither lost nor doubled."""
    path = tmp_path / "programs.jsonl"
    state = load_journal(path, REMEMBERED_PROGRAMS)
    lock = threading.Lock()
    reports: dict[str, list[bytes]] = {}

    def snapshot():
        return len(state.ids), [(pid, list(p)) for pid, p in reports.items()]

    writer = journal.JournalWriter(path, state.ids, snapshot, lock, compact_after_lines=50)
    for i in range(500):
        pid = f"p{i % 120}"
        with lock:
            if pid not in reports:
                reports[pid] = []
                state.ids.append(pid)
            payload = encode(
                ExecutionReport(
                    program_id=pid,
                    command_index=-1,
                    status="done",  # final: a reload adds no closing report
                    wrench_S=np.zeros(6),
                    message=str(i),
                    stamp_s=1.0,
                    seq=len(reports[pid]),
                )
            )
            reports[pid].append(payload)
            writer.append(pid, payload)
    writer.close()
    assert writer.rewrites >= 1
    again = load_journal(path, 1000)
    assert dict(again.reports) == reports
    assert again.seen == set(reports)


@pytest.mark.parametrize("reserved", sorted(RESERVED_PROGRAM_IDS))
def test_a_program_named_as_the_work_sites_own_answers_is_refused(
    tmp_path, world, reserved: str
) -> None:
    """Stops that find nothing running are answered under ``stop``, programs without a valid id
    under ``invalid``: a program so named would have those answers taken for its reports."""
    server = server_on(tmp_path / "programs.jsonl", world)
    try:
        reports = send(server, one_move_program(reserved))
        assert server._execution is None and not server._ready
        assert [r[:3] for r in reports] == [("invalid", -1, "refused")], reports
        assert repr(reserved) in reports[0][3] and "choose another" in reports[0][3]
        assert [r[2] for r in send(server, one_move_program("fine"))] == ["accepted"]
    finally:
        server._journal.close()


def test_a_report_is_sent_only_once_it_is_on_file(tmp_path) -> None:
    """A work site killed after sending a report must find it in its journal on restart (else
    it could run a program it said it had received): each report's sending waits for its line."""
    path = tmp_path / "programs.jsonl"
    writer = journal.JournalWriter(path)
    lines_when_sent: list[int] = []
    for seq in range(3):
        payload = encode(
            ExecutionReport(
                program_id="p", command_index=-1, status="accepted", wrench_S=np.zeros(6),
                message="", stamp_s=0.0, seq=seq,
            )
        )  # fmt: skip
        writer.append(
            "p", payload, lambda: lines_when_sent.append(len(path.read_text().splitlines()))
        )
    assert writer.sync(10.0)
    writer.close()
    assert len(lines_when_sent) == 3
    assert all(n >= k + 1 for k, n in enumerate(lines_when_sent)), lines_when_sent


def test_reports_still_go_out_when_the_journal_cannot_be_written(tmp_path) -> None:
    """A journal that fails (its file closed under it, as after a failed rewrite) logs why and
    still sends each report: the operators must keep seeing the robot's state."""
    writer = journal.JournalWriter(tmp_path / "programs.jsonl")
    writer._file.close()
    sent: list[int] = []
    writer.append("p", b"\x00", lambda: sent.append(1))
    assert writer.sync(10.0)
    assert sent == [1]
    writer.close()
