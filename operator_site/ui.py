"""The operator's web page (viser): the 3D work-site model, the live camera image, link status.

Only this module calls viser. Poses go to viser as position + ``wxyz`` quaternion, converted by
``models.transforms`` (viser's own convention), never inline.
"""

from __future__ import annotations

import logging
import threading
import time

import cv2
import numpy as np
import viser

from models.robot import RobotModel, load_robot
from models.scene import Scene
from models.transforms import R_to_quat_wxyz, make_pose, quat_wxyz_to_R
from operator_site.link import LinkStatus, WorkSiteLink
from operator_site.program import choose_grasp_yaw, pick_and_place
from operator_site.task import TaskSession

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
    "**Capture mode**: click the frame or the table to keep the block touching it."
)
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


class OperatorPage:
    """Builds the page for ``scene`` and keeps it in step with ``link`` while running."""

    def __init__(
        self, scene: Scene, link: WorkSiteLink, host: str = "127.0.0.1", port: int = 8080
    ) -> None:
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
        self.session = TaskSession(scene)
        self._lock = threading.Lock()
        self.message = ""
        self.finger_meshes: list = []
        self.pending_program = None
        self._programs_made = 0
        self._build_gui()
        self._build_scene()
        self.frames_shown = 0
        self.states_shown = 0

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        gui.add_markdown("### Telerobot — operator site")
        self.status_md = gui.add_markdown(status_markdown(self.link.site_id, self.link.status))
        cam = self.scene.camera
        self.camera_image = gui.add_image(
            # Half size: cheap to send, and never mistaken for a frame from the work site.
            waiting_image(cam.width // 2, cam.height // 2, "waiting for the work site's camera"),
            label="work-site camera",
            format="jpeg",
            jpeg_quality=85,
        )
        with gui.add_folder("Task"):
            gui.add_markdown(TASK_HELP)
            names = [o.name for o in self.scene.movable]
            self.workpiece_dropdown = gui.add_dropdown("workpiece", (NO_WORKPIECE, *names))
            self.capture_mode = gui.add_checkbox("capture mode", False)
            self.reset_button = gui.add_button("put the block back")
            self.task_md = gui.add_markdown("")
            self.program_button = gui.add_button("make the robot program")
            self.send_button = gui.add_button("send it to the robot", disabled=True)
            self.program_md = gui.add_markdown("")
        self.workpiece_dropdown.on_update(lambda _: self.on_select(self.workpiece_dropdown.value))
        self.reset_button.on_click(lambda _: self.on_reset())
        self.program_button.on_click(lambda _: self.on_make_program())
        self.send_button.on_click(lambda _: self.on_send_program())

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

    # ------------------------------------------------------------------- operator actions

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
            except ValueError as e:
                self.message = str(e)
                return
            X = self.session.X_WO[name]
            _set_pose(self.dragger, X)
            self.dragger.visible = True
            self._show_fingers(name)
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

    def on_click_object(self, name: str) -> None:
        """A click on an object: toggles capture in capture mode, else picks a movable block."""
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
        with self._lock:
            if self.session.sim is not None:
                self.session.set_target(X_WD)

    def on_reset(self) -> None:
        """Put the workpiece back where it was picked up, dragger too."""
        with self._lock:
            self.session.reset()
            if self.session.workpiece is not None:
                X = self.session.X_WO[self.session.workpiece]
                _set_pose(self.dragger, X)
                _set_pose(self.object_frames[self.session.workpiece], X)

    def on_make_program(self) -> None:
        """Turn the task (the block from where it was picked to where it is now) into a robot
        program, and show it for confirmation."""
        with self._lock:
            name = self.session.workpiece
            if name is None or self.session.start_X_WO is None:
                self.program_md.content = "Pick a block and move it first."
                return
            start, goal = self.session.start_X_WO, self.session.X_WO[name]
            self._programs_made += 1
            program_id = f"{name}-{int(time.time())}-{self._programs_made}"
            X_GP = choose_grasp_yaw(start, self.session.X_GP)
            self.pending_program = pick_and_place(program_id, start, goal, X_GP)
        lines = [f"**program `{program_id}`**, {len(self.pending_program.commands)} commands:"]
        for i, c in enumerate(self.pending_program.commands):
            p = c.X_WP[:3, 3]
            lines.append(
                f"{i}. {c.kind} to ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m at "
                f"{c.speed_mps * 1000:.0f} mm/s"
            )
        self.program_md.content = "  \n".join(lines)
        self.send_button.disabled = False

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

    def update(self) -> None:
        """Poll the link once and show what changed."""
        new_state, new_frame = self.link.poll()
        if new_state and self.link.robot_state is not None:
            s = self.link.robot_state
            self._show_robot(s.q, s.gripper_opening_m)
            self.states_shown += 1
        if new_frame and self.link.camera_frame is not None:
            self.camera_image.image = self.link.camera_frame.image
            self.frames_shown += 1

    def run(self, stop: threading.Event) -> None:
        """Refresh the page until ``stop`` is set."""
        next_status = 0.0
        while not stop.is_set():
            t = time.monotonic()
            self.update()
            self.step_task()
            if t >= next_status:
                self.status_md.content = status_markdown(self.link.site_id, self.link.status)
                next_status = t + STATUS_PERIOD_S
            stop.wait(max(0.0, UI_PERIOD_S - (time.monotonic() - t)))

    def close(self) -> None:
        self.server.stop()
