"""The page's 3D view: the work site's objects, the robot, the camera, the dragger, the
contacts, the gripper's fingers on the workpiece and the paths. Poses go to viser as position
+ ``wxyz`` quaternion, converted by ``models.transforms``, never inline."""

from __future__ import annotations

import numpy as np
import viser

from models.robot import RobotModel
from models.scene import Scene
from models.transforms import R_to_quat_wxyz
from operator_site.model_editor import WorkSiteModel
from operator_site.task import TaskSession

CONTACT_RGB = (230, 40, 40)
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
LABEL_ABOVE_M = 0.01
"""A block's name floats this far above its top."""


def block_label(name: str) -> str:
    """A block's name as the page writes it ("tall block" for ``tall_block``)."""
    return name.replace("_", " ")


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

    def _show_robot(self, q: np.ndarray, opening_m: float) -> None:
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
