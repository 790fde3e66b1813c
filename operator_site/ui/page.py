"""The operator's web page (viser), Fig. 5 as one page: the live camera image with the recognised
objects drawn over it, the list of recognitions to accept into the model, the 3D model in which
the operator drags the workpiece, the program to confirm, the execution log, and a stop button
that is always there.

Only this package calls viser. Poses go to viser as position + ``wxyz`` quaternion, converted by
``models.transforms`` (viser's own convention), never inline.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import viser

from models.robot import RobotModel, load_robot
from models.scene import Scene
from models.transforms import R_to_quat_wxyz, make_pose, quat_wxyz_to_R
from operator_site.link import LinkStatus, WorkSiteLink
from operator_site.model_editor import WorkSiteModel
from operator_site.program import choose_grasp_yaw, generate_program
from operator_site.task import TaskSession
from operator_site.ui.overlay import draw_wireframes
from operator_site.ui.taskfile import TaskFile, load_task, save_task

log = logging.getLogger("operator-site")

UI_PERIOD_S = 0.05
"""The page is refreshed from the link at most this often (20 Hz)."""
STATUS_PERIOD_S = 0.5
NO_WORKPIECE = "(none)"
CONTACT_RGB = (230, 40, 40)
FINGER_RGB = (40, 40, 48)
TASK_HELP = (
    "Pick a block (click it, or choose it below), then drag the arrows and rings around it: "
    "the block follows on a spring and bumps, slides and settles against what it meets. "
    "**Capture mode**: click the frame or the table to keep the block touching it. "
    "**Undo** takes the last drag back."
)
MODEL_HELP = (
    "Blocks the work site's camera recognised are outlined on its image (orange: not in the "
    "model yet, green: in it). Accept them to build the model the robot will work in; "
    "**remove mode**: click a block in the 3D view to take it out."
)
ACCEPT_SCORE = 0.5
"""Recognitions scoring at least this are accepted by "accept the recognised blocks"."""
LOG_LINES = 8
DEFAULT_TASK_FILE = "task.json"
GESTURE_GAP_S = 0.5
"""A dragger update after a pause this long begins a new drag (what "undo" takes back)."""
INITIAL_EYE_W = (1.05, -0.85, 0.75)
INITIAL_LOOK_AT_W = (0.40, 0.0, 0.05)


def _rgb255(rgba) -> tuple[int, int, int]:
    return tuple(round(255 * c) for c in rgba[:3])


def _set_pose(handle, X_WL: np.ndarray) -> None:
    handle.position = X_WL[:3, 3]
    handle.wxyz = R_to_quat_wxyz(X_WL[:3, :3])


def waiting_image(width: int, height: int, text: str) -> np.ndarray:
    """A dark grey placeholder with ``text`` centred, (h, w, 3) uint8."""
    img = np.full((height, width, 3), 40, dtype=np.uint8)
    scale = width / 640
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
    cv2.putText(
        img,
        text,
        ((width - tw) // 2, (height + th) // 2),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        (200, 200, 200),
        2,
        cv2.LINE_AA,
    )
    return img


def status_markdown(site_id: str, status: LinkStatus) -> str:
    """The status panel's text for the link state ``status``."""
    lines = [f"**work site: {status.label}** (`{site_id}`)"]
    if status.work_site_alive:
        lines.append(
            f"robot state {status.state_rate_hz:.0f} Hz · camera {status.frame_rate_hz:.1f} Hz"
        )
    if status.last_frame_age_s is not None:
        lines.append(f"last camera frame {status.last_frame_age_s:.1f} s ago")
    if status.rejected:
        lines.append(f"⚠ {status.rejected} invalid messages rejected")
    if status.reports:
        r = status.reports[-1]
        lines.append(f"last report: program `{r.program_id}` {r.status}: {r.message}")
    return "  \n".join(lines)


def _reason(error: Exception) -> str:
    """An exception's message (a KeyError's without the quotes its str() adds)."""
    return str(error.args[0]) if error.args else type(error).__name__


def log_markdown(reports) -> str:
    """The execution log: the last :data:`LOG_LINES` reports, newest last."""
    if not reports:
        return "no program sent yet"
    lines = []
    for r in reports[-LOG_LINES:]:
        where = "program" if r.command_index < 0 else f"command {r.command_index}"
        lines.append(f"`{r.program_id}` {where}: **{r.status}** {r.message}")
    return "  \n".join(lines)


class OperatorPage:
    """Builds the page for ``scene`` and keeps it in step with ``link`` while running.

    ``initial_model``: "scene" starts the model from the scene file's layout (the demo without
    vision), "empty" from the fixed environment alone, waiting for recognitions.
    """

    def __init__(
        self,
        scene: Scene,
        link: WorkSiteLink,
        host: str = "127.0.0.1",
        port: int = 8080,
        initial_model: str = "scene",
    ) -> None:
        if initial_model not in ("scene", "empty"):
            raise ValueError(f"initial_model must be 'scene' or 'empty', not {initial_model!r}")
        self.scene, self.link = scene, link
        self.robot: RobotModel = load_robot(scene.robot.urdf_path)
        self.server = viser.ViserServer(
            host=host, port=port, label="Telerobot operator site", verbose=False
        )
        self.url = f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:{port}"
        self.server.scene.set_up_direction("+z")
        self.server.initial_camera.position = INITIAL_EYE_W
        self.server.initial_camera.look_at = INITIAL_LOOK_AT_W
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self.model = WorkSiteModel(scene)
        if initial_model == "scene":
            for obj in scene.movable:
                self.model.accept(obj.name, obj.X_WO)
        self.session = TaskSession(self.model.scene())
        self._lock = threading.Lock()
        self.message = ""
        self.finger_meshes: list = []
        self.path_lines: list = []
        self.pending_program = None
        self._programs_made = 0
        self._recognitions_shown: int | None = None
        self._build_gui()
        self._build_scene()
        self._show_model()
        self.frames_shown = 0
        self.states_shown = 0
        self._last_drag_s = -math.inf

    # ------------------------------------------------------------------------------ building

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        gui.add_markdown("### Telerobot — operator site")
        self.stop_button = gui.add_button(
            "STOP the robot", color="red", icon=None, hint="stops any motion at the work site"
        )
        self.stop_button.on_click(lambda _: self.on_stop())
        self.status_md = gui.add_markdown(status_markdown(self.link.site_id, self.link.status))
        cam = self.scene.camera
        self.camera_image = gui.add_image(
            # Half size: cheap to send, and never mistaken for a frame from the work site.
            waiting_image(cam.width // 2, cam.height // 2, "waiting for the work site's camera"),
            label="work-site camera",
            format="jpeg",
            jpeg_quality=85,
        )
        with gui.add_folder("Model"):
            gui.add_markdown(MODEL_HELP)
            self.recognitions_md = gui.add_markdown("no recognitions yet")
            self._rec_folder = gui.add_folder("recognised, not in the model: click to add")
            self._rec_buttons: dict[str, object] = {}
            self.accept_button = gui.add_button("accept the recognised blocks")
            self.scene_layout_button = gui.add_button("use the scene file's layout (no vision)")
            self.remove_mode = gui.add_checkbox("remove mode", False)
            self.model_md = gui.add_markdown("")
        with gui.add_folder("Task"):
            gui.add_markdown(TASK_HELP)
            self.workpiece_dropdown = gui.add_dropdown("workpiece", self._workpiece_options())
            self.capture_mode = gui.add_checkbox("capture mode", False)
            self.undo_button = gui.add_button("undo the last drag")
            self.reset_button = gui.add_button("put the block back")
            self.task_md = gui.add_markdown("")
            self.task_file = gui.add_text("task file", DEFAULT_TASK_FILE)
            self.save_button = gui.add_button("save the task")
            self.load_button = gui.add_button("load a task")
        with gui.add_folder("Program"):
            self.program_button = gui.add_button("make the robot program")
            self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.program_md = gui.add_markdown("")
            self.send_button = gui.add_button("send it to the robot", disabled=True)
            # The panel scrolls: a second stop where the operator's eyes are after sending.
            gui.add_button("STOP", color="red").on_click(lambda _: self.on_stop())
        with gui.add_folder("Execution log"):
            self.log_md = gui.add_markdown(log_markdown([]))
        self.accept_button.on_click(lambda _: self.on_accept_recognitions())
        self.scene_layout_button.on_click(lambda _: self.on_use_scene_layout())
        self.workpiece_dropdown.on_update(lambda _: self.on_select(self.workpiece_dropdown.value))
        self.undo_button.on_click(lambda _: self.on_undo())
        self.reset_button.on_click(lambda _: self.on_reset())
        self.save_button.on_click(lambda _: self.on_save(self.task_file.value))
        self.load_button.on_click(lambda _: self.on_load(self.task_file.value))
        self.program_button.on_click(lambda _: self.on_make_program())
        self.send_button.on_click(lambda _: self.on_send_program())

    def _workpiece_options(self) -> tuple[str, ...]:
        return (NO_WORKPIECE, *[o.name for o in self.scene.movable if o.name in self.model.poses])

    def _build_scene(self) -> None:
        scene = self.server.scene
        self.object_frames = {}
        for obj in self.scene.objects:
            frame = scene.add_frame(f"/world/{obj.name}", show_axes=False)
            _set_pose(frame, obj.X_WO)
            self.object_frames[obj.name] = frame
            for k, part in enumerate(obj.model.parts):
                mesh = scene.add_mesh_simple(
                    f"/world/{obj.name}/part_{k}",
                    part.vertices_O,
                    part.triangles(),
                    color=_rgb255(obj.model.rgba),
                    flat_shading=True,
                )
                mesh.on_click(lambda _, name=obj.name: self.on_click_object(name))
        self.dragger = scene.add_transform_controls("/dragger", scale=0.12, visible=False)
        self.dragger.on_update(lambda _: self.on_drag())
        self.contact_points = scene.add_point_cloud(
            "/contacts", np.zeros((0, 3)), CONTACT_RGB, point_size=0.006, visible=False
        )
        cam = self.scene.camera
        fov_y = 2 * np.arctan2(cam.height / 2, cam.K[1, 1])
        frustum = scene.add_camera_frustum(
            "/world/camera",
            fov=float(fov_y),
            aspect=cam.width / cam.height,
            scale=0.05,
            thickness=0.002,
            color=(60, 60, 60),
        )
        _set_pose(frustum, cam.X_WC)
        self.link_frames = {}
        for link in self.robot.links.values():
            frame = scene.add_frame(f"/robot/{link.name}", show_axes=False)
            self.link_frames[link.name] = frame
            for k, v in enumerate(link.visuals):
                name = f"/robot/{link.name}/visual_{k}"
                color = _rgb255(v.rgba)
                if v.kind == "box":
                    h = scene.add_box(name, color=color, dimensions=tuple(v.size))
                elif v.kind == "cylinder":
                    h = scene.add_cylinder(name, radius=v.size[0], height=v.size[1], color=color)
                else:
                    h = scene.add_icosphere(name, radius=v.size[0], color=color)
                _set_pose(h, v.X_LV)
        self._show_robot(self.scene.robot.q_home_rad, 0.04)

    def _show_robot(self, q: np.ndarray, opening_m: float) -> None:
        poses = self.robot.link_poses_W(q, opening_m, self.scene.robot.X_WB)
        with self.server.atomic():
            for name, X_WL in poses.items():
                _set_pose(self.link_frames[name], X_WL)

    def _show_model(self) -> None:
        """Show the model's objects where it has them; hide the rest."""
        for obj in self.scene.objects:
            frame = self.object_frames[obj.name]
            in_model = obj.fixed or obj.name in self.model.poses
            frame.visible = in_model
            if in_model:
                _set_pose(frame, self.session.X_WO.get(obj.name, obj.X_WO))
        self.workpiece_dropdown.options = self._workpiece_options()

    # ------------------------------------------------------------------------------ model

    def _model_changed(self, corrections=()) -> None:
        """The model's objects changed: a new task session over it (the workpiece is let go)."""
        self.session = TaskSession(self.model.scene(), self.session.params)
        self.dragger.visible = False
        self._show_fingers(None)
        self._show_path(None, None)
        self._show_model()
        lines = [f"model: {len(self.model.poses)} blocks ({', '.join(sorted(self.model.poses))})"]
        lines += [
            f"{c.name}: moved {c.moved_mm:.1f} mm, turned {c.turned_deg:.1f}° ({c.why})"
            for c in corrections
            if c.moved_mm >= 0.05 or c.turned_deg >= 0.05
        ]
        self.model_md.content = "  \n".join(lines)
        self._recognitions_shown = None  # the list says what is in the model: redraw it

    def on_accept_recognitions(self, min_score: float = ACCEPT_SCORE) -> int:
        """Accept every recognition scoring at least ``min_score`` into the model, then make
        the model consistent; the number accepted."""
        recs = self.link.recognitions
        if recs is None or not recs.objects:
            self.model_md.content = (
                "Nothing recognised yet: wait for the camera, or use the scene file's layout."
            )
            return 0
        with self._lock:
            accepted = 0
            for r in recs.objects:
                if r.score >= min_score and r.model in {o.name for o in self.scene.movable}:
                    self.model.accept(r.model, r.X_WO, r.score)
                    accepted += 1
            try:
                corrections = self.model.make_consistent(self.session.params)
            except ValueError as e:
                self.model_md.content = f"⚠ {e}"
                return accepted
            self._model_changed(corrections)
        return accepted

    def on_accept_one(self, name: str) -> bool:
        """Accept the latest recognition of ``name`` into the model (made consistent); False
        if vision has no such object now."""
        recs = self.link.recognitions
        found = [r for r in (recs.objects if recs else ()) if r.model == name]
        if not found:
            self.model_md.content = f"{name} is not among the latest recognitions"
            return False
        with self._lock:
            self.model.accept(name, found[0].X_WO, found[0].score)
            try:
                corrections = self.model.make_consistent(self.session.params)
            except ValueError as e:
                self.model.remove(name)
                self.model_md.content = f"⚠ {name} not added: {e}"
                return False
            self._model_changed(corrections)
        self._show_recognitions()
        return True

    def on_use_scene_layout(self) -> None:
        """The model from the scene file's layout: every block where the file puts it."""
        with self._lock:
            for obj in self.scene.movable:
                self.model.accept(obj.name, obj.X_WO)
            self._model_changed()

    def on_remove(self, name: str) -> None:
        """Take ``name`` out of the model."""
        with self._lock:
            if name in self.model.poses:
                self.model.remove(name)
                self._model_changed()

    # ------------------------------------------------------------------- operator actions

    def on_stop(self) -> None:
        """The stop button: stop the robot now."""
        self.link.send_stop("operator pressed stop")
        self.program_md.content = "**stop sent to the work site**"

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
                self.session.select(name)
            except (KeyError, ValueError) as e:
                self.message = _reason(e)
                return
            X = self.session.X_WO[name]
            _set_pose(self.dragger, X)
            self.dragger.visible = True
            self._show_fingers(name)
            self._show_path(None, None)
            self.message = f"dragging **{name}**, held as the gripper will hold it"
        if self.workpiece_dropdown.value != name:
            self.workpiece_dropdown.value = name

    def _show_fingers(self, name: str | None) -> None:
        """The gripper's fingers, drawn on the workpiece where the grasp puts them."""
        for handle in self.finger_meshes:
            handle.remove()
        self.finger_meshes = []
        if name is None:
            return
        for k, part in enumerate(self.session.fingers_O):
            self.finger_meshes.append(
                self.server.scene.add_mesh_simple(
                    f"/world/{name}/finger_{k}",
                    part.vertices_O,
                    part.triangles(),
                    color=FINGER_RGB,
                    flat_shading=True,
                )
            )

    def _show_path(self, raw_W: np.ndarray | None, program_W: np.ndarray | None) -> None:
        """The dragged path (grey) and the program's path (green), as 3D polylines."""
        for handle in self.path_lines:
            handle.remove()
        self.path_lines = []
        for name, points, rgb in (
            ("/paths/raw", raw_W, (150, 150, 150)),
            ("/paths/program", program_W, (30, 170, 60)),
        ):
            if points is None or len(points) < 2:
                continue
            segments = np.stack([points[:-1], points[1:]], axis=1)
            self.path_lines.append(
                self.server.scene.add_line_segments(name, segments, rgb, thickness=0.002)
            )

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
                    now = self.session.toggle_capture(name)
                    self.message = f"{name}: {'captured' if now else 'released'}"
                except ValueError as e:
                    self.message = str(e)
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
                    self.session.mark()  # a new drag begins: undo comes back here
                self._last_drag_s = now
                self.session.set_target(X_WD)

    def on_undo(self) -> None:
        """Take the last drag back: the block, its captures and its path as they were before."""
        with self._lock:
            X = self.session.undo()
            if X is None:
                self.message = "nothing to undo"
            else:
                _set_pose(self.dragger, self.session.sim.state.X_WD)
                _set_pose(self.object_frames[self.session.workpiece], X)
                self._show_path(None, None)
                self.message = "the last drag was undone"
            self.task_md.content = self.message

    def on_reset(self) -> None:
        """Put the workpiece back where it was picked up, dragger too."""
        with self._lock:
            self.session.reset()
            self._show_path(None, None)
            if self.session.workpiece is not None:
                X = self.session.X_WO[self.session.workpiece]
                _set_pose(self.dragger, X)
                _set_pose(self.object_frames[self.session.workpiece], X)

    def on_save(self, path: str) -> None:
        """Save the model, the workpiece and its dragged path to ``path``."""
        with self._lock:
            sim = self.session.sim
            task = TaskFile(
                scene=self.scene.name,
                model={n: X.copy() for n, X in self.model.poses.items()},
                workpiece=self.session.workpiece,
                path=[r.X_WO for r in sim.history] if sim else [],
                captured=sorted(self.session.captured),
            )
            if sim is not None and self.session.start_X_WO is not None:
                task.model[sim.world.workpiece] = self.session.start_X_WO.copy()
        try:
            save_task(path, task)
        except OSError as e:
            self.task_md.content = f"⚠ could not save to `{path}`: {e.strerror}"
            return
        self.task_md.content = f"saved to `{Path(path).resolve()}` ({len(task.path)} steps)"

    def on_load(self, path: str) -> None:
        """Load a task file: its model, its workpiece, and its path dragged again."""
        try:
            task = load_task(path)
            if task.scene != self.scene.name:
                raise ValueError(f"{path}: made for scene {task.scene!r}, not {self.scene.name!r}")
        except ValueError as e:
            self.task_md.content = f"⚠ {e}"
            return
        with self._lock:
            try:
                model = WorkSiteModel(self.scene, task.model)
            except (KeyError, ValueError) as e:
                self.task_md.content = f"⚠ {path}: {_reason(e)}"
                return
            self.model = model
            self._model_changed()
        if task.workpiece is not None:
            self.on_select(task.workpiece)
            with self._lock:
                for name in task.captured:
                    self.session.toggle_capture(name)
                self.session.replay(task.path)
                X = self.session.X_WO[task.workpiece]
                _set_pose(self.dragger, X)
                _set_pose(self.object_frames[task.workpiece], X)
        # As the message, so that the live task text (rewritten every step) keeps it.
        self.message = f"loaded `{path}` ({len(task.path)} steps replayed)"
        self.task_md.content = self.message

    def on_make_program(self) -> None:
        """Turn the task into a robot program (§VI: the dragged path deformed, fitted with few
        moves keeping its required contacts, checked), and show it for confirmation."""
        self.progress.visible = True
        self.progress.value = 0.0
        self.send_button.disabled = True
        with self._lock:
            name = self.session.workpiece
            sim = self.session.sim
            if name is None or sim is None or len(sim.history) < 2:
                self.program_md.content = "Pick a block and move it first."
                self.progress.visible = False
                return
            self._programs_made += 1
            program_id = f"{name}-{int(time.time())}-{self._programs_made}"
            X_GP = choose_grasp_yaw(self.session.start_X_WO, self.session.X_GP)
            try:
                made = generate_program(
                    program_id,
                    self.session.scene,
                    name,
                    self.session.path_history(),
                    X_GP,
                    attached_O=self.session.fingers_O,
                    sim_params=self.session.params,
                    X_WO=self.session.X_WO,
                    progress=self._show_progress,
                )
            except ValueError as e:  # ProgramRefusedError says which command and why
                self.pending_program = None
                self.program_md.content = f"⚠ no program: {e}"
                self.progress.visible = False
                return
            self.pending_program = made.program
        self.progress.value = 100.0
        self._show_path(made.raw.centres_W, made.deformed.path.centres_W)
        lines = [
            f"**program `{program_id}`**, {len(made.program.commands)} commands; path "
            f"{made.raw.length_m() * 1e3:.0f} → {made.deformed.path.length_m() * 1e3:.0f} mm "
            f"(grey: as dragged, green: as the robot will go):"
        ]
        for i, c in enumerate(made.program.commands):
            p = c.X_WP[:3, 3]
            contacts = f" keeping {', '.join(x.object for x in c.contacts)}" if c.contacts else ""
            lines.append(
                f"{i}. {c.kind} to ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m at "
                f"{c.speed_mps * 1000:.0f} mm/s{contacts}"
            )
        lines.append("Check the green path in the 3D view, then send it.")
        self.program_md.content = "  \n".join(lines)
        self.progress.visible = False
        self.send_button.disabled = False

    def _show_progress(self, fraction: float, stage: str) -> None:
        self.progress.value = 100.0 * fraction
        self.program_md.content = f"making the program: {stage}…"

    def on_send_program(self) -> None:
        """Second confirmation: send the pending program to the work site."""
        program, self.pending_program = self.pending_program, None
        self.send_button.disabled = True
        if program is None:
            return
        self.link.send_program(program)
        self.program_md.content += f"  \nsent to the work site `{self.link.site_id}`"

    def step_task(self) -> None:
        """One simulator step of the workpiece, shown on the page."""
        with self._lock:
            result = self.session.step()
            captured = sorted(self.session.captured)
        if result is None:
            return
        _set_pose(self.object_frames[self.session.workpiece], result.X_WO)
        points = [c.points_W for c in result.contacts]
        self.contact_points.points = np.vstack(points) if points else np.zeros((0, 3))
        self.contact_points.visible = bool(points)
        touching = ", ".join(sorted(c.object for c in result.contacts)) or "nothing"
        self.task_md.content = "  \n".join(
            filter(
                None,
                [
                    self.message,
                    f"touching: {touching}",
                    f"captured: {', '.join(captured)}" if captured else "",
                ],
            )
        )

    # ------------------------------------------------------------------------------ link

    def _show_recognitions(self) -> None:
        recs = self.link.recognitions
        if recs is None or recs.seq == self._recognitions_shown:
            return
        self._recognitions_shown = recs.seq
        if not recs.objects:
            self.recognitions_md.content = f"frame {recs.seq}: nothing recognised"
            return
        lines = [f"frame {recs.seq}, {recs.elapsed_s * 1e3:.0f} ms:"]
        for r in sorted(recs.objects, key=lambda r: -r.score):
            state = "in the model" if r.model in self.model.poses else "not accepted"
            lines.append(f"- {r.model}: score {r.score:.2f} ({state})")
        self.recognitions_md.content = "\n".join(lines)
        self._show_add_buttons(
            {r.model: r.score for r in recs.objects if r.model not in self.model.poses}
        )

    def _show_add_buttons(self, scores: dict[str, float]) -> None:
        """One "add" button per recognised block not in the model."""
        for name in [n for n in self._rec_buttons if n not in scores]:
            self._rec_buttons.pop(name).remove()
        known = {o.name for o in self.scene.movable}
        with self._rec_folder:
            for name, score in scores.items():
                if name in self._rec_buttons or name not in known:
                    continue
                button = self.server.gui.add_button(f"add {name} ({score:.2f})")
                button.on_click(lambda _, n=name: self.on_accept_one(n))
                self._rec_buttons[name] = button

    def _camera_view(self) -> np.ndarray:
        """The latest frame, with the latest recognitions outlined (vision runs slower than
        the camera: they may be of a frame or two before)."""
        frame = self.link.camera_frame
        recs = self.link.recognitions
        if recs is None or not recs.objects:
            return frame.image
        known = {o.name: o.model for o in self.scene.movable}
        objects = [
            (known[r.model], r.X_WO, r.model in self.model.poses)
            for r in recs.objects
            if r.model in known
        ]
        return draw_wireframes(frame.image, self.scene.camera, objects)[..., ::-1]

    def update(self) -> None:
        """Poll the link once and show what changed."""
        new_state, new_frame = self.link.poll()
        if new_state and self.link.robot_state is not None:
            s = self.link.robot_state
            self._show_robot(s.q, s.gripper_opening_m)
            self.states_shown += 1
        if new_frame and self.link.camera_frame is not None:
            self.camera_image.image = self._camera_view()
            self.frames_shown += 1
        self._show_recognitions()

    def run(self, stop: threading.Event) -> None:
        """Refresh the page until ``stop`` is set."""
        next_status = 0.0
        while not stop.is_set():
            t = time.monotonic()
            self.update()
            self.step_task()
            if t >= next_status:
                self.status_md.content = status_markdown(self.link.site_id, self.link.status)
                self.log_md.content = log_markdown(self.link.status.reports)
                next_status = t + STATUS_PERIOD_S
            stop.wait(max(0.0, UI_PERIOD_S - (time.monotonic() - t)))

    def close(self) -> None:
        self.server.stop()
