"""``operator-site demo --scripted TASK``: the whole chain without a person.

The work site renders its camera frame (blocks laid out by the seed, camera a little off its
calibration); vision recognises the blocks; the model editor accepts every recognition above the
score threshold and makes the model consistent; a scripted operator drags the workpiece in the
task simulator as a person would (the dragger's target moved through waypoints); the program
generator makes the robot program; the work site executes it under its execution monitor. The
block's final pose is read from the simulated work site's ground truth (``TruthPoses``) and
compared with the simulator's goal. The chain itself is :mod:`operator_site.chain`, which runs
task files too (:mod:`operator_site.runner`).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.layout import random_layout
from models.scene import Box2, Scene, frame_bar_height_m, frame_opening_W, frame_outer_W, load_scene
from models.transforms import make_pose, rpy_to_R
from operator_site.chain import ChainTask, Judgement, ProgramMaker, run_chain
from operator_site.model_editor import WorkSiteModel
from operator_site.session import generated_program
from operator_site.task import TaskSession
from operator_site.taskdrag import drag, turn_rad

TASKS = ("corner", "around-corner")
WORKPIECES = ("cube", "tall_block")
"""Blocks the scripted tasks may choose: tall enough to be held above the frame's bars."""
SUCCESS_MM, SUCCESS_DEG = 1.5, 1.5


def _yaw(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def _squared_with_frame(X_WO: np.ndarray, bbox_O: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The block's rotation turned about z to the nearest quarter turn (square with the frame),
    and the half-extents (m) along W's axes of its bounding box so turned."""
    yaw = _yaw(X_WO[:3, :3])
    R = rpy_to_R(np.array([0.0, 0.0, round(yaw / (math.pi / 2)) * (math.pi / 2)]))
    R = R @ rpy_to_R(np.array([0.0, 0.0, -yaw])) @ X_WO[:3, :3]
    lo, hi = bbox_O
    V = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    return R, np.abs(V @ R.T).max(axis=0)


def corner_waypoints(
    X_WO: np.ndarray, bbox_O: np.ndarray, corner: int, opening_W: Box2
) -> tuple[list[np.ndarray], np.ndarray]:
    """The dragger's targets for putting a block at ``X_WO`` into inside corner ``corner`` (0–3)
    of the frame whose inner walls are ``opening_W`` (:func:`~models.scene.frame_opening_W`), as
    a person would: lift, carry over the bars to above a point 2 cm out from both walls, turn
    square with the frame, lower onto the table, push into the corner. Also the ideal goal pose
    (touching both walls and the table)."""
    (x0, x1), (y0, y1) = opening_W
    cx, sx = (x0, 1.0) if corner in (0, 3) else (x1, -1.0)
    cy, sy = (y0, 1.0) if corner in (0, 1) else (y1, -1.0)
    R, half = _squared_with_frame(X_WO, bbox_O)
    z = X_WO[2, 3]
    goal = make_pose(R, (cx + sx * half[0], cy + sy * half[1], z))
    up = X_WO.copy()
    up[2, 3] = z + 0.07
    out = np.array([sx, sy, 0.0]) * 0.02
    above = make_pose(R, goal[:3, 3] + out + [0.0, 0.0, 0.07])
    down = make_pose(R, goal[:3, 3] + out - [0.0, 0.0, 0.005])
    push = make_pose(R, goal[:3, 3] - np.array([sx, sy, 0.0]) * 0.005 - [0.0, 0.0, 0.005])
    return [up, above, down, push], goal


PRESS_M = 0.004
"""The dragger is held this far into a surface the block should stay against (m)."""


AROUND_END_M = (0.05, 0.04, 0.03, 0.02)
"""How far along the frame's outer face at its smallest x past the corner the around-corner task
may end (m): the first whose end pose is :data:`END_CLEARANCE_M` clear of every other block."""
END_CLEARANCE_M = 0.005


def around_corner_waypoints(
    X_WO: np.ndarray,
    bbox_O: np.ndarray,
    corner: int,
    outer_W: Box2,
    end_m: float = AROUND_END_M[0],
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Fig. 2 / Fig. 13: the block set down against the outside of the frame's near bar (the
    outer face at y0 of ``outer_W`` for ``corner`` 0, y1 for 1; see
    :func:`~models.scene.frame_outer_W`), slid along it past the outer corner at x0, round the
    corner and along the x0 face. Returns the waypoints before capturing frame and table, those
    after, and the ideal end pose (against the x0 face, on the table)."""
    (ox0, _), (oy0, oy1) = outer_W
    sy = -1.0 if corner == 0 else 1.0  # the side of the frame the block starts on
    face_y = oy0 if corner == 0 else oy1
    R, half = _squared_with_frame(X_WO, bbox_O)
    z = X_WO[2, 3]
    along_y = face_y + sy * half[1]  # centre line when touching the y face
    start_x = ox0 + 0.06
    up = X_WO.copy()
    up[2, 3] = z + 0.07
    above = make_pose(R, (start_x, along_y + sy * 0.02, z + 0.07))
    down = make_pose(R, (start_x, along_y + sy * 0.02, z - PRESS_M))
    touch = make_pose(R, (start_x, along_y - sy * PRESS_M, z - PRESS_M))
    before = [up, above, down, touch]
    past = make_pose(R, (ox0 - half[0] - 0.01, along_y - sy * PRESS_M, z - PRESS_M))
    end_y = face_y - sy * end_m
    end = make_pose(R, (ox0 - half[0] + PRESS_M, end_y, z - PRESS_M))
    goal = make_pose(R, (ox0 - half[0], end_y, z))
    return before, [past, end], goal


@dataclass(frozen=True, eq=False)
class Demonstration:
    """What the scripted operator did: the task session (its history is the demonstration),
    the workpiece, the corner (0–3 for ``corner``, 0–1 for ``around-corner``) and the ideal
    goal pose of the workpiece."""

    session: TaskSession
    workpiece: str
    corner: int
    ideal_X_WO: np.ndarray


def workpiece_candidates(task: str, model: WorkSiteModel) -> list[str]:
    """The blocks in ``model`` fit to be ``task``'s workpiece, in :data:`WORKPIECES` order."""
    candidates = [n for n in WORKPIECES if n in model.poses]
    if task == "around-corner":
        # Pushed along a bar by its centre, a block whose centre is above the bar's top tips
        # over the bar's edge, in the simulator as a real one would.
        bar_m = frame_bar_height_m(model.base)
        candidates = [n for n in candidates if _centre_height_m(model, n) < bar_m]
    return candidates


def demonstrate(task: str, model: WorkSiteModel, rng: np.random.Generator) -> Demonstration:
    """The scripted operator: choose the workpiece among :data:`WORKPIECES` in ``model`` and
    the corner with ``rng``, then drag the block through ``task`` in a task session of the
    model; RuntimeError if no candidate block is in the model."""
    candidates = workpiece_candidates(task, model)
    if not candidates:
        raise RuntimeError(f"none of {WORKPIECES} fit for {task} was recognised")
    workpiece = str(rng.choice(candidates))
    corner = int(rng.integers(4))
    session = TaskSession(model.scene())
    session.select(workpiece)
    bbox = session.scene.object(workpiece).model.bbox_O
    if task == "corner":
        opening_W = frame_opening_W(session.scene)
        waypoints, ideal = corner_waypoints(session.X_WO[workpiece], bbox, corner, opening_W)
        drag(session, waypoints)
    else:
        corner %= 2
        outer_W = frame_outer_W(session.scene)
        for end_m in AROUND_END_M:  # as a person would: end where there is room
            before, after, ideal = around_corner_waypoints(
                session.X_WO[workpiece], bbox, corner, outer_W, end_m
            )
            if _clearance_to_blocks_m(session, ideal) >= END_CLEARANCE_M:
                break
        drag(session, before)
        for name in ("frame", "table"):
            session.toggle_capture(name)
        drag(session, after)
    return Demonstration(session, workpiece, corner, ideal)


def layout_demonstration(task: str, seed: int, scene: Scene | None = None) -> Demonstration:
    """The scripted operator's demonstration of ``task`` on seed ``seed``'s layout (the work
    site's ``--seed`` one), taken as recognised: no vision, no work site. For measuring and
    testing what comes after the demonstration."""
    scene = scene or load_scene()
    model = WorkSiteModel(scene, random_layout(scene, seed))
    model.make_consistent()
    return demonstrate(task, model, np.random.default_rng(seed))


def _clearance_to_blocks_m(session: TaskSession, X_WO: np.ndarray) -> float:
    """Distance from the workpiece at ``X_WO`` to the nearest block other than the frame and
    the table (m; inf when none is within 2 cm)."""
    world = session.sim.world
    lo, hi = world.workpiece_box(X_WO, 0.02)
    fixed = ("frame", "table")
    near = [i for i in world.candidates(lo, hi) if world.obstacle_object[i] not in fixed]
    if not near:
        return math.inf
    return min(pair.distance_m for pair in world.distances(X_WO, np.array(near)))


def _centre_height_m(model: WorkSiteModel, name: str) -> float:
    """Height of block ``name``'s centre of mass above its lowest point, as it lies (m)."""
    X = model.poses[name]
    obj = model.base.object(name).model
    V_W = np.vstack([part.vertices_O for part in obj.parts]) @ X[:3, :3].T
    return float((X[:3, :3] @ obj.com_O)[2] - V_W[:, 2].min())


def _scripted_task(task: str, rng: np.random.Generator) -> ChainTask:
    """The rehearsed ``corner`` and ``around-corner`` as a :class:`ChainTask`: judged against
    where the simulated block ended, up to its symmetries, within
    :data:`SUCCESS_MM` and :data:`SUCCESS_DEG`."""

    def judge(demo, model, truth):
        goal, X = demo.session.X_WO[demo.workpiece], truth[demo.workpiece]
        error_m = float(np.linalg.norm(X[:3, 3] - goal[:3, 3]))
        # Modulo the block's symmetries: a cube turned a quarter turn is the same cube.
        error_rad = min(
            turn_rad(goal[:3, :3] @ S, X[:3, :3]) for S in model.symmetries(demo.workpiece)
        )
        within = error_m * 1e3 <= SUCCESS_MM and math.degrees(error_rad) <= SUCCESS_DEG
        return Judgement(error_m, error_rad, within)

    return ChainTask(
        label=task,
        program_label=task,
        ready=lambda model: bool(workpiece_candidates(task, model)),
        demonstrate=lambda model: demonstrate(task, model, rng),
        judge=judge,
        describe=lambda demo: {"corner": demo.corner},
    )


def run_scripted(
    task: str,
    seed: int,
    connect: str | None = None,
    site_id: str | None = None,
    scene: Scene | None = None,
    make_program: ProgramMaker = generated_program,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
) -> dict:
    """Run ``task`` with ``seed`` end to end; the result's JSON-ready dict. Starts a work site
    on loopback (``--seed``-ed) unless ``connect`` names a running one. ``oracle``: take the
    blocks' poses from the simulated work site's ground truth instead of vision (to measure
    the rest of the chain alone). ``time_scale``: how much faster than real time the started
    work site simulates (the result's ``time_scale_achieved`` says how fast it really did,
    while executing); ``work_site_args``: more options for it."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
    return run_chain(
        _scripted_task(task, np.random.default_rng(seed)),
        seed,
        connect=connect,
        site_id=site_id,
        scene=scene,
        make_program=make_program,
        log=log,
        oracle=oracle,
        time_scale=time_scale,
        work_site_args=work_site_args,
    )
