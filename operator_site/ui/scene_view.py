"""The page's 3D view: the work site's objects, the robot, the camera, the dragger, the
contacts, the gripper's fingers on the workpiece and the paths. Poses go to viser as position
+ ``wxyz`` quaternion, converted by ``models.transforms``, never inline."""

from __future__ import annotations

import math

import numpy as np
import viser

from models.robot import RobotModel
from models.scene import Scene
from models.transforms import R_to_quat_wxyz, so3_log
from operator_site.model_editor import WorkSiteModel
from operator_site.session import disagreement
from operator_site.task import TaskSession
from operator_site.taskfile import pose_error

CONTACT_RGB = (230, 40, 40)
FELT_RGB = (40, 170, 60)
UNFELT_RGB = (240, 140, 20)
"""Contact points: green where the robot will feel the contact by force (a contact move keeping
the contacts shown presses each with the force the work site verifies), orange where not."""
FINGER_RGB = (40, 40, 48)
BLOCK_RGBS = (
    (214, 160, 92),
    (96, 150, 205),
    (120, 180, 110),
    (200, 110, 120),
    (160, 130, 200),
    (210, 190, 90),
    (110, 185, 180),
    (190, 140, 160),
)
"""The movable blocks' colours in the 3D view, one each in the scene's order (the camera sees
them all the same wood): which block is which at a glance."""
GHOST_OPACITY = 0.35
GHOST_REDRAW_M = 2.5e-4
GHOST_REDRAW_RAD = math.radians(0.25)
"""A ghost is moved only when vision's pose of it moves farther than these: less is under a
pixel at the page's framing, and every change to the 3D view costs the browser a redrawn
frame (vision sends several a second while it tracks)."""
GHOST_RGBS = {
    "agrees": (60, 190, 80),
    "off": (240, 150, 30),
    "far": (220, 40, 40),
    "new": (90, 140, 235),
}
"""What vision sees now, drawn see-through over the model, by
:func:`~operator_site.session.disagreement`: green where it agrees with the model (within the
task's tolerance), orange a few millimetres off, red far off, blue for a block not in it."""
SKY_RGB = (255, 255, 255)
GROUND_RGB = (110, 100, 90)
ROBOT_SHOWN_RAD = 1e-4
"""The 3D view's arm is redrawn when a joint moved more than this ..."""
FINGERS_SHOWN_M = 1e-4
"""... or the gripper's opening changed by more than this."""
GIZMO_PX = 150.0
"""The gizmo's size on the screen, in pixels."""
LABEL_ABOVE_M = 0.01
"""A block's name floats this far above its top."""


def block_label(name: str) -> str:
    """A block's name as the page writes it ("tall block" for ``tall_block``)."""
    return name.replace("_", " ")


VIEW_FOV_RAD = math.radians(45.0)
VIEW_DIRECTION_W = (0.65, -0.85, 0.70)
"""The 3D view starts looking along this direction (from the far side of the work area, to
the robot's right, from above) with this vertical field of view."""
VIEW_MARGIN_M = 0.05
ABOVE_TILT = 1e-3
ABOVE_FIELD_M = 0.30
"""Seen from above over a picked block, the view is this much of the table high."""
VIEWS = ("from the start", "from above")
"""The views a button puts every browser's camera in."""


def work_area_W(scene: Scene) -> tuple[np.ndarray, float]:
    """The work area's centre in W and its radius (m): every movable block and the frame (or,
    without one, the blocks alone), with a margin."""
    names = [o.name for o in scene.movable] + [o.name for o in scene.objects if o.name == "frame"]
    points = np.array([scene.object(n).X_WO[:3, 3] for n in names])
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    return centre, float(np.max(np.linalg.norm(points - centre, axis=1))) + VIEW_MARGIN_M


def initial_view_W(scene: Scene, fov_rad: float = VIEW_FOV_RAD) -> tuple[np.ndarray, np.ndarray]:
    """``(eye, look_at)`` in W framing the work area from :data:`VIEW_DIRECTION_W`."""
    centre, radius = work_area_W(scene)
    direction = np.asarray(VIEW_DIRECTION_W) / np.linalg.norm(VIEW_DIRECTION_W)
    return centre + direction * radius / math.sin(fov_rad / 2), centre


def view_from_above_W(
    scene: Scene, look_at_W: np.ndarray | None = None, fov_rad: float = VIEW_FOV_RAD
) -> tuple[np.ndarray, np.ndarray]:
    """``(eye, look_at)`` in W looking down, the table's +x (away from the robot) up on the
    screen: on the whole work area, or close over ``look_at_W`` (:data:`ABOVE_FIELD_M` across)
    to place a block precisely."""
    centre, radius = work_area_W(scene)
    if look_at_W is None:
        look_at, distance = centre, radius / math.sin(fov_rad / 2)
    else:
        look_at = np.asarray(look_at_W, dtype=np.float64)
        distance = (ABOVE_FIELD_M / 2) / math.tan(fov_rad / 2)
    # Straight down is a pole of the orbit controls: a hair towards the robot gives the view
    # its up direction.
    direction = np.array([-ABOVE_TILT, 0.0, 1.0]) / math.hypot(ABOVE_TILT, 1.0)
    return look_at + direction * distance, look_at


def rgb255(rgba) -> tuple[int, int, int]:
    """An RGBA colour in [0, 1] as viser's 0..255 RGB."""
    return tuple(round(255 * c) for c in rgba[:3])


def set_pose(handle, X_WL: np.ndarray) -> None:
    """Place a viser scene node at ``X_WL`` (position and ``wxyz`` quaternion)."""
    handle.position = X_WL[:3, 3]
    handle.wxyz = R_to_quat_wxyz(X_WL[:3, :3])


class SceneView:
    """The 3D view of :class:`~operator_site.ui.page.OperatorPage`."""

    server: viser.ViserServer
    scene: Scene
    robot: RobotModel
    model: WorkSiteModel
    session: TaskSession
    finger_meshes: list
    path_lines: list

    def _build_scene(self) -> None:
        scene = self.server.scene
        # Image-based lighting and shadow maps are most of what a browser without a graphics
        # card spends on this view (a frame several times slower): a sky-and-ground light
        # instead, shadows on request (the Task panel's view options).
        scene.configure_environment_map(None)
        scene.configure_default_lights(True, cast_shadow=False)
        scene.add_light_hemisphere(
            "/lights/sky", sky_color=SKY_RGB, ground_color=GROUND_RGB, intensity=1.2
        )
        scene.add_light_ambient("/lights/ambient", intensity=0.3)
        self._shown_q: tuple[np.ndarray, float] | None = None  # (joints, opening) drawn
        self.object_frames = {}
        self.object_meshes: dict[str, list] = {}
        self.labels = {}
        movable = [o.name for o in self.scene.movable]
        for obj in self.scene.objects:
            frame = scene.add_frame(f"/world/{obj.name}", show_axes=False)
            set_pose(frame, obj.X_WO)
            self.object_frames[obj.name] = frame
            color = (
                BLOCK_RGBS[movable.index(obj.name) % len(BLOCK_RGBS)]
                if obj.name in movable
                else rgb255(obj.model.rgba)
            )
            for k, part in enumerate(obj.model.parts):
                mesh = scene.add_mesh_simple(
                    f"/world/{obj.name}/part_{k}",
                    part.vertices_O,
                    part.triangles(),
                    color=color,
                    flat_shading=True,
                )
                mesh.on_click(lambda _, name=obj.name: self.on_click_object(name))
                self.object_meshes.setdefault(obj.name, []).append(mesh)
            if obj.name in movable:
                top_O = max(float(part.vertices_O[:, 2].max()) for part in obj.model.parts)
                self.labels[obj.name] = scene.add_label(
                    f"/world/{obj.name}/label",
                    block_label(obj.name),
                    position=(0.0, 0.0, top_O + LABEL_ABOVE_M),
                    anchor="bottom-center",
                )
        # Sized in pixels, drawn over everything: visible at any zoom, never inside the
        # block or behind the fingers.
        self.vision_root = scene.add_frame("/vision", show_axes=False)
        self.ghosts: dict[str, tuple] = {}  # (frame, meshes) of each ghost shown
        self._lost_ghosts: dict[str, tuple] = {}  # hidden, kept to be shown again
        self._ghost_shown: dict[str, tuple[np.ndarray, str]] = {}  # each ghost's pose and kind
        self.dragger = scene.add_transform_controls(
            "/dragger", scale=GIZMO_PX, fixed=True, depth_test=False, visible=False
        )
        self.dragger.on_update(lambda e: self.on_drag(e.phase))
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
        set_pose(frustum, cam.X_WC)
        self.link_frames = {}
        for link in self.robot.links.values():
            frame = scene.add_frame(f"/robot/{link.name}", show_axes=False)
            self.link_frames[link.name] = frame
            for k, v in enumerate(link.visuals):
                name = f"/robot/{link.name}/visual_{k}"
                color = rgb255(v.rgba)
                if v.kind == "box":
                    h = scene.add_box(name, color=color, dimensions=tuple(v.size))
                elif v.kind == "cylinder":
                    h = scene.add_cylinder(name, radius=v.size[0], height=v.size[1], color=color)
                else:
                    h = scene.add_icosphere(name, radius=v.size[0], color=color)
                set_pose(h, v.X_LV)
        self._show_robot(self.scene.robot.q_home_rad, 0.04)

    def set_view(self, view: str, client: viser.ClientHandle | None = None) -> None:
        """Put ``client``'s camera (default: every browser's) in ``view`` (:data:`VIEWS`);
        from above, over the workpiece when one is picked."""
        if view == "from above":
            name = self.session.workpiece
            target = self.session.X_WO[name][:3, 3] if name is not None else None
            eye, look_at = view_from_above_W(self.scene, target)
        elif view == "from the start":
            eye, look_at = initial_view_W(self.scene)
        else:
            raise ValueError(f"view must be one of {VIEWS}, not {view!r}")
        clients = [client] if client is not None else self.server.get_clients().values()
        for c in clients:
            c.camera.position = tuple(eye)
            c.camera.look_at = tuple(look_at)
            c.camera.up_direction = (0.0, 0.0, 1.0)

    def set_shadows(self, on: bool) -> None:
        """Shadows in the 3D view (a cue for contact; costly without a graphics card)."""
        self.server.scene.configure_default_lights(True, cast_shadow=on)

    def _show_robot(self, q: np.ndarray, opening_m: float) -> None:
        """The arm at joint angles ``q`` (rad) and finger opening (m), redrawn only when it
        moved: an arm at rest sends the browsers nothing."""
        q = np.asarray(q, dtype=np.float64)
        if self._shown_q is not None:
            shown_q, shown_opening_m = self._shown_q
            if (
                np.max(np.abs(q - shown_q)) < ROBOT_SHOWN_RAD
                and abs(opening_m - shown_opening_m) < FINGERS_SHOWN_M
            ):
                return
        self._shown_q = (q.copy(), float(opening_m))
        poses = self.robot.link_poses_W(q, opening_m, self.scene.robot.X_WB)
        with self.server.atomic():
            for name, X_WL in poses.items():
                set_pose(self.link_frames[name], X_WL)

    def _show_model(self) -> None:
        """Show the model's objects where it has them; hide the rest."""
        for obj in self.scene.objects:
            frame = self.object_frames[obj.name]
            in_model = obj.fixed or obj.name in self.model.poses
            frame.visible = in_model
            if in_model:
                set_pose(frame, self.session.X_WO.get(obj.name, obj.X_WO))
        self.workpiece_dropdown.options = self._workpiece_options()
        self.reference_dropdown.options = self._reference_options()
        if self.reference_dropdown.value != self.op.reference:
            self.reference_dropdown.value = self.op.reference

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

    def _ghost_kinds(self, recognitions) -> dict[str, tuple[object, str]]:
        """For each recognised block of the scene (``name``, or ``name#2`` for a second one):
        its recognition and how far it is from the model (a key of ``GHOST_RGBS``)."""
        known = {o.name for o in self.scene.movable}
        counts: dict[str, int] = {}
        kinds: dict[str, tuple[object, str]] = {}
        for r in recognitions:
            if r.model not in known:
                continue
            counts[r.model] = counts.get(r.model, 0) + 1
            tag = r.model if counts[r.model] == 1 else f"{r.model}#{counts[r.model]}"
            X_model = self.model.poses.get(r.model)
            if X_model is None:
                kind = disagreement(None, None)
            else:
                kind = disagreement(*pose_error(X_model, r.X_WO, self.model.symmetries(r.model)))
            kinds[tag] = (r, kind)
        return kinds

    def _show_ghosts(self, recognitions) -> dict[str, str]:
        """What vision sees now, see-through, coloured by how far it is from the model; for
        each recognised block (``name`` or ``name#2`` for a second one), its colour's key."""
        known = {o.name: o.model for o in self.scene.movable}
        seen: dict[str, str] = {}
        for tag, (r, kind) in self._ghost_kinds(recognitions).items():
            seen[tag] = kind
            # A block vision lost for a frame or two comes back: its ghost is shown again, not
            # sent again (its meshes are most of what a ghost costs the browsers).
            lost = self._lost_ghosts.pop(tag, None)
            if lost is not None:
                self.ghosts[tag] = lost
            elif tag not in self.ghosts:
                frame = self.server.scene.add_frame(f"/vision/{tag}", show_axes=False)
                meshes = [
                    self.server.scene.add_mesh_simple(
                        f"/vision/{tag}/part_{k}",
                        part.vertices_O,
                        part.triangles(),
                        color=GHOST_RGBS[kind],
                        opacity=GHOST_OPACITY,
                        flat_shading=True,
                        cast_shadow=False,
                        receive_shadow=False,
                    )
                    for k, part in enumerate(known[r.model].parts)
                ]
                self.ghosts[tag] = (frame, meshes)
                self._ghost_shown.pop(tag, None)
            frame, meshes = self.ghosts[tag]
            shown = self._ghost_shown.get(tag)
            if shown is None or not _within(shown[0], r.X_WO, GHOST_REDRAW_M, GHOST_REDRAW_RAD):
                set_pose(frame, r.X_WO)
                shown = (np.array(r.X_WO), shown[1] if shown else None)
            if shown[1] != kind:
                for mesh in meshes:
                    mesh.color = GHOST_RGBS[kind]
            self._ghost_shown[tag] = (shown[0], kind)
            if lost is not None:
                frame.visible = True  # where it is now, in its colour now
        for tag in [t for t in self.ghosts if t not in seen]:
            self._lost_ghosts[tag] = self.ghosts.pop(tag)
            self._lost_ghosts[tag][0].visible = False
        return seen


def _within(X_a: np.ndarray, X_b: np.ndarray, distance_m: float, angle_rad: float) -> bool:
    """Whether two poses are within ``distance_m`` and ``angle_rad`` of each other."""
    if np.linalg.norm(X_a[:3, 3] - X_b[:3, 3]) > distance_m:
        return False
    return float(np.linalg.norm(so3_log(X_a[:3, :3].T @ X_b[:3, :3]))) <= angle_rad
