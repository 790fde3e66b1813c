"""The gizmo's geometry: world axes by default, the block's target through the gizmo's motion,
snapping of that motion to its steps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.transforms import make_pose, rpy_to_R, so3_exp, so3_log
from operator_site.ui.gizmo import NO_SNAP, Gizmo, Snap, gizmo_pose_W, snapped_motion
from tests.conftest import examples

X_WO = make_pose(rpy_to_R(np.radians([3.0, -7.0, 127.0])), np.array([0.41, -0.12, 0.026]))


def test_the_gizmo_has_world_axes_at_the_block_origin_by_default() -> None:
    X_WG = gizmo_pose_W(X_WO, world_axes=True)
    np.testing.assert_array_equal(X_WG[:3, :3], np.eye(3))
    np.testing.assert_array_equal(X_WG[:3, 3], X_WO[:3, 3])
    np.testing.assert_array_equal(gizmo_pose_W(X_WO, world_axes=False), X_WO)


@pytest.mark.parametrize("world_axes", [True, False])
def test_an_unmoved_gizmo_asks_for_the_block_where_it_is(world_axes: bool) -> None:
    gizmo = Gizmo(world_axes)
    X_WG = gizmo.place(X_WO)
    gizmo.begin()
    np.testing.assert_allclose(gizmo.target_W(X_WG), X_WO, atol=1e-12)


def test_a_turn_about_the_world_z_axis_turns_the_block_about_its_origin() -> None:
    gizmo = Gizmo(world_axes=True, snap=NO_SNAP)
    X_WG = gizmo.place(X_WO)
    gizmo.begin()
    turn = make_pose(rpy_to_R(np.array([0.0, 0.0, math.radians(30.0)])), X_WG[:3, 3])
    target = gizmo.target_W(turn)
    np.testing.assert_allclose(target[:3, 3], X_WO[:3, 3], atol=1e-12)
    np.testing.assert_allclose(
        target[:3, :3],
        rpy_to_R(np.array([0.0, 0.0, math.radians(30.0)])) @ X_WO[:3, :3],
        atol=1e-12,
    )


def test_snapping_rounds_the_motion_to_a_millimetre_and_five_degrees() -> None:
    X0 = make_pose(np.eye(3), np.array([0.4123, 0.0, 0.02]))
    X = make_pose(rpy_to_R(np.radians([0.0, 0.0, 12.6])), X0[:3, 3] + [0.01234, -0.0026, 0.0])
    out = snapped_motion(X0, X, Snap())
    np.testing.assert_allclose(out[:3, 3] - X0[:3, 3], [0.012, -0.003, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        so3_log(out[:3, :3] @ X0[:3, :3].T), [0.0, 0.0, math.radians(15.0)], atol=1e-12
    )
    np.testing.assert_allclose(snapped_motion(X0, X, NO_SNAP), X, atol=1e-12)


@settings(max_examples=examples(200))
@given(
    st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.floats(1e-4, 0.05),
    st.floats(math.radians(0.5), math.radians(90.0)),
)
def test_snapped_motion_is_on_its_steps_and_within_half_a_step(shift, rotvec, step_m, step_rad):
    X0 = make_pose(rpy_to_R(np.array([0.1, -0.2, 0.3])), np.array([0.4, 0.1, 0.03]))
    R = so3_exp(np.array(rotvec)) @ X0[:3, :3]
    X = make_pose(R, X0[:3, 3] + shift)
    out = snapped_motion(X0, X, Snap(step_m, step_rad))
    moved = (out[:3, 3] - X0[:3, 3]) / step_m
    np.testing.assert_allclose(moved, np.round(moved), atol=1e-6)
    assert np.all(np.abs(out[:3, 3] - X[:3, 3]) <= step_m / 2 + 1e-12)
    # A whole number of steps about one axis: an angle beyond π shows as 2π less about the
    # opposite axis.
    angle = np.linalg.norm(so3_log(out[:3, :3] @ X0[:3, :3].T))
    steps = [a / step_rad for a in (angle, 2 * math.pi - angle)]
    assert min(abs(n - round(n)) for n in steps) < 1e-6, steps
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize(("step_m", "step_rad"), [(0.0, None), (1.0, None), (None, 0.0)])
def test_a_snap_outside_its_range_is_refused_naming_it(step_m, step_rad) -> None:
    with pytest.raises(ValueError, match=r"must be in \["):
        Snap(step_m, step_rad)
