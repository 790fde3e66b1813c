"""The check before sending (operator_site/program/feasibility.py): a program the robot cannot do
is refused with the reason in plain words and the command it concerns. Real geometry and the
arm's own IK; programs made by the task session and the program generator where they can be."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.robot import load_robot
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R
from operator_site.program import (
    check_feasibility,
    choose_grasp_yaw,
    generate_program,
    pick_and_place,
)
from operator_site.program import feasibility as fz
from operator_site.program.commands import contact_states
from operator_site.program.path import path_from_history
from operator_site.task import TaskSession
from protocol import ContactState, MotionCommand, MotionProgram
from work_site.control import controller, executor

SCENE = load_scene()
ROBOT = load_robot(SCENE.robot.urdf_path)


def test_the_work_site_opens_the_fingers_as_wide_as_the_operators_finger_model() -> None:
    """The rules both sites share live in protocol.execution; the finger opening is the robot
    model's, and the work site's executor must open to it."""
    assert executor.GRIPPER_OPEN_M == pytest.approx(ROBOT.finger_opening_max)
    assert controller.Impedance().stiffness_n_per_m == fz.NORMAL_STIFFNESS_N_PER_M


def _cube_against_the_frame() -> TaskSession:
    """The natural first drag: the cube from where it lies straight into the frame's outer
    face near the frame's corner, touching frame and table."""
    session = TaskSession(SCENE)
    session.select("cube")
    target = session.X_WO["cube"].copy()
    target[:3, 3] = (0.345, -0.12, 0.02)
    session.set_target(target)
    for _ in range(200):
        session.step()
    goal = session.path_history()[-1]
    assert {c.object for c in goal.contacts} == {"table", "frame"}
    return session


@pytest.fixture(scope="module")
def against_frame():
    session = _cube_against_the_frame()
    X_GP = choose_grasp_yaw(session.start_X_WO, session.X_GP)
    generated = generate_program(
        "cube-frame",
        SCENE,
        "cube",
        session.path_history(),
        X_GP,
        attached_O=session.fingers_O,
        X_WO=session.X_WO,
    )
    return session, generated.program


def test_a_generated_program_pressing_the_frame_is_feasible(against_frame) -> None:
    session, program = against_frame
    result = check_feasibility(SCENE, "cube", program, session.fingers_O, session.X_WO)
    assert result.ok, result.reason
    assert result.command is None and result.reason == ""


def test_touching_the_frame_but_never_pressing_it_is_refused_naming_the_frame(
    against_frame,
) -> None:
    """Set down next to the frame with the goal's contacts: the guarded move down presses only
    the table, and the work site would read 0 N from the frame."""
    session, generated = against_frame
    path = path_from_history(session.path_history(), "cube", SCENE.object("cube").model.com_O)
    goal = path.nodes[-1]
    program = pick_and_place("set-down", path.nodes[0].X_WO, goal.X_WO, generated.X_GP)
    k = next(i for i, c in enumerate(program.commands) if c.kind == "guarded_move")
    commands = list(program.commands)
    commands[k] = replace(commands[k], contacts=contact_states(goal))
    program = replace(program, commands=tuple(commands))
    result = check_feasibility(SCENE, "cube", program, session.fingers_O, session.X_WO)
    assert not result.ok and result.check == "contact" and result.command == k
    assert "the contact with the frame" in result.reason
    assert "0.0 N" in result.reason
    assert "must be pressed against the frame, or that contact removed" in result.reason


@pytest.mark.parametrize(("off_m", "ok"), [(0.002, True), (0.0045, False)])
def test_a_contact_the_bias_cannot_reach_is_refused(against_frame, off_m, ok) -> None:
    """The goal's frame contact with the block off the frame in the model: the 5 mm bias at
    1,000 N/m presses it with (5 mm − gap) × 1 N/mm, verified from 1 N."""
    session, program = against_frame
    k = max(i for i, c in enumerate(program.commands) if c.kind == "contact_move")
    moved = program.commands[k].X_WP.copy()
    moved[1, 3] -= off_m  # away from the frame's face (its normal is −y)
    commands = list(program.commands)
    commands[k] = replace(commands[k], X_WP=moved)
    program = replace(program, commands=tuple(commands))
    result = check_feasibility(SCENE, "cube", program, session.fingers_O, session.X_WO)
    assert result.ok is ok, result.reason
    if not ok:
        assert result.check == "contact" and result.command == k
        assert "the contact with the frame" in result.reason and "mm from it" in result.reason


def test_a_program_needing_an_unreachable_pose_is_refused() -> None:
    """A carry inside the work site's workspace box but beyond the arm's reach."""
    X_WO = SCENE.object("cube").X_WO
    far = make_pose(X_WO[:3, :3], (0.74, 0.44, 0.025))
    program = pick_and_place("far", X_WO, far, _plain_grasp())
    result = check_feasibility(SCENE, "cube", program)
    assert not result.ok and result.check == "reach"
    assert result.command == 2  # the carry over to the far pose
    assert "the arm cannot move the gripper" in result.reason and "unreachable" in result.reason


def test_a_program_outside_the_workspace_is_refused() -> None:
    X_WO = SCENE.object("cube").X_WO
    off = make_pose(X_WO[:3, :3], (0.80, 0.0, 0.025))
    result = check_feasibility(SCENE, "cube", pick_and_place("off", X_WO, off, _plain_grasp()))
    assert not result.ok and result.check == "reach" and result.command == 2
    assert "outside the robot's workspace" in result.reason


def _plain_grasp() -> np.ndarray:
    """The cube's grasp from above, as the session chooses it."""
    session = TaskSession(SCENE)
    session.select("cube")
    return choose_grasp_yaw(session.X_WO["cube"], session.X_GP)


def test_a_grasp_wider_than_the_gripper_opens_is_refused() -> None:
    """The plank held by its ends, 0.10 m apart."""
    X_WO = SCENE.object("plank").X_WO
    X_OG = make_pose(rpy_to_R(np.array([np.pi, 0.0, 0.5 * np.pi])), (0.0, 0.0, 0.0085))
    program = pick_and_place("ends", X_WO, X_WO, np.linalg.inv(X_OG))
    result = check_feasibility(SCENE, "plank", program)
    assert not result.ok and result.check == "grasp" and result.command == 0
    assert "across 0.100 m" in result.reason


def test_a_grasp_with_a_finger_between_the_block_and_the_wall_is_refused() -> None:
    """The plank pushed side-first against a bar while held across its width: the finger on
    the pressed side is between the plank and the bar."""
    session = TaskSession(SCENE)
    R = rpy_to_R(np.array([0.0, 0.0, 0.5 * np.pi]))
    session.X_WO["plank"] = make_pose(R, (0.45, 0.0, 0.0125))
    session.select("plank")
    start = session.X_WO["plank"].copy()
    goal = start.copy()
    goal[0, 3] = 0.55 - 0.025 - 1e-4  # its long side on the bar's inner face
    frame = ContactState(object="frame", normals_W=np.array([[-1.0, 0.0, 0.0]]))
    table = ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]]))
    commands = (
        MotionCommand("guarded_grasp", start, 0.1, 10.0, (table,)),
        MotionCommand("contact_move", goal, 0.01, 30.0, (table, frame)),
        MotionCommand("release", goal, 0.0, 10.0, (table, frame)),
    )
    program = MotionProgram(program_id="side", X_GP=session.X_GP, commands=commands)
    result = check_feasibility(SCENE, "plank", program, session.fingers_O, session.X_WO)
    assert not result.ok and result.check == "grasp"
    assert "a finger would be between the plank and the frame" in result.reason


@pytest.mark.parametrize(("task", "seed"), [("corner", 0), ("corner", 1), ("around-corner", 4)])
def test_the_scripted_tasks_programs_are_feasible(task, seed) -> None:
    """No false refusals: the programs the end-to-end runs send (and the robot does)."""
    from operator_site.scripted import layout_demonstration
    from operator_site.session import generated_program

    session = layout_demonstration(task, seed).session
    program = generated_program(session, f"{task}-{seed}").program  # checks feasibility itself
    result = check_feasibility(
        session.scene, session.workpiece, program, session.fingers_O, session.X_WO
    )
    assert result.ok, result.reason


def test_the_generator_refuses_a_task_the_robot_cannot_do() -> None:
    """The plank pushed side-first against a bar, held as selected: the page's "make program"
    gets the reason (a ValueError, as for the sweep's refusals)."""
    from operator_site.program import ProgramInfeasibleError, ProgramRefusedError

    session = TaskSession(SCENE)
    R = rpy_to_R(np.array([0.0, 0.0, 0.5 * np.pi]))
    session.X_WO["plank"] = make_pose(R, (0.45, 0.0, 0.0125))
    session.select("plank")
    target = session.X_WO["plank"].copy()
    target[:3, 3] = (0.53, 0.0, 0.0075)
    session.set_target(target)
    for _ in range(300):
        session.step()
    assert session.choose_grasp_for_path().grasp is None
    with pytest.raises(ProgramInfeasibleError, match="between the plank and the frame") as info:
        generate_program(
            "side",
            SCENE,
            "plank",
            session.path_history(),
            choose_grasp_yaw(session.start_X_WO, session.X_GP),
            attached_O=session.fingers_O,
            X_WO=session.X_WO,
        )
    assert isinstance(info.value, ProgramRefusedError) and isinstance(info.value, ValueError)
    assert info.value.feasibility.check == "grasp" and info.value.check.segment == 0


def test_a_grasp_from_below_is_refused() -> None:
    X_WO = SCENE.object("cube").X_WO
    program = pick_and_place("below", X_WO, X_WO, np.eye(4))  # the gripper's z up
    result = check_feasibility(SCENE, "cube", program)
    assert not result.ok and result.check == "grasp" and result.command == 0
    assert "does not hold the cube from above" in result.reason


def test_the_grasp_yaw_is_chosen_for_the_whole_way_not_only_the_start() -> None:
    """A block that lies a little off the best wrist angle and is then turned by a hundred
    degrees: chosen at the start alone, the grasp ends with the gripper's x along +x of W, at
    the end of joint 6's range; chosen over the path, it takes the grasp turned half a turn."""
    X_GP = make_pose(np.diag([-1.0, 1.0, -1.0]))

    def at(yaw_deg: float) -> np.ndarray:
        return make_pose(rpy_to_R(np.radians([0.0, 0.0, yaw_deg])), (0.45, 0.0, 0.025))

    def x_W(X_WP: np.ndarray, grasp: np.ndarray) -> float:
        return float((X_WP @ np.linalg.inv(grasp))[0, 0])

    start, path = at(80.0), [at(a) for a in (100.0, 140.0, 180.0)]
    np.testing.assert_array_equal(choose_grasp_yaw(start, X_GP), X_GP)  # the start alone
    chosen = choose_grasp_yaw(start, X_GP, path)
    assert max(x_W(X, chosen) for X in [start, *path]) < 0.2
    assert x_W(path[-1], X_GP) == pytest.approx(1.0)  # what the start alone would have done


def test_a_movable_object_is_predicted_pressed_as_the_work_site_presses_it() -> None:
    """The work site caps a sideways press on a movable block at MOVABLE_PRESS_N: the operator
    site predicts that force (and the table's 5 N), so a contact 1 mm off in the model still
    verifies, and one 1.6 mm off does not."""
    from operator_site.program.feasibility import predicted_contact_forces_n
    from protocol import ContactState, MotionCommand, MotionProgram
    from protocol.execution import MOVABLE_PRESS_N

    contacts = (
        ContactState(object="l_block", normals_W=np.array([[-1.0, 0.0, 0.0]])),
        ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]])),
    )
    move = MotionCommand("contact_move", np.eye(4), 0.01, 10.0, contacts)
    program = MotionProgram(program_id="p", X_GP=np.eye(4), commands=(move,))
    forces = predicted_contact_forces_n(program, 0, {"l_block": 0.0}, {"l_block"})
    assert [(name, round(f, 9)) for name, _, f in forces] == [
        ("l_block", MOVABLE_PRESS_N),
        ("table", 5.0),
    ]
    near = predicted_contact_forces_n(program, 0, {"l_block": 0.001}, {"l_block"})
    far = predicted_contact_forces_n(program, 0, {"l_block": 0.0016}, {"l_block"})
    assert near[0][2] == pytest.approx(MOVABLE_PRESS_N) and far[0][2] < 1.0
    fixed = predicted_contact_forces_n(program, 0, {"l_block": 0.0}, set())
    assert fixed[0][2] == pytest.approx(5.0)


def test_contacts_the_robot_can_feel_and_those_it_cannot() -> None:
    from types import SimpleNamespace

    from operator_site.program.feasibility import contact_move_forces_n, felt_contacts

    def touching(*pairs):
        return SimpleNamespace(
            contacts=[
                SimpleNamespace(object=name, normals_W=np.array([n], dtype=float))
                for name, n in pairs
            ]
        )

    # In a corner, a contact move presses the table and both walls: all three are felt.
    corner = touching(("table", (0, 0, 1)), ("frame", (1, 0, 0)), ("bar", (0, 1, 0)))
    assert felt_contacts(corner) == {"table": True, "frame": True, "bar": True}
    # Squeezed between two opposite walls: no press reaches both, so neither is felt.
    squeezed = touching(("table", (0, 0, 1)), ("frame", (1, 0, 0)), ("bar", (-1, 0, 0)))
    felt = felt_contacts(squeezed)
    assert felt["table"] and not (felt["frame"] and felt["bar"])
    # A movable block pressed sideways is pressed with at most MOVABLE_PRESS_N: still felt.
    side = touching(("table", (0, 0, 1)), ("cube", (1, 0, 0)))
    assert felt_contacts(side, {"cube"}) == {"table": True, "cube": True}
    assert contact_move_forces_n([]).shape == (0,)
