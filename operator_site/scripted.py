"""``operator-site demo --scripted TASK``: the whole chain without a person.

The work site renders its camera frame (blocks laid out by the seed, camera a little off its
calibration); vision recognises the blocks; the model editor accepts every recognition above the
score threshold and makes the model consistent; a scripted operator drags the workpiece in the
task simulator as a person would (the dragger's target moved through waypoints); the program
generator makes the robot program; the work site executes it under its execution monitor. The
block's final pose is read from the simulated work site's ground truth (``TruthPoses``) and
compared with the simulator's goal. The same chain (:func:`run_chain`) runs a task file
(``operator_site/runner.py``); it differs only in the operator's drag and in the judging.
"""

from __future__ import annotations

import math
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.layout import random_layout
from models.scene import Box2, Scene, frame_bar_height_m, frame_opening_W, frame_outer_W, load_scene
from models.transforms import make_pose, rpy_to_R, so3_log
from operator_site.link import WorkSiteLink
from operator_site.model_editor import Correction, WorkSiteModel
from operator_site.program import (
    CommandParams,
    DeformParams,
    choose_grasp_yaw,
    generate_program,
    pick_and_place,
)
from operator_site.simulator import SimParams
from operator_site.task import TaskSession
from protocol import MotionProgram, Recognition, Recognitions, TruthPoses, decode, key, make_config
from protocol.messages import contact_directions
from protocol.session import free_port_pair, link_endpoints

TASKS = ("corner", "around-corner")
WORKPIECES = ("cube", "tall_block")
"""Blocks the scripted tasks may choose: tall enough to be held above the frame's bars."""
ACCEPT_SCORE = 0.5
CONNECT_TIMEOUT_S = 60.0
VISION_TIMEOUT_S = 120.0
VISION_FRAMES = 3
"""Recognised frames waited for at most while they come back empty."""
WORKPIECE_FRAMES = 6
"""Recognised frames looked at in all, at most, while none fit for the task's workpiece is
among them (3 s at the work site's 2 Hz)."""
FRAME_TIMEOUT_S = 10.0
"""A next recognised frame is waited for at most this long (the work site sends one a 0.5 s)."""
EXECUTE_TIMEOUT_S = 240.0
STATE_RATE_HZ = 100.0
"""The started work site's robot-state rate: one state a simulated control period, so that
counting states over the execution measures the time scale it really achieved."""
SLOW_TIME_SCALE_FRACTION = 0.9
"""A work site simulating at less than this fraction of its asked time scale is reported: the
physics is stepped alike (per control period, not per wall second), but the run takes longer
than asked."""
WAYPOINT_MAX_STEPS = 200
WAYPOINT_REACHED_M = 0.5e-3
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


def drag(session: TaskSession, waypoints: list[np.ndarray], reached_rad: float = math.inf) -> None:
    """Move the dragger through ``waypoints``, each until the block is there (within
    :data:`WAYPOINT_REACHED_M`, and turned within ``reached_rad``) or stops."""
    for X in waypoints:
        session.set_target(X)
        for _ in range(WAYPOINT_MAX_STEPS):
            result = session.step()
            if result.s_fraction == 0.0 or (
                np.linalg.norm(result.X_WO[:3, 3] - X[:3, 3]) < WAYPOINT_REACHED_M
                and _turn_rad(result.X_WO[:3, :3], X[:3, :3]) < reached_rad
            ):
                break


def _turn_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.linalg.norm(so3_log(R_a.T @ R_b)))


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


@dataclass(frozen=True, eq=False)
class RecognisedModel:
    """The model the scripted operator built from vision: the model, the model editor's
    corrections, the recognised frames looked at, their vision time summed (s) and the model
    editor's time for the last build (s)."""

    model: WorkSiteModel
    corrections: list[Correction]
    frames: int
    vision_s: float
    model_s: float


def model_from_frames(
    task: str,
    scene: Scene,
    frames: Iterable[Recognitions],
    log: Callable[[str], None] = lambda _: None,
    max_frames: int = WORKPIECE_FRAMES,
    ready: Callable[[WorkSiteModel], bool] | None = None,
) -> RecognisedModel:
    """The model editor fed as a person would: every recognition of the first of ``frames``
    scoring at least :data:`ACCEPT_SCORE` accepted and made consistent; while no block fit for
    ``task``'s workpiece is in the model (or, given ``ready``, until it says the model holds
    what the task needs), the next frames' recognitions of blocks not yet in it are added
    (each frame has its own sensor noise), ``max_frames`` frames in all at most."""
    if ready is None:
        ready = lambda model: bool(workpiece_candidates(task, model))  # noqa: E731
    found: dict[str, tuple[np.ndarray, float]] = {}
    model, corrections, model_s = WorkSiteModel(scene), [], 0.0
    n, vision_s = 0, 0.0
    for recs in frames:
        n += 1
        vision_s += recs.elapsed_s
        new = {
            r.model: (r.X_WO, r.score)
            for r in recs.objects
            if r.score >= ACCEPT_SCORE and r.model not in found
        }
        log(f"frame {n}: recognised {[(r.model, round(r.score, 2)) for r in recs.objects]}")
        if new or n == 1:
            found |= new
            t0 = time.monotonic()
            model = WorkSiteModel(scene)
            for name, (X, score) in found.items():
                model.accept(name, X, score)
            corrections = model.make_consistent()
            model_s = time.monotonic() - t0
        if ready(model) or n >= max_frames:
            break
    return RecognisedModel(model, corrections, n, vision_s, model_s)


ProgramMaker = Callable[[TaskSession, str], MotionProgram]


def pick_and_place_program(session: TaskSession, program_id: str) -> MotionProgram:
    """The simple program: lift, carry, set down where the task ended (no contacts)."""
    name = session.workpiece
    start, goal = session.start_X_WO, session.X_WO[name]
    return pick_and_place(program_id, start, goal, choose_grasp_yaw(start, session.X_GP))


def generated_program(
    session: TaskSession,
    program_id: str,
    sim_params: SimParams | None = None,
    deform_params: DeformParams | None = None,
    command_params: CommandParams | None = None,
) -> MotionProgram:
    """The program generator's program (§VI): deformed path, contact moves, checked. The
    parameters default to the session's simulator and the generator's defaults."""
    return generate_program(
        program_id,
        session.scene,
        session.workpiece,
        session.path_history(),
        choose_grasp_yaw(session.start_X_WO, session.X_GP),
        attached_O=session.fingers_O,
        sim_params=sim_params or session.params,
        deform_params=deform_params,
        command_params=command_params,
        X_WO=session.X_WO,
    ).program


class _Truth:
    def __init__(self, link: WorkSiteLink) -> None:
        self.latest: TruthPoses | None = None
        self._sub = link.session.declare_subscriber(key(link.site_id, "truth"), self._on)

    def _on(self, sample) -> None:
        self.latest = decode(sample.payload.to_bytes(), expected=TruthPoses)

    def latest_after(self, t_s: float, timeout_s: float = 5.0) -> TruthPoses:
        """The first ground truth stamped at or after ``t_s`` (wall-clock s)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            truth = self.latest
            if truth is not None and truth.stamp_s >= t_s:
                return truth
            time.sleep(0.05)
        raise TimeoutError("no ground truth from the work site")


def _wait(predicate: Callable[[], bool], link: WorkSiteLink, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.poll()
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _start_work_site(
    site_id: str,
    endpoint: str,
    log_path: Path,
    time_scale: float,
    extra_args: tuple[str, ...] = (),
) -> subprocess.Popen:
    cmd = [
        sys.executable, "-m", "work_site", "serve", "--listen", endpoint, "--site-id", site_id,
        "--vision-rate", "2", "--time-scale", str(time_scale),
        "--state-rate", str(STATE_RATE_HZ), *extra_args,
    ]  # fmt: skip
    with log_path.open("w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def _recognised_frames(link: WorkSiteLink) -> Iterator[Recognitions]:
    """The work site's recognised frames as they arrive: first the first one with objects (or
    the :data:`VISION_FRAMES`-th if they all come back empty; RuntimeError if none within
    :data:`VISION_TIMEOUT_S`), then each next one until none comes within
    :data:`FRAME_TIMEOUT_S`."""
    seen: list[Recognitions] = []

    def arrived(after: int, need_objects: bool) -> Callable[[], bool]:
        def check() -> bool:
            r = link.recognitions
            if r is not None and (not seen or seen[-1].seq != r.seq):
                seen.append(r)
            if len(seen) <= after:
                return False
            return not need_objects or bool(seen[-1].objects) or len(seen) >= VISION_FRAMES

        return check

    if not _wait(arrived(0, need_objects=True), link, VISION_TIMEOUT_S):
        raise RuntimeError(f"no recognitions within {VISION_TIMEOUT_S:.0f} s")
    yield seen[-1]
    while _wait(arrived(len(seen), need_objects=False), link, FRAME_TIMEOUT_S):
        yield seen[-1]


FAILURES = (
    "not_recognised",
    "no_grasp",
    "infeasible",
    "program_refused",
    "execution_failed",
    "goal_missed",
)
"""Why a run did not succeed, as its result's ``failure.kind`` says."""


class RunError(RuntimeError):
    """A run that cannot go on: ``kind`` is one of :data:`FAILURES`, the message says why."""

    def __init__(self, kind: str, message: str) -> None:
        if kind not in FAILURES:
            raise ValueError(f"unknown failure kind {kind!r}")
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class Judgement:
    """How the block ended at the work site against the task's goal: distance (m), angle
    (rad), whether that is within the goal's tolerances, the goal contacts that must be
    verified by force (by object), and more fields for the result."""

    error_m: float
    error_rad: float
    within: bool
    goal_contacts: tuple[str, ...] = ()
    extra: dict | None = None


@dataclass(frozen=True)
class ChainTask:
    """What one end-to-end run needs of its task: a label (the result's ``task``, the program
    id's prefix), when a model holds what the task needs (``ready``), the operator's
    demonstration on a model (an object with ``session``, ``workpiece``, ``ideal_X_WO``; raises
    :class:`RunError` or RuntimeError), a check of that demonstration before a program is
    made (raises :class:`RunError`), and the judgement of the block's true final pose given
    the work site's ground truth of every object."""

    label: str
    program_label: str
    ready: Callable[[WorkSiteModel], bool]
    demonstrate: Callable[[WorkSiteModel], object]
    judge: Callable[[object, WorkSiteModel, dict[str, np.ndarray]], Judgement]
    check: Callable[[object, WorkSiteModel], None] = lambda _demo, _model: None
    describe: Callable[[object], dict] = lambda _demo: {}


def _scripted_task(task: str, rng: np.random.Generator) -> ChainTask:
    """The rehearsed ``corner`` and ``around-corner`` as a :class:`ChainTask`: judged against
    where the simulated block ended, up to its symmetries, within
    :data:`SUCCESS_MM` and :data:`SUCCESS_DEG`."""

    def judge(demo, model, truth):
        goal, X = demo.session.X_WO[demo.workpiece], truth[demo.workpiece]
        error_m = float(np.linalg.norm(X[:3, 3] - goal[:3, 3]))
        # Modulo the block's symmetries: a cube turned a quarter turn is the same cube.
        error_rad = min(
            _turn_rad(goal[:3, :3] @ S, X[:3, :3]) for S in model.symmetries(demo.workpiece)
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


_VERIFIED_RE = re.compile(r"([A-Za-z0-9_.-]+) -?[0-9.]+ N along ")


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


def run_chain(
    task: ChainTask,
    seed: int,
    connect: str | None = None,
    site_id: str | None = None,
    scene: Scene | None = None,
    make_program: ProgramMaker = generated_program,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
    seeded_layout: bool = True,
) -> dict:
    """The whole chain for ``task`` (see :func:`run_scripted`); ``seeded_layout``: the started
    work site lays the blocks out by ``seed`` (else as its scene file has them, unseeded). The
    result says ``failure`` (None, or its ``kind`` among :data:`FAILURES` and a ``message``)."""
    scene = scene or load_scene()
    stage_s: dict[str, float] = {}
    out: dict = {"task": task.label, "seed": seed, "success": False, "failure": None}
    out["stage_s"] = stage_s
    proc = None
    site_id = site_id or (f"e2e-{seed}" if connect is None else "site1")
    if connect is None:
        connect = f"tcp/127.0.0.1:{free_port_pair()}"
        log_path = Path(tempfile.gettempdir()) / f"telerobot-e2e-{seed}-work-site.log"
        seed_args = ("--seed", str(seed)) if seeded_layout else ()
        proc = _start_work_site(
            site_id, connect, log_path, time_scale, (*seed_args, *work_site_args)
        )
        log(f"work site started (log: {log_path})")
    link = WorkSiteLink(make_config(connect=link_endpoints([connect])[0]), site_id)
    truth = _Truth(link)
    kind = "execution_failed"  # what an unexpected error means at the stage reached
    try:
        t0 = time.monotonic()
        if not _wait(lambda: link.status.label == "connected", link, CONNECT_TIMEOUT_S):
            raise RuntimeError(f"no work site at {connect} within {CONNECT_TIMEOUT_S:.0f} s")
        stage_s["connect"] = time.monotonic() - t0
        t0 = time.monotonic()
        kind = "not_recognised"
        if oracle:
            X_truth = {o.name: o.X_WO for o in truth.latest_after(time.time()).objects}
            truth_frame = Recognitions(
                seq=0,
                stamp_s=time.time(),
                elapsed_s=0.0,
                objects=tuple(
                    Recognition(model=n, X_WO=X, score=1.0)
                    for n, X in X_truth.items()
                    if not scene.object(n).fixed
                ),
            )
            frames: Iterable[Recognitions] = [truth_frame]
        else:
            frames = _recognised_frames(link)
        rec = model_from_frames(task.label, scene, frames, log, ready=task.ready)
        model, corrections = rec.model, rec.corrections
        stage_s["vision"], stage_s["model"] = rec.vision_s, rec.model_s
        out["vision_frames"] = rec.frames
        stage_s["vision_wait"] = time.monotonic() - t0
        out["recognised"] = sorted(model.poses)
        out["corrections_mm"] = {c.name: round(c.moved_mm, 2) for c in corrections}

        t0 = time.monotonic()
        demo = task.demonstrate(model)
        session, workpiece, ideal = demo.session, demo.workpiece, demo.ideal_X_WO
        out["workpiece"] = workpiece
        out |= task.describe(demo)
        goal = session.X_WO[workpiece]
        final = session.sim.history[-1]
        stage_s["operator"] = time.monotonic() - t0
        required = sorted({c.object for c in final.contacts})
        out["contacts_required"] = len(contact_directions(final.contacts))
        out["contacts_required_objects"] = required
        out["goal_off_ideal_mm"] = float(np.linalg.norm(goal[:3, 3] - ideal[:3, 3]) * 1e3)
        kind = "infeasible"
        task.check(demo, model)

        t0 = time.monotonic()
        try:
            program = make_program(session, _program_id(task.program_label, seed))
        except ValueError as e:
            raise RunError("infeasible", f"no program for the demonstration: {e}") from None
        stage_s["program"] = time.monotonic() - t0
        out["commands"] = len(program.commands)

        t0 = time.monotonic()
        kind = "execution_failed"
        state0 = link.robot_state
        link.send_program(program)

        def finished() -> bool:
            return any(
                r.program_id == program.program_id and r.command_index == -1
                and r.status in ("done", "failed", "refused", "stopped")
                for r in link.status.reports
            )  # fmt: skip

        if not _wait(finished, link, EXECUTE_TIMEOUT_S):
            raise RuntimeError(f"the program did not finish within {EXECUTE_TIMEOUT_S:.0f} s")
        stage_s["execute"] = time.monotonic() - t0
        if proc is not None and state0 is not None and link.robot_state is not None:
            simulated_s = (link.robot_state.seq - state0.seq) / STATE_RATE_HZ
            out["time_scale"] = time_scale
            out["time_scale_achieved"] = simulated_s / stage_s["execute"]
            if out["time_scale_achieved"] < SLOW_TIME_SCALE_FRACTION * time_scale:
                log(
                    f"warning: the work site simulated at {out['time_scale_achieved']:.2f}× "
                    f"real time, asked {time_scale:g}× (the machine is too slow or loaded: "
                    "the physics is the same, the run slower)"
                )
        reports = [r for r in link.status.reports if r.program_id == program.program_id]
        out["execution"] = f"{reports[-1].status}: {reports[-1].message}"
        verified = [r for r in reports if r.status == "contact_verified"]
        out["contacts_verified"] = verified[-1].message.count(" N along ") if verified else 0
        verified_objects = set(_VERIFIED_RE.findall(verified[-1].message)) if verified else set()
        out["contacts_verified_objects"] = sorted(verified_objects)

        kind = "goal_missed"
        X_truth = {o.name: o.X_WO for o in truth.latest_after(time.time() + 0.3).objects}
        if workpiece not in X_truth:
            raise ValueError(f"the work site's ground truth has no {workpiece!r}")
        for obj in scene.objects:  # the fixed objects where the truth does not list them
            X_truth.setdefault(obj.name, obj.X_WO)
        judgement = task.judge(demo, model, X_truth)
        out["final_error_mm"] = judgement.error_m * 1e3
        out["final_error_deg"] = math.degrees(judgement.error_rad)
        out |= judgement.extra or {}
        missing = sorted(set(judgement.goal_contacts) - verified_objects)
        contacts_ok = out["contacts_verified"] >= out["contacts_required"] and not missing
        out["success"] = bool(reports[-1].status == "done" and judgement.within and contacts_ok)
        if reports[-1].status == "refused":
            out["failure"] = _failure("program_refused", out["execution"])
        elif reports[-1].status != "done":
            out["failure"] = _failure("execution_failed", out["execution"])
        elif not judgement.within:
            off = f"{out['final_error_mm']:.2f} mm, {out['final_error_deg']:.2f}°"
            out["failure"] = _failure("goal_missed", f"the block ended {off} from the goal")
        elif not contacts_ok:
            why = ", ".join(missing) or f"{out['contacts_verified']} of the directions"
            out["failure"] = _failure("goal_missed", f"contacts not verified: {why}")
        stage_s["computation"] = sum(stage_s.get(k, 0.0) for k in ("vision", "model", "program"))
    except RunError as e:
        out["error"] = str(e)
        out["failure"] = _failure(e.kind, str(e))
    except (RuntimeError, TimeoutError, ValueError) as e:
        out["error"] = str(e)
        out["failure"] = _failure(kind, str(e))
    finally:
        link.close()
        if proc is not None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return out


def _failure(kind: str, message: str) -> dict:
    return {"kind": kind, "message": message}


def _program_id(label: str, seed: int) -> str:
    """A program id (letters, digits, ``_.-`` only) made of ``label``, the seed and the time."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", label).strip("-")[:40] or "task"
    return f"{slug}-{seed}-{int(time.time())}"
