"""Path deformation at the extremes of its knobs: node spacing from 10 µm to 10 cm, tension,
repulsion and holding over six decades, every other knob over its accepted range
(``deform.RANGES``). Whatever the knobs, the deformation keeps the required contacts, never
brings the workpiece nearer anything than the simulator's floor, leaves the fixed nodes where
they were, and stops within its caps, saying why."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench import scenarios
from models.scene import Scene
from models.transforms import make_pose
from operator_site.program.deform import (
    INT_RANGES,
    MAX_NODES,
    RANGES,
    Deformer,
    DeformParams,
)
from operator_site.program.path import lost_contact_nodes, path_from_history
from operator_site.simulator import SimParams, Simulator
from tests.conftest import examples

SIM = SimParams()
FLOOR_M = SIM.floor_m
CUBE_HALF_M = 0.025
BAR_OUTER_Y_M = -0.12
"""The frame's −y bar's outer face (DESIGN.md: bars 20 mm wide round a 0.20 m opening)."""
NODES_PER_PATH = 20
"""About this many nodes at the finest spacing: each is a contact step a sweep."""
STOP_REASONS = {"settled", "no progress", "sweep cap", "node cap"}


@pytest.fixture(scope="module")
def scene() -> Scene:
    return scenarios.figure_scene()


def _log(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: min(max(10.0**e, lo), hi))


@st.composite
def deform_params(draw) -> DeformParams:
    """Every float knob over its range; the sweep caps small enough for a unit test (their
    ranges only bound the cost)."""
    values = {name: draw(_log(lo, hi)) for name, (lo, hi, _) in RANGES.items()}
    values["max_sweeps"] = draw(st.integers(0, 30))
    values["max_sweeps_coarse"] = draw(st.integers(0, 10))
    values["patience_sweeps"] = draw(st.integers(*INT_RANGES["patience_sweeps"]))
    return DeformParams(**values)


def _demonstration(scene: Scene, length_m: float, wiggle_m: float, captured: bool):
    """The cube dragged −x along the −y bar's outer face for ``length_m``, swinging
    ``wiggle_m`` towards and away from it; frame and table captured or not. Dragger steps
    of a twentieth of the length: the path's nodes are about that far apart."""
    gap = (SIM.eps_barrier_m + SIM.eps_contact_m) / 2
    y_face = BAR_OUTER_Y_M - CUBE_HALF_M - gap
    x0 = 0.50
    z = CUBE_HALF_M + gap
    sim = Simulator(scene, "cube", X_WO={"cube": make_pose(np.eye(3), (x0, y_face, z))})
    if captured:
        sim.capture("frame")
        sim.capture("table")
    history = [sim.step()]
    n = NODES_PER_PATH
    for k in range(1, n + 1):
        s = k / n
        y = y_face + (1e-3 if captured else 0.0) - wiggle_m * math.sin(math.pi * s) ** 2
        sim.set_target(make_pose(np.eye(3), (x0 - length_m * s, y, z - 1e-3)))
        history.append(sim.step())
    for _ in range(5):
        history.append(sim.step())
    return path_from_history(history, "cube", sim.c_O)


@settings(
    max_examples=examples(200),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(params=deform_params(), wiggle=st.floats(0.0, 1.0), captured=st.booleans())
def test_any_knobs_keep_contacts_clearance_and_ends_and_stop_with_a_reason(
    scene, params, wiggle, captured
) -> None:
    length = min(0.15, NODES_PER_PATH * params.spacing_m)
    raw = _demonstration(scene, length, wiggle * min(0.01, length / 4), captured)
    deformer = Deformer(scene, "cube", params)
    result = deformer.deform(raw)
    assert result.stopped in STOP_REASONS
    assert result.settled == (result.stopped == "settled")
    assert result.sweeps <= params.max_sweeps
    path = result.path
    assert 2 <= len(path) <= 2 * MAX_NODES
    X = path.poses
    assert np.all(np.isfinite(X))
    R = X[:, :3, :3]
    assert np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3))) < 1e-9
    np.testing.assert_array_equal(X[0], raw.nodes[0].X_WO)
    np.testing.assert_array_equal(X[-1], raw.nodes[-1].X_WO)
    assert lost_contact_nodes(path) == []
    for node in path.nodes:
        near = deformer.stepper.probe(node.X_WO).nearest
        assert all(pair.distance_m >= FLOOR_M * (1 - 1e-9) for pair in near.values())


def test_a_spacing_too_fine_for_the_path_is_refused_naming_the_finest_it_takes(scene) -> None:
    raw = _demonstration(scene, 0.1, 0.0, captured=True)
    with pytest.raises(ValueError, match=r"spacing_m 1e-05 m would put \d+ nodes .* at least"):
        Deformer(scene, "cube", DeformParams(spacing_m=1e-5)).deform(raw)


def test_knobs_outside_their_ranges_are_refused_naming_the_range() -> None:
    for name, (lo, hi, _) in RANGES.items():
        for bad in (lo / 10, hi * 10, math.nan):
            with pytest.raises(ValueError, match=rf"DeformParams\.{name} must be a number in \["):
                DeformParams(**{name: bad})
    for name, (lo, hi) in INT_RANGES.items():
        for bad in (lo - 1, hi + 1, 2.5):
            with pytest.raises(ValueError, match=rf"DeformParams\.{name} must be an integer in"):
                DeformParams(**{name: bad})


def test_a_deformation_that_would_grow_past_the_node_cap_stops_saying_so(scene, monkeypatch):
    """Insertions that would take a path past :data:`MAX_NODES` stop the sweeps."""
    import operator_site.program.deform as deform

    raw = _demonstration(scene, 0.1, 0.005, captured=False)
    monkeypatch.setattr(deform, "MAX_NODES", 12)
    params = DeformParams(spacing_m=0.01, coarse_spacing_m=0.01, insert_factor=1.1)
    result = Deformer(scene, "cube", params).deform(raw)
    assert result.stopped == "node cap" and not result.settled


def test_the_reason_is_sweep_cap_when_the_cap_stops_it(scene) -> None:
    raw = _demonstration(scene, 0.1, 0.005, captured=False)
    result = Deformer(scene, "cube", DeformParams(max_sweeps=1)).deform(raw)
    assert (result.stopped, result.sweeps, result.settled) == ("sweep cap", 1, False)
