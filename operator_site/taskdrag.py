"""A task file dragged in the task simulator (§V) on a work-site model, as a person would drag
it: the operator's demonstration of a :class:`~operator_site.taskfile.Task`.

Every pose of the file is the workpiece's frame O in the reference's frame R; here each becomes a
dragger target in W through the reference's pose in the model (``X_WD = X_WR @ X_RD``). One
symmetry rotation S of the workpiece, chosen so that the first step's orientation needs the least
turn from how the block lies, is applied to every step and to the goal, so that a task that turns
the block a quarter turn still turns it a quarter turn. Before the first step the block is carried
as a person would carry it: lifted clear of everything it passes, turned on the way, lowered onto
the first step; a task whose first step is where the block lies (one recorded in the page) needs
no such carry.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.transforms import make_pose, so3_exp, so3_log
from operator_site.failures import RunError
from operator_site.grasp import Grasp, choose_grasp, grasp_problem, pressed_contacts
from operator_site.model_editor import WorkSiteModel
from operator_site.program.pick_place import HALF_TURN, carried_arm_path
from operator_site.simulator.world import SimWorld
from operator_site.task import TaskSession
from operator_site.taskfile import Task

WAYPOINT_MAX_STEPS = 200
"""Simulator steps a dragger target is held at most."""
WAYPOINT_REACHED_M = 0.5e-3
"""A dragger target is reached when the workpiece is this close to it (m)."""
TRANSIT_CLEARANCE_M = 0.02
"""The carried workpiece passes this far above the highest object top along its way."""
TRANSIT_SAMPLE_M = 0.005
"""The way to the first step is sampled this finely when looking for what it passes over."""
MAX_TRANSIT_SAMPLES = 2000
UP_TOL = 0.1
"""A symmetry keeps the block standing as it does when it turns W's z, seen in the block's
frame, by less than this (a unit vector's change: about 6°)."""
WAYPOINT_REACHED_RAD = 1e-3
"""A step that turns the workpiece is held until it is turned this close (rad), as well as moved
within :data:`WAYPOINT_REACHED_M`."""


@dataclass(frozen=True, eq=False)
class TaskDemonstration:
    """A task file dragged in a task session: the session (its history is the demonstration),
    the workpiece, the goal ``ideal_X_WO`` in W with the symmetry ``S_O`` (3×3, in O) applied
    on the reference's frame ``S_R``,
    the dragger targets in W (the transit's, then the steps'), and, for each of the task's
    steps, the simulator's captured set and the history's length once that step was reached."""

    session: TaskSession
    workpiece: str
    ideal_X_WO: np.ndarray
    S_O: np.ndarray
    S_R: np.ndarray  # the reference's frame chosen (:func:`reference_frame`), 3×3 in R
    transit_X_WD: tuple[np.ndarray, ...]
    steps_X_WD: tuple[np.ndarray, ...]
    captured_after_step: tuple[frozenset[str], ...]
    history_after_step: tuple[int, ...]


def reference_pose_W(model: WorkSiteModel, name: str) -> np.ndarray:
    """``X_WR``: where object ``name`` lies in the model (a fixed object, or an accepted
    block); :class:`RunError` ``not_recognised`` for a block not in the model."""
    if name in model.poses:
        return model.poses[name].copy()
    for obj in model.fixed:
        if obj.name == name:
            return obj.X_WO.copy()
    raise RunError("not_recognised", f"{name!r} is not in the model the vision built")


def nearest_symmetry(
    R_WD_first: np.ndarray, R_WO_now: np.ndarray, symmetries: Sequence[np.ndarray]
) -> np.ndarray:
    """Of the workpiece's symmetry rotations S (in O; identity when none are given), the one
    for which ``R_WD_first @ S`` is nearest ``R_WO_now``, among those that keep the block
    standing on the face it stands on now, if any does (no symmetry tumbles the block)."""
    candidates = list(symmetries) or [np.eye(3)]
    up_O = R_WO_now[2, :]  # W's z in O, as the block lies now
    upright = [S for S in candidates if np.linalg.norm((R_WD_first @ S)[2, :] - up_O) < UP_TOL]
    return min(
        upright or candidates,
        key=lambda S: float(np.linalg.norm(so3_log(R_WO_now.T @ R_WD_first @ S))),
    )


def _with_symmetry(X: np.ndarray, S_O: np.ndarray) -> np.ndarray:
    return X @ make_pose(S_O)


def transit_height_m(world: SimWorld, X_WO_start: np.ndarray, X_WD_first: np.ndarray) -> float:
    """The height (z of O in W, m) at which the workpiece of ``world`` is carried from
    ``X_WO_start`` to above ``X_WD_first``: :data:`TRANSIT_CLEARANCE_M` above the highest object
    top within the workpiece's reach of the straight line between them, plus how far the
    workpiece (fingers included) reaches below O in either orientation."""
    V_O = world.wp_vertices_O
    reach_m = float(np.max(np.linalg.norm(V_O, axis=1)))  # any orientation on the way
    p0, p1 = X_WO_start[:2, 3], X_WD_first[:2, 3]
    n = int(min(MAX_TRANSIT_SAMPLES, max(2, math.ceil(np.linalg.norm(p1 - p0) / TRANSIT_SAMPLE_M))))
    line = p0 + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0)  # (n, 2)
    # Distance from each sample to each obstacle part's box, in the horizontal plane.
    gap = np.maximum(world.lo_W[None, :, :2] - line[:, None, :], 0.0) + np.maximum(
        line[:, None, :] - world.hi_W[None, :, :2], 0.0
    )
    passed = np.linalg.norm(gap, axis=2).min(axis=0) <= reach_m + TRANSIT_CLEARANCE_M
    top_m = float(world.hi_W[passed, 2].max()) if np.any(passed) else 0.0
    below_m = max(float(-(V_O @ X[:3, :3].T)[:, 2].min()) for X in (X_WO_start, X_WD_first))
    return max(top_m + TRANSIT_CLEARANCE_M + below_m, X_WO_start[2, 3], X_WD_first[2, 3])


def transit_waypoints(
    world: SimWorld, X_WO_start: np.ndarray, X_WD_first: np.ndarray, long_way: bool = False
) -> list[np.ndarray]:
    """The dragger targets before the first step: straight up to :func:`transit_height_m`,
    across to above the first step turning to its orientation on the way; the first step
    itself (lowering onto it) is the task's. The turn is the shorter one, or with ``long_way``
    the other way round the same axis, in targets a quarter turn apart at most (the simulator
    turns the block the short way to each)."""
    z = transit_height_m(world, X_WO_start, X_WD_first)
    up = X_WO_start.copy()
    up[2, 3] = z
    above = X_WD_first.copy()
    above[2, 3] = z
    w = so3_log(up[:3, :3].T @ above[:3, :3])
    angle = float(np.linalg.norm(w))
    if not long_way or angle < WAYPOINT_REACHED_RAD:
        return [up, above]
    w_long = -w / angle * (2 * math.pi - angle)
    n = math.ceil((2 * math.pi - angle) / (math.pi / 2))
    between = [
        make_pose(
            up[:3, :3] @ so3_exp(w_long * i / n), up[:3, 3] + (above[:3, 3] - up[:3, 3]) * i / n
        )
        for i in range(1, n)
    ]
    return [up, *between, above]


def already_there(X_WO: np.ndarray, X_WD: np.ndarray) -> bool:
    """Whether a block at ``X_WO`` has reached the dragger target ``X_WD`` (within
    :data:`WAYPOINT_REACHED_M` and :data:`WAYPOINT_REACHED_RAD`)."""
    return bool(
        np.linalg.norm(X_WO[:3, 3] - X_WD[:3, 3]) < WAYPOINT_REACHED_M
        and turn_rad(X_WO[:3, :3], X_WD[:3, :3]) < WAYPOINT_REACHED_RAD
    )


def task_targets_W(
    task: Task, model: WorkSiteModel, X_WO_start: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """The task's dragger targets and goal in W, with the symmetry S (3×3) chosen for the
    workpiece lying at ``X_WO_start`` applied to all, on the reference's frame chosen by
    :func:`reference_frame`: ``(steps_X_WD, goal_X_WO, S_O, S_R)``."""
    S_R = reference_frame(task, model, X_WO_start)
    X_WR = reference_pose_W(model, task.reference)
    steps = [X_WR @ make_pose(S_R) @ step.X_RD for step in task.steps]
    S_O = nearest_symmetry(steps[0][:3, :3], X_WO_start[:3, :3], model.symmetries(task.workpiece))
    steps = [_with_symmetry(X, S_O) for X in steps]
    return steps, goal_on_reference_W(task, X_WR, S_O, S_R), S_O, S_R


def reference_frame(task: Task, model: WorkSiteModel, X_WO_start: np.ndarray) -> np.ndarray:
    """Of the frames a symmetric block used as the reference looks the same in, upright as the
    model has it (turned about its own z), the one (a symmetry S_R in R, 3×3) whose first
    step lies nearest the workpiece: "the plank's +x end" is then the nearer end, whichever
    end vision called +x. The identity for a fixed reference: its frame is the scene's."""
    if task.reference not in model.poses:
        return np.eye(3)
    X_WR = model.poses[task.reference]
    p_first_R = task.steps[0].X_RD[:3, 3]
    best, best_m = np.eye(3), math.inf
    for S in model.symmetries(task.reference):
        if not np.isclose(S[2, 2], 1.0):  # turns the reference's z away: not upright
            continue
        p_first_W = X_WR[:3, :3] @ (S @ p_first_R) + X_WR[:3, 3]
        d_m = float(np.linalg.norm(p_first_W - X_WO_start[:3, 3]))
        if d_m < best_m - SAME_DISTANCE_M:
            best, best_m = S, d_m
    return best


SAME_DISTANCE_M = 1e-6
"""Two frames whose first steps lie this close to the same distance from the workpiece tie:
the first (the identity, the model's own frame) is kept."""


def goal_on_reference_W(
    task: Task, X_WR: np.ndarray, S_O: np.ndarray, S_R: np.ndarray
) -> np.ndarray:
    """The goal ``X_WO`` with the reference at ``X_WR`` (the work site's true one, say), in the
    frame ``S_R`` and with the symmetry ``S_O`` the drag chose."""
    return _with_symmetry(X_WR @ make_pose(S_R) @ task.goal.X_RO, S_O)


def _play(
    task: Task, model: WorkSiteModel, grasp: Grasp | None, fingers: bool, long_way: bool = False
) -> TaskDemonstration:
    """One drag of ``task`` in a new task session, the workpiece held in ``grasp`` (or the
    block alone, ``fingers=False``), turned on the way to the first step the shorter way round
    (or the other, ``long_way``)."""
    session = TaskSession(model.scene())
    try:
        session.select(task.workpiece, grasp=grasp, fingers=fingers)
    except ValueError as e:
        raise RunError("no_grasp", f"{task.workpiece!r} cannot be held: {e}") from None
    X_start = session.X_WO[task.workpiece].copy()
    steps, goal, S_O, S_R = task_targets_W(task, model, X_start)
    transit = (
        []
        if already_there(X_start, steps[0])
        else transit_waypoints(session.sim.world, X_start, steps[0], long_way)
    )
    drag(session, transit, reached_rad=WAYPOINT_REACHED_RAD)
    captured, lengths = [], []
    for step, X_WD in zip(task.steps, steps, strict=True):
        drag(session, [X_WD], reached_rad=WAYPOINT_REACHED_RAD)
        for name in step.capture or ():
            if name not in session.captured:
                session.toggle_capture(name)
        for name in step.release or ():
            if name in session.captured:
                session.toggle_capture(name)
        captured.append(frozenset(session.captured))
        lengths.append(len(session.sim.history))
    return TaskDemonstration(
        session=session,
        workpiece=task.workpiece,
        ideal_X_WO=goal,
        S_O=S_O,
        S_R=S_R,
        transit_X_WD=tuple(transit),
        steps_X_WD=tuple(steps),
        captured_after_step=tuple(captured),
        history_after_step=tuple(lengths),
    )


def _path_of(session: TaskSession) -> tuple[dict[str, np.ndarray], list[np.ndarray], list]:
    """A demonstration's start poses (the workpiece where it began), its path and the
    contacts it presses, as :func:`~operator_site.grasp.choose_grasp` takes them."""
    path = session.path_history()
    X_WO = session.X_WO | {session.workpiece: session.start_X_WO}
    return X_WO, [step.X_WO for step in path], pressed_contacts(path)


def drag_task(task: Task, model: WorkSiteModel) -> TaskDemonstration:
    """Play ``task`` as a person would drag it in a task session of ``model``: select the
    workpiece, carry it to the first step, then hold each step until the workpiece is there
    (or stops against something) and make its captures and releases. The grasp is chosen for
    the task: the block is first dragged alone, the grasp chosen for that path
    (:func:`~operator_site.grasp.choose_grasp`: no finger between the block and what it
    presses, none run into anything), and the task dragged again held so. :class:`RunError`
    when the workpiece or the reference is not in the model (``not_recognised``) or no grasp
    can do the task (``no_grasp``)."""
    if task.workpiece not in model.poses:
        raise RunError("not_recognised", f"the workpiece {task.workpiece!r} is not in the model")
    alone = _play(task, model, grasp=None, fingers=False)
    session = alone.session
    choice = choose_grasp(session.robot, session.scene, task.workpiece, *_path_of(session))
    if choice.grasp is None:
        raise RunError("no_grasp", choice.reason)
    demo = _play(task, model, grasp=choice.grasp, fingers=True)
    if demo.transit_X_WD and not arm_can_carry(demo.session):
        # The wrist's joint limits may allow the turn to the first step only the other way
        # round (the arm's base turns too as the block is carried across).
        other = _play(task, model, grasp=choice.grasp, fingers=True, long_way=True)
        if arm_can_carry(other.session):
            demo = other
    # Held, the block may take another path (the fingers meet what the block alone passed).
    X_WO, path_X_WO, pressed = _path_of(demo.session)
    problem = grasp_problem(
        session.robot, session.scene, task.workpiece, X_WO, choice.grasp, path_X_WO, pressed
    )
    if problem:
        raise RunError("no_grasp", f"no grasp of the {task.workpiece} can do this task: {problem}")
    return demo


def arm_can_carry(session: TaskSession) -> bool:
    """Whether the robot's arm, from its home, can take the workpiece of ``session`` where it
    started and carry it along the dragged path in the session's grasp or the same grasp
    turned half a turn (:func:`~operator_site.program.pick_place.carried_arm_path`)."""
    path = [step.X_WO for step in session.path_history()]
    arm = (session.robot, session.scene.robot.X_WB, session.scene.robot.q_home_rad)
    return any(
        carried_arm_path(*arm, session.start_X_WO, X_GP, path).ok
        for X_GP in (session.X_GP, HALF_TURN @ session.X_GP)
    )


def drag(session: TaskSession, waypoints: list[np.ndarray], reached_rad: float = math.inf) -> None:
    """Move the dragger through ``waypoints``, each until the block is there (within
    :data:`WAYPOINT_REACHED_M`, and turned within ``reached_rad``) or stops."""
    for X in waypoints:
        session.set_target(X)
        for _ in range(WAYPOINT_MAX_STEPS):
            result = session.step()
            if result.s_fraction == 0.0 or (
                np.linalg.norm(result.X_WO[:3, 3] - X[:3, 3]) < WAYPOINT_REACHED_M
                and turn_rad(result.X_WO[:3, :3], X[:3, :3]) < reached_rad
            ):
                break


def turn_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """The angle (rad) of the rotation between ``R_a`` and ``R_b``."""
    return float(np.linalg.norm(so3_log(R_a.T @ R_b)))
