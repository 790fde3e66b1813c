"""The page's task panel: the workpiece picked and dragged on its spring, captures, undo and
reset, the task saved to and loaded from a task file (``docs/tasks.md``), relative to the object
the operator measures it from."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import viser

from models.scene import Scene
from models.transforms import R_to_rpy, make_pose, quat_wxyz_to_R, rpy_to_R
from operator_site.failures import RunError
from operator_site.model_editor import WorkSiteModel
from operator_site.program.feasibility import felt_contacts, movable_names
from operator_site.session import OperatorSession
from operator_site.task import TaskSession
from operator_site.taskfile import load_task, save_task
from operator_site.ui.gizmo import NO_SNAP, SNAP_STEP_M, SNAP_STEP_RAD, Gizmo, Snap
from operator_site.ui.scene_view import FELT_RGB, UNFELT_RGB, VIEWS, set_pose
from operator_site.ui.text import plain

NO_WORKPIECE = "(none)"
TASK_HELP = (
    "Pick a block (click it, or choose it below), then drag the arrows and rings around it "
    "(red, green, blue: the table's x, y, z), or type a pose or nudge it below: the block "
    "follows on a spring and bumps, slides and settles against what it meets. "
    "Contacts show as dots: **green** where the robot will feel the contact by force, "
    "**orange** where it cannot (a program that needs it is refused). "
    "**Capture mode**: click the frame or the table to keep the block touching it. "
    "**Undo** takes the last drag back. A saved task is measured from the object chosen "
    "below: loaded on another layout, it is done relative to where that object is there."
)
PICK_HELP = "Pick a block to move (click it, or choose it below)."
DEFAULT_TASK_FILE = "task.json"
NUDGES = {
    "−x": (0, -1), "+x": (0, 1), "−y": (1, -1), "+y": (1, 1), "−z": (2, -1), "+z": (2, 1),
    "↻z": (5, -1), "↺z": (5, 1),
}  # fmt: skip
"""The nudge buttons: which coordinate of (x, y, z, roll, pitch, yaw) in the world, and which
way; a nudge is one snapping step (a millimetre, five degrees)."""


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

    def _build_task_panel(self, gui: viser.GuiApi) -> None:
        """The panel's widgets, in the folder ``gui`` has open, and their callbacks."""
        gui.add_markdown(TASK_HELP)
        self.workpiece_dropdown = gui.add_dropdown("workpiece", self._workpiece_options())
        self.gizmo = Gizmo()
        self.snap_checkbox = gui.add_checkbox(
            f"snap: {SNAP_STEP_M * 1e3:g} mm, {math.degrees(SNAP_STEP_RAD):g}°",
            True,
            hint="the gizmo moves the block in whole steps from where the drag began",
        )
        self.own_axes_checkbox = gui.add_checkbox(
            "gizmo along the block's own axes",
            False,
            hint="off: the gizmo's axes are the table's (red x, green y, blue z)",
        )
        self.nudge_buttons = gui.add_button_group("nudge", tuple(NUDGES))
        self.view_buttons = gui.add_button_group("view", VIEWS)
        self.shadows_checkbox = gui.add_checkbox(
            "shadows", False, hint="a cue for contact; slow in a browser without a graphics card"
        )
        self.pose_xyz = gui.add_vector3("target x, y, z (mm)", (0.0, 0.0, 0.0), step=1.0)
        self.pose_rpy = gui.add_vector3("roll, pitch, yaw (°)", (0.0, 0.0, 0.0), step=1.0)
        self.pose_button = gui.add_button("move the block there")
        self.capture_mode = gui.add_checkbox("capture mode", False)
        self.undo_button = gui.add_button("undo the last drag")
        self.reset_button = gui.add_button("put the block back")
        self.task_md = gui.add_markdown(PICK_HELP)
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
        self.snap_checkbox.on_update(lambda _: self._set_snap(self.snap_checkbox.value))
        self.own_axes_checkbox.on_update(lambda _: self._set_axes(self.own_axes_checkbox.value))
        self.nudge_buttons.on_click(lambda _: self.on_nudge(self.nudge_buttons.value))
        self.view_buttons.on_click(lambda e: self.set_view(self.view_buttons.value, e.client))
        self.shadows_checkbox.on_update(lambda _: self.set_shadows(self.shadows_checkbox.value))
        self.pose_button.on_click(
            lambda _: self.on_pose_typed(self.pose_xyz.value, self.pose_rpy.value)
        )
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
                self._nothing_picked()
                return
            try:
                self.op.select(name)
            except (KeyError, ValueError) as e:
                self.message = plain(_reason(e))
                return
            self._place_gizmo(self.session.X_WO[name])
            self.dragger.visible = True
            self._show_fingers(name)
            self._task_changed()
            self.message = f"dragging **{plain(name)}**, held as the gripper will hold it"
            self.task_md.content = self.message
        if self.workpiece_dropdown.value != name:
            self.workpiece_dropdown.value = name

    def _nothing_picked(self) -> None:
        """No block picked: no gizmo, fingers, contacts or "dragging …" left from before."""
        self.dragger.visible = False
        self._show_fingers(None)
        self.contact_points.visible = False
        self.message = ""
        self.task_md.content = PICK_HELP

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

    def _place_gizmo(self, X_WO: np.ndarray) -> None:
        """Put the gizmo on the block's target ``X_WO`` and show that pose in the fields."""
        set_pose(self.dragger, self.gizmo.place(X_WO))
        self.pose_xyz.value = tuple(float(v) for v in np.round(X_WO[:3, 3] * 1e3, 2))
        self.pose_rpy.value = tuple(
            float(v) for v in np.round(np.degrees(R_to_rpy(X_WO[:3, :3])), 2)
        )

    def _set_snap(self, on: bool) -> None:
        self.gizmo.snap = Snap() if on else NO_SNAP

    def _set_axes(self, own: bool) -> None:
        """The gizmo's axes: the block's own or the table's, on the block's current target."""
        with self._lock:
            self.gizmo.world_axes = not own
            if self.session.sim is not None:
                self._place_gizmo(self.session.sim.state.X_WD)

    def on_drag(self, phase: str = "update") -> None:
        """The gizmo moved (``phase``: start, update, end of a drag): the block's target is
        where the gizmo's motion since the drag began puts it, snapped; at the end the gizmo
        shows the snapped pose."""
        X_WG = make_pose(
            quat_wxyz_to_R(np.asarray(self.dragger.wxyz)), np.asarray(self.dragger.position)
        )
        with self._lock:
            if self.session.sim is None:
                return
            if phase == "start" or self.gizmo.X_WG0 is None:
                self.op.mark()  # a new drag begins: undo comes back here
                self.gizmo.begin()
            target_WO = self.gizmo.target_W(X_WG)
            self.op.set_target(target_WO)
            if phase == "end":
                self._place_gizmo(target_WO)

    def _move_target(self, move, what: str) -> None:
        """The block's target set at once (typed or nudged) to ``move(current target)``: one
        undo step, the gizmo on it."""
        with self._lock:
            if self.session.sim is None:
                self.message = "Pick a block first."
                self.task_md.content = self.message
                return
            X_WO = move(self.session.sim.state.X_WD.copy())
            self.op.mark()
            self.op.set_target(X_WO)
            self._place_gizmo(X_WO)
            self.message = what

    def on_nudge(self, which: str) -> None:
        """Move the block's target one snapping step along or about a world axis."""
        if which not in NUDGES:
            return
        axis, sign = NUDGES[which]

        def nudged(X: np.ndarray) -> np.ndarray:
            if axis < 3:
                X[axis, 3] += sign * SNAP_STEP_M
            else:
                X[:3, :3] = rpy_to_R(np.array([0.0, 0.0, sign * SNAP_STEP_RAD])) @ X[:3, :3]
            return X

        self._move_target(nudged, f"nudged {which}")

    def on_pose_typed(self, xyz_mm, rpy_deg) -> None:
        """The block's target typed in: position (mm) and roll, pitch, yaw (°) in the world."""
        values = np.array([*xyz_mm, *rpy_deg], dtype=np.float64)
        if not np.all(np.isfinite(values)):
            self.message = "⚠ the pose needs six numbers"
            self.task_md.content = self.message
            return
        X = make_pose(rpy_to_R(np.radians(values[3:])), values[:3] * 1e-3)
        x, y, z = values[:3]
        self._move_target(lambda _: X, f"target set to ({x:.1f}, {y:.1f}, {z:.1f}) mm")

    def on_undo(self) -> None:
        """Take the last drag back: the block, its captures and its path as they were before."""
        with self._lock:
            X = self.op.undo()
            if X is None:
                self.message = "nothing to undo"
            else:
                self._place_gizmo(self.session.sim.state.X_WD)
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
                self._place_gizmo(X)
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
            self._place_gizmo(self.session.sim.state.X_WD)
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
        # Each contact coloured by whether the robot will be able to feel it by force.
        felt = felt_contacts(result, movable_names(self.scene))
        points = [c.points_W for c in result.contacts]
        self.contact_points.points = np.vstack(points) if points else np.zeros((0, 3))
        self.contact_points.colors = (
            np.vstack(
                [
                    np.tile(FELT_RGB if felt[c.object] else UNFELT_RGB, (len(c.points_W), 1))
                    for c in result.contacts
                ]
            ).astype(np.uint8)
            if points
            else np.zeros((0, 3), dtype=np.uint8)
        )
        self.contact_points.visible = bool(points)
        touching = ", ".join(
            f"{plain(c)} (the robot {'can' if felt[c] else '**cannot**'} feel it)"
            for c in sorted(felt)
        )
        text = "  \n".join(
            filter(
                None,
                [
                    self.message,
                    f"touching: {touching or 'nothing'}",
                    f"captured: {plain(', '.join(captured))}" if captured else "",
                ],
            )
        )
        if text != self.task_md.content:  # redrawn on change only
            self.task_md.content = text
