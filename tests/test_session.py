"""The operator's workflow, headless (:class:`OperatorSession`): a task recorded as it is dragged,
saved in the task-file format, loaded and made into the same program; programs saved, loaded and
sent again under new ids; and a task saved from the session run with ``operator-site run``
making the same program."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.scene import load_scene
from models.transforms import so3_exp, so3_log
from operator_site.program.commands import CommandParams
from operator_site.session import OperatorSession, load_program, save_program
from operator_site.taskfile import load_task, save_task
from tests.conftest import REPO

SAME_PROGRAM_M = 1e-3
SAME_PROGRAM_RAD = np.radians(0.5)


def _drag(op: OperatorSession, X_WD: np.ndarray, steps: int = 80) -> None:
    op.mark()
    for k in range(1, 11):  # a mouse drag: the target moves in small moves
        X = X_WD.copy()
        X[:3, 3] = op.task.sim.state.X_WD[:3, 3] + (X_WD[:3, 3] - op.task.sim.state.X_WD[:3, 3]) * (
            k / 10
        )
        op.set_target(X)
        op.step()
    for _ in range(steps):
        op.step()


def _corner_session() -> OperatorSession:
    """The cube of the scene file's layout dragged into the frame's near left inside corner:
    over the bar, down inside, pressed into the corner."""
    op = OperatorSession(load_scene())
    op.use_scene_layout()
    op.select("cube")
    X = op.task.X_WO["cube"].copy()
    up = X.copy()
    up[2, 3] += 0.06
    _drag(op, up)
    inside = up.copy()
    inside[:3, 3] = (0.40, -0.05, up[2, 3])
    _drag(op, inside)
    down = inside.copy()
    down[2, 3] = X[2, 3] - 0.003
    _drag(op, down)
    corner = down.copy()
    corner[:3, 3] += (-0.06, -0.06, 0.0)
    _drag(op, corner)
    return op


def assert_same_program(a, b) -> None:
    assert len(a.commands) == len(b.commands)
    for ca, cb in zip(a.commands, b.commands, strict=True):
        assert ca.kind == cb.kind
        assert np.linalg.norm(ca.X_WP[:3, 3] - cb.X_WP[:3, 3]) <= SAME_PROGRAM_M
        turn = np.linalg.norm(so3_log(ca.X_WP[:3, :3].T @ cb.X_WP[:3, :3]))
        assert turn <= SAME_PROGRAM_RAD
        assert [c.object for c in ca.contacts] == [c.object for c in cb.contacts]


def test_a_dragged_task_is_recorded_relative_to_its_reference(tmp_path: Path) -> None:
    op = _corner_session()
    task = op.recorded_task("cube into the corner")
    assert task.workpiece == "cube" and task.reference == "frame"
    assert set(task.goal.contacts) == {"frame", "table"}
    X_WF = op.model.scene().object("frame").X_WO
    np.testing.assert_allclose(X_WF @ task.steps[0].X_RD, op.task.start_X_WO, atol=1e-12)
    np.testing.assert_allclose(X_WF @ task.goal.X_RO, op.task.X_WO["cube"], atol=1e-12)
    # Recorded at most a millimetre apart (and where a drag ended), not every mouse event.
    assert 4 < len(task.steps) < 400
    path = tmp_path / "corner.json"
    save_task(task, path)
    back = load_task(path)
    assert back.name == task.name and len(back.steps) == len(task.steps)
    for a, b in zip(back.steps, task.steps, strict=True):
        np.testing.assert_allclose(a.X_RD, b.X_RD, atol=1e-9)
    # Measured from the table instead: the same task in W.
    op.set_reference("table")
    X_WT = op.model.scene().object("table").X_WO
    np.testing.assert_allclose(
        X_WT @ op.recorded_task().goal.X_RO, X_WF @ task.goal.X_RO, atol=1e-12
    )
    with pytest.raises(ValueError, match="own reference"):
        op.set_reference("cube")


def test_captures_are_recorded_where_they_were_made() -> None:
    op = OperatorSession(load_scene())
    op.use_scene_layout()
    op.select("cube")
    X = op.task.X_WO["cube"].copy()
    along = X.copy()
    along[:3, 3] += (0.03, 0.0, -0.003)
    _drag(op, along)
    assert op.toggle_capture("table")
    n = len(op.recorded_task().steps)
    further = along.copy()
    further[0, 3] += 0.02
    _drag(op, further)
    steps = op.recorded_task().steps
    assert steps[n - 1].capture == ("table",) and all(s.capture is None for s in steps[n:])
    assert not op.toggle_capture("table")
    assert op.recorded_task().steps[-1].release == ("table",)
    op.undo()  # takes back the last drag and what was recorded in it
    assert len(op.recorded_task().steps) == n


def test_the_program_is_made_from_the_task_as_data(tmp_path: Path) -> None:
    """The page's program, and the program of the same task loaded from its file in another
    session on the same layout, are one program."""
    op = _corner_session()
    made = op.make_program("corner-a")
    path = tmp_path / "corner.json"
    save_task(op.recorded_task(), path)
    other = OperatorSession(load_scene())
    other.use_scene_layout()
    other.load(load_task(path))
    assert_same_program(made.program, other.make_program("corner-b").program)


def test_a_task_that_cannot_be_done_here_says_why() -> None:
    op = OperatorSession(load_scene())
    with pytest.raises(ValueError, match="pick a block"):
        op.recorded_task()
    op.use_scene_layout()
    op.remove("cube")
    task = load_task(REPO / "examples" / "tasks" / "cube-corner.json")
    with pytest.raises(ValueError, match="workpiece: 'cube' is not in the model"):
        op.load(task)
    op.use_scene_layout()
    op.set_reference("plank")
    op.select("plank")  # the reference was the workpiece: back to the frame
    assert op.reference == "frame"
    with pytest.raises(ValueError, match="'nonexistent' is not in the model"):
        op.set_reference("nonexistent")


def test_programs_are_saved_loaded_and_sent_again_under_new_ids(tmp_path: Path) -> None:
    op = _corner_session()
    program = op.make_program().program
    path = tmp_path / "p.msgpack"
    save_program(path, program)
    back = load_program(path)
    assert back.program_id == program.program_id and len(back.commands) == len(program.commands)
    again = op.renamed(back)
    assert again.program_id != program.program_id and again.commands == back.commands
    path.write_bytes(b"\x93garbage")
    with pytest.raises(ValueError, match=r"p\.msgpack: not a robot program"):
        load_program(path)
    with pytest.raises(ValueError, match="cannot read it"):
        load_program(tmp_path / "missing.msgpack")
    with pytest.raises(RuntimeError, match="no work site"):
        op.send(program)


@pytest.mark.integration
def _merged(program) -> list[tuple[str, list[str]]]:
    """The program's kinds and contacts in order, a run of equal ones counted once."""
    steps = [(c.kind, [k.object for k in c.contacts]) for c in program.commands]
    return [step for i, step in enumerate(steps) if i == 0 or step != steps[i - 1]]


def _along(X: np.ndarray, path: list[np.ndarray]) -> tuple[float, float]:
    """How far (m) and how much turned (rad) the pose X is from the nearest point of the
    piecewise-linear pose path (positions linear, rotations geodesic between its poses)."""
    best = (np.inf, np.inf)
    for A, B in itertools.pairwise(path):
        ab = B[:3, 3] - A[:3, 3]
        t = float(np.clip((X[:3, 3] - A[:3, 3]) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0))
        R = A[:3, :3] @ so3_exp(t * so3_log(A[:3, :3].T @ B[:3, :3]))
        d = float(np.linalg.norm(X[:3, 3] - A[:3, 3] - t * ab))
        best = min(best, (d, float(np.linalg.norm(so3_log(R.T @ X[:3, :3])))))
    return best


def assert_same_motion(a, b) -> None:
    """``a`` and ``b`` move the block alike, to the fit's tolerances: the same kinds and contacts
    in order (a run of one kind may have a target more or fewer), every target within the
    fit's tolerances of the other's targets' path, and the same first and last targets. The
    fit places a target where the path strays further than its tolerance from a chord, so a
    path micrometres different may cross that line and gain or lose a target."""
    params = CommandParams()
    assert _merged(a) == _merged(b)
    for one, other in ((a, b), (b, a)):
        path = [c.X_WP for c in other.commands]
        for c in one.commands:
            d, turn = _along(c.X_WP, path)
            assert d <= params.position_tol_m and turn <= params.angle_tol_rad, (d, turn)
    for i in (0, -1):
        apart_m = np.linalg.norm(a.commands[i].X_WP[:3, 3] - b.commands[i].X_WP[:3, 3])
        assert apart_m <= SAME_PROGRAM_M


def test_a_task_saved_from_the_session_runs_with_the_same_program(tmp_path: Path) -> None:
    """``operator-site run`` on the scene file's layout (its vision the work site's ground
    truth, so both sides see one layout, to the micrometres the physics settles the blocks by)
    makes the program the session made, to the fit's tolerances; ``--dry-run`` sends it not."""
    op = _corner_session()
    mine = op.make_program("mine").program
    task_path = tmp_path / "corner.json"
    save_task(op.recorded_task("cube into the corner, from the session"), task_path)
    program_path = tmp_path / "run.msgpack"
    scene_path = REPO / "models" / "scenes" / "puzzle.json"
    out = subprocess.run(
        [sys.executable, "-m", "operator_site", "run", str(task_path), "--scene",
         str(scene_path), "--oracle-vision", "--dry-run", "--json",
         "--save-program", str(program_path)],
        capture_output=True, text=True, timeout=600, cwd=REPO,
    )  # fmt: skip
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert program_path.exists(), (result, out.stderr[-3000:])
    assert_same_motion(mine, load_program(program_path))
    assert result["success"] and out.returncode == 0, result
    assert result["sent"] is False and "execution" not in result, result
