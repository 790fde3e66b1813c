"""The gripper's fingers as part of the moving body (docs/design.md, "Grasp and program frames").

When the operator drags a block, the fingers that will hold it move with it: the simulator and
the program check treat them as convex parts of the workpiece, so a task never drives a finger
into a wall. Frames: G gripper TCP, P (= O) the workpiece; ``X_GP`` is the grasp.
"""

from __future__ import annotations

import numpy as np

from models.geometry import ConvexPart, make_convex_part
from models.robot import TCP_LINK, RobotModel
from models.scene import Scene
from models.transforms import invert_pose, make_pose, rpy_to_R
from operator_site.simulator.world import SimWorld

_BOX_FACES = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def finger_parts_O(robot: RobotModel, X_GP: np.ndarray, opening_m: float) -> list[ConvexPart]:
    """The fingers' collision boxes, at ``opening_m``, as convex parts in the workpiece frame."""
    poses = robot.link_poses_W(np.zeros(robot.n_arm), opening_m)
    X_OG = invert_pose(np.asarray(X_GP, dtype=np.float64))
    X_GW = invert_pose(poses[TCP_LINK])
    parts = []
    for name in robot.finger_joints:
        link = robot.links[robot.joint(name).child]
        for shape in link.collisions:
            if shape.kind != "box":
                raise ValueError(f"{robot.source}: finger {link.name} must be made of boxes")
            half = np.asarray(shape.size) / 2
            corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            X_OS = X_OG @ X_GW @ poses[link.name] @ shape.X_LV
            V = (corners * half) @ X_OS[:3, :3].T + X_OS[:3, 3]
            parts.append(make_convex_part(V, _BOX_FACES, f"{link.name} collision box"))
    return parts


BAR_CLEARANCE_M = 0.032
"""Fingertips at least this high above the table pass over the frame's 30 mm bars, so a block
held that way can be pushed against a bar (docs/design.md: grip high enough to clear them)."""
MIN_GRIP_STRIP_M = 0.015
"""A grip shorter than this down the block's sides is not trusted to carry the block; lower
blocks are held at mid-height."""


def bar_clearing_depth_m(bbox_O: np.ndarray) -> float | None:
    """How far down an upright block (bottom on the table) the fingertips may reach and still
    clear the bars; None if that leaves less than :data:`MIN_GRIP_STRIP_M` to hold."""
    lo, hi = np.asarray(bbox_O, dtype=np.float64)
    depth = float(hi[2] - lo[2]) - BAR_CLEARANCE_M
    return depth if depth >= MIN_GRIP_STRIP_M else None


def top_grasp(
    robot: RobotModel, bbox_O: np.ndarray, fingertip_depth_m: float | None = None
) -> tuple[np.ndarray, float]:
    """A grasp from above (``X_GP``, finger opening m) for a block with bounding box (2, 3) in O:
    gripper z down, fingers on the block's ±y faces, the TCP at the block's centre, or, with
    ``fingertip_depth_m``, the fingertips that far below its top (never lower than centred)."""
    lo, hi = bbox_O
    opening = float(hi[1] - lo[1])
    # How far the fingertips reach below the TCP (G's z points down, out of the palm).
    X_GP0 = np.eye(4)
    tip_below_tcp = max(
        float(part.vertices_O[:, 2].max()) for part in finger_parts_O(robot, X_GP0, opening)
    )
    centred = 0.5 * (lo[2] + hi[2]) - tip_below_tcp
    z_tips = centred if fingertip_depth_m is None else max(hi[2] - fingertip_depth_m, centred)
    centre = 0.5 * (lo + hi)
    X_OG = np.eye(4)
    X_OG[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    X_OG[:3, 3] = (centre[0], centre[1], z_tips + tip_below_tcp)
    return invert_pose(X_OG), opening


GRASP_CLEARANCE_M = 0.005
"""Open fingers nearer than this to another object may touch it on the way down to the grasp
(the model's poses are vision's, off by up to a few millimetres; the work site stops at the
first touch). A block square in section is then taken by its other pair of faces if the open
fingers are clearer there."""
SQUARE_SECTION_TOL_M = 1e-6
_QUARTER_TURN_Z = make_pose(rpy_to_R(np.array([0.0, 0.0, 0.5 * np.pi])))


def open_finger_clearance_m(
    robot: RobotModel, scene: Scene, name: str, X_WO: dict[str, np.ndarray], X_GP: np.ndarray
) -> float:
    """Least distance (m) from the fully open fingers of grasp ``X_GP`` on block ``name``, as it
    lies at ``X_WO[name]``, to every other object at ``X_WO`` (≤ 0: they overlap)."""
    fingers = tuple(finger_parts_O(robot, X_GP, robot.finger_opening_max))
    world = SimWorld(scene, name, X_WO, attached_O=fingers)
    pairs = world.distances(X_WO[name], np.arange(len(world.obstacle_object)))
    return min(p.distance_m for p in pairs if p.wp_part >= world.n_own_parts)


def clear_top_grasp(
    robot: RobotModel, scene: Scene, name: str, X_WO: dict[str, np.ndarray]
) -> tuple[np.ndarray, float]:
    """:func:`top_grasp` of block ``name`` (deep enough to clear the bars where it is tall
    enough), or, for a block square in section whose open fingers come within
    :data:`GRASP_CLEARANCE_M` of another object, the same grasp a quarter turn round on its
    other pair of faces when the fingers are clearer there."""
    bbox = scene.object(name).model.bbox_O
    X_GP, opening = top_grasp(robot, bbox, bar_clearing_depth_m(bbox))
    lo, hi = np.asarray(bbox, dtype=np.float64)
    if abs((hi[0] - lo[0]) - (hi[1] - lo[1])) > SQUARE_SECTION_TOL_M:
        return X_GP, opening
    clearance = open_finger_clearance_m(robot, scene, name, X_WO, X_GP)
    if clearance >= GRASP_CLEARANCE_M:
        return X_GP, opening
    # The turn is about the gripper's z through the TCP, which top_grasp puts on the block's
    # vertical centre line: the fingers land on the other two faces, centred as before.
    turned = _QUARTER_TURN_Z @ X_GP
    if open_finger_clearance_m(robot, scene, name, X_WO, turned) > clearance:
        return turned, opening
    return X_GP, opening
