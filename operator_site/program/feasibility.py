"""Can the robot do this program at all? Checked at the operator site before sending, with the
reason in plain words (the sweep of :mod:`.check` asks only whether it collides).

Three questions, each answered with the work site's own rules:

- every contact the program expects must be one the robot can verify: the work site verifies a
  contact by the wrist force along its normal (``work_site/control/executor.py``), so a contact
  that no motion presses into (a face the block only touches, moves away from or slides past
  with no bias into it) reads 0 N there and fails the program half done;
- the program's grasp must exist: from above, the faces it holds no wider apart than the
  gripper opens, enough of the pads on the block, no finger on the way down or along the path
  into anything, none between the workpiece and a surface it presses
  (:func:`operator_site.grasp.grasp_problem`);
- every gripper pose the program's motions aim at must be in the work site's workspace box, and
  every straight move to one followed within the joint limits without a swing to another arm
  configuration, by the same closed-form IK the work site's acceptance check uses
  (:func:`models.kinematics.follow_line_tcp`), move after move from the arm's home.
"""

from __future__ import annotations

import math
from collections.abc import Container, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import nnls

from models.geometry import ConvexPart
from models.kinematics import PathFollow, arm_geometry, follow_line_tcp, plan_approach
from models.robot import RobotModel, load_robot
from models.scene import Scene
from models.transforms import invert_pose
from operator_site.grasp import (
    GRASP_CLEARANCE_M,
    MIN_GRIP_AREA_M2,
    Grasp,
    PressedContact,
    grasp_problem,
    grip_area_m2,
)
from operator_site.program.commands import contact_states
from operator_site.simulator.world import SimWorld
from protocol import MotionCommand, MotionProgram
from protocol.execution import (
    CONTACT_VERIFY_N,
    GRASP_LIFT_M,
    GUARD_OVERTRAVEL_M,
    NORMAL_STIFFNESS_N_PER_M,
    WORKSPACE_MAX_W,
    WORKSPACE_MIN_W,
    contact_bias_W,
    grasp_approach_W,
    press_caps_n,
)
from protocol.messages import contact_directions

FROM_ABOVE_COS = float(np.cos(np.pi / 4))
"""A grasp comes from above when the gripper's z is within 45° of straight down: the work site
descends onto it vertically, and the finger model here measures pads on vertical faces."""
_UP_W = np.array([0.0, 0.0, 1.0])
_CARRYING = ("guarded_grasp", "move", "guarded_move", "contact_move")


@dataclass(frozen=True)
class Feasibility:
    """Whether the robot can do a program: ``ok``; when not, the ``reason`` in plain words,
    the index of the ``command`` it concerns and which ``check`` refused it ("contact",
    "grasp" or "reach")."""

    ok: bool
    reason: str = ""
    command: int | None = None
    check: str = ""


def _where(k: int, cmd: MotionCommand) -> str:
    return f"command {k} ({cmd.kind})"


def _gaps_m(world: SimWorld, X_WP: np.ndarray, names: set[str]) -> dict[str, float]:
    """Distance (m, ≥ 0) from the workpiece at ``X_WP`` to each named object. The block's own
    parts only: a finger passing over a bar is near it, but it is the block that is pressed."""
    out: dict[str, float] = {}
    for name in names:
        parts = np.flatnonzero(np.array(world.obstacle_object) == name)
        pairs = world.distances(X_WP, parts) if len(parts) else []
        own = (p.distance_m for p in pairs if p.wp_part < world.n_own_parts)
        out[name] = max(0.0, min(own, default=np.inf))
    return out


def contact_move_forces_n(
    directions: Sequence[tuple[str, np.ndarray]],
    movable: Container[str] = frozenset(),
    gaps_m: dict[str, float] | None = None,
) -> np.ndarray:
    """The force (N) a contact move keeping these contact directions (object, unit normal into
    the workpiece) reads along each when the work site verifies it: each pressed by stiffness ×
    (how far the bias reaches into it − its gap, default 0), capped as the work site caps it,
    the wrist force split over the normals by non-negative least squares."""
    if not directions:
        return np.zeros(0)
    gaps_m = gaps_m or {}
    N = np.array([n for _, n in directions]).reshape(-1, 3)
    dp = contact_bias_W(directions, movable)
    depth = np.array([-(n @ dp) - gaps_m.get(name, 0.0) for name, n in directions])
    press = np.minimum(
        NORMAL_STIFFNESS_N_PER_M * np.maximum(depth, 0.0), press_caps_n(directions, movable)
    )
    return nnls(N.T, press @ N)[0]


def felt_contacts(step, movable: Container[str] = frozenset()) -> dict[str, bool]:
    """For each object the workpiece touches in ``step`` (a simulator step's result, or a path
    node: anything with ``contacts``), whether a contact move keeping all of them would press
    it with :data:`CONTACT_VERIFY_N` along each of its directions: whether the robot can feel
    it by force (a program that needs one it cannot feel is refused)."""
    directions = contact_directions(contact_states(step))
    forces = contact_move_forces_n(directions, movable)
    felt = {c.object: True for c in step.contacts}
    for (name, _), f in zip(directions, forces, strict=True):
        felt[name] = felt[name] and f >= CONTACT_VERIFY_N
    return felt


def predicted_contact_forces_n(
    program: MotionProgram,
    k: int,
    gaps_m: dict[str, float],
    movable: Container[str] = frozenset(),
) -> list[tuple[str, np.ndarray, float]]:
    """The force (N) the work site would read along each contact direction of command ``k``
    when it verifies it, as (object, unit normal, force) in :func:`contact_directions` order.

    A contact move's impedance aims past the target by the bias Δp of §VI-B: each contact is
    pressed by stiffness × (how far Δp reaches into it − its gap in the model); a guarded move
    stops on the force against its motion, at its force limit. The wrist force is split over
    the contact normals by non-negative least squares, as the work site does."""
    cmd = program.commands[k]
    directions = contact_directions(cmd.contacts)
    N = np.array([n for _, n in directions]).reshape(-1, 3)
    if cmd.kind == "contact_move":
        f = contact_move_forces_n(directions, movable, gaps_m)
        return [(name, n, float(fi)) for (name, n), fi in zip(directions, f, strict=True)]
    else:  # guarded_move: the force that stops it is against its motion
        here = program.commands[k - 1].X_WP if k > 0 else cmd.X_WP
        direction = np.asarray(cmd.X_WP)[:3, 3] - np.asarray(here)[:3, 3]
        if np.linalg.norm(direction) > 0.0:
            against = -direction / np.linalg.norm(direction)
        else:
            against = N.sum(axis=0)
            against /= np.linalg.norm(against)
        force_W = cmd.force_limit_n * against
    f = nnls(N.T, force_W)[0]
    return [(name, n, float(fi)) for (name, n), fi in zip(directions, f, strict=True)]


def contact_feasibility(
    scene: Scene,
    workpiece: str,
    program: MotionProgram,
    attached_O: tuple[ConvexPart, ...] = (),
    X_WO: dict[str, np.ndarray] | None = None,
) -> Feasibility:
    """Refuse a program with a contact the work site would verify (a contact move's or a
    guarded move's) but that its motion does not press with :data:`CONTACT_VERIFY_N`."""
    poses = {o.name: o.X_WO for o in scene.objects} | (X_WO or {})
    world = SimWorld(scene, workpiece, poses, attached_O)
    movable = movable_names(scene)
    for k, cmd in enumerate(program.commands):
        if cmd.kind not in ("contact_move", "guarded_move") or not cmd.contacts:
            continue
        gaps = _gaps_m(world, np.asarray(cmd.X_WP), {c.object for c in cmd.contacts})
        for name, n, force_n in predicted_contact_forces_n(program, k, gaps, movable):
            if force_n >= CONTACT_VERIFY_N:
                continue
            how = (
                "the move stops on the force against its motion"
                if cmd.kind == "guarded_move"
                else f"the block is {gaps[name] * 1e3:.1f} mm from it in the model"
                if gaps[name] > 0.0
                else "the move's bias does not push into it"
            )
            return Feasibility(
                False,
                f"{_where(k, cmd)}: the contact with the {name} (normal "
                f"{np.round(n, 2).tolist()}) cannot be verified: the robot would press it with "
                f"{force_n:.1f} N, the work site needs {CONTACT_VERIFY_N:.1f} N ({how}). "
                f"The {workpiece} must be pressed against the {name}, or that contact removed "
                "from the goal.",
                k,
                "contact",
            )
    return Feasibility(True)


def _carried(program: MotionProgram) -> list[int]:
    """Indices of the commands from the grasp up to the release (the workpiece is held)."""
    out = []
    for k, cmd in enumerate(program.commands):
        if cmd.kind not in _CARRYING:
            break
        out.append(k)
    return out


def grasp_feasibility(
    robot: RobotModel,
    scene: Scene,
    workpiece: str,
    program: MotionProgram,
    X_WO: dict[str, np.ndarray] | None = None,
) -> Feasibility:
    """Refuse a program whose grasp cannot exist: not from above, the faces it holds wider apart
    than the gripper opens, too little of the pads on the block, or a finger in the way on the
    way down, along the program's targets or between the workpiece and a surface a command
    presses."""
    commands = program.commands
    if not commands or commands[0].kind != "guarded_grasp":
        return Feasibility(False, "the program must start with a guarded grasp", 0, "grasp")
    X_GP = np.asarray(program.X_GP, dtype=np.float64)
    z_G_W = (np.asarray(commands[0].X_WP) @ invert_pose(X_GP))[:3, 2]
    if float(z_G_W @ -_UP_W) < FROM_ABOVE_COS:
        return Feasibility(
            False,
            f"the grasp does not hold the {workpiece} from above (the gripper would point "
            f"{np.round(z_G_W, 2).tolist()}): the robot comes down onto every grasp from above",
            0,
            "grasp",
        )
    model = scene.object(workpiece).model
    d_O = invert_pose(X_GP)[:3, 1]
    V = np.vstack([p.vertices_O for p in model.parts])
    opening = float(np.ptp(V @ d_O))
    if opening + 2 * GRASP_CLEARANCE_M > robot.finger_opening_max:
        return Feasibility(
            False,
            f"the grasp holds the {workpiece} across {opening:.3f} m: the gripper opens "
            f"{robot.finger_opening_max:.3f} m, which leaves less than {GRASP_CLEARANCE_M:.3f} m "
            "each side to close on it; choose the grasp again",
            0,
            "grasp",
        )
    area = grip_area_m2(robot, scene, workpiece, X_GP)
    if area < MIN_GRIP_AREA_M2:
        return Feasibility(
            False,
            f"the grasp's finger pads would touch only {area * 1e4:.1f} cm² of the {workpiece} "
            f"(at least {MIN_GRIP_AREA_M2 * 1e4:.1f} cm² holds it); choose the grasp again",
            0,
            "grasp",
        )
    carried = _carried(program)
    start = np.asarray(commands[0].X_WP, dtype=np.float64)
    poses = {o.name: o.X_WO for o in scene.objects} | (X_WO or {}) | {workpiece: start}
    path = [np.asarray(commands[k].X_WP) for k in carried]
    pressed = [
        PressedContact(c.object, np.asarray(c.normals_W), np.asarray(commands[k].X_WP))
        for k in carried
        if commands[k].kind in ("contact_move", "guarded_move")
        for c in commands[k].contacts
    ]
    grasp = Grasp(X_GP, opening, "the program's grasp", area)
    problem = grasp_problem(robot, scene, workpiece, poses, grasp, path, pressed)
    if problem:
        return Feasibility(False, f"{problem}; choose the grasp again", 0, "grasp")
    return Feasibility(True)


def movable_names(scene: Scene) -> frozenset[str]:
    """The objects of ``scene`` a program may push about (the work site presses them gently)."""
    return frozenset(o.name for o in scene.movable)


def gripper_targets_W(
    program: MotionProgram, k: int, movable: Container[str] = frozenset()
) -> list[np.ndarray]:
    """The TCP poses ``X_WG`` command ``k``'s motions aim at, in order, as the work site
    expands it: a grasp's approach over the top and from above, the grasp and its lift; a
    guarded move's overtravel; a contact move's biased target (``movable``: the objects it may
    push); a move's target."""
    cmd = program.commands[k]
    if cmd.kind not in _CARRYING:
        return []
    X_WG = np.asarray(cmd.X_WP) @ invert_pose(np.asarray(program.X_GP))
    if cmd.kind == "guarded_grasp":
        lifted = X_WG.copy()
        lifted[2, 3] += GRASP_LIFT_M
        return [*grasp_approach_W(X_WG), X_WG, lifted]
    if cmd.kind == "contact_move" and cmd.contacts:
        biased = X_WG.copy()
        biased[:3, 3] += contact_bias_W(contact_directions(cmd.contacts), movable)
        return [biased]
    if cmd.kind == "guarded_move":
        here = program.commands[k - 1].X_WP if k > 0 else cmd.X_WP
        direction = np.asarray(cmd.X_WP)[:3, 3] - np.asarray(here)[:3, 3]
        if np.linalg.norm(direction) > 0.0:
            along = direction / np.linalg.norm(direction)
        else:  # no motion: the work site presses along the expected contacts' normals
            normals = [n for _, n in contact_directions(cmd.contacts)] or [-_UP_W]
            along = -np.sum(normals, axis=0) / np.linalg.norm(np.sum(normals, axis=0))
        beyond = X_WG.copy()
        beyond[:3, 3] += GUARD_OVERTRAVEL_M * along
        return [beyond]
    return [X_WG]


def reach_feasibility(
    robot: RobotModel,
    program: MotionProgram,
    q_start: np.ndarray,
    X_WB: np.ndarray | None = None,
    movable: Container[str] = frozenset(),
) -> Feasibility:
    """Refuse a program with a gripper target outside the work site's workspace box, or a move
    the arm cannot follow within its joint limits without swinging to another configuration,
    followed from ``q_start`` (rad) move after move as the work site's acceptance check does
    (the empty hand's approach to the grasp through joint space where it must); ``movable``
    as for :func:`gripper_targets_W`."""
    geometry = arm_geometry(robot)
    q = np.asarray(q_start, dtype=np.float64)
    X_WG_here = robot.tcp_pose_W(q, X_WB)
    for k, cmd in enumerate(program.commands):
        X_WG_cmd = np.asarray(cmd.X_WP) @ invert_pose(np.asarray(program.X_GP))
        p = X_WG_cmd[:3, 3]
        if cmd.kind in _CARRYING and (np.any(p < WORKSPACE_MIN_W) or np.any(p > WORKSPACE_MAX_W)):
            return Feasibility(
                False,
                f"{_where(k, cmd)}: the gripper would go to {np.round(p, 3).tolist()} m, outside "
                f"the robot's workspace {WORKSPACE_MIN_W.tolist()}–{WORKSPACE_MAX_W.tolist()} m",
                k,
                "reach",
            )
        for j, X_WG in enumerate(gripper_targets_W(program, k, movable)):
            if cmd.kind == "guarded_grasp" and j == 0:  # the empty hand's approach
                then = [*gripper_targets_W(program, k, movable)[1:]]
                for i in range(k + 1, len(program.commands)):
                    if program.commands[i].kind == "guarded_grasp":
                        break  # the next grasp's approach is planned again
                    then += gripper_targets_W(program, i, movable)
                plan = plan_approach(X_WG_here, q, X_WG, then, robot, X_WB, geometry)
                result = (
                    PathFollow(plan.ok, plan.q_joint, reason=plan.reason)
                    if not plan.ok or plan.q_joint is not None
                    else follow_line_tcp(X_WG_here, X_WG, q, robot, X_WB, geometry)
                )
            else:
                result = follow_line_tcp(X_WG_here, X_WG, q, robot, X_WB, geometry)
            if not result.ok:
                return Feasibility(
                    False,
                    f"{_where(k, cmd)}: the arm cannot move the gripper to "
                    f"{np.round(X_WG[:3, 3], 3).tolist()} m ({result.reason})",
                    k,
                    "reach",
                )
            q, X_WG_here = result.q, X_WG
    return Feasibility(True)


PARK_JOINT_STEP_RAD = math.pi / 4
"""Parking through joint space, the gripper's waypoints are at most this far apart in every
joint (rad): each straight move between them then stays on the arm's configuration."""


def parked_through_joints(
    robot: RobotModel,
    program: MotionProgram,
    q_start: np.ndarray,
    X_WB: np.ndarray | None,
    movable: Container[str] = frozenset(),
) -> MotionProgram:
    """``program``, or, when its last move (the park at the arm's home) cannot be followed as
    one straight move (the shortest turn of the gripper would take the wrist past a limit),
    the same program parking through waypoints on the straight line in joint space from where
    the arm is to its home ``q_start``. Unchanged when an earlier move cannot be followed:
    :func:`reach_feasibility` says why; ``movable`` as for :func:`gripper_targets_W`."""
    commands = program.commands
    if len(commands) < 2 or commands[-1].kind != "move":
        return program
    geometry = arm_geometry(robot)
    q = np.asarray(q_start, dtype=np.float64)
    here = robot.tcp_pose_W(q, X_WB)
    for k in range(len(commands) - 1):
        for X_WG in gripper_targets_W(program, k, movable):
            result = follow_line_tcp(here, X_WG, q, robot, X_WB, geometry)
            if not result.ok:
                return program
            q, here = result.q, X_WG
    park = commands[-1]
    X_GP = np.asarray(program.X_GP)
    q_home = np.asarray(q_start, dtype=np.float64)
    if follow_line_tcp(here, park.X_WP @ invert_pose(X_GP), q, robot, X_WB, geometry).ok:
        return program
    n = max(1, math.ceil(float(np.max(np.abs(q_home - q))) / PARK_JOINT_STEP_RAD))
    waypoints = [
        replace(park, X_WP=robot.tcp_pose_W(q + (q_home - q) * i / n, X_WB) @ X_GP)
        for i in range(1, n + 1)
    ]
    return replace(program, commands=(*commands[:-1], *waypoints))


def check_feasibility(
    scene: Scene,
    workpiece: str,
    program: MotionProgram,
    attached_O: tuple[ConvexPart, ...] = (),
    X_WO: dict[str, np.ndarray] | None = None,
    robot: RobotModel | None = None,
    q_start: Sequence[float] | None = None,
) -> Feasibility:
    """Whether the robot can do ``program`` for ``workpiece``: its grasp exists, every gripper
    pose is reachable and every contact it expects can be verified; the first refusal found,
    grasp first. ``X_WO`` overrides the scene's object poses (the task session's);
    ``attached_O`` are the fingers of the program's grasp, as the simulator had them;
    ``q_start`` the arm's joints when the program starts (default: its home)."""
    robot = robot or load_robot(scene.robot.urdf_path)
    q0 = scene.robot.q_home_rad if q_start is None else np.asarray(q_start, dtype=np.float64)
    for result in (
        grasp_feasibility(robot, scene, workpiece, program, X_WO),
        reach_feasibility(robot, program, q0, scene.robot.X_WB, movable_names(scene)),
        contact_feasibility(scene, workpiece, program, attached_O, X_WO),
    ):
        if not result.ok:
            return result
    return Feasibility(True)
