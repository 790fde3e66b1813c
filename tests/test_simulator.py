"""The task simulator on hand-worked cases with exact answers (§V)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.geometry import make_convex_part, mass_properties
from models.scene import ObjectModel, Scene, SceneObject, load_scene
from models.transforms import make_pose, rpy_to_R, so3_exp, so3_log
from operator_site.simulator.contacts import contact_manifold
from operator_site.simulator.params import RANGES, SimParams
from operator_site.simulator.stepper import Simulator

REPO = Path(__file__).resolve().parents[1]

P = SimParams()
CUBE_HALF = 0.025
# The frame's inner corner at its smallest x and y (DESIGN.md: opening 0.20 m centred at 0.45).
CORNER_XY = np.array([0.35, -0.10])


@pytest.fixture(scope="module")
def scene() -> Scene:
    return load_scene()


def at(x: float, y: float, z: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_pose(rpy_to_R(np.array([0.0, 0.0, np.deg2rad(yaw_deg)])), (x, y, z))


def box_object(name: str, size: tuple[float, float, float], X_WO: np.ndarray) -> SceneObject:
    """A fixed box obstacle made on the spot (for scenes the puzzle does not have)."""
    hx, hy, hz = (s / 2 for s in size)
    V = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)])
    F = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    part = make_convex_part(V, F, name)
    volume, com, _ = mass_properties([part])
    model = ObjectModel(
        name,
        None,
        (part,),
        np.zeros((0, 2, 3)),
        volume,
        1.0,
        com,
        np.array([V.min(0), V.max(0)]),
        (0.5, 0.5, 0.5, 1.0),
    )
    return SceneObject(name, model, X_WO, True)


def run(sim: Simulator, steps: int):
    return [sim.step() for _ in range(steps)]


def test_so3_exp_and_log_are_inverse() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        w = rng.normal(size=3)
        w *= rng.uniform(0, np.pi - 1e-3) / np.linalg.norm(w)
        np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-9)


def test_manifold_face_on_face_is_the_four_corners() -> None:
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * CUBE_HALF
    table = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-0.04, 0)])
    A = cube + np.array([0, 0, CUBE_HALF + 1e-4])
    points, n, gaps = contact_manifold(
        A, table, np.array([0, 0, 1e-4]), np.zeros(3), P.eps_contact_m
    )
    np.testing.assert_allclose(n, [0, 0, -1])
    assert len(points) == 4
    np.testing.assert_allclose(np.sort(np.abs(points[:, :2]), axis=0), CUBE_HALF)
    np.testing.assert_allclose(points[:, 2], 5e-5)
    np.testing.assert_allclose(gaps, 1e-4)
    # Tilted by 0.2 mm over its width: still four points, each with its own gap.
    tilt = 2e-4 / (2 * CUBE_HALF)
    R = so3_exp(np.array([0.0, tilt, 0.0]))
    A = cube @ R.T
    A += [0, 0, 1e-4 - A[:, 2].min()]
    low = A[np.argmin(A[:, 2])]
    points, n, gaps = contact_manifold(A, table, low, low * [1, 1, 0], P.eps_contact_m)
    assert len(points) == 4
    np.testing.assert_allclose(np.sort(gaps), [1e-4, 1e-4, 3e-4, 3e-4], atol=1e-9)


def test_free_motion_converges_on_the_target_without_queries(scene: Scene) -> None:
    start = at(0.3, 0.3, 0.2)
    sim = Simulator(scene, "cube", X_WO={"cube": start})
    target = at(0.32, 0.31, 0.2, yaw_deg=20)
    sim.set_target(target)
    results = run(sim, 80)
    np.testing.assert_allclose(sim.X_WO, target, atol=1e-6)
    assert sum(r.queries for r in results) == 0  # nothing near: the broad phase skips it all


# x = Δt·d_t·k_t, the spring's step gain: the default is 0.25; an explicit step overshoots past 1
# and swings for ever from 2 on.
STEP_GAINS = (0.01, 0.25, 1.0, 2.0, 5.0, 250.0, 1e6)


@pytest.mark.parametrize("gain", STEP_GAINS)
def test_a_free_pull_approaches_the_target_without_overshoot_at_any_step_gain(
    scene: Scene, gain: float
) -> None:
    params = SimParams(d_t=gain / (P.dt_s * P.k_t))
    start = at(0.3, 0.3, 0.2)
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    target = at(0.32, 0.31, 0.2, yaw_deg=20)
    sim.set_target(target)
    u = (target[:3, 3] - start[:3, 3]) / np.linalg.norm(target[:3, 3] - start[:3, 3])
    left_m, left_rad = [], []
    for r in run(sim, 400):
        left_m.append(float((target[:3, 3] - r.X_WO[:3, 3]) @ u))  # < 0: past the target
        left_rad.append(float(np.linalg.norm(so3_log(target[:3, :3] @ r.X_WO[:3, :3].T))))
    assert min(left_m) >= -1e-12 and min(left_rad) >= 0.0
    assert np.all(np.diff(left_m) <= 1e-12) and np.all(np.diff(left_rad) <= 1e-12)
    if gain >= 0.25:
        np.testing.assert_allclose(sim.X_WO, target, atol=1e-6)


@pytest.mark.parametrize("gain", [0.01, 0.25, 1.5])
def test_a_free_pull_follows_the_springs_exact_first_order_decay(scene, gain: float) -> None:
    """Below the speed limit each step leaves e^(−x) of the way, as v = d_t·k_t·(c_D − c)
    integrated exactly over Δt does."""
    params = SimParams(d_t=gain / (P.dt_s * P.k_t))
    start = at(0.3, 0.3, 0.2)
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    target = at(0.3005, 0.3002, 0.2, yaw_deg=2)  # near: below the speed limit throughout
    sim.set_target(target)
    c0 = np.linalg.norm(target[:3, 3] - start[:3, 3])
    steps = min(30, int(np.log(c0 / 1e-9) / gain))  # until 1 nm is left: a step then rests
    for k, r in enumerate(run(sim, steps), 1):
        assert not r.speed_limited
        left = np.linalg.norm(target[:3, 3] - r.X_WO[:3, 3])
        assert left == pytest.approx(c0 * np.exp(-gain * k), rel=1e-9)


@pytest.mark.parametrize("gain", [0.25, 250.0])
def test_a_block_pushed_into_the_corner_comes_to_rest_at_any_step_gain(
    scene: Scene, gain: float
) -> None:
    """Pressed into the frame's inside corner, the block settles: no swinging against the
    walls, the same pose step after step."""
    params = SimParams(d_t=gain / (P.dt_s * P.k_t))
    sim = Simulator(scene, "cube", params, X_WO={"cube": at(0.45, 0.0, CUBE_HALF + 2e-4, 5)})
    sim.set_target(at(*(CORNER_XY + 0.02), CUBE_HALF - 0.005))
    results = run(sim, 300)
    assert {c.object for c in results[-1].contacts} == {"table", "frame"}
    last = np.array([r.X_WO for r in results[-20:]])
    assert np.max(np.abs(last - last[-1])) < 1e-9
    gaps = sim.X_WO[:3, 3] - [*(CORNER_XY + CUBE_HALF), CUBE_HALF]
    assert np.all(gaps >= P.eps_barrier_m / 2) and np.all(gaps < P.eps_contact_m), gaps


def test_parameters_that_would_make_a_step_cost_without_bound_are_refused(scene) -> None:
    fast = {"max_speed_mps": 10.0, "dt_s": 1.0}  # 10 m a step: 50,001 samples 0.2 mm apart
    with pytest.raises(ValueError, match=r"tunnel_fraction 0.01 .* must be in \[[0-9.e-]+, 1\]"):
        Simulator(scene, "cube", SimParams(tunnel_fraction=0.01, **fast))
    Simulator(scene, "cube", SimParams(tunnel_fraction=0.1, **fast))  # 5,001: made
    with pytest.raises(ValueError, match=r"golden_rel_tol must be a number in \[1e-12, 0.5\]"):
        SimParams(golden_rel_tol=1e-20)


def test_block_resting_on_the_table_stays_and_the_reaction_balances_the_push(scene) -> None:
    start = at(0.2, 0.3, CUBE_HALF + 0.3 * P.eps_contact_m)
    sim = Simulator(scene, "cube", X_WO={"cube": start})
    sim.set_target(at(0.2, 0.3, CUBE_HALF - 0.01))  # pushed 1 cm into the table
    results = run(sim, 20)
    last = results[-1]
    (table,) = [c for c in last.contacts if c.object == "table"]
    assert len(table.points_W) == 4
    np.testing.assert_allclose(table.normals_W, np.tile([0, 0, 1.0], (4, 1)), atol=1e-12)
    z = sim.X_WO[2, 3] - CUBE_HALF
    assert P.eps_barrier_m / 2 <= z < P.eps_contact_m
    np.testing.assert_allclose(sim.X_WO[:2, 3], [0.2, 0.3], atol=1e-9)
    np.testing.assert_allclose(sim.X_WO[:3, :3], np.eye(3), atol=1e-9)


def test_block_slides_along_the_table(scene: Scene) -> None:
    start = at(0.2, 0.3, CUBE_HALF + 0.3 * P.eps_contact_m)
    sim = Simulator(scene, "cube", X_WO={"cube": start})
    sim.set_target(at(0.1, 0.3, CUBE_HALF - 0.005))
    results = run(sim, 60)
    assert sim.X_WO[0, 3] == pytest.approx(0.1, abs=1e-4)
    gaps = [r.X_WO[2, 3] - CUBE_HALF for r in results]
    assert min(gaps) >= P.eps_barrier_m / 2 and max(gaps) < P.eps_contact_m
    np.testing.assert_allclose(sim.X_WO[:3, :3], np.eye(3), atol=1e-9)


def test_block_pushed_into_the_inside_corner_settles_against_two_walls(scene) -> None:
    sim = Simulator(scene, "cube", X_WO={"cube": at(0.45, 0.0, CUBE_HALF + 2e-4, yaw_deg=5)})
    # Drag towards the corner, past the walls and slightly down, square with the frame.
    sim.set_target(at(*(CORNER_XY + 0.02), CUBE_HALF - 0.005))
    results = run(sim, 200)
    last = results[-1]
    assert {c.object for c in last.contacts} == {"table", "frame"}
    frame = next(c for c in last.contacts if c.object == "frame")
    normals = {tuple(np.round(n, 6)) for n in frame.normals_W}
    assert normals == {(1.0, 0.0, 0.0), (0.0, 1.0, 0.0)}
    gaps = sim.X_WO[:3, 3] - [*(CORNER_XY + CUBE_HALF), CUBE_HALF]
    assert np.all(gaps >= P.eps_barrier_m / 2) and np.all(gaps < P.eps_contact_m), gaps
    assert abs(np.rad2deg(np.linalg.norm(so3_log(sim.X_WO[:3, :3])))) < 0.05


def test_rotation_stays_orthonormal(scene: Scene) -> None:
    sim = Simulator(scene, "cube", X_WO={"cube": at(0.3, 0.3, 0.2)})
    sim.set_target(at(0.3, 0.3, 0.2, yaw_deg=179))
    for k in range(2000):
        if k % 50 == 0:
            sim.set_target(at(0.3, 0.3, 0.2, yaw_deg=(k * 37) % 360))
        sim.step()
    R = sim.X_WO[:3, :3]
    assert np.max(np.abs(R.T @ R - np.eye(3))) < 1e-12


def test_no_tunnelling_through_a_thin_plate_at_full_speed(scene: Scene) -> None:
    plate = box_object("plate", (0.005, 0.3, 0.3), at(0.25, 0.3, 0.2))
    scene2 = dataclasses.replace(scene, objects=(*scene.objects, plate))
    sim = Simulator(scene2, "cube", X_WO={"cube": at(0.15, 0.3, 0.2)})
    sim.set_target(at(0.6, 0.3, 0.2))  # far beyond the plate: the spring saturates the speed
    results = run(sim, 60)
    assert any(r.speed_limited for r in results)
    xs = [r.X_WO[0, 3] for r in results]
    assert max(xs) < 0.25 - 0.0025 - CUBE_HALF  # never past the plate's near face
    assert results[-1].min_distance_m >= P.eps_barrier_m / 2


def test_captured_block_stays_near_the_capture_object_and_leaves_when_released(scene) -> None:
    sim = Simulator(scene, "cube", X_WO={"cube": at(0.2, 0.3, CUBE_HALF + 0.3e-3)})
    sim.capture("table")
    sim.set_target(at(0.2, 0.3, 0.1))  # pull straight up
    run(sim, 40)
    d = sim.X_WO[2, 3] - CUBE_HALF
    assert 0 < d <= P.eps_capture_m
    sim.release("table")
    run(sim, 80)
    assert sim.X_WO[2, 3] == pytest.approx(0.1, abs=1e-4)


@pytest.mark.parametrize("points_per_pair", [3, 4])
def test_dropped_contact_corners_never_block_a_slide_for_good(scene, points_per_pair) -> None:
    """Slid along the frame's outside and round its corner, frame and table captured, with the
    contact polygons reduced below their corners: the LCP does not see the dropped corners and
    can drive one into its face, which blocked every later step. Such a blocked step is planned
    again with the whole polygons, and the cube goes round."""
    params = SimParams(max_points_per_pair=points_per_pair)
    cx, cy = 0.57, 0.12  # the frame's outside corner at its largest x and y
    start = at(cx - 0.08, cy + CUBE_HALF + 2e-4, CUBE_HALF + 2e-4)
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    sim.capture("frame")
    sim.capture("table")
    legs = [(cx - 0.08, cy + 0.015), (cx + 0.035, cy + 0.015), (cx + 0.015, cy - 0.08)]
    for k in range(240):
        leg = min(k // 100, 1)
        f = min(1.0, (k - leg * 100) / 80)
        (x0, y0), (x1, y1) = legs[leg], legs[leg + 1]
        sim.set_target(at(x0 + f * (x1 - x0), y0 + f * (y1 - y0), CUBE_HALF - 0.003))
        r = sim.step()
        assert r.queries <= sim.max_queries_per_step
        assert r.min_distance_m > params.floor_m
    assert sim.X_WO[0, 3] > cx and sim.X_WO[1, 3] < cy - 0.03  # round the corner
    assert {c.object for c in sim.state.contacts} == {"frame", "table"}


# ------------------------------------------------------------------- properties at the extremes


def _log(lo: float, hi: float):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0**e))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    eps_b=_log(*RANGES["eps_barrier_m"][:2]),
    d_t=_log(3e-5, 1e6),
    d_ratio=_log(1e-3, 3e2),
    force=_log(1e-9, 1e6),
    direction=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 0.2)),
    turn=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
    start_gap=st.floats(0.5, 3.0),
)
def test_random_pushes_never_break_the_invariants(
    scene: Scene, eps_b, d_t, d_ratio, force, direction, turn, start_gap
) -> None:
    params = SimParams(
        eps_barrier_m=eps_b,
        eps_contact_m=max(5 * eps_b, 0.5e-3),
        eps_capture_m=max(20 * eps_b, 2e-3),
        d_t=d_t,
        char_length_m=0.025 * d_ratio,
        k_t=1.0,
    )
    u = np.array(direction, dtype=float)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-6 else np.array([0.0, 0.0, -1.0])
    start = at(0.2, 0.3, CUBE_HALF + start_gap * eps_b)
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    # Spring force f = k_t·offset: an offset of `force` newtons' worth at k_t = 1 N/m.
    target = start.copy()
    target[:3, 3] += u * force
    target[:3, :3] = so3_exp(np.array(turn)) @ start[:3, :3]
    sim.set_target(target)
    for _ in range(15):
        r = sim.step()
        assert np.all(np.isfinite(r.X_WO))
        R = r.X_WO[:3, :3]
        assert np.max(np.abs(R.T @ R - np.eye(3))) < 1e-12
        assert r.min_distance_m >= eps_b / 2
        assert r.X_WO[2, 3] - CUBE_HALF > 0  # never through the table


def test_faces_parallel_to_1e9_rad_at_the_smallest_barrier(scene: Scene) -> None:
    eps_b = RANGES["eps_barrier_m"][0]
    params = SimParams(eps_barrier_m=eps_b, eps_contact_m=2 * eps_b, eps_capture_m=4 * eps_b)
    R = so3_exp(np.array([1e-9, 0.0, 0.0]))
    start = make_pose(R, (0.2, 0.3, CUBE_HALF + eps_b))
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    sim.set_target(at(0.21, 0.3, CUBE_HALF - 0.01))
    for _ in range(20):
        r = sim.step()
        assert np.all(np.isfinite(r.X_WO)) and r.min_distance_m > 0
        assert r.lcp_ok


def test_many_redundant_contact_points(scene: Scene) -> None:
    # A hexagonal prism lying on a box: 100 coincident contact rows from repeated manifolds.
    params = SimParams(max_points_per_pair=100)
    sim = Simulator(scene, "hex_prism", params, X_WO={"hex_prism": at(0.2, 0.3, CUBE_HALF + 2e-4)})
    sim.set_target(at(0.2, 0.3, 0.0))
    contact = sim.state.contacts[0]
    n = len(contact.points_W)
    reps = -(-100 // n)
    sim.state.contacts = (
        dataclasses.replace(
            contact,
            points_W=np.tile(contact.points_W, (reps, 1)),
            normals_W=np.tile(contact.normals_W, (reps, 1)),
            gaps_m=np.tile(contact.gaps_m, reps),
        ),
    )
    r = sim.step()
    assert r.lcp_ok and np.all(np.isfinite(r.X_WO))
    assert r.X_WO[2, 3] - CUBE_HALF >= P.eps_barrier_m / 2


def test_manifold_edge_on_face_is_two_points_and_vertex_on_face_one() -> None:
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * CUBE_HALF
    table = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-0.04, 0)])
    # Turned 45° about x: the bottom is the edge along x.
    A = cube @ so3_exp(np.array([np.pi / 4, 0.0, 0.0])).T
    A += np.array([0.0, 0.0, 1e-4 - A[:, 2].min()])
    points, n, gaps = contact_manifold(
        A, table, np.array([0, 0, 1e-4]), np.zeros(3), P.eps_contact_m
    )
    np.testing.assert_allclose(np.sort(points[:, 0]), [-CUBE_HALF, CUBE_HALF], atol=1e-12)
    np.testing.assert_allclose(points[:, 1:], [[0, 5e-5]] * 2, atol=1e-12)
    np.testing.assert_allclose(gaps, 1e-4, atol=1e-12)
    # Then 35.26° about y as well: a single corner at the bottom.
    A = (
        cube
        @ (
            so3_exp(np.array([0.0, np.arctan(1 / np.sqrt(2)), 0.0]))
            @ so3_exp(np.array([np.pi / 4, 0.0, 0.0]))
        ).T
    )
    low = A[np.argmin(A[:, 2])]
    A += np.array([0.0, 0.0, 1e-4 - low[2]])
    low = A[np.argmin(A[:, 2])]
    points, n, _ = contact_manifold(A, table, low, low * [1, 1, 0], P.eps_contact_m)
    assert len(points) == 1
    np.testing.assert_allclose(points[0], low - [0, 0, 5e-5], atol=1e-12)
    np.testing.assert_allclose(n, [0, 0, -1], atol=1e-12)


def test_manifold_crossing_edges_is_their_crossing_point() -> None:
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * CUBE_HALF
    below = cube @ so3_exp(np.array([np.pi / 4, 0.0, 0.0])).T  # top edge along x
    below -= np.array([0.0, 0.0, below[:, 2].max()])
    above = cube @ so3_exp(np.array([0.0, np.pi / 4, 0.0])).T  # bottom edge along y
    above += np.array([0.0, 0.0, 1e-4 - above[:, 2].min()])
    points, n, _ = contact_manifold(
        above, below, np.array([0, 0, 1e-4]), np.zeros(3), P.eps_contact_m
    )
    np.testing.assert_allclose(points, [[0.0, 0.0, 5e-5]], atol=1e-12)
    np.testing.assert_allclose(n, [0, 0, -1], atol=1e-12)


@pytest.mark.integration
def test_benchmark_command_runs_and_reports_the_issue_keys(tmp_path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "bench", "sim", "--quick", "--out", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    scenes = {r["scene"]: r for r in json.loads(result.stdout.strip().splitlines()[-1])}
    for name in ("free", "slide", "corner", "around_corner"):
        for key in ("step_ms_median", "step_ms_p99", "queries_per_step", "min_separation_m"):
            assert key in scenes[name], (name, key)
    assert scenes["corner"]["final_error_mm"] < 0.05
    assert scenes["corner"]["final_error_deg"] < 0.05
    assert scenes["around_corner"]["went_around"]
    assert "far_objects_cost_ratio" in scenes["corner+1000_far"]
    assert (tmp_path / "sim.csv").is_file()


def test_a_step_that_would_collide_stops_at_the_barrier_not_where_it_started(scene) -> None:
    # 1.5 mm above the table, pulled down hard: the full step would go through the table, so
    # the search must find the barrier's minimum near ε_b (both probes past the wall: go left).
    sim = Simulator(scene, "cube", X_WO={"cube": at(0.2, 0.3, CUBE_HALF + 1.5e-3)})
    sim.set_target(at(0.2, 0.3, CUBE_HALF - 0.05))
    r = sim.step()
    assert 0 < r.s_fraction < 1
    assert P.eps_barrier_m / 2 <= r.X_WO[2, 3] - CUBE_HALF < P.eps_contact_m


@pytest.mark.parametrize("with_fingers", [False, True])
def test_fingers_held_on_the_block_meet_a_wall_first(scene: Scene, with_fingers: bool) -> None:
    from models.robot import load_robot
    from operator_site.grasp import finger_parts_O, top_grasp

    wall = box_object("wall", (0.3, 0.02, 0.1), at(0.2, 0.41, 0.05))  # inner face at y = 0.40
    scene2 = dataclasses.replace(scene, objects=(*scene.objects, wall))
    fingers = ()
    if with_fingers:
        robot = load_robot(scene.robot.urdf_path)
        X_GP, opening = top_grasp(robot, scene.object("cube").model.bbox_O)
        fingers = tuple(finger_parts_O(robot, X_GP, opening))
    sim = Simulator(
        scene2, "cube", X_WO={"cube": at(0.2, 0.3, CUBE_HALF + 2e-4)}, attached_O=fingers
    )
    sim.set_target(at(0.2, 0.45, CUBE_HALF - 0.003))  # through the wall
    run(sim, 100)
    gap = 0.40 - (sim.X_WO[1, 3] + CUBE_HALF)  # the cube's +y face to the wall
    finger_thickness = 0.015
    if with_fingers:
        # The finger, 15 mm thick, meets the wall first; pushed high up, the block also tips a
        # little towards the wall, so the gap is less than the full thickness.
        assert finger_thickness / 2 < gap < finger_thickness + P.eps_contact_m
    else:
        assert gap == pytest.approx(P.eps_barrier_m, abs=2e-5)
