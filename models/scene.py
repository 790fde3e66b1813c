"""One typed view of a work-site scene for both sites: objects, their convex parts, the camera.

``load_scene()`` reads a scene JSON (default: ``models/scenes/puzzle.json``) and every file it
names; anything missing or malformed raises :class:`ModelError` naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.errors import ModelError
from models.geometry import (
    ConvexPart,
    check_no_interpenetration,
    feature_edges,
    make_convex_part,
    mass_properties,
    read_obj,
    shape_symmetries,
)
from models.transforms import ROTATION_ORTHONORMAL_TOL, is_rigid_transform, make_pose, rpy_to_R

GRAVITY_W = (0.0, 0.0, -9.81)
"""Gravity (m/s², W): the work site's physics, and what both sites take off the wrist's
reading as the hand's and the block's weight."""

MODELS_DIR = Path(__file__).resolve().parent
DEFAULT_SCENE = MODELS_DIR / "scenes" / "puzzle.json"
MAX_IMAGE_SIDE_PX = 8192


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """Geometry of one rigid object, in its frame O (the URDF base link frame).

    ``feature_edges_O``: (m, 2, 3) segment end points (m) where the surface creases, for vision.
    ``bbox_O``: (2, 3) min and max corner. ``com_O``: centre of mass (3,).
    """

    name: str
    urdf_path: Path
    parts: tuple[ConvexPart, ...]
    feature_edges_O: np.ndarray
    volume_m3: float
    mass_kg: float
    com_O: np.ndarray
    bbox_O: np.ndarray
    rgba: tuple[float, float, float, float]

    @functools.cached_property
    def symmetries(self) -> np.ndarray:
        """(s, 3, 3) rotations in O that map the shape onto itself, identity first: the ones
        of its corners (the feature edges' ends; part vertices include points where parts
        touch, which need not be symmetric)."""
        corners_O = np.unique(np.round(self.feature_edges_O.reshape(-1, 3), 9), axis=0)
        return shape_symmetries(corners_O)


@dataclass(frozen=True, eq=False)
class SceneObject:
    """An object placed in the scene at pose ``X_WO``; fixed objects are the environment."""

    name: str
    model: ObjectModel
    X_WO: np.ndarray
    fixed: bool


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A pinhole camera with OpenCV conventions: ``K`` (3, 3) px, ``dist`` (5,), pose ``X_WC``."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    X_WC: np.ndarray
    frame_rate_hz: float

    def to_json(self) -> dict:
        """The camera JSON of docs/design.md (plus ``frame_rate_hz``)."""
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "X_WC": self.X_WC.tolist(),
            "frame_rate_hz": self.frame_rate_hz,
        }

    def scaled(self, factor: float) -> CameraModel:
        """The same camera with its image resized by ``factor`` (e.g. 0.5: 640×480 → 320×240),
        pixel centres at integer coordinates before and after (as OpenCV's INTER_AREA)."""
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"camera scale factor must be finite and > 0, got {factor!r}")
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return dataclasses.replace(
            self, width=round(self.width * factor), height=round(self.height * factor), K=K
        )


@dataclass(frozen=True, eq=False)
class RobotPlacement:
    """The robot's URDF, base pose ``X_WB`` and home configuration ``q_home_rad`` (6,)."""

    urdf_path: Path
    X_WB: np.ndarray
    q_home_rad: np.ndarray


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything both sites agree on about a work site."""

    name: str
    path: Path
    objects: tuple[SceneObject, ...]
    robot: RobotPlacement
    camera: CameraModel

    def object(self, name: str) -> SceneObject:
        """The object called ``name``; KeyError listing the known names otherwise."""
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise KeyError(
            f"no object {name!r} in scene {self.name!r} "
            f"(known: {', '.join(o.name for o in self.objects)})"
        )

    @property
    def movable(self) -> tuple[SceneObject, ...]:
        return tuple(o for o in self.objects if not o.fixed)


def _floats(text: str | None, n: int, where: str, default: str) -> np.ndarray:
    words = (text if text is not None else default).split()
    try:
        values = np.array([float(w) for w in words], dtype=np.float64)
    except ValueError as e:
        raise ModelError(f"{where}: cannot read numbers from {text!r}") from e
    if values.shape != (n,):
        raise ModelError(f"{where}: expected {n} numbers, got {len(values)} in {text!r}")
    if not np.all(np.isfinite(values)):
        raise ModelError(f"{where}: NaN or infinity in {text!r}")
    return values


def _origin(elem: ET.Element, where: str) -> np.ndarray:
    o = elem.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(o.get("xyz"), 3, f"{where} origin xyz", "0 0 0")
    rpy = _floats(o.get("rpy"), 3, f"{where} origin rpy", "0 0 0")
    return make_pose(rpy_to_R(rpy), xyz)


def _geometry_part(geom: ET.Element, urdf: Path, X_OV: np.ndarray, where: str) -> ConvexPart:
    mesh, box = geom.find("mesh"), geom.find("box")
    if mesh is not None:
        filename = mesh.get("filename")
        if not filename:
            raise ModelError(f"{where}: <mesh> without a filename")
        path = (urdf.parent / filename).resolve()
        if not path.is_file():
            raise ModelError(f"{where}: mesh file {path} does not exist")
        scale = _floats(mesh.get("scale"), 3, f"{where} mesh scale", "1 1 1")
        V, faces = read_obj(path)
        V = V * scale
        if np.prod(scale) < 0:
            faces = [f[::-1] for f in faces]
        source = str(path)
    elif box is not None:
        half = _floats(box.get("size"), 3, f"{where} box size", "") / 2
        if np.any(half <= 0):
            raise ModelError(f"{where}: box size must be positive")
        V = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
        source = where
    else:
        raise ModelError(
            f"{where}: only <mesh> (convex OBJ) and <box> collision shapes are "
            "supported for objects"
        )
    V = V @ X_OV[:3, :3].T + X_OV[:3, 3]
    return make_convex_part(V, faces, source)


def load_object(urdf_path: Path | str) -> ObjectModel:
    """Read an object URDF: one link whose collision elements are its convex parts."""
    urdf = Path(urdf_path).resolve()
    if not urdf.is_file():
        raise ModelError(f"{urdf}: object model file does not exist")
    try:
        root = ET.parse(urdf).getroot()
    except ET.ParseError as e:
        raise ModelError(f"{urdf}: not valid XML ({e})") from e
    links = root.findall("link")
    if len(links) != 1:
        raise ModelError(f"{urdf}: an object model must have exactly one link, got {len(links)}")
    collisions = links[0].findall("collision")
    if not collisions:
        raise ModelError(f"{urdf}: the link has no <collision> element")
    parts = []
    for k, col in enumerate(collisions):
        where = f"{urdf}: collision {k}"
        geom = col.find("geometry")
        if geom is None:
            raise ModelError(f"{where}: no <geometry>")
        parts.append(_geometry_part(geom, urdf, _origin(col, where), where))
    check_no_interpenetration(parts, str(urdf))
    volume, com, _ = mass_properties(parts)
    mass_elem = links[0].find("inertial/mass")
    mass = float(mass_elem.get("value", "nan")) if mass_elem is not None else 0.0
    if not math.isfinite(mass) or mass < 0:
        raise ModelError(f"{urdf}: inertial mass must be a finite number ≥ 0")
    color = links[0].find("visual/material/color")
    rgba = _floats(
        color.get("rgba") if color is not None else None, 4, f"{urdf} colour", "0.8 0.8 0.8 1"
    )
    V = np.vstack([p.vertices_O for p in parts])
    return ObjectModel(
        name=root.get("name") or urdf.stem,
        urdf_path=urdf,
        parts=tuple(parts),
        feature_edges_O=feature_edges(parts),
        volume_m3=volume,
        mass_kg=mass,
        com_O=com,
        bbox_O=np.array([V.min(axis=0), V.max(axis=0)]),
        rgba=tuple(float(c) for c in rgba),
    )


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise ModelError(f"{path}: {what} file does not exist")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ModelError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(data, dict):
        raise ModelError(f"{path}: expected a JSON object at the top level")
    return data


def _array(value, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ModelError(f"{where}: expected numbers of shape {shape}") from e
    if a.shape != shape:
        raise ModelError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{where}: NaN or infinity")
    return a


def _pose(value, where: str) -> np.ndarray:
    X = _array(value, (4, 4), where)
    if not is_rigid_transform(X, ROTATION_ORTHONORMAL_TOL):
        raise ModelError(
            f"{where}: not a rigid transform (rotation must be orthonormal with "
            "det +1, last row 0 0 0 1)"
        )
    return X


def load_camera(path: Path | str) -> CameraModel:
    """Read a camera JSON (docs/design.md format) and check it is usable."""
    path = Path(path).resolve()
    data = _read_json(path, "camera")
    for key in ("width", "height", "K", "dist", "X_WC"):
        if key not in data:
            raise ModelError(f"{path}: missing key {key!r}")
    w, h = data["width"], data["height"]
    for key, v in (("width", w), ("height", h)):
        if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= MAX_IMAGE_SIDE_PX:
            raise ModelError(f"{path}: {key} must be an integer in 1..{MAX_IMAGE_SIDE_PX}")
    K = _array(data["K"], (3, 3), f"{path}: K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] or K[2, 0]:
        raise ModelError(f"{path}: K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    rate = data.get("frame_rate_hz", 5.0)
    if not isinstance(rate, int | float) or not 0 < rate <= 1000:
        raise ModelError(f"{path}: frame_rate_hz must be a number in (0, 1000]")
    return CameraModel(
        width=w,
        height=h,
        K=K,
        dist=_array(data["dist"], (5,), f"{path}: dist"),
        X_WC=_pose(data["X_WC"], f"{path}: X_WC"),
        frame_rate_hz=float(rate),
    )


def load_scene(path: Path | str = DEFAULT_SCENE) -> Scene:
    """Read a scene JSON and every model it names (paths relative to the scene file)."""
    path = Path(path).resolve()
    data = _read_json(path, "scene")
    for key in ("name", "camera", "robot", "objects"):
        if key not in data:
            raise ModelError(f"{path}: missing key {key!r}")
    if not isinstance(data["objects"], list) or not data["objects"]:
        raise ModelError(f"{path}: 'objects' must be a non-empty list")
    models: dict[Path, ObjectModel] = {}
    objects = []
    for i, entry in enumerate(data["objects"]):
        where = f"{path}: objects[{i}]"
        if not isinstance(entry, dict) or not {"name", "model", "X_WO"} <= entry.keys():
            raise ModelError(f"{where}: needs 'name', 'model' and 'X_WO'")
        name = entry["name"]
        if not isinstance(name, str) or not name or any(o.name == name for o in objects):
            raise ModelError(f"{where}: name must be a unique non-empty string, got {name!r}")
        model_path = (path.parent / str(entry["model"])).resolve()
        if model_path not in models:
            models[model_path] = load_object(model_path)
        fixed = entry.get("fixed", False)
        if not isinstance(fixed, bool):
            raise ModelError(f"{where}: 'fixed' must be true or false")
        objects.append(SceneObject(name, models[model_path], _pose(entry["X_WO"], where), fixed))
    robot = data["robot"]
    if not isinstance(robot, dict) or "urdf" not in robot:
        raise ModelError(f"{path}: 'robot' must be an object with a 'urdf' path")
    robot_urdf = (path.parent / str(robot["urdf"])).resolve()
    if not robot_urdf.is_file():
        raise ModelError(f"{path}: robot model {robot_urdf} does not exist")
    placement = RobotPlacement(
        urdf_path=robot_urdf,
        X_WB=_pose(robot.get("X_WB", np.eye(4).tolist()), f"{path}: robot.X_WB"),
        q_home_rad=_array(robot.get("q_home_rad", [0.0] * 6), (6,), f"{path}: robot.q_home_rad"),
    )
    camera = load_camera(path.parent / str(data["camera"]))
    return Scene(
        name=str(data["name"]), path=path, objects=tuple(objects), robot=placement, camera=camera
    )


FRAME_DECIMALS = 9
"""The frame's walls are rounded to this many decimals of a metre, far below the model files'
precision, so that a frame placed at round coordinates has round walls (0.57, not 0.45 + 0.12 =
0.5700000000000001)."""

Box2 = tuple[tuple[float, float], tuple[float, float]]
"""An axis-aligned rectangle in W: ``((x0, x1), (y0, y1))`` m."""


def _part_boxes_W(scene: Scene, name: str) -> np.ndarray:
    """Axis-aligned boxes (parts, 2, 3) m in W of object ``name``'s convex parts, rounded to
    :data:`FRAME_DECIMALS`; ValueError unless its pose turns O's axes onto W's."""
    obj = scene.object(name)
    R = obj.X_WO[:3, :3]
    if not np.allclose(np.abs(R), np.round(np.abs(R)), atol=1e-9):
        raise ValueError(f"object {name!r} is not square with W's axes")
    boxes = []
    for part in obj.model.parts:
        V_W = part.vertices_O @ R.T + obj.X_WO[:3, 3]
        boxes.append([V_W.min(axis=0), V_W.max(axis=0)])
    return np.round(np.array(boxes), FRAME_DECIMALS)


def frame_outer_W(scene: Scene, name: str = "frame") -> Box2:
    """The frame's outer faces in W, ``((x0, x1), (y0, y1))`` m."""
    boxes = _part_boxes_W(scene, name)
    lo, hi = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


def frame_opening_W(scene: Scene, name: str = "frame") -> Box2:
    """The frame's inner walls in W, ``((x0, x1), (y0, y1))`` m: the faces of the first bars met
    going out from the centre of its outline along ±x and ±y; ValueError where there is none."""
    boxes = _part_boxes_W(scene, name)
    centre = (boxes[:, 0].min(axis=0) + boxes[:, 1].max(axis=0)) / 2
    walls = []
    for axis, across in ((0, 1), (1, 0)):
        # the parts that the line through the centre along ``axis`` passes through
        on_line = (boxes[:, 0, across] <= centre[across]) & (centre[across] <= boxes[:, 1, across])
        below = boxes[on_line & (boxes[:, 1, axis] <= centre[axis]), 1, axis]
        above = boxes[on_line & (boxes[:, 0, axis] >= centre[axis]), 0, axis]
        if below.size == 0 or above.size == 0:
            raise ValueError(f"object {name!r} has no wall on both sides along {'xy'[axis]}")
        walls.append((float(below.max()), float(above.min())))
    return walls[0], walls[1]


def frame_bar_height_m(scene: Scene, name: str = "frame") -> float:
    """How high the frame's bars stand above its base (m): above the table it stands on."""
    boxes = _part_boxes_W(scene, name)
    return float(np.round(boxes[:, 1, 2].max() - boxes[:, 0, 2].min(), FRAME_DECIMALS))
