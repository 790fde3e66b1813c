"""``operator-site run TASK.json``: a task file through the whole chain
(:func:`~operator_site.chain.run_chain`). The operator's drag is
:func:`~operator_site.taskdrag.drag_task`, the one an
:class:`~operator_site.session.OperatorSession` makes its programs from; the block's end is
judged on the work site's ground truth.
"""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from models.geometry import convex_gap_2d
from models.layout import CLEARANCE_M, radius_xy
from models.scene import Scene, load_scene
from operator_site.chain import ChainTask, Judgement, ProgramMaker, run_chain
from operator_site.failures import RunError
from operator_site.model_editor import WorkSiteModel
from operator_site.session import generated_program
from operator_site.taskdrag import (
    TaskDemonstration,
    drag_task,
    goal_on_reference_W,
    reference_pose_W,
)
from operator_site.taskfile import Task, pose_error, symmetric_nearest


def _needs_in_model(task: Task) -> Callable[[WorkSiteModel], bool]:
    """Whether a model holds the task's workpiece and (a block) reference."""

    def ready(model: WorkSiteModel) -> bool:
        fixed = {o.name for o in model.fixed}
        return task.workpiece in model.poses and (
            task.reference in fixed or task.reference in model.poses
        )

    return ready


def check_reaches_goal(task: Task, demo: TaskDemonstration, model: WorkSiteModel) -> None:
    """:class:`RunError` ``infeasible`` unless the simulated drag ended within the goal's
    tolerances and touching every goal contact: a block in the way, the goal place occupied."""
    X = demo.session.X_WO[demo.workpiece]
    error_m, error_rad = pose_error(demo.ideal_X_WO, X, model.symmetries(demo.workpiece))
    touching = {c.object for c in demo.session.sim.state.contacts}
    if error_m > task.goal.tolerance_m or error_rad > task.goal.tolerance_rad:
        against = f", the {demo.workpiece} touching the {' and the '.join(sorted(touching))}"
        raise RunError(
            "infeasible",
            f"the simulated drag ends {error_m * 1e3:.1f} mm, {math.degrees(error_rad):.1f}° "
            f"from the goal{against if touching else ''}: something is in the way or the "
            "goal place is occupied",
        )
    missing = sorted(set(task.goal.contacts) - touching)
    if missing:
        raise RunError(
            "infeasible", f"the simulated drag ends without touching {', '.join(missing)}"
        )


def room_for_task(task: Task, scene: Scene, X_WO: dict[str, np.ndarray]) -> str | None:
    """Why the blocks laid out as ``X_WO`` leave ``task`` no room, or None when they do: a block
    other than the workpiece and the reference lies in the way of the workpiece's path through
    the task's steps to its goal (the workpiece's footprint as its bounding circle, turned any
    way, the block's as it lies, at least :data:`~models.layout.CLEARANCE_M` apart: room for
    fingers). Such a layout is a different task, one the operator would first clear; run, it
    is refused or pushes the block aside."""
    X_WR = X_WO[task.reference] if task.reference in X_WO else scene.object(task.reference).X_WO
    points = [(X_WR @ s.X_RD)[:2, 3] for s in task.steps] + [(X_WR @ task.goal.X_RO)[:2, 3]]
    r_workpiece = radius_xy(scene, task.workpiece)
    for name, X in X_WO.items():
        if name in (task.workpiece, task.reference) or scene.object(name).fixed:
            continue
        V_O = np.vstack([p.vertices_O for p in scene.object(name).model.parts])
        footprint = (X[:3, :3] @ V_O.T + X[:3, 3:4]).T[:, :2]
        gap_m = min(
            convex_gap_2d(np.array([a, b]), footprint) for a, b in itertools.pairwise(points)
        )
        gap_m -= r_workpiece
        if gap_m < CLEARANCE_M:
            return (
                f"the {name} lies in the way of the {task.workpiece}'s path "
                f"({gap_m * 1e3:.0f} mm from it, less than {CLEARANCE_M * 1e3:.0f} mm)"
            )
    return None


def judge_on_truth(
    task: Task, demo: TaskDemonstration, model: WorkSiteModel, truth: dict[str, np.ndarray]
) -> Judgement:
    """The block's true final pose against the goal placed on the reference's true final pose
    (both from the work site's ground truth ``truth``), up to the block's symmetries.

    A symmetric reference's frame is any of its symmetric frames: the program placed the goal
    on the one vision gave the model, turned by the frame the drag chose (``demo.S_R``: which
    end of a plank is its +x end), so the true pose is taken in the symmetric frame nearest
    the model's and turned the same."""
    X_WR, X_WO = truth[task.reference].copy(), truth[task.workpiece]
    R_model = reference_pose_W(model, task.reference)[:3, :3]
    X_WR[:3, :3] = symmetric_nearest(X_WR[:3, :3], R_model, model.symmetries(task.reference))
    goal = goal_on_reference_W(task, X_WR, demo.S_O, demo.S_R)
    error_m, error_rad = pose_error(goal, X_WO, model.symmetries(task.workpiece))
    return Judgement(
        error_m=error_m,
        error_rad=error_rad,
        within=error_m <= task.goal.tolerance_m and error_rad <= task.goal.tolerance_rad,
        goal_contacts=task.goal.contacts,
        extra={"final_X_WO": X_WO.tolist(), "reference_X_WO": X_WR.tolist()},
    )


def run_task(
    task: Task,
    seed: int,
    scene: Scene | None = None,
    scene_file: Path | None = None,
    connect: str | None = None,
    site_id: str | None = None,
    make_program: ProgramMaker = generated_program,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
    label: str | None = None,
    dry_run: bool = False,
) -> dict:
    """Run ``task`` end to end (the chain of :func:`~operator_site.chain.run_chain`, the
    operator's drag :func:`drag_task`); the result's JSON-ready dict. With ``scene_file`` the
    started work site lays the blocks out as that scene file does, else by ``seed``.
    ``label``: the program id's prefix (default: the task's name); ``dry_run``: make the
    program and send nothing."""
    scene = scene or (load_scene(scene_file) if scene_file is not None else load_scene())
    chain = ChainTask(
        label=task.name,
        program_label=label or task.name,
        ready=_needs_in_model(task),
        demonstrate=lambda model: drag_task(task, model),
        check=lambda demo, model: check_reaches_goal(task, demo, model),
        judge=lambda demo, model, truth: judge_on_truth(task, demo, model, truth),
        describe=lambda demo: {
            "symmetry_O": np.round(demo.S_O, 6).tolist(),
            "symmetry_R": np.round(demo.S_R, 6).tolist(),
        },
    )
    # With a scene file the layout is the file's: the seed draws only the camera's error.
    extra = (
        ("--scene", str(scene_file), "--camera-seed", str(seed)) if scene_file is not None else ()
    )
    return run_chain(
        chain,
        seed,
        connect=connect,
        site_id=site_id,
        scene=scene,
        make_program=make_program,
        log=log,
        oracle=oracle,
        time_scale=time_scale,
        work_site_args=(*extra, *work_site_args),
        seeded_layout=scene_file is None,
        dry_run=dry_run,
    )
