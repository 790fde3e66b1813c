"""Scripted operators for the paper's program-generation figures, in the puzzle scene.

Each scenario drives a :class:`~operator_site.simulator.Simulator`'s dragger through waypoints at
an operator's pace, capturing and releasing objects on the way, and returns the simulator with
its history: the raw workpiece path that §VI starts from. Used by the tests and the benchmark.

The puzzle frame (DESIGN.md): inner opening 0.20 m centred at (0.45, 0), bars 0.02 m wide and
0.03 m tall; the table top is z = 0. Only the table, the frame and the workpiece are kept, so
that the figures' geometry is what the path meets.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.geometry import ConvexPart
from models.scene import Scene, load_scene
from models.transforms import make_pose, rpy_to_R, so3_exp, so3_log
from operator_site.simulator import SimParams, Simulator

CUBE_HALF_M = 0.025
OPERATOR_SPEED_MPS = 0.05
"""The dragger moves this fast between waypoints (a calm hand: 2.5 mm per 50 ms step)."""
SETTLE_STEPS = 6
"""Steps held at each waypoint, so that the spring (time constant 0.2 s) catches up."""
PRESS_M = 0.004
"""A target this far inside a surface keeps the workpiece pressed against it while sliding."""
FIG12_CORNER_W = np.array([0.375, -0.075, CUBE_HALF_M])
"""The cube's centre in the frame's inner corner at the smallest x and y (Fig. 12's B)."""


@dataclass(frozen=True)
class Waypoint:
    """Where the dragger goes next (centre of the cube, yaw), and captures to change there."""

    p_W: tuple[float, float, float]
    yaw_deg: float = 0.0
    capture: tuple[str, ...] = ()
    release: tuple[str, ...] = ()


def figure_scene(scene: Scene | None = None, keep: Sequence[str] = ("table", "frame")) -> Scene:
    """The puzzle scene with only ``keep`` and the cube (the figures' obstacles)."""
    scene = scene or load_scene()
    names = {*keep, "cube"}
    return dataclasses.replace(scene, objects=tuple(o for o in scene.objects if o.name in names))


def _pose(p_W: Sequence[float], yaw_deg: float) -> np.ndarray:
    return make_pose(rpy_to_R(np.array([0.0, 0.0, np.deg2rad(yaw_deg)])), np.array(p_W, float))


def drive(
    scene: Scene,
    X_WO_start: np.ndarray,
    waypoints: Sequence[Waypoint],
    params: SimParams | None = None,
    speed_mps: float = OPERATOR_SPEED_MPS,
    attached_O: tuple[ConvexPart, ...] = (),
) -> Simulator:
    """Drag the cube from ``X_WO_start`` through ``waypoints`` (the dragger moving at
    ``speed_mps``, its yaw interpolated) and return the simulator with its history;
    ``attached_O``: the gripper's fingers, moving with the cube."""
    sim = Simulator(scene, "cube", params, X_WO={"cube": X_WO_start}, attached_O=attached_O)
    dt = sim.params.dt_s
    X_D = sim.X_WO
    for wp in waypoints:
        for name in wp.capture:
            sim.capture(name)
        for name in wp.release:
            sim.release(name)
        X_goal = _pose(wp.p_W, wp.yaw_deg)
        dp = X_goal[:3, 3] - X_D[:3, 3]
        w = so3_log(X_goal[:3, :3] @ X_D[:3, :3].T)
        n = max(1, int(np.ceil(np.linalg.norm(dp) / (speed_mps * dt))))
        R0, p0 = X_D[:3, :3].copy(), X_D[:3, 3].copy()
        for k in range(1, n + 1):
            X_D = make_pose(so3_exp(w * k / n) @ R0, p0 + dp * k / n)
            sim.set_target(X_D)
            sim.step()
        for _ in range(SETTLE_STEPS):
            sim.step()
    return sim


def fig12(
    scene: Scene | None = None,
    speed_mps: float = OPERATOR_SPEED_MPS,
    attached_O: tuple[ConvexPart, ...] = (),
) -> Simulator:
    """Fig. 12: the operator grabs the cube at A (outside the frame's −y bar), wanders off to
    the left, pushes it against the bar's outer face to align it, drags it over the bar (tilting
    it on the way) and slides it into the frame's inner corner B."""
    scene = figure_scene(scene)
    z_rest = CUBE_HALF_M - PRESS_M  # pressed onto the table while sliding
    z_over = 0.03 + CUBE_HALF_M + 0.012  # 12 mm above the bar
    A = _pose((0.40, -0.20, CUBE_HALF_M), 15.0)
    waypoints = [
        Waypoint((0.30, -0.23, z_rest), 25.0),  # wander off to the left
        Waypoint((0.24, -0.17, z_rest), 10.0),
        Waypoint((0.40, -0.145 + PRESS_M, z_rest), 0.0),  # against the bar's outer face: align
        Waypoint((0.43, -0.12 - CUBE_HALF_M + PRESS_M, z_rest), 0.0),
        Waypoint((0.43, -0.13, z_over), 8.0),  # up over the bar, going out of alignment
        Waypoint((0.45, -0.06, z_over), 12.0),
        Waypoint((0.45, -0.04, z_rest), 0.0),  # down onto the table inside the frame
        Waypoint((0.40, -0.07, z_rest), 0.0),
        Waypoint((0.375 - PRESS_M, -0.075 - PRESS_M, z_rest), 0.0),  # slide into the corner
    ]
    return drive(scene, A, waypoints, speed_mps=speed_mps, attached_O=attached_O)


def fig13_bottom(scene: Scene | None = None, speed_mps: float = OPERATOR_SPEED_MPS) -> Simulator:
    """Fig. 13 bottom: the cube slides along the outside of the frame's −y bar and round the
    outer corner at (0.33, −0.12) onto the −x bar's outer face, with frame and table captured
    from the bar to past the corner; before and after, it is dragged loosely on the table."""
    scene = figure_scene(scene)
    z_rest = CUBE_HALF_M - PRESS_M
    y_face = -0.12 - CUBE_HALF_M  # centre of a cube touching the −y bar's outer face
    x_face = 0.33 - CUBE_HALF_M  # … and the −x bar's outer face
    A = _pose((0.50, -0.22, CUBE_HALF_M), 10.0)
    waypoints = [
        Waypoint((0.48, -0.19, z_rest), 0.0),
        Waypoint((0.46, y_face + PRESS_M, z_rest), 0.0, capture=("table", "frame")),
        Waypoint((0.33, y_face + PRESS_M, z_rest), 0.0),  # along the −y bar
        Waypoint((x_face + 0.01, y_face + 0.01, z_rest), 0.0),  # round the corner
        Waypoint((x_face + PRESS_M, -0.10, z_rest), 0.0),
        Waypoint((x_face + PRESS_M, -0.03, z_rest), 0.0),  # along the −x bar
        Waypoint((x_face - 0.01, -0.02, z_rest), 0.0, release=("table", "frame")),
        Waypoint((0.23, 0.02, z_rest), 0.0),  # away on the table
        Waypoint((0.20, 0.06, CUBE_HALF_M), -10.0),
    ]
    return drive(scene, A, waypoints, speed_mps=speed_mps)
