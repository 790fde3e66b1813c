"""The operator's workflow, headless, once: the page's panels and the command-line runner both
drive an :class:`OperatorSession`.

It holds the model built from the work site's recognitions (:class:`WorkSiteModel`), the task
being demonstrated in it (:class:`TaskSession`, the simulator of §V), the demonstration as data
(the dragger's targets and the captures as they happened, relative to the reference object the
operator chose: a :class:`~operator_site.taskfile.Task`), and the programs made from it and sent.

A program is always made from the task as data: the recorded task is dragged again
(:func:`~operator_site.taskdrag.drag_task`, which also chooses the grasp for its path) and that
drag is made into the program. So a task saved from the page and run from the command line on the
same layout makes the same program, and what the page shows is what the robot will be sent.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.scene import Scene
from models.transforms import invert_pose
from operator_site.failures import RunError
from operator_site.link import WorkSiteLink
from operator_site.model_editor import Correction, WorkSiteModel
from operator_site.program import (
    CommandParams,
    DeformParams,
    Generated,
    choose_grasp_yaw,
    generate_program,
)
from operator_site.recovery import recovery_program
from operator_site.simulator import SimParams
from operator_site.task import MAX_UNDO, TaskSession
from operator_site.taskdrag import TaskDemonstration, drag_task, reference_pose_W, turn_rad
from operator_site.taskfile import Task, TaskGoal, TaskStep
from protocol import MotionProgram, ProtocolError, Recognitions, encode
from protocol.codec import decode_saved
from protocol.messages import ExecutionReport

ACCEPT_SCORE = 0.5
"""Recognitions scoring at least this are accepted by :meth:`OperatorSession.accept_all`."""
RECORD_SPACING_M = 1e-3
RECORD_SPACING_RAD = math.radians(0.5)
"""The dragger's targets are recorded at least this far apart (or at the end of a drag, or where
a capture or release is made): fine enough that dragging through them again follows the same
path to well within a millimetre."""
DEFAULT_TOLERANCE_MM = 1.5
DEFAULT_TOLERANCE_DEG = 1.5
FAR_FACTOR = 5.0
"""A recognition more than this many default tolerances from a pose of its block is "far": a
different placement (or a different block), not vision's error about the same one."""
MAX_PROGRAM_FILE_BYTES = 16 * 1024 * 1024
FINISHED = ("done", "failed", "refused", "stopped")
"""A whole-program report with one of these statuses ends the program."""


def disagreement(error_m: float | None, angle_rad: float | None) -> str:
    """How a recognition compares with another pose of that block (None: there is none):
    ``agrees`` (within the default tolerance), ``off`` (up to :data:`FAR_FACTOR` times it),
    ``far`` (beyond) or ``new``."""
    if error_m is None or angle_rad is None:
        return "new"
    within = error_m / (DEFAULT_TOLERANCE_MM * 1e-3)
    turned = angle_rad / math.radians(DEFAULT_TOLERANCE_DEG)
    worst = max(within, turned)
    if worst <= 1.0:
        return "agrees"
    return "off" if worst <= FAR_FACTOR else "far"


def generated_program(
    session: TaskSession,
    program_id: str,
    sim_params: SimParams | None = None,
    deform_params: DeformParams | None = None,
    command_params: CommandParams | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> Generated:
    """The program generator's program (§VI) for the path dragged in ``session``: deformed,
    made into contact moves, checked (:class:`~operator_site.program.ProgramRefusedError`, a
    ValueError, when it cannot be). The parameters default to the session's simulator and the
    generator's defaults."""
    path = session.path_history()
    return generate_program(
        program_id,
        session.scene,
        session.workpiece,
        path,
        choose_grasp_yaw(
            session.start_X_WO,
            session.X_GP,
            [s.X_WO for s in path],
            (session.robot, session.scene.robot.X_WB, session.scene.robot.q_home_rad),
        ),
        attached_O=session.fingers_O,
        sim_params=sim_params or session.params,
        deform_params=deform_params,
        command_params=command_params,
        X_WO=session.X_WO,
        progress=progress,
        grip_opening_m=session.opening_m if session.fingers_O else None,
    )


@dataclass
class _Recorded:
    """One recorded dragger target in W and what was captured or released there."""

    X_WD: np.ndarray
    capture: list[str] = dataclasses.field(default_factory=list)
    release: list[str] = dataclasses.field(default_factory=list)
    frozen: bool = False
    """A frozen target is kept as it is; the newest unfrozen one follows the dragger."""


class OperatorSession:
    """One operator's work on one work site: model, task, programs (see the module docstring).

    ``link`` is the work site's link (None: nothing can be sent, as in tests of the workflow).
    Not thread-safe: the page calls it under its lock.
    """

    def __init__(
        self,
        scene: Scene,
        link: WorkSiteLink | None = None,
        params: SimParams | None = None,
    ) -> None:
        self.scene = scene
        self.link = link
        self.model = WorkSiteModel(scene)
        self.task = TaskSession(self.model.scene(), params)
        self.reference = self._default_reference()
        self.loaded: Task | None = None
        """The task file the demonstration began from (None: dragged here)."""
        self.demonstration: TaskDemonstration | None = None
        """The last drag of the task as data (by :meth:`make_program` or :meth:`load`)."""
        self._recorded: list[_Recorded] = []
        self._marks: list[int] = []
        self.corrections: list[Correction] = []
        """What making the model consistent last changed."""
        self._programs_made = 0
        self._sent: dict[str, MotionProgram] = {}  # by id, as sent

    def _default_reference(self) -> str:
        """The frame, if the scene has one; else its first fixed object (the table)."""
        fixed = [o.name for o in self.scene.objects if o.fixed]
        return "frame" if "frame" in fixed else fixed[0]

    # ------------------------------------------------------------------------------ the model

    def accept_all(self, recognitions: Recognitions, min_score: float = ACCEPT_SCORE) -> int:
        """Accept every recognition of a movable block scoring at least ``min_score``, make the
        model consistent and start the task afresh; the number accepted. ValueError (the model
        unchanged) when the recognitions cannot be made consistent."""
        movable = {o.name for o in self.scene.movable}
        kept = [r for r in recognitions.objects if r.score >= min_score and r.model in movable]
        self._accept([(r.model, r.X_WO, r.score) for r in kept])
        return len(kept)

    def accept(self, name: str, X_WO: np.ndarray, score: float = 1.0) -> list[Correction]:
        """Accept one block into the model at ``X_WO``, made consistent; ValueError (the model
        unchanged) when it cannot be."""
        return self._accept([(name, X_WO, score)])

    def use_scene_layout(self) -> list[Correction]:
        """Every block where the scene file puts it (a model without vision)."""
        return self._accept([(o.name, o.X_WO, 1.0) for o in self.scene.movable])

    def remove(self, name: str) -> None:
        """Take block ``name`` out of the model (the task starts afresh)."""
        self.model.remove(name)
        self._model_changed()

    def _accept(self, found: Iterable[tuple[str, np.ndarray, float]]) -> list[Correction]:
        poses = {n: X.copy() for n, X in self.model.poses.items()}
        scores = dict(self.model.scores)
        try:
            for name, X, score in found:
                self.model.accept(name, X, score)
            corrections = self.model.make_consistent(self.task.params)
        except (KeyError, ValueError):
            self.model.poses, self.model.scores = poses, scores
            raise
        self.corrections = corrections
        self._model_changed()
        return corrections

    def _model_changed(self) -> None:
        self.task = TaskSession(self.model.scene(), self.task.params)
        if self.reference not in self.model.poses and self.reference not in {
            o.name for o in self.model.fixed
        }:
            self.reference = self._default_reference()
        self.loaded = self.demonstration = None
        self._recorded, self._marks = [], []

    # ------------------------------------------------------------------------------- the task

    def select(self, name: str) -> None:
        """Make block ``name`` the workpiece (held as the gripper would hold it) and begin
        recording its task where it lies; ValueError for an object that cannot be moved."""
        self.task.select(name)
        if self.reference == name:  # a block is not measured from itself
            self.reference = self._default_reference()
        self.loaded = self.demonstration = None
        self._recorded = [_Recorded(self.task.start_X_WO.copy(), frozen=True)]
        self._marks = []

    def set_reference(self, name: str) -> None:
        """The object the task's poses are measured from (the frame, the table, a block);
        ValueError if it is not in the model or is the workpiece."""
        try:
            reference_pose_W(self.model, name)
        except RunError as e:
            raise ValueError(str(e)) from None
        if name == self.task.workpiece:
            raise ValueError(f"the workpiece {name!r} cannot be its own reference")
        self.reference = name

    def set_target(self, X_WD: np.ndarray) -> None:
        """The dragger moved to ``X_WD``: the spring's new target, recorded."""
        if self.task.sim is None:
            return
        self.task.set_target(X_WD)
        X = np.array(X_WD, dtype=np.float64)
        last = self._recorded[-1] if self._recorded else None
        if last is not None and not last.frozen:
            anchor = self._recorded[-2].X_WD if len(self._recorded) >= 2 else last.X_WD
            if _near(anchor, X):
                last.X_WD = X
                return
            last.frozen = True
        self._recorded.append(_Recorded(X))

    def step(self):
        """One simulator step of the workpiece (None when nothing is selected)."""
        return self.task.step()

    def toggle_capture(self, name: str) -> bool:
        """Capture ``name`` (or release it if captured), recorded at the current target;
        whether it is captured now."""
        now = self.task.toggle_capture(name)
        if self._recorded:
            here = self._recorded[-1]
            (here.capture if now else here.release).append(name)
            here.frozen = True
        return now

    def mark(self) -> None:
        """A drag begins: :meth:`undo` comes back here."""
        self.task.mark()
        if self._recorded:
            self._recorded[-1].frozen = True
        self._marks.append(len(self._recorded))
        del self._marks[:-MAX_UNDO]

    def undo(self) -> np.ndarray | None:
        """Back to the last :meth:`mark`: the block, its captures, its path and its recorded
        targets; the block's pose, or None when there is nothing to undo."""
        X = self.task.undo()
        if X is not None and self._marks:
            del self._recorded[self._marks.pop() :]
        return X

    def reset(self) -> None:
        """The workpiece back where it was picked up; the recording begins again."""
        self.task.reset()
        if self.task.start_X_WO is not None:
            self._recorded = [_Recorded(self.task.start_X_WO.copy(), frozen=True)]
        self._marks = []
        self.loaded = self.demonstration = None

    def recorded_task(self, name: str | None = None) -> Task:
        """The task demonstrated so far, as data: the targets and captures relative to
        :attr:`reference`, and the goal where the block is now, touching what it touches now
        (a loaded task not dragged further keeps its own goal and name). ValueError when there
        is no demonstration."""
        workpiece = self.task.workpiece
        if workpiece is None or not self._recorded:
            raise ValueError("pick a block and move it first")
        X_RW = invert_pose(reference_pose_W(self.model, self.reference))
        steps = tuple(
            TaskStep(X_RW @ r.X_WD, tuple(r.capture) or None, tuple(r.release) or None)
            for r in self._recorded
        )
        loaded = self.loaded
        if loaded is not None and len(steps) == len(loaded.steps):
            if self.reference == loaded.reference:
                return dataclasses.replace(loaded, name=name or loaded.name)
            goal = dataclasses.replace(loaded.goal, X_RO=X_RW @ self.demonstration.ideal_X_WO)
        else:
            contacts = tuple(sorted({c.object for c in self.task.sim.state.contacts}))
            goal = TaskGoal(
                X_RW @ self.task.X_WO[workpiece],
                contacts,
                DEFAULT_TOLERANCE_MM * 1e-3,
                math.radians(DEFAULT_TOLERANCE_DEG),
            )
        default = loaded.name if loaded else f"{workpiece} moved, relative to the {self.reference}"
        return Task(name or default, workpiece, self.reference, steps, goal)

    def load(self, task: Task) -> TaskDemonstration:
        """Drag ``task`` (a task file) in this model, as the runner does: the block carried to
        its first step, the steps followed, the grasp chosen for the path. TaskFileError for
        names the model does not have, RunError (``not_recognised``, ``no_grasp``) when it
        cannot be dragged; the session as it was then."""
        task.check_names(set(self.model.poses), {o.name for o in self.model.fixed}, task.name)
        demo = drag_task(task, self.model)
        self.task = demo.session
        self.reference = task.reference
        self.loaded, self.demonstration = task, demo
        self._recorded = [
            _Recorded(X_WD, list(step.capture or ()), list(step.release or ()), frozen=True)
            for X_WD, step in zip(demo.steps_X_WD, task.steps, strict=True)
        ]
        self._marks = []
        return demo

    # ---------------------------------------------------------------------------- the program

    def make_program(
        self,
        program_id: str | None = None,
        name: str | None = None,
        progress: Callable[[float, str], None] | None = None,
        **params,
    ) -> Generated:
        """The robot program for the task as data (see the module docstring): the recorded
        task dragged again with the grasp chosen for its path, then §VI. ``params``: the
        generator's (``sim_params``, ``deform_params``, ``command_params``). RunError
        ``no_grasp`` when no grasp can do the task; ValueError (ProgramRefusedError,
        ProgramInfeasibleError) when the program fails its check."""
        say = progress or (lambda _fraction, _stage: None)
        task = self.recorded_task(name)
        say(0.01, "dragging the task again, held as the robot will hold it")
        self.demonstration = demo = drag_task(task, self.model)
        self._recorded[-1].frozen = True
        program_id = program_id or self.new_program_id(task.workpiece)
        return generated_program(demo.session, program_id, progress=progress, **params)

    def new_program_id(self, label: str) -> str:
        """A program id no program of this session had: letters, digits and ``_.-``."""
        slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", label).strip("-")[:40] or "program"
        while True:
            self._programs_made += 1
            candidate = f"{slug}-{int(time.time())}-{self._programs_made}"
            if candidate not in self._sent:
                return candidate

    def renamed(self, program: MotionProgram) -> MotionProgram:
        """``program`` under a new id (a program loaded from a file, which a work site may
        have run before: it runs each id once)."""
        base = re.sub(r"-\d+-\d+$", "", program.program_id)
        return dataclasses.replace(program, program_id=self.new_program_id(base))

    def send(self, program: MotionProgram) -> MotionProgram:
        """Send ``program`` to the work site; a program sent before goes again under a new id
        (the work site runs each id once). The program as sent."""
        if self.link is None:
            raise RuntimeError("no work site to send to")
        if program.program_id in self._sent:
            program = self.renamed(program)
        self._sent[program.program_id] = program
        self.link.send_program(program)
        return program

    def recover(self, action: str) -> MotionProgram:
        """Send recovery ``action`` (:data:`~operator_site.recovery.RECOVERY_ACTIONS`: release,
        retract, home), made from the robot's latest state; the program sent. RuntimeError
        without a work site or its robot state."""
        if self.link is None or self.link.robot_state is None:
            raise RuntimeError("no robot state from the work site yet")
        program = recovery_program(
            action, self.link.robot_state, self.scene, self.new_program_id(action)
        )
        return self.send(program)

    def resume(self, program: MotionProgram) -> MotionProgram:
        """Send ``program``, which the work site stopped, to go on from the command it was
        stopped in (a new id that ``continues`` it; the work site refuses it, saying why, when
        another program ran since or it was not stopped). The program as sent."""
        if self.link is None:
            raise RuntimeError("no work site to send to")
        resumed = dataclasses.replace(
            program,
            program_id=self.new_program_id(f"{program.program_id}-resumed"),
            continues=program.program_id,
        )
        return self.send(resumed)

    def released(self, program_id: str) -> tuple[str, np.ndarray] | None:
        """The block that program ``program_id`` (sent from this session) carries and the
        pose ``X_WO`` it lets go of it at; None for a program not sent from here, or one that
        carries nothing it names (a recovery's release)."""
        program = self._sent.get(program_id)
        if program is None or not program.holds:
            return None
        releases = [c.X_WP for c in program.commands if c.kind in ("release", "open_gripper")]
        return (program.holds[0].name, releases[-1]) if releases else None

    def outcome(self, program_id: str) -> ExecutionReport | None:
        """The whole-program report that ended ``program_id`` (done, failed, refused, stopped),
        or None while it has not ended."""
        if self.link is None:
            return None
        for report in self.link.status.reports:
            if (
                report.program_id == program_id
                and report.command_index == -1
                and report.status in FINISHED
            ):
                return report
        return None


def _near(X_a: np.ndarray, X_b: np.ndarray) -> bool:
    return bool(
        np.linalg.norm(X_a[:3, 3] - X_b[:3, 3]) < RECORD_SPACING_M
        and turn_rad(X_a[:3, :3], X_b[:3, :3]) < RECORD_SPACING_RAD
    )


# ----------------------------------------------------------------------------- program files


def save_program(path: Path | str, program: MotionProgram) -> None:
    """Write ``program`` to ``path`` as the work site receives it (the wire's msgpack)."""
    Path(path).write_bytes(encode(program))


def load_program(path: Path | str) -> MotionProgram:
    """Read a program saved by :func:`save_program`, checked as the work site checks it;
    ValueError naming the file and what is wrong."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_PROGRAM_FILE_BYTES:
            raise ValueError(f"{path}: larger than {MAX_PROGRAM_FILE_BYTES} bytes")
        payload = path.read_bytes()
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e.strerror})") from None
    try:
        return decode_saved(payload, expected=MotionProgram)
    except ProtocolError as e:
        raise ValueError(f"{path}: not a robot program ({e})") from None
