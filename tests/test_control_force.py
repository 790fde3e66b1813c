"""Force at the work site: the wrist sensor, guarded moves, impedance and the execution monitor,
in real pybullet with the block's real pose as the judge (issue 5)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pybullet as p
import pytest

from bench import control as benchmark
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R
from protocol import ContactState, MotionCommand, MotionProgram
from work_site.control.controller import Impedance, compliant_projector
from work_site.control.executor import (
    CONTACT_VERIFY_N,
    TARGET_BIAS_M,
    TARGET_BIAS_MAX_M,
    Execution,
    contact_forces_n,
    program_refusal,
    target_bias_W,
)

pytestmark = pytest.mark.slow  # seconds of simulated physics each

TABLE = ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]]))


@pytest.fixture
def site():
    world, controller = benchmark._site()
    yield world, controller
    world.close()


def run(program: MotionProgram, controller) -> list[tuple]:
    reports: list[tuple] = []
    problem = program_refusal(program, controller)
    assert problem == "", problem
    execution = Execution(program, controller, lambda *r: reports.append(r))
    for _ in range(6000):
        execution.tick()
        if execution.finished:
            return reports
    raise AssertionError("program did not finish")


@pytest.mark.parametrize("rpy", [(math.pi, 0.0, math.pi), (math.pi, 0.4, 2.0)])
def test_the_wrist_sensor_reads_a_known_force_on_the_hand(site, rpy) -> None:
    world, c = site
    c.start_move(make_pose(rpy_to_R(np.array(rpy)), (0.45, -0.1, 0.2)), 0.2)
    while c.tick().status == "moving":
        pass
    for _ in range(30):
        c.tick()
    np.testing.assert_allclose(c.force_W, 0.0, atol=0.01)  # the hand's weight is removed
    F_W = np.array([3.0, -2.0, 4.0])
    hand = world.finger_joints[0] - 1  # gripper_base, the fingers' parent link
    for _ in range(30):
        at = c.measured_tcp_W()[:3, 3]
        p.applyExternalForce(world.robot, hand, F_W, at, p.WORLD_FRAME, physicsClientId=world.cid)
        c.steps_per_tick = 1  # applyExternalForce lasts one step
        c.tick()
    np.testing.assert_allclose(c.force_W, F_W, atol=0.1)


def test_a_guarded_move_stops_on_the_table_within_5_N_of_its_threshold() -> None:
    result = benchmark.guarded_touch(0.02)
    assert result["status"] == "guarded"
    assert 0.0 <= result["overshoot_n"] <= 5.0, result
    assert result["held_n"] > 0.0  # still touching after the stop, not bounced off


def test_corner_placement_ends_within_1_mm_and_1_degree_with_three_contacts_verified() -> None:
    result = benchmark.corner()
    assert result["corner_status"] == "done", result["corner_message"]
    assert result["corner_contacts_verified"]
    assert result["corner_error_mm"] <= 1.0, result
    assert result["corner_error_deg"] <= 1.0, result
    report = result["corner_contact_report"]
    assert "table" in report and report.count("frame") == 2, report


def test_sliding_along_a_wall_keeps_the_normal_force_in_its_band() -> None:
    result = benchmark.slide()
    assert result["slide_status"] == "done", result["slide_message"]
    assert result["slide_samples"] > 100
    low, high = result["slide_band_n"]
    assert low <= result["slide_normal_n_min"] <= result["slide_normal_n_max"] <= high, result
    # The cube ends within a millimetre of its goal along the wall, stiffer along the surfaces
    # (the default); isotropic (the knob's other end) friction holds it friction / stiffness
    # short: μ 0.25 (wood on wood) on ≈ 9 N of pressing forces is ≈ 2.2 N, 2.2 mm at 1,000 N/m
    # (measured 2.16 mm with the pads holding the cube on an area; 0.27 mm while they held it
    # on one point each). The normal force stays in its band either way.
    assert abs(result["slide_end_along_wall_mm"]) <= 1.0, result
    isotropic = benchmark.slide(Impedance(tangential_stiffness_n_per_m=1000.0))
    assert isotropic["slide_status"] == "done", isotropic["slide_message"]
    assert abs(isotropic["slide_end_along_wall_mm"]) <= 3.0, isotropic
    assert low <= isotropic["slide_normal_n_min"] <= isotropic["slide_normal_n_max"] <= high


def _grasp_and_lift(world) -> tuple[list[MotionCommand], np.ndarray]:
    X = world.object_pose("cube")
    lifted = X.copy()
    lifted[2, 3] += 0.06
    return [benchmark._cmd("guarded_grasp", X, 0.1), benchmark._cmd("move", lifted, 0.1)], lifted


def test_a_contact_that_is_not_there_fails_the_program(site) -> None:
    world, c = site
    commands, lifted = _grasp_and_lift(world)
    down = lifted.copy()
    down[:3, 3] = (0.25, -0.2, benchmark.CUBE_HALF_M)  # open table: no wall at −x
    above = down.copy()
    above[2, 3] += 0.05
    # The wall is looked for with the cube held 3 mm above the table: dragged along the table
    # by the bias towards the wall, the table's friction (μ 0.25 on ≈ 5 N) read 1.0 N along the
    # missing wall's normal, at CONTACT_VERIFY_N (a known limit of verifying by force alone).
    hover = down.copy()
    hover[2, 3] += 0.003
    wall = ContactState(object="frame", normals_W=np.array([[1.0, 0.0, 0.0]]))
    program = MotionProgram(
        program_id="ghost",
        X_GP=benchmark.corner_grasp_GP(),
        commands=(
            *commands,
            benchmark._cmd("move", above, 0.1),
            benchmark._cmd("guarded_move", down, 0.02, (TABLE,), benchmark.PLACE_GUARD_N),
            benchmark._cmd("move", hover, 0.01),
            benchmark._cmd("contact_move", hover, 0.01, (wall,)),
        ),
    )
    reports = run(program, c)
    assert reports[-1][2] == "failed", reports[-1]
    assert "contact with frame not verified" in reports[-1][3]
    assert any(r[2] == "contact_verified" and "table" in r[3] for r in reports)


def test_a_guarded_move_that_meets_nothing_fails(site) -> None:
    world, c = site
    commands, lifted = _grasp_and_lift(world)
    floating = lifted.copy()
    floating[2, 3] += 0.02  # upwards, into the air, expecting the table
    program = MotionProgram(
        program_id="air",
        X_GP=benchmark.corner_grasp_GP(),
        commands=(*commands, benchmark._cmd("guarded_move", floating, 0.02, (TABLE,))),
    )
    reports = run(program, c)
    assert reports[-1][2] == "failed" and "without contact" in reports[-1][3], reports[-1]


def test_an_unexpected_force_stops_the_arm_at_the_commands_limit(site) -> None:
    world, c = site
    commands, lifted = _grasp_and_lift(world)
    pressed = lifted.copy()
    pressed[2, 3] = benchmark.CUBE_HALF_M - 0.004  # 4 mm into the table: a plain move
    program = MotionProgram(
        program_id="press",
        X_GP=benchmark.corner_grasp_GP(),
        commands=(*commands, benchmark._cmd("move", pressed, 0.02, force_n=8.0)),
    )
    reports = run(program, c)
    assert reports[-1][2] == "failed", reports[-1]
    assert "exceeds the limit of 8.0 N" in reports[-1][3]
    assert c.move is None  # held where it stopped


def test_the_frames_opening_is_read_from_its_parts_wherever_it_stands() -> None:
    scene = load_scene()
    (x0, x1), (y0, y1) = benchmark.frame_inner_W(scene)
    np.testing.assert_allclose([x0, x1, y0, y1], [0.35, 0.55, -0.10, 0.10], atol=1e-12)
    # Moved 5 cm along x and turned a quarter turn: the square opening moves with it.
    X_WO = make_pose(rpy_to_R(np.array([0.0, 0.0, np.pi / 2])), (0.50, 0.0, 0.0))
    moved = dataclasses.replace(
        scene,
        objects=tuple(
            dataclasses.replace(o, X_WO=X_WO) if o.name == "frame" else o for o in scene.objects
        ),
    )
    (x0, x1), (y0, y1) = benchmark.frame_inner_W(moved)
    np.testing.assert_allclose([x0, x1, y0, y1], [0.40, 0.60, -0.10, 0.10], atol=1e-12)


def test_the_target_bias_solves_N_dp_equals_minus_d() -> None:
    corner = np.eye(3)
    dp = target_bias_W(corner)
    np.testing.assert_allclose(corner @ dp, -TARGET_BIAS_M * np.ones(3), atol=1e-15)
    # Nearly parallel normals would ask for a long bias along the surfaces: the bias goes
    # along their common direction instead, pressing both by d.
    tilt = math.radians(2.0)
    wedge = np.array([[1.0, 0.0, 0.0], [math.cos(tilt), math.sin(tilt), 0.0]])
    dp = target_bias_W(wedge)
    assert np.linalg.norm(dp) <= TARGET_BIAS_MAX_M + 1e-15
    np.testing.assert_allclose(wedge @ dp, -TARGET_BIAS_M, rtol=1e-3)
    # A block between two nearly opposite walls (seen end to end: least squares biased it 83 mm
    # along the walls): no bias along the squeeze, none along the walls, the table still pressed.
    squeeze = np.array([[-1.0, 0.0, 0.0], [0.99, -0.12, 0.0], [0.0, 0.0, 1.0]])
    squeeze /= np.linalg.norm(squeeze, axis=1, keepdims=True)
    dp = target_bias_W(squeeze)
    assert abs(dp[1]) < 1e-3 and dp[2] == pytest.approx(-TARGET_BIAS_M)


def test_contact_forces_split_a_wrench_along_the_normals() -> None:
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(contact_forces_n([3.0, 4.0, 5.0], normals), [5.0, 3.0, 4.0])
    # A pull away from a wall is no contact force (never negative).
    f = contact_forces_n([-3.0, 0.0, 5.0], normals)
    assert f[1] == 0.0 and f[0] == pytest.approx(5.0)
    assert CONTACT_VERIFY_N > 0


def test_the_compliant_directions_are_the_span_of_the_contact_normals() -> None:
    P = compliant_projector(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 1e-6, 0.0]]))
    np.testing.assert_allclose(P, np.diag([1.0, 0.0, 1.0]), atol=1e-5)
    corner = compliant_projector(np.eye(3))
    np.testing.assert_allclose(corner, np.eye(3), atol=1e-12)
    tilted = np.array([[0.0, -0.6, 0.8]])
    np.testing.assert_allclose(compliant_projector(tilted), tilted.T @ tilted, atol=1e-12)
    assert not compliant_projector(np.zeros((0, 3))).any()


def test_leaving_a_contact_the_hand_does_not_push_back_into_it() -> None:
    """The cube pressed onto a wall and the table, then moved 3 mm off the wall with the table
    alone: the offset the wall's bias left does not pull the hand back into the wall (it did,
    stiffer along the surfaces: 21.5 N, over the move's 20 N limit)."""
    world, c = benchmark._site()
    (x0, _), _ = benchmark.frame_inner_W(world.scene)
    wall = ContactState(object="frame", normals_W=np.array([[1.0, 0.0, 0.0]]))
    on_wall = make_pose(np.eye(3), (x0 + benchmark.CUBE_HALF_M, 0.0, benchmark.CUBE_HALF_M))
    off_wall = on_wall.copy()
    off_wall[:3, 3] += (0.003, 0.01, 0.0)
    program = MotionProgram(
        program_id="leave-wall",
        X_GP=benchmark.corner_grasp_GP(),
        commands=(
            *benchmark._set_down(world.object_pose("cube"), on_wall, (0.01, 0.0, 0.0), TABLE),
            benchmark._cmd("contact_move", on_wall, 0.01, (TABLE, wall)),
            benchmark._cmd("contact_move", off_wall, 0.01, (TABLE,)),
        ),
    )
    reports: list[tuple] = []
    try:
        execution = Execution(
            program,
            c,
            lambda *r: reports.append(r),
            impedance=Impedance(tangential_stiffness_n_per_m=5000.0),
        )
        for _ in range(6000):
            execution.tick()
            if execution.finished:
                break
        off_m = float(world.object_pose("cube")[0, 3] - on_wall[0, 3])
    finally:
        world.close()
    assert reports[-1][2] == "done", reports[-1]
    assert off_m > 0.002, off_m


def test_the_impedance_presses_along_its_normals_with_at_most_max_press(site) -> None:
    """15 mm out along the table's normal (a block hanging lower in the grip than the model
    says), 12 N measured: an uncapped 1,000 N/m spring would push the hand further in (15 N >
    12 N); capped at 10 N it yields. Along the surface the spring is unchanged."""
    _, c = site
    P = compliant_projector(np.array([[0.0, 0.0, 1.0]]))
    c.impedance = Impedance(compliant_W=P, tangential_stiffness_n_per_m=5000.0)
    assert c.impedance.max_press_n == pytest.approx(1000.0 * TARGET_BIAS_MAX_M)
    c.offset_W = np.array([0.0, 0.0, 0.015])
    c._window = [np.array([0.0, 0.0, 12.0])] * 4
    c._admittance(1e-3)
    rate_mps = (c.offset_W[2] - 0.015) / 1e-3
    assert rate_mps == pytest.approx((12.0 - 10.0) / c.impedance.damping_n_s_per_m)
    # Along the surface: 0.5 mm at 5,000 N/m pulls back with 2.5 N, as before.
    c.offset_W = np.array([0.0005, 0.0, 0.0])
    c._window = [np.zeros(3)] * 4
    c._admittance(1e-3)
    assert (c.offset_W[0] - 0.0005) / 1e-3 == pytest.approx(-2.5 / 200.0)


def test_a_capped_normal_presses_with_at_most_its_cap_and_the_others_as_before(site) -> None:
    """A movable object's sideways normal capped at 1.5 N: 2 mm into it, 3 N measured, the hand
    backs off along it at (3 − 1.5)/B; along the table's normal, uncapped, 2 mm balance 2 N."""
    _, c = site
    side, up = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    c.impedance = Impedance(
        compliant_W=compliant_projector(np.array([side, up])), press_caps=((side, 1.5),)
    )
    c.offset_W = np.array([0.002, 0.0, 0.002])
    c._window = [np.array([3.0, 0.0, 2.0])] * 4
    c._admittance(1e-3)
    rate_mps = (c.offset_W - [0.002, 0.0, 0.002]) / 1e-3
    B = c.impedance.damping_n_s_per_m
    np.testing.assert_allclose(rate_mps, [(3.0 - 1.5) / B, 0.0, 0.0], atol=1e-12)


def test_an_impedance_that_would_overshoot_at_the_physics_step_is_refused(site) -> None:
    """K·Δt/B above 1: the offset would overshoot zero at every update. 1e5 N/m against the
    default 200 N·s/m is the stiffest a 2 ms step takes (the work site's slowest physics)."""
    _, c = site
    assert Impedance(tangential_stiffness_n_per_m=1e5).step_gain(2e-3) == pytest.approx(1.0)
    X = c.commanded_tcp_W()
    stiff = Impedance(tangential_stiffness_n_per_m=1e5, damping_n_s_per_m=50.0)
    with pytest.raises(ValueError, match=r"the damping must be at least stiffness × step, 100"):
        c.start_move(X, 0.01, impedance=stiff)
    c.start_move(X, 0.01, impedance=Impedance(tangential_stiffness_n_per_m=1e5))
    for bad in ({"damping_n_s_per_m": 0.0}, {"stiffness_n_per_m": math.nan}):
        with pytest.raises(ValueError, match=r"Impedance\.\w+ must be finite and > 0"):
            Impedance(**bad)


@pytest.mark.parametrize(("stiffness_n_per_m", "physics_rate_hz"), [(1e5, 500.0), (100.0, 2000.0)])
def test_sliding_keeps_its_force_band_at_the_ends_of_stiffness_and_physics_rate(
    stiffness_n_per_m: float, physics_rate_hz: float
) -> None:
    """The work site's accepted extremes: the stiffest surface spring at the slowest physics
    (K·Δt/B = 1) and the softest at the fastest. No swinging: the normal force stays in its
    band and the move finishes."""
    result = benchmark.slide(
        Impedance(tangential_stiffness_n_per_m=stiffness_n_per_m), 1.0 / physics_rate_hz
    )
    assert result["slide_status"] == "done", result["slide_message"]
    low, high = result["slide_band_n"]
    assert low <= result["slide_normal_n_min"] <= result["slide_normal_n_max"] <= high, result
