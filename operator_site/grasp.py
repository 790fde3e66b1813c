"""The gripper's fingers as part of the moving body (docs/design.md, "Grasp and program frames").

When the operator drags a block, the fingers that will hold it move with it: the simulator and
the program check treat them as convex parts of the workpiece, so a task never drives a finger
into a wall. Frames: G gripper TCP, P (= O) the workpiece; ``X_GP`` is the grasp.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.geometry import ConvexPart, make_convex_part
from models.robot import TCP_LINK, RobotModel
from models.scene import Scene
from models.transforms import invert_pose, make_pose, rpy_to_R
from operator_site.simulator import StepResult
from operator_site.simulator.world import SimWorld
from protocol.messages import SAME_CONTACT_DIRECTION_RAD

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
FINGERTIP_TABLE_CLEARANCE_M = 0.006
"""Fingertips never lower than this above the block's bottom (the table): the work site keeps
every TCP target where the fingertips are 5 mm above the table, and one more millimetre keeps
rounding from putting a grasp just outside its workspace."""


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
    ``fingertip_depth_m``, the fingertips that far below its top (never lower than centred);
    the fingertips stay :data:`FINGERTIP_TABLE_CLEARANCE_M` above the block's bottom."""
    lo, hi = bbox_O
    opening = float(hi[1] - lo[1])
    # How far the fingertips reach below the TCP (G's z points down, out of the palm).
    X_GP0 = np.eye(4)
    tip_below_tcp = max(
        float(part.vertices_O[:, 2].max()) for part in finger_parts_O(robot, X_GP0, opening)
    )
    centred = 0.5 * (lo[2] + hi[2]) - tip_below_tcp
    z_tips = centred if fingertip_depth_m is None else max(hi[2] - fingertip_depth_m, centred)
    z_tips = max(z_tips, lo[2] + FINGERTIP_TABLE_CLEARANCE_M)
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


# ----------------------------------------------------------------------------------------------
# Grasps chosen for the task: which pair of faces, where along them, how high.

PAD_FACING_SIN = float(np.sin(SAME_CONTACT_DIRECTION_RAD))
"""A finger pad faces a contact normal when the normal is further than the protocol's "same
direction" angle from perpendicular to the pad: the finger is then on the pressed face."""
PRESSED_FINGER_CLEARANCE_M = 0.001
"""A finger on a pressed face must stay this clear of the object pressing it (m): above a bar
it is out of the way; anywhere else it would be squeezed between the block and the surface."""
MIN_GRIP_AREA_M2 = MIN_GRIP_STRIP_M * 0.02
"""Least pad area on material on both faces: a strip of :data:`MIN_GRIP_STRIP_M` across a
finger 20 mm wide (less and the block turns in the grip under the contact forces)."""
GRIP_SLIDE_POSITIONS = 7
"""Places tried along each pair of faces (the face's centre among them)."""
PAD_SAMPLES_U, PAD_SAMPLES_V = 5, 9
"""Sample grid over a finger pad (across, down) for the area it presses on material."""
PAD_INSET_M = 1e-4
"""Pad samples are taken this far inside the block's support plane (on its face)."""
MAX_PATH_POSES_CHECKED = 120
"""At most this many poses of the path are checked for the fingers (evenly spread, both ends
always among them): a drag records a pose every step."""
_DIRECTION_TOL = 1e-6


@dataclass(frozen=True)
class Grasp:
    """A grasp: ``X_GP`` (the workpiece in the gripper frame), the finger opening (m) that holds
    it, the pair of faces in words, the pad area on material (m²) and the fingertips' height
    above the block's bottom (m; clear of the bars from :data:`BAR_CLEARANCE_M`)."""

    X_GP: np.ndarray
    opening_m: float
    faces: str
    grip_area_m2: float
    tip_height_m: float = 0.0


@dataclass(frozen=True)
class PressedContact:
    """A contact the task presses: ``object``, its unit normals (k, 3) into the workpiece in
    W, and the workpiece pose ``X_WO`` where it is pressed."""

    object: str
    normals_W: np.ndarray
    X_WO: np.ndarray


@dataclass(frozen=True)
class GraspChoice:
    """The chosen grasp (None: no grasp does the task) and, when none, why, in plain words;
    ``rejected`` says why each pair of faces was turned down."""

    grasp: Grasp | None
    reason: str = ""
    rejected: tuple[str, ...] = ()


def _finger_box_G(robot: RobotModel) -> tuple[float, float, float]:
    """The closed fingers' half-width across the pad (along G's x, m), how far the fingertips
    reach below the TCP (along G's z, m), and the pad's length up from the tips (m)."""
    V = np.vstack([p.vertices_O for p in finger_parts_O(robot, np.eye(4), 0.0)])
    half_width = 0.5 * float(V[:, 0].max() - V[:, 0].min())
    tip = float(V[:, 2].max())
    return half_width, tip, tip - float(V[:, 2].min())


def _closing_directions_O(model, up_O: np.ndarray) -> list[np.ndarray]:
    """Unit directions (up to sign) across the block's vertical faces, in O, each once."""
    N = np.vstack([p.normals_O for p in model.parts])
    horizontal = N[np.abs(N @ up_O) < _DIRECTION_TOL]
    out: list[np.ndarray] = []
    for n in horizontal:
        if all(abs(float(n @ m)) < 1.0 - _DIRECTION_TOL for m in out):
            out.append(n / np.linalg.norm(n))
    return out


def _inside(model, p_O: np.ndarray) -> np.ndarray:
    """Whether each point (n, 3) lies inside one of the block's convex parts, (n,) bool."""
    inside = np.zeros(len(p_O), dtype=bool)
    for part in model.parts:
        inside |= part.signed_distance_upper_bound(p_O) < 0.0
    return inside


def _grip_area_m2(model, d_O, e_u, up_O, s_lo, s_hi, u, z_tip, half_width, pad_len) -> float:
    """Area (m²) of the pad at ``u`` across and from ``z_tip`` up that presses material on both
    of the faces at ``s_lo`` and ``s_hi`` along ``d_O``."""
    us = np.linspace(u - half_width, u + half_width, PAD_SAMPLES_U)
    vs = np.linspace(z_tip, z_tip + pad_len, PAD_SAMPLES_V)
    U, V = (a.ravel() for a in np.meshgrid(us, vs))
    base = U[:, None] * e_u + V[:, None] * up_O
    both = _inside(model, base + (s_lo + PAD_INSET_M) * d_O) & _inside(
        model, base + (s_hi - PAD_INSET_M) * d_O
    )
    return float(both.mean()) * 2.0 * half_width * pad_len


def grasp_candidates(robot: RobotModel, scene: Scene, name: str, X_WO: np.ndarray) -> list[Grasp]:
    """Every grasp from above of block ``name`` lying at ``X_WO``: the fingers closing across
    each pair of its vertical faces no wider apart than the stroke, at
    :data:`GRIP_SLIDE_POSITIONS` places along them and at the heights :func:`top_grasp` uses
    (clear of the bars where the block is tall enough, centred, and as low as the table
    allows), each pressing at least :data:`MIN_GRIP_AREA_M2` of material on both faces. The
    gripper's z points down: the work site descends onto every grasp from above."""
    model = scene.object(name).model
    up_O = np.asarray(X_WO, dtype=np.float64)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    V = np.vstack([p.vertices_O for p in model.parts])
    half_width, tip_below_tcp, pad_len = _finger_box_G(robot)
    h = V @ up_O
    bottom, top = float(h.min()), float(h.max())
    centred = 0.5 * (bottom + top) - tip_below_tcp
    low = bottom + FINGERTIP_TABLE_CLEARANCE_M
    tips = [max(centred, low), low]
    if top - (bottom + BAR_CLEARANCE_M) >= MIN_GRIP_STRIP_M:
        tips.insert(0, max(bottom + BAR_CLEARANCE_M, centred))
    tips = list(dict.fromkeys(round(t, 12) for t in tips))
    c_O = model.com_O
    out: list[Grasp] = []
    for d_O in _closing_directions_O(model, up_O):
        s = V @ d_O
        s_lo, s_hi = float(s.min()), float(s.max())
        opening = s_hi - s_lo
        if opening + 2 * GRASP_CLEARANCE_M > robot.finger_opening_max:
            continue
        e_u = np.cross(up_O, d_O)
        u_all = V @ e_u
        u_lo, u_hi = float(u_all.min()) + half_width, float(u_all.max()) - half_width
        u_mid = 0.5 * (float(u_all.min()) + float(u_all.max()))
        slides = np.linspace(u_lo, u_hi, GRIP_SLIDE_POSITIONS) if u_hi > u_lo else np.array([])
        # The face's centre first, then nearest the centre of mass (least torque in the grip).
        slides = [u_mid, *sorted(slides.tolist(), key=lambda u: abs(u - float(c_O @ e_u)))]
        faces = _faces_words(d_O)
        for z_tip in tips:
            for u in slides:
                area = _grip_area_m2(
                    model, d_O, e_u, up_O, s_lo, s_hi, u, z_tip, half_width, pad_len
                )
                if area < MIN_GRIP_AREA_M2:
                    continue
                X_OG = np.eye(4)
                X_OG[:3, :3] = np.column_stack([np.cross(d_O, -up_O), d_O, -up_O])
                X_OG[:3, 3] = 0.5 * (s_lo + s_hi) * d_O + u * e_u + (z_tip + tip_below_tcp) * up_O
                out.append(Grasp(invert_pose(X_OG), opening, faces, area, z_tip - bottom))
    return out


def grip_area_m2(robot: RobotModel, scene: Scene, name: str, X_GP: np.ndarray) -> float:
    """Area (m²) of a finger pad of grasp ``X_GP`` (gripper z down) that presses material of
    block ``name`` on both faces it holds."""
    model = scene.object(name).model
    X_OG = invert_pose(np.asarray(X_GP, dtype=np.float64))
    d_O, up_O = X_OG[:3, 1], -X_OG[:3, 2]
    e_u = np.cross(up_O, d_O)
    half_width, tip_below_tcp, pad_len = _finger_box_G(robot)
    s = np.vstack([p.vertices_O for p in model.parts]) @ d_O
    p_O = X_OG[:3, 3]
    return _grip_area_m2(
        model,
        d_O,
        e_u,
        up_O,
        float(s.min()),
        float(s.max()),
        float(p_O @ e_u),
        float(p_O @ up_O) - tip_below_tcp,
        half_width,
        pad_len,
    )


def _faces_words(d_O: np.ndarray) -> str:
    """The pair of faces across ``d_O`` in words ("±y faces", or their normal)."""
    for k, axis in enumerate("xyz"):
        if abs(abs(float(d_O[k])) - 1.0) < _DIRECTION_TOL:
            return f"±{axis} faces"
    return f"faces ±{np.round(d_O, 3).tolist()}"


def pressed_contacts(path: Sequence[StepResult]) -> list[PressedContact]:
    """The contacts a demonstrated path presses: every captured contact along it and the whole
    contact state at its end (the task's goal), as :func:`path_from_history` marks them
    required; the captured ones along the way at most :data:`MAX_PATH_POSES_CHECKED`, spread
    evenly."""
    along = [
        PressedContact(c.object, np.asarray(c.normals_W), step.X_WO)
        for step in path[:-1]
        for c in step.contacts
        if c.captured
    ]
    goal = [
        PressedContact(c.object, np.asarray(c.normals_W), path[-1].X_WO)
        for c in (path[-1].contacts if path else ())
    ]
    return _spread(along, MAX_PATH_POSES_CHECKED) + goal


def _spread(poses: Sequence[np.ndarray], n_max: int) -> list[np.ndarray]:
    """At most ``n_max`` of ``poses``, evenly spread, first and last kept."""
    if len(poses) <= n_max:
        return list(poses)
    keep = np.unique(np.round(np.linspace(0, len(poses) - 1, n_max)).astype(int))
    return [poses[i] for i in keep]


def grasp_problem(
    robot: RobotModel,
    scene: Scene,
    name: str,
    X_WO: dict[str, np.ndarray],
    grasp: Grasp,
    path_X_WO: Sequence[np.ndarray],
    pressed: Sequence[PressedContact],
) -> str:
    """Why ``grasp`` cannot do the task ("" if it can): the open fingers meet something on the
    way down to it, a finger is between the workpiece and a surface the task presses, or the
    fingers run into something along ``path_X_WO`` (fcl, the simulator's geometry), in that
    order: a finger pressed into a wall is said to be between, the more useful reason."""
    start = X_WO[name]
    if open_finger_clearance_m(robot, scene, name, X_WO, grasp.X_GP) <= 0.0:
        return f"{grasp.faces}: the open fingers would hit a neighbour on the way down"
    fingers = tuple(finger_parts_O(robot, grasp.X_GP, grasp.opening_m))
    world = SimWorld(scene, name, X_WO, attached_O=fingers)
    for contact in pressed:
        d_W = contact.X_WO[:3, :3] @ (invert_pose(grasp.X_GP)[:3, :3] @ [0.0, 1.0, 0.0])
        if np.max(np.abs(np.asarray(contact.normals_W) @ d_W)) <= PAD_FACING_SIN:
            continue  # the pads are side-on to this contact: out of its way
        parts = np.flatnonzero(np.array(world.obstacle_object) == contact.object)
        pairs = world.distances(contact.X_WO, parts)
        if (
            min((p.distance_m for p in pairs if p.wp_part >= world.n_own_parts), default=np.inf)
            < PRESSED_FINGER_CLEARANCE_M
        ):
            return f"{grasp.faces}: a finger would be between the {name} and the {contact.object}"
    for X in _spread([start, *path_X_WO], MAX_PATH_POSES_CHECKED):
        lo, hi = world.workpiece_box(X, PRESSED_FINGER_CLEARANCE_M)
        near = world.candidates(lo, hi)
        for pair in world.distances(X, near) if len(near) else []:
            if pair.wp_part >= world.n_own_parts and pair.distance_m <= 0.0:
                other = world.obstacle_object[pair.obstacle]
                return f"{grasp.faces}: a finger would run into the {other} on the way"
    return ""


def _side_on(grasp: Grasp, pressed: Sequence[PressedContact]) -> bool:
    """Whether both pads are side-on to every pressed contact normal."""
    for contact in pressed:
        d_W = contact.X_WO[:3, :3] @ (invert_pose(grasp.X_GP)[:3, :3] @ [0.0, 1.0, 0.0])
        if np.max(np.abs(np.asarray(contact.normals_W) @ d_W)) > PAD_FACING_SIN:
            return False
    return True


def choose_grasp(
    robot: RobotModel,
    scene: Scene,
    name: str,
    X_WO: dict[str, np.ndarray],
    path_X_WO: Sequence[np.ndarray] = (),
    pressed: Sequence[PressedContact] = (),
) -> GraspChoice:
    """The grasp for moving block ``name`` from ``X_WO[name]`` along ``path_X_WO`` (its poses,
    the goal last) pressing ``pressed``: today's :func:`clear_top_grasp` when it can do the
    task (:func:`grasp_problem`) with its pads side-on to every pressed normal; else, among
    :func:`grasp_candidates`, the first that can, preferring pads side-on to every pressed
    normal (when today's grasp can do the task, only those with the open fingers
    :data:`GRASP_CLEARANCE_M` clear of every neighbour; failing them, today's grasp), then
    fingers clear of the bars, then the most pad area, then the nearest the block's centre. No
    grasp: the reason for each pair of faces."""
    X_GP, opening = clear_top_grasp(robot, scene, name, X_WO)
    faces = _faces_words(invert_pose(X_GP)[:3, :3] @ [0.0, 1.0, 0.0])
    up_O = X_WO[name][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    V = np.vstack([p.vertices_O for p in scene.object(name).model.parts])
    tip_O = invert_pose(X_GP)[:3, 3] @ up_O - _finger_box_G(robot)[1]
    area = grip_area_m2(robot, scene, name, X_GP)
    default = Grasp(X_GP, opening, faces, area, float(tip_O - (V @ up_O).min()))
    default_ok = default.grip_area_m2 >= MIN_GRIP_AREA_M2 and not grasp_problem(
        robot, scene, name, X_WO, default, path_X_WO, pressed
    )
    if default_ok and _side_on(default, pressed):
        return GraspChoice(default)
    candidates = grasp_candidates(robot, scene, name, X_WO[name])
    candidates.sort(
        key=lambda g: (
            not _side_on(g, pressed),
            g.tip_height_m < BAR_CLEARANCE_M - _DIRECTION_TOL,
            -round(g.grip_area_m2, 6),
        )
    )
    rejected: dict[str, str] = {}
    for grasp in candidates:
        if default_ok:
            # Pads facing a pressed surface pass it only just above a bar (the program's
            # deformation may tilt them into it): side-on pads clear of the neighbours are
            # preferred; else today's grasp, which does the task too.
            if not _side_on(grasp, pressed):
                return GraspChoice(default)
            clear = open_finger_clearance_m(robot, scene, name, X_WO, grasp.X_GP)
            if clear < GRASP_CLEARANCE_M:
                continue
        problem = grasp_problem(robot, scene, name, X_WO, grasp, path_X_WO, pressed)
        if not problem:
            return GraspChoice(grasp)
        rejected.setdefault(grasp.faces, problem)
    if default_ok:
        return GraspChoice(default)
    for d_O in _closing_directions_O(scene.object(name).model, up_O):
        faces = _faces_words(d_O)
        width = float(np.ptp(V @ d_O))
        if faces not in rejected:
            rejected[faces] = (
                f"{faces}: {width:.3f} m apart, wider than the gripper opens "
                f"({robot.finger_opening_max:.3f} m, less a {GRASP_CLEARANCE_M:.3f} m margin "
                "each side)"
                if width + 2 * GRASP_CLEARANCE_M > robot.finger_opening_max
                else f"{faces}: the fingers would press too little of the block"
            )
    reasons = "; ".join(rejected.values()) or "it has no vertical faces to hold"
    return GraspChoice(
        None, f"no grasp of the {name} can do this task: {reasons}", tuple(rejected.values())
    )
