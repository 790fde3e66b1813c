"""Path deformation (§VI-A) on the paper's figures and on cases with known answers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench import scenarios
from models.geometry import make_convex_part, mass_properties
from models.scene import ObjectModel, Scene, SceneObject
from models.transforms import make_pose
from operator_site.program.contact_step import ContactStepper
from operator_site.program.deform import Deformer, DeformParams, DeformResult
from operator_site.program.path import (
    WorkpiecePath,
    lost_contact_nodes,
    path_from_history,
    unwanted_contact_nodes,
)
from operator_site.simulator import SimParams
from operator_site.simulator.world import SimWorld

P = SimParams()
FLOOR_M = P.floor_m


@dataclasses.dataclass
class Case:
    scene: Scene
    raw: WorkpiecePath
    result: DeformResult
    deformer: Deformer


def _case(sim) -> Case:
    raw = path_from_history(sim.history, "cube", sim.c_O)
    deformer = Deformer(sim.scene, "cube")
    return Case(sim.scene, raw, deformer.deform(raw), deformer)


@pytest.fixture(scope="module")
def fig12() -> Case:
    return _case(scenarios.fig12())


@pytest.fixture(scope="module")
def fig13() -> Case:
    return _case(scenarios.fig13_bottom())


def distances(case: Case, X_WO: np.ndarray) -> dict[str, float]:
    """Exact distance from the cube at ``X_WO`` to every object of the scene (m)."""
    world = case.deformer.world
    pairs = world.distances(X_WO, np.arange(len(world.obstacle_object)))
    out: dict[str, float] = {}
    for pair in pairs:
        name = world.obstacle_object[pair.obstacle]
        out[name] = min(out.get(name, np.inf), pair.distance_m)
    return out


def box_object(name: str, size: tuple[float, float, float], X_WO: np.ndarray) -> SceneObject:
    """A fixed box obstacle made on the spot."""
    hx, hy, hz = (s / 2 for s in size)
    V = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)])
    F = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    part = make_convex_part(V, F, name)
    volume, com, _ = mass_properties([part])
    bbox = np.array([V.min(0), V.max(0)])
    model = ObjectModel(name, None, (part,), np.zeros((0, 2, 3)), volume, 1.0, com, bbox, (1,) * 4)
    return SceneObject(name, model, X_WO, True)


# ------------------------------------------------------------------------------ Fig. 12


def test_fig12_path_is_shortened_by_at_least_40_percent(fig12: Case) -> None:
    reduction = 1.0 - fig12.result.path.length_m() / fig12.raw.length_m()
    assert reduction >= 0.40
    assert fig12.result.settled


def _centres_apart_m(a: WorkpiecePath, b: WorkpiecePath) -> float:
    assert len(a) == len(b)
    return float(np.abs(a.centres_W - b.centres_W).max())


def test_only_the_ratios_of_the_forces_shape_the_path_not_the_simulator_s_step(
    fig12: Case,
) -> None:
    """Forces become displacements scaled to the tension: every force ten times as strong, or
    the simulator's Δt or d_t changed, gives the same path up to rounding (amplified over the
    sweeps, well under a tenth of the spacing); the tension alone ten times as strong does not."""
    tolerance_m = 0.1 * DeformParams().spacing_m

    def deform(dp: DeformParams | None = None, sp: SimParams | None = None) -> WorkpiecePath:
        return Deformer(fig12.scene, "cube", dp, sp).deform(fig12.raw).path

    path = fig12.result.path
    stronger = DeformParams(tension_n=10.0, repulsion_n=30.0, hold_n=5.0)
    assert _centres_apart_m(deform(stronger), path) < tolerance_m
    assert _centres_apart_m(deform(sp=SimParams(dt_s=0.025)), path) < tolerance_m
    assert _centres_apart_m(deform(sp=SimParams(d_t=0.5, k_t=10.0)), path) < tolerance_m
    taut = deform(DeformParams(tension_n=10.0))
    assert abs(taut.length_m() - path.length_m()) > tolerance_m


def test_fig12_keeps_only_the_final_corner_contact(fig12: Case) -> None:
    assert len(unwanted_contact_nodes(fig12.raw)) > 50  # the operator slid and aligned
    path = fig12.result.path
    assert unwanted_contact_nodes(path) == []
    assert {c.object for c in path.nodes[-1].contacts} == {"frame", "table"}
    assert path.nodes[-1].required == {"frame", "table"}
    np.testing.assert_array_equal(path.nodes[-1].X_WO, fig12.raw.nodes[-1].X_WO)
    np.testing.assert_array_equal(path.nodes[0].X_WO, fig12.raw.nodes[0].X_WO)


def test_fig12_corner_is_approached_from_the_open_side_and_from_above(fig12: Case) -> None:
    C = fig12.result.path.centres_W
    final = C[-1]
    np.testing.assert_allclose(final, scenarios.FIG12_CORNER_W, atol=P.eps_contact_m)
    last_stretch = [c - final for c in C[:-1] if np.linalg.norm(c - final) < 0.03]
    assert last_stretch, "no node within 30 mm of the corner"
    for d in last_stretch:
        # The corner's walls are at smaller x and y: the open side is +x, +y.
        assert d[0] > 0.002 and d[1] > 0.002 and d[2] > 0.002, d


def test_fig12_every_node_is_collision_free(fig12: Case) -> None:
    for node in fig12.result.path.nodes:
        assert min(distances(fig12, node.X_WO).values()) > FLOOR_M


# ------------------------------------------------------------------------------ Fig. 13


def test_fig13_keeps_contact_through_the_corner_stretch(fig13: Case) -> None:
    path = fig13.result.path
    assert lost_contact_nodes(path) == []
    stretch = [n for n in path.nodes if n.required == {"frame", "table"}]
    C = np.array([n.X_WO[:3, :3] @ path.c_O + n.X_WO[:3, 3] for n in stretch])
    # The stretch goes round the outer corner at (0.33, −0.12): along both bars.
    assert C[:, 0].max() > 0.40 and C[:, 1].max() > -0.05
    for node in stretch:
        d = distances(fig13, node.X_WO)
        assert FLOOR_M < d["frame"] < P.eps_capture_m
        assert FLOOR_M < d["table"] < P.eps_capture_m


def test_fig13_pushes_nodes_off_the_table_elsewhere(fig13: Case) -> None:
    path = fig13.result.path
    free = [n for n in path.nodes[1:-1] if not n.required]
    assert len(free) >= 10
    heights = [distances(fig13, n.X_WO)["table"] for n in free]
    assert min(heights) > P.eps_contact_m  # no free node touches the table
    assert np.median(heights) > 0.5 * DeformParams().repulsion_range_m
    assert len(unwanted_contact_nodes(fig13.raw)) > 0
    assert unwanted_contact_nodes(path) == []


def test_required_stretch_ends_stay_fixed(fig13: Case) -> None:
    raw_fixed = [n.X_WO for n in fig13.raw.nodes if n.fixed]
    new_fixed = [n.X_WO for n in fig13.result.path.nodes if n.fixed]
    assert len(raw_fixed) == len(new_fixed) >= 4
    for a, b in zip(raw_fixed, new_fixed, strict=True):
        np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------------------ known answers


def test_a_straight_path_stays_straight() -> None:
    scene = scenarios.figure_scene()
    start = make_pose(p_AB=np.array([0.20, 0.25, 0.20]))
    sim = scenarios.drive(scene, start, [scenarios.Waypoint((0.45, 0.35, 0.20))])
    raw = path_from_history(sim.history, "cube", sim.c_O)
    result = Deformer(scene, "cube").deform(raw)
    C = result.path.centres_W
    a, b = C[0], C[-1]
    u = (b - a) / np.linalg.norm(b - a)
    off_line = (C - a) - np.outer((C - a) @ u, u)
    assert np.max(np.linalg.norm(off_line, axis=1)) < 1e-9
    assert result.path.length_m() == pytest.approx(np.linalg.norm(b - a), rel=1e-9)
    R = np.array([n.X_WO[:3, :3] for n in result.path.nodes])
    np.testing.assert_allclose(R, np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


def test_a_path_through_a_narrow_gap_is_never_pushed_into_collision() -> None:
    """Two tall walls leave a gap 2 mm wider than the cube; the operator's path bends through
    it, so tension pulls every node towards the walls' edges."""
    base = scenarios.figure_scene(keep=("table",))
    half_gap = scenarios.CUBE_HALF_M + 0.001
    walls = [
        box_object(
            f"wall_{s}", (0.10, 0.10, 0.20), make_pose(p_AB=(0.45, s * (half_gap + 0.05), 0.1))
        )
        for s in (-1, 1)
    ]
    scene = dataclasses.replace(base, objects=(*base.objects, *walls))
    start = make_pose(p_AB=np.array([0.30, 0.12, 0.10]))
    waypoints = [
        scenarios.Waypoint((0.37, 0.0, 0.10)),
        scenarios.Waypoint((0.53, 0.0, 0.10)),
        scenarios.Waypoint((0.60, -0.12, 0.10)),
    ]
    sim = scenarios.drive(scene, start, waypoints)
    raw = path_from_history(sim.history, "cube", sim.c_O)
    deformer = Deformer(scene, "cube")
    result = deformer.deform(raw)
    world = SimWorld(scene, "cube")
    everything = np.arange(len(world.obstacle_object))
    in_gap = 0
    for node in result.path.nodes:
        assert min(p.distance_m for p in world.distances(node.X_WO, everything)) > FLOOR_M
        c = node.X_WO[:3, :3] @ sim.c_O + node.X_WO[:3, 3]
        in_gap += 0.40 < c[0] < 0.50
    assert in_gap >= 5  # the path still runs through the gap, node by node


def test_contact_step_never_ends_in_collision_nor_loses_a_required_contact() -> None:
    scene = scenarios.figure_scene()
    world = SimWorld(scene, "cube")
    c_O = scene.object("cube").model.com_O
    stepper = ContactStepper(world, c_O, P, 0.01)
    X = make_pose(p_AB=scenarios.FIG12_CORNER_W + np.full(3, 0.0003))
    required = frozenset({"frame", "table"})
    rng = np.random.default_rng(6)
    probe = stepper.probe(X)
    assert stepper.admissible(probe, required)
    for _ in range(60):
        f, m = rng.normal(scale=3.0, size=3), rng.normal(scale=0.05, size=3)
        X1, probe1, moved = stepper.displace(X, probe, f, m, required, 0.004)
        assert moved <= 0.004 + 1e-12
        assert stepper.admissible(probe1, required)
        X, probe = X1, probe1


# ------------------------------------------------------------------------------ the path


def test_path_marks_the_captured_stretches_and_the_goal_as_required(fig13: Case) -> None:
    raw = fig13.raw
    runs = [objects for _, _, objects in raw.stretches()]
    # Captured on the table, then frame and table round the corner; the goal rests on the table.
    assert runs == [{"table"}, {"frame", "table"}, {"table"}]
    first, last, _ = raw.stretches()[1]
    fixed = [i for i, n in enumerate(raw.nodes) if n.fixed]
    assert {0, len(raw) - 1, first, last} <= set(fixed)
    assert len(fixed) == 6  # path ends + both ends of the two capture stretches (goal = end)
    for node in raw.nodes[first : last + 1]:
        assert {c.object for c in node.contacts} >= {"frame", "table"}
    # A resting workpiece adds steps but no nodes: consecutive poses differ.
    steps = np.abs(np.diff(raw.poses, axis=0)).max(axis=(1, 2))
    assert np.all(steps > 0)
    history = list(scenarios.fig13_bottom().history[:5])
    rest = dataclasses.replace(history[-1], time_s=history[-1].time_s + P.dt_s)
    assert len(path_from_history([*history, rest, rest], "cube", raw.c_O)) == 5


def test_an_empty_history_is_refused() -> None:
    with pytest.raises(ValueError, match="history is empty"):
        path_from_history([], "cube", np.zeros(3))
