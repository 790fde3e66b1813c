"""The gripper's fingers as part of the moving body (DESIGN.md, "Grasp and program frames").

When the operator drags a block, the fingers that will hold it move with it: the simulator and
the program check treat them as convex parts of the workpiece, so a task never drives a finger
into a wall. Frames: G gripper TCP, P (= O) the workpiece; ``X_GP`` is the grasp.
"""

from __future__ import annotations

import numpy as np

from models.geometry import ConvexPart, make_convex_part
from models.robot import TCP_LINK, RobotModel
from models.transforms import invert_pose

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
held that way can be pushed against a bar (DESIGN.md: grip high enough to clear them)."""
MIN_GRIP_STRIP_M = 0.015
"""A grip shorter than this down the block's sides is not trusted; lower blocks are held at
mid-height (measured at the work site: an 18 mm strip carries the cube, 0.06 mm off)."""


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
