"""Grasps chosen for the task (operator_site/grasp.py): every block held within the stroke clear
of the table, no finger between the workpiece and a surface it is pushed against, today's grasp
kept where it already works. Real geometry: the scene's models, fcl through the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from models.robot import load_robot
from models.scene import load_scene
from models.transforms import invert_pose, make_pose, rpy_to_R
from operator_site.grasp import (
    FINGERTIP_TABLE_CLEARANCE_M,
    GRASP_CLEARANCE_M,
    MIN_GRIP_AREA_M2,
    PAD_FACING_SIN,
    choose_grasp,
    clear_top_grasp,
    finger_parts_O,
    grip_area_m2,
)
from operator_site.scripted import layout_demonstration
from operator_site.simulator.world import SimWorld
from operator_site.task import TaskSession

BLOCKS = ("cube", "tall_block", "plank", "wedge", "l_block", "hex_prism")
SCENE = load_scene()
ROBOT = load_robot(SCENE.robot.urdf_path)


def _closing_W(X_WO: np.ndarray, X_GP: np.ndarray) -> np.ndarray:
    """The fingers' closing direction (G's y) in W for the workpiece at ``X_WO``."""
    return (X_WO @ invert_pose(X_GP))[:3, 1]


@pytest.mark.parametrize("name", BLOCKS)
def test_every_block_on_the_table_has_a_grasp_within_the_stroke_clear_of_the_table(name) -> None:
    X_WO = {o.name: o.X_WO for o in SCENE.objects}
    choice = choose_grasp(ROBOT, SCENE, name, X_WO)
    assert choice.grasp is not None, choice.reason
    grasp = choice.grasp
    assert grasp.opening_m + 2 * GRASP_CLEARANCE_M <= ROBOT.finger_opening_max
    assert grip_area_m2(ROBOT, SCENE, name, grasp.X_GP) >= MIN_GRIP_AREA_M2
    # The closed fingers, placed with the block: above the table by the set margin, touching
    # nothing but the block.
    fingers = finger_parts_O(ROBOT, grasp.X_GP, grasp.opening_m)
    X = X_WO[name]
    lowest_W = min(float((p.vertices_O @ X[:3, :3].T + X[:3, 3])[:, 2].min()) for p in fingers)
    assert lowest_W >= FINGERTIP_TABLE_CLEARANCE_M - 1e-9
    world = SimWorld(SCENE, name, X_WO, attached_O=tuple(fingers))
    pairs = world.distances(X, np.arange(len(world.obstacle_object)))
    assert min(p.distance_m for p in pairs if p.wp_part >= world.n_own_parts) > 0.0
    # The gripper points down: the work site descends onto every grasp from above.
    np.testing.assert_allclose((X @ invert_pose(grasp.X_GP))[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)


def test_the_wedge_is_held_where_it_is_thick_not_where_todays_grasp_holds_it() -> None:
    """Today's grasp holds the wedge high on its triangular ends, where they narrow to an edge:
    the chosen grasp slides towards the thick back and presses enough of it."""
    X_WO = {o.name: o.X_WO for o in SCENE.objects}
    today, _ = clear_top_grasp(ROBOT, SCENE, "wedge", X_WO)
    assert grip_area_m2(ROBOT, SCENE, "wedge", today) < MIN_GRIP_AREA_M2
    grasp = choose_grasp(ROBOT, SCENE, "wedge", X_WO).grasp
    assert grasp is not None
    # The wedge's back face is at −x of O: the TCP moves that way from the centre.
    assert invert_pose(grasp.X_GP)[0, 3] < 0.0


def _plank_pushed(yaw_deg: float, target_xy: tuple[float, float]) -> TaskSession:
    """The plank lying flat inside the frame at yaw ``yaw_deg`` (long side along x at 0),
    dragged along the table towards ``target_xy`` until it stops against a bar."""
    session = TaskSession(SCENE)
    R = rpy_to_R(np.array([0.0, 0.0, np.deg2rad(yaw_deg)]))
    session.X_WO["plank"] = make_pose(R, (0.45, 0.0, 0.0125))
    session.select("plank")
    target = session.X_WO["plank"].copy()
    target[:3, 3] = (*target_xy, 0.0075)  # pressed onto the table too
    session.set_target(target)
    for _ in range(300):
        session.step()
    return session


@pytest.mark.parametrize(("yaw_deg", "target_xy"), [(0.0, (0.53, 0.0)), (90.0, (0.45, 0.08))])
def test_the_plank_pushed_end_first_against_a_wall_has_no_finger_between(
    yaw_deg, target_xy
) -> None:
    session = _plank_pushed(yaw_deg, target_xy)
    goal = session.path_history()[-1]
    frame = [c for c in goal.contacts if c.object == "frame"]
    assert frame, "the plank must end against the bar"
    choice = session.choose_grasp_for_path()
    assert choice.grasp is not None, choice.reason
    np.testing.assert_array_equal(session.X_GP, choice.grasp.X_GP)
    d_W = _closing_W(goal.X_WO, choice.grasp.X_GP)
    # Across the plank's 0.05 m width, the pads side-on to the wall it is pushed against.
    assert choice.grasp.opening_m == pytest.approx(0.05)
    assert np.max(np.abs(frame[0].normals_W @ d_W)) <= PAD_FACING_SIN


def test_the_plank_pushed_side_first_against_a_wall_is_refused_with_the_reason() -> None:
    """Long side against the bar: the fingers across its width would be between it and the
    bar (lower than the bar, they cannot pass over it), and its ends are further apart than the
    gripper opens."""
    session = _plank_pushed(90.0, (0.53, 0.0))
    before = session.X_GP.copy()
    choice = session.choose_grasp_for_path()
    assert choice.grasp is None
    assert "between the plank and the frame" in choice.reason
    assert "0.100 m apart, wider than the gripper opens" in choice.reason
    np.testing.assert_array_equal(session.X_GP, before)  # nothing changed


@pytest.mark.parametrize(("task", "seed"), [("corner", 0), ("corner", 1), ("around-corner", 0)])
def test_todays_corner_and_around_corner_grasps_are_kept(task, seed) -> None:
    demo = layout_demonstration(task, seed)
    before = demo.session.X_GP.copy()
    choice = demo.session.choose_grasp_for_path()
    assert choice.grasp is not None, choice.reason
    np.testing.assert_array_equal(choice.grasp.X_GP, before)


def test_select_takes_a_chosen_grasp() -> None:
    X_WO = {o.name: o.X_WO for o in SCENE.objects}
    grasp = choose_grasp(ROBOT, SCENE, "wedge", X_WO).grasp
    session = TaskSession(SCENE)
    session.select("wedge", grasp=grasp)
    np.testing.assert_array_equal(session.X_GP, grasp.X_GP)
    assert session.opening_m == grasp.opening_m
    session.select("cube")  # by default, today's grasp
    np.testing.assert_array_equal(session.X_GP, clear_top_grasp(ROBOT, SCENE, "cube", X_WO)[0])
    session.select("wedge")  # … unless it would hold too little: then the chooser's
    np.testing.assert_array_equal(session.X_GP, grasp.X_GP)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "yaw_deg"), [("plank", 0.0), ("wedge", 180.0), ("l_block", 180.0), ("hex_prism", 90.0)]
)
def test_each_new_block_pushed_against_a_wall_runs_end_to_end(name, yaw_deg) -> None:
    """Inside the frame, dragged along the table against the bar at +x (the wedge by its back,
    the L by its low end, the prism by a flat): the grasp chosen for the path, the program
    generated and found feasible, then run by the work site's executor in pybullet, which
    verifies the wall's contact by force; the block ends where the program put it."""
    from operator_site.program import check_feasibility, choose_grasp_yaw, generate_program
    from work_site.control.controller import TaskController
    from work_site.control.executor import Execution, program_refusal
    from work_site.world import World

    session = TaskSession(SCENE)
    R = rpy_to_R(np.array([0.0, 0.0, np.deg2rad(yaw_deg)]))
    session.X_WO[name] = make_pose(R, (0.45, 0.0, session.X_WO[name][2, 3]))
    session.select(name)
    target = session.X_WO[name].copy()
    target[:3, 3] += (0.08, 0.0, -0.005)
    session.set_target(target)
    for _ in range(300):
        session.step()
    assert session.choose_grasp_for_path().grasp is not None
    X_GP = choose_grasp_yaw(session.start_X_WO, session.X_GP)
    program = generate_program(
        name,
        SCENE,
        name,
        session.path_history(),
        X_GP,
        attached_O=session.fingers_O,
        X_WO=session.X_WO,
    ).program
    assert check_feasibility(SCENE, name, program, session.fingers_O, session.X_WO).ok
    world = World(SCENE)
    try:
        world.set_object_pose(name, session.start_X_WO)
        controller = TaskController(world, ROBOT)
        assert program_refusal(program, controller) == ""
        reports = []
        execution = Execution(program, controller, lambda *r: reports.append(r))
        for _ in range(8000):
            execution.tick()
            if execution.finished:
                break
        assert reports[-1][2:] == ("done", "program complete"), reports[-1]
        verified = [r[3] for r in reports if r[2] == "contact_verified"]
        assert verified and "frame" in verified[-1]
        kinds = [c.kind for c in program.commands]
        goal = program.commands[kinds.index("release")].X_WP  # (then up, rise, park)
        np.testing.assert_allclose(world.object_pose(name)[:3, 3], goal[:3, 3], atol=2e-3)
    finally:
        world.close()


def test_a_tall_block_pushed_against_the_outside_of_a_bar_is_held_side_on() -> None:
    """Today's grasp holds the tall block on the faces that end up facing the bar, its fingers
    2 mm above the bar's top: a grasp that passes only just, and a program's deformed path may
    tilt the block and the fingers into the bar. The pads side-on to the bar are chosen."""
    session = TaskSession(SCENE)
    session.X_WO["tall_block"] = make_pose(np.eye(3), (0.45, -0.19, 0.05))
    session.select("tall_block")
    X_WO = dict(session.X_WO)
    today, _ = clear_top_grasp(ROBOT, SCENE, "tall_block", X_WO)
    target = session.X_WO["tall_block"].copy()
    target[:3, 3] = (0.45, -0.141, 0.046)  # into the near bar's outer face and the table
    session.set_target(target)
    for _ in range(300):
        session.step()
    goal = session.path_history()[-1]
    frame = [c for c in goal.contacts if c.object == "frame"]
    assert frame, "the tall block must end against the bar"
    assert np.max(np.abs(frame[0].normals_W @ _closing_W(goal.X_WO, today))) > PAD_FACING_SIN
    choice = session.choose_grasp_for_path()
    assert choice.grasp is not None, choice.reason
    assert np.max(np.abs(frame[0].normals_W @ _closing_W(goal.X_WO, choice.grasp.X_GP))) <= (
        PAD_FACING_SIN
    )
    assert choice.grasp.tip_height_m >= 0.03  # still clear of the bars
