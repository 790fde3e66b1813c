"""A stopped program resumed: the real WorkSiteServer's program handling in-process (a real
world, a stand-in report publisher), as tests/test_journal.py drives it. Over zenoh with the
operator's command line: tests/test_recovery.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.transforms import make_pose
from protocol import MotionCommand, MotionProgram
from tests.conftest import GRIPPER_DOWN
from tests.test_journal import send, server_on, world  # noqa: F401  (a fixture)

MOVE_TICKS_MAX = 3000


def three_moves(program_id: str) -> MotionProgram:
    """Three reachable moves of the empty hand, slow enough to be stopped in the second."""
    poses = [(0.40, -0.10, 0.15), (0.40, 0.05, 0.15), (0.35, 0.05, 0.20)]
    commands = tuple(
        MotionCommand(
            kind="move", X_WP=make_pose(GRIPPER_DOWN, p), speed_mps=0.05, force_limit_n=10.0,
            contacts=(),
        )
        for p in poses
    )  # fmt: skip
    return MotionProgram(program_id=program_id, X_GP=np.eye(4), commands=commands)


def run_until(server, done) -> None:
    for _ in range(MOVE_TICKS_MAX):
        server._control_tick()
        if done():
            assert server._journal.sync(10.0)  # its reports sent, as they go once on file
            return
    raise AssertionError("the program did not get there")


def reports_of(server, pid: str) -> list[tuple]:
    assert server._journal.sync(10.0)  # reports go out once they are on file
    return [
        (r.command_index, r.status, r.message)
        for r in server._pub_report.reports
        if r.program_id == pid
    ]


@pytest.fixture
def server(tmp_path, world):  # noqa: F811
    server = server_on(tmp_path / "programs.jsonl", world)
    yield server
    server._journal.close()


def stopped_in_its_second_move(server) -> MotionProgram:
    program = three_moves("first")
    assert [r[2] for r in send(server, program)] == ["accepted"]
    run_until(server, lambda: server._execution.index == 1)
    server._execution.stop("no heartbeat from the operator for 0.5 s")
    server._control_tick()
    assert reports_of(server, "first")[-1][:2] == (-1, "stopped")
    return program


def test_a_stopped_program_resumes_at_the_command_it_was_stopped_in(server) -> None:
    program = stopped_in_its_second_move(server)
    resumed = dataclasses.replace(program, program_id="first-again", continues="first")
    assert [r[2] for r in send(server, resumed)] == ["accepted"]
    run_until(server, lambda: server._execution.finished)
    got = reports_of(server, "first-again")
    started = [i for i, status, _ in got if status == "started" and i >= 0]
    assert started == [1, 2], got  # not the first move again
    assert got[-1][:2] == (-1, "done"), got
    X = server._controller.commanded_tcp_W()
    np.testing.assert_allclose(X[:3, 3], program.commands[-1].X_WP[:3, 3], atol=1e-3)


def test_a_resume_is_refused_with_the_reason_unless_it_goes_on_from_the_last_stop(server) -> None:
    program = stopped_in_its_second_move(server)
    other = dataclasses.replace(three_moves("x"), X_GP=make_pose(np.eye(3), (0, 0, 0.01)))
    changed = dataclasses.replace(other, program_id="changed", continues="first")
    (refusal,) = send(server, changed)
    assert refusal[2] == "refused" and "not that program's" in refusal[3]
    unknown = dataclasses.replace(program, program_id="who", continues="nobody")
    (refusal,) = send(server, unknown)
    assert refusal[2] == "refused" and "program first ran last" in refusal[3]
    # Another program runs: the stopped one can no longer be resumed.
    assert [r[2] for r in send(server, three_moves("between"))] == ["accepted"]
    run_until(server, lambda: server._execution.finished)
    late = dataclasses.replace(program, program_id="late", continues="first")
    (refusal,) = send(server, late)
    assert refusal[2] == "refused" and "program between ran last" in refusal[3]
    done = dataclasses.replace(program, program_id="done-one", continues="between")
    (refusal,) = send(server, done)
    assert refusal[2] == "refused" and "ran to its end, not stopped" in refusal[3]


def test_the_approach_the_check_planned_is_the_one_the_execution_takes(server) -> None:
    """A grasp whose approach needs a joint-space move: the check plans it on its own thread
    and hands it over, so the control loop does not plan (it may take longer than a period)."""
    from models.transforms import rpy_to_R

    X_WP = make_pose(rpy_to_R(np.radians([0.0, 0.0, 20.0])), (0.2, 0.22, 0.025))
    X_GP = make_pose(rpy_to_R(np.array([0.0, 0.0, np.pi]))) @ make_pose(
        rpy_to_R(np.array([np.pi, 0.0, np.pi]))
    )
    grasp = MotionCommand(
        kind="guarded_grasp", X_WP=X_WP, speed_mps=0.05, force_limit_n=10.0, contacts=()
    )
    program = MotionProgram(program_id="turned-grasp", X_GP=X_GP, commands=(grasp,))
    assert [r[2] for r in send(server, program)] == ["accepted"]
    approach = server._execution.approaches[0]
    assert approach.ok and approach.q_joint is not None
    server._execution.stop("enough")
