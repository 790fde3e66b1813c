"""The page's task panel: the workpiece picked and dragged on its spring, captures, undo and
reset, the task saved to and loaded from a task file (``docs/tasks.md``), relative to the object
the operator measures it from."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import viser

from models.scene import Scene
from models.transforms import make_pose, quat_wxyz_to_R
from operator_site.failures import RunError
from operator_site.model_editor import WorkSiteModel
from operator_site.session import OperatorSession
from operator_site.task import TaskSession
from operator_site.taskfile import load_task, save_task
from operator_site.ui.scene_view import set_pose
from operator_site.ui.text import plain

NO_WORKPIECE = "(none)"
TASK_HELP = (
    "Pick a block (click it, or choose it below), then drag the arrows and rings around it: "
    "the block follows on a spring and bumps, slides and settles against what it meets. "
    "**Capture mode**: click the frame or the table to keep the block touching it. "
    "**Undo** takes the last drag back. A saved task is measured from the object chosen "
    "below: loaded on another layout, it is done relative to where that object is there."
)
DEFAULT_TASK_FILE = "task.json"
GESTURE_GAP_S = 0.5
"""A dragger update after a pause this long begins a new drag (what "undo" takes back)."""


def _reason(error: Exception) -> str:
    """An exception's message (a KeyError's without the quotes its str() adds)."""
    return str(error.args[0]) if error.args else type(error).__name__


class TaskPanel:
    """The task panel of :class:`~operator_site.ui.page.OperatorPage`."""

    scene: Scene
    model: WorkSiteModel
    session: TaskSession
    op: OperatorSession
    message: str
    _lock: threading.Lock
    _last_drag_s: float

    def _build_task_panel(self, gui: viser.GuiApi) -> None:
        """The panel's widgets, in the folder ``gui`` has open, and their callbacks."""
        gui.add_markdown(TASK_HELP)
        self.workpiece_dropdown = gui.add_dropdown("workpiece", self._workpiece_options())
        self.capture_mode = gui.add_checkbox("capture mode", False)
        self.undo_button = gui.add_button("undo the last drag")
        self.reset_button = gui.add_button("put the block back")
        self.task_md = gui.add_markdown("")
        self.reference_dropdown = gui.add_dropdown(
            "measured from", self._reference_options(), initial_value=self.op.reference
        )
        self.task_file = gui.add_text("task file", DEFAULT_TASK_FILE)
        self.save_button = gui.add_button("save the task")
        self.load_button = gui.add_button("load a task")
        # Only a person's choice acts: the page setting a dropdown itself (under its lock)
        # calls these synchronously too.
        self.workpiece_dropdown.on_update(
            lambda e: e.client is None or self.on_select(self.workpiece_dropdown.value)
        )
        self.reference_dropdown.on_update(
            lambda e: e.client is None or self.on_reference(self.reference_dropdown.value)
        )
        self.undo_button.on_click(lambda _: self.on_undo())
        self.reset_button.on_click(lambda _: self.on_reset())
        self.save_button.on_click(lambda _: self.on_save(self.task_file.value))
        self.load_button.on_click(lambda _: self.on_load(self.task_file.value))

    def _workpiece_options(self) -> tuple[str, ...]:
        return (NO_WORKPIECE, *[o.name for o in self.scene.movable if o.name in self.model.poses])

    def _reference_options(self) -> tuple[str, ...]:
        fixed = [o.name for o in self.scene.objects if o.fixed]
        return (*fixed, *[o.name for o in self.scene.movable if o.name in self.model.poses])

    def on_reference(self, name: str) -> None:
        """Measure the task from ``name`` (the frame, the table, a block in the model)."""
        with self._lock:
            try:
                self.op.set_reference(name)
            except ValueError as e:
                self.message = f"⚠ {plain(e)}"
                return
            self.message = f"the task is measured from the **{plain(name)}**"

    def on_select(self, name: str) -> None:
        """Make ``name`` the workpiece (or none) and put the dragger on it."""
        with self._lock:
            if name == self.session.workpiece:
                return  # the dropdown echoing our own selection back
            if name == NO_WORKPIECE:
                self.dragger.visible = False
                self._show_fingers(None)
                self.message = ""
                return
            try:
                self.op.select(name)
            except (KeyError, ValueError) as e:
                self.message = plain(_reason(e))
                return
            X = self.session.X_WO[name]
            set_pose(self.dragger, X)
            self.dragger.visible = True
            self._show_fingers(name)
            self._task_changed()
            self.message = f"dragging **{plain(name)}**, held as the gripper will hold it"
        if self.workpiece_dropdown.value != name:
            self.workpiece_dropdown.value = name

    def on_click_object(self, name: str) -> None:
        """A click on an object: removes it in remove mode, toggles capture in capture mode,
        else picks a movable block."""
        if self.remove_mode.value:
            if not self.scene.object(name).fixed:
                self.on_remove(name)
            return
        if self.capture_mode.value and self.session.sim is not None:
            with self._lock:
                try:
                    now = self.op.toggle_capture(name)
                    self.message = f"{plain(name)}: {'captured' if now else 'released'}"
                except ValueError as e:
                    self.message = plain(e)
            return
        if not self.scene.object(name).fixed:
            self.on_select(name)

    def on_drag(self) -> None:
        """The dragger moved: it is the spring's new target."""
        X_WD = make_pose(
            quat_wxyz_to_R(np.asarray(self.dragger.wxyz)), np.asarray(self.dragger.position)
        )
        now = time.monotonic()
        with self._lock:
            if self.session.sim is not None:
                if now - self._last_drag_s > GESTURE_GAP_S:
                    self.op.mark()  # a new drag begins: undo comes back here
                self._last_drag_s = now
                self.op.set_target(X_WD)

    def on_undo(self) -> None:
        """Take the last drag back: the block, its captures and its path as they were before."""
        with self._lock:
            X = self.op.undo()
            if X is None:
                self.message = "nothing to undo"
            else:
                set_pose(self.dragger, self.session.sim.state.X_WD)
                set_pose(self.object_frames[self.session.workpiece], X)
                self._task_changed()
                self.message = "the last drag was undone"
            self.task_md.content = self.message

    def on_reset(self) -> None:
        """Put the workpiece back where it was picked up, dragger too."""
        with self._lock:
            self.op.reset()
            self._task_changed()
            if self.session.workpiece is not None:
                X = self.session.X_WO[self.session.workpiece]
                set_pose(self.dragger, X)
                set_pose(self.object_frames[self.session.workpiece], X)

    def on_save(self, path: str) -> None:
        """Save the task demonstrated so far to ``path`` (docs/tasks.md's format)."""
        with self._lock:
            try:
                task = self.op.recorded_task()
            except ValueError as e:
                self.message = f"⚠ nothing saved: {plain(e)}"
                self.task_md.content = self.message
                return
        try:
            save_task(task, path)
        except OSError as e:
            self.message = f"⚠ could not save to {plain(path)}: {plain(e.strerror)}"
        else:
            self.message = (
                f"saved to {plain(Path(path).resolve())}: {len(task.steps)} steps, measured "
                f"from the {plain(task.reference)}"
            )
        self.task_md.content = self.message

    def on_load(self, path: str) -> None:
        """Load a task file and drag it in this model as the runner would (carried to its
        first step, its steps followed, its captures made)."""
        try:
            task = load_task(path)
        except ValueError as e:  # TaskFileError: one line naming the file and the field
            self.message = f"⚠ {plain(e)}"
            self.task_md.content = self.message
            return
        with self._lock:
            try:
                self.op.load(task)
            except (RunError, ValueError) as e:
                self.message = f"⚠ {plain(path)} cannot be done in this model: {plain(e)}"
                self.task_md.content = self.message
                return
            name = task.workpiece
            X = self.op.task.X_WO[name]
            set_pose(self.dragger, X)
            set_pose(self.object_frames[name], X)
            self.dragger.visible = True
            self._show_fingers(name)
            self._task_changed()
        if self.workpiece_dropdown.value != name:
            self.workpiece_dropdown.value = name
        if self.reference_dropdown.value != task.reference:
            self.reference_dropdown.value = task.reference
        self.message = f"loaded {plain(path)}: {plain(task.name)} ({len(task.steps)} steps)"
        self.task_md.content = self.message

    def step_task(self) -> None:
        """One simulator step of the workpiece, shown on the page."""
        with self._lock:
            result = self.op.step()
            captured = sorted(self.session.captured)
        if result is None:
            return
        set_pose(self.object_frames[self.session.workpiece], result.X_WO)
        points = [c.points_W for c in result.contacts]
        self.contact_points.points = np.vstack(points) if points else np.zeros((0, 3))
        self.contact_points.visible = bool(points)
        touching = ", ".join(sorted(c.object for c in result.contacts)) or "nothing"
        self.task_md.content = "  \n".join(
            filter(
                None,
                [
                    self.message,
                    f"touching: {plain(touching)}",
                    f"captured: {plain(', '.join(captured))}" if captured else "",
                ],
            )
        )
