"""Robot description: a small URDF kinematics reader and forward kinematics in numpy.

Frames follow Drake's monogram notation: ``X_WL`` is the pose of link frame L in world W,
``X_PJ`` a joint frame J in its parent link P, ``X_LV`` a visual shape V in its link L (4×4
float64). Link frames are the URDF link frames (not the centres of mass).

The product's arm is ``models/robots/puma.urdf`` (:data:`PUMA_URDF`): base frame B, flange F,
force/torque sensor S (the ``ft_sensor`` link and its joint frame), gripper TCP G.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from models.errors import ModelError
from models.transforms import make_pose, rpy_to_R

PUMA_URDF = Path(__file__).resolve().parent / "robots" / "puma.urdf"
"""The product's 6-DOF Puma-type arm with wrist F/T sensor and parallel-jaw gripper."""

HOME_Q: tuple[float, float, float, float, float, float] = (
    0.0,
    -0.5140397387422824,
    2.098725637427858,
    0.0,
    1.556906754904217,
    0.0,
)
"""Home arm configuration (rad) of the Puma: gripper z axis along −z of W, TCP G at
(0.18, 0, 0.40) m in W, elbow up (behind the base), wrist pitch ≈ 1.56 rad (far from the
q5 = 0 singularity). Out of the camera's view, so that the arm at rest hides no block from
vision. Found with the closed-form IK; ``tests/test_robot_model.py`` checks it with forward
kinematics and ``tests/test_work_site_world.py`` that the camera sees all of the layout region
past it."""

FLANGE_LINK = "flange"
SENSOR_LINK = "ft_sensor"
TCP_LINK = "gripper_tcp"
FT_SENSOR_JOINT = "ft_sensor_joint"
"""The wrist force sensor's joint: fixed at the flange, unrotated (sensor frame S)."""

JointType = Literal["revolute", "continuous", "prismatic", "fixed"]
ShapeKind = Literal["box", "cylinder", "sphere"]
_JOINT_TYPES: tuple[str, ...] = ("revolute", "continuous", "prismatic", "fixed")
_MOVING_TYPES: tuple[str, ...] = ("revolute", "continuous", "prismatic")
_AXIS_NORM_TOL = 1e-4
"""Largest accepted ``||axis| − 1|`` (4-digit axes like 0.7071 pass, then normalised)."""


def _frozen(a: np.ndarray) -> np.ndarray:
    """A float64 copy of ``a`` that cannot be written to (values in frozen dataclasses)."""
    out = np.array(a, dtype=np.float64)
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class Shape:
    """A primitive visual or collision shape V of a link L.

    ``size``: box → full edge lengths (x, y, z); cylinder → (radius, length) with its axis along
    the shape's z; sphere → (radius,). Metres. ``rgba`` is (1, 1, 1, 1) when the URDF gives none.
    """

    kind: ShapeKind
    size: tuple[float, ...]
    X_LV: np.ndarray
    rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)


@dataclass(frozen=True)
class Link:
    """A URDF link: inertial (mass kg, inertial frame I in L, inertia kg·m² about I) and shapes."""

    name: str
    mass: float
    X_LI: np.ndarray
    I_I: np.ndarray
    visuals: tuple[Shape, ...]
    collisions: tuple[Shape, ...]


@dataclass(frozen=True)
class Joint:
    """A URDF joint J: child frame = ``X_PJ`` (in parent P) moved by q about/along ``axis`` (in J).

    Limits are rad (revolute) or m (prismatic); ±inf for continuous and fixed joints.
    ``velocity`` rad/s or m/s, ``effort`` N·m or N (inf when unspecified). ``axis`` is a unit
    vector (zero for fixed joints).
    """

    name: str
    type: JointType
    parent: str
    child: str
    X_PJ: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    velocity: float
    effort: float

    def X_JC(self, q: float) -> np.ndarray:
        """Pose of the child link frame C in joint frame J at joint position q."""
        X = np.eye(4)
        if self.type in ("revolute", "continuous"):
            X[:3, :3] = _axis_angle_to_R(self.axis, q)
        elif self.type == "prismatic":
            X[:3, 3] = self.axis * q
        return X


@dataclass(frozen=True)
class RobotModel:
    """The unchanging description of a robot: links, joints in tree order, named joint groups.

    ``arm_joints`` are the revolute/continuous joints in order from the root; ``finger_joints`` the
    prismatic ones (a finger opening of d m puts each finger at d/2).
    """

    name: str
    source: Path
    root_link: str
    links: Mapping[str, Link]
    joints: tuple[Joint, ...]
    arm_joints: tuple[str, ...]
    finger_joints: tuple[str, ...]
    _joint_by_name: Mapping[str, Joint] = field(repr=False, compare=False)

    def joint(self, name: str) -> Joint:
        """The joint called ``name`` (KeyError if absent)."""
        return self._joint_by_name[name]

    @property
    def n_arm(self) -> int:
        """Number of arm joints."""
        return len(self.arm_joints)

    @property
    def q_lower(self) -> np.ndarray:
        """Lower arm joint limits, shape (n_arm,), rad."""
        return np.array([self.joint(n).lower for n in self.arm_joints])

    @property
    def q_upper(self) -> np.ndarray:
        """Upper arm joint limits, shape (n_arm,), rad."""
        return np.array([self.joint(n).upper for n in self.arm_joints])

    @property
    def v_max(self) -> np.ndarray:
        """Arm joint speed limits, shape (n_arm,), rad/s."""
        return np.array([self.joint(n).velocity for n in self.arm_joints])

    @property
    def effort_max(self) -> np.ndarray:
        """Arm joint effort limits, shape (n_arm,), N·m."""
        return np.array([self.joint(n).effort for n in self.arm_joints])

    def mass_beyond_kg(self, joint_name: str) -> float:
        """The mass of every link beyond joint ``joint_name`` (its child and descendants)."""
        children: dict[str, list[str]] = {}
        for j in self.joints:
            children.setdefault(j.parent, []).append(j.child)
        stack, total = [self.joint(joint_name).child], 0.0
        for _ in range(len(self.links)):  # a tree: each link once
            if not stack:
                break
            link = stack.pop()
            total += self.links[link].mass
            stack.extend(children.get(link, []))
        return total

    @property
    def finger_opening_max(self) -> float:
        """Widest gripper opening (m): twice the smallest finger upper limit."""
        if not self.finger_joints:
            return 0.0
        return 2.0 * min(self.joint(n).upper for n in self.finger_joints)

    def joint_positions(self, q_arm: np.ndarray, finger_opening_m: float = 0.0) -> dict[str, float]:
        """Every moving joint's position from the arm vector and the finger opening."""
        q = np.asarray(q_arm, dtype=np.float64)
        if q.shape != (self.n_arm,):
            raise ValueError(f"q_arm must have shape ({self.n_arm},), got {q.shape}")
        if not np.all(np.isfinite(q)) or not math.isfinite(finger_opening_m):
            raise ValueError("joint positions must be finite")
        positions = dict(zip(self.arm_joints, q.tolist(), strict=True))
        for name in self.finger_joints:
            positions[name] = 0.5 * float(finger_opening_m)
        return positions

    def link_poses_W(
        self,
        q_arm: np.ndarray,
        finger_opening_m: float = 0.0,
        X_WB: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Pose ``X_WL`` of every link frame L in W; ``X_WB`` is the root link pose (default I)."""
        positions = self.joint_positions(q_arm, finger_opening_m)
        X_WRoot = np.eye(4) if X_WB is None else np.array(X_WB, dtype=np.float64)
        if X_WRoot.shape != (4, 4):
            raise ValueError(f"X_WB must be 4×4, got {X_WRoot.shape}")
        poses = {self.root_link: X_WRoot}
        for j in self.joints:  # tree order: a joint's parent pose is always known
            X_JC = j.X_JC(positions.get(j.name, 0.0))
            poses[j.child] = poses[j.parent] @ j.X_PJ @ X_JC
        return poses

    def flange_pose_W(self, q_arm: np.ndarray, X_WB: np.ndarray | None = None) -> np.ndarray:
        """Pose ``X_WF`` of the flange frame F."""
        return self.link_poses_W(q_arm, 0.0, X_WB)[FLANGE_LINK]

    def tcp_pose_W(self, q_arm: np.ndarray, X_WB: np.ndarray | None = None) -> np.ndarray:
        """Pose ``X_WG`` of the gripper TCP frame G (the grasp centre)."""
        return self.link_poses_W(q_arm, 0.0, X_WB)[TCP_LINK]


def _axis_angle_to_R(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


class _Reader:
    """Parses one URDF file; every error names the file."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, problem: str) -> ModelError:
        return ModelError(f"{self.path}: {problem}")

    def floats(self, text: str | None, n: int, what: str, default: str | None = None) -> np.ndarray:
        """Parse n finite floats from an attribute value."""
        if text is None:
            if default is None:
                raise self.fail(f"{what}: missing")
            text = default
        try:
            values = np.array([float(t) for t in text.split()], dtype=np.float64)
        except ValueError:
            raise self.fail(f"{what}: not numbers: {text!r}") from None
        if values.shape != (n,):
            raise self.fail(f"{what}: expected {n} numbers, got {text!r}")
        if not np.all(np.isfinite(values)):
            raise self.fail(f"{what}: NaN or infinity in {text!r}")
        return values

    def scalar(self, el: ET.Element, attr: str, what: str, default: float | None = None) -> float:
        text = el.get(attr)
        if text is None and default is not None:
            return default
        return float(self.floats(text, 1, f"{what} {attr}")[0])

    def origin(self, parent: ET.Element, what: str) -> np.ndarray:
        """The pose given by an optional ``<origin xyz rpy>`` child (identity if absent)."""
        el = parent.find("origin")
        if el is None:
            return np.eye(4)
        xyz = self.floats(el.get("xyz"), 3, f"{what} origin xyz", default="0 0 0")
        rpy = self.floats(el.get("rpy"), 3, f"{what} origin rpy", default="0 0 0")
        return make_pose(rpy_to_R(rpy), xyz)

    def materials(self, root: ET.Element) -> dict[str, tuple[float, float, float, float]]:
        """Top-level named materials with a colour."""
        out = {}
        for el in root.findall("material"):
            color = el.find("color")
            if el.get("name") and color is not None:
                rgba = self.floats(color.get("rgba"), 4, f"material {el.get('name')!r} rgba")
                out[el.get("name")] = tuple(rgba.tolist())
        return out

    def shape(
        self,
        el: ET.Element,
        what: str,
        materials: Mapping[str, tuple[float, float, float, float]],
    ) -> Shape | None:
        """A box/cylinder/sphere shape, or None for a mesh (not used by our models)."""
        geometry = el.find("geometry")
        if geometry is None or len(geometry) != 1:
            raise self.fail(f"{what}: needs exactly one geometry")
        g = geometry[0]
        if g.tag == "box":
            size = tuple(self.floats(g.get("size"), 3, f"{what} box size").tolist())
        elif g.tag == "cylinder":
            size = (self.scalar(g, "radius", f"{what} cylinder"), self.scalar(g, "length", what))
        elif g.tag == "sphere":
            size = (self.scalar(g, "radius", f"{what} sphere"),)
        elif g.tag == "mesh":
            return None
        else:
            raise self.fail(f"{what}: unknown geometry {g.tag!r}")
        if min(size) <= 0.0:
            raise self.fail(f"{what}: {g.tag} dimensions must be positive, got {size}")
        rgba = (1.0, 1.0, 1.0, 1.0)
        mat = el.find("material")
        if mat is not None:
            color = mat.find("color")
            if color is not None:
                rgba = tuple(self.floats(color.get("rgba"), 4, f"{what} rgba").tolist())
            elif mat.get("name") in materials:
                rgba = materials[mat.get("name")]
            else:
                raise self.fail(f"{what}: undefined material {mat.get('name')!r}")
        return Shape(g.tag, size, _frozen(self.origin(el, what)), rgba)  # type: ignore[arg-type]

    def link(self, el: ET.Element, materials: Mapping) -> Link:
        """One ``<link>``: inertial (zero mass if absent), visual and collision primitives."""
        name = el.get("name")
        if not name:
            raise self.fail("a link has no name")
        mass, X_LI, I_I = 0.0, np.eye(4), np.zeros((3, 3))
        inertial = el.find("inertial")
        if inertial is not None:
            what = f"link {name!r} inertial"
            X_LI = self.origin(inertial, what)
            m_el, i_el = inertial.find("mass"), inertial.find("inertia")
            if m_el is None or i_el is None:
                raise self.fail(f"{what}: needs mass and inertia")
            mass = self.scalar(m_el, "value", f"{what} mass")
            i = {k: self.scalar(i_el, k, what) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
            I_I = np.array(
                [
                    [i["ixx"], i["ixy"], i["ixz"]],
                    [i["ixy"], i["iyy"], i["iyz"]],
                    [i["ixz"], i["iyz"], i["izz"]],
                ]
            )
        visuals = [self.shape(v, f"link {name!r} visual", materials) for v in el.findall("visual")]
        collisions = [
            self.shape(c, f"link {name!r} collision", materials) for c in el.findall("collision")
        ]
        return Link(
            name=name,
            mass=mass,
            X_LI=_frozen(X_LI),
            I_I=_frozen(I_I),
            visuals=tuple(s for s in visuals if s is not None),
            collisions=tuple(s for s in collisions if s is not None),
        )

    def joint(self, el: ET.Element, link_names: set[str]) -> Joint:
        """One ``<joint>``; limits are required for revolute and prismatic joints."""
        name = el.get("name")
        if not name:
            raise self.fail("a joint has no name")
        what = f"joint {name!r}"
        jtype = el.get("type")
        if jtype not in _JOINT_TYPES:
            raise self.fail(f"{what}: unsupported joint type {jtype!r} (know {_JOINT_TYPES})")
        ends = {}
        for tag in ("parent", "child"):
            e = el.find(tag)
            link = None if e is None else e.get("link")
            if link is None:
                raise self.fail(f"{what}: no {tag} link")
            if link not in link_names:
                raise self.fail(f"{what}: {tag} link {link!r} is not defined")
            ends[tag] = link
        axis = np.zeros(3)
        lower, upper, velocity, effort = -math.inf, math.inf, math.inf, math.inf
        if jtype in _MOVING_TYPES:
            axis_el = el.find("axis")
            axis = self.floats(
                None if axis_el is None else axis_el.get("xyz"), 3, f"{what} axis", "1 0 0"
            )
            norm = float(np.linalg.norm(axis))
            if abs(norm - 1.0) > _AXIS_NORM_TOL:  # pybullet scales prismatic travel by |axis|
                raise self.fail(f"{what}: axis {axis.tolist()} is not a unit vector")
            axis = axis / norm
            limit = el.find("limit")
            if limit is None and jtype != "continuous":
                raise self.fail(f"{what}: a {jtype} joint needs a <limit>")
            if limit is not None:
                velocity = self.scalar(limit, "velocity", f"{what} limit")
                effort = self.scalar(limit, "effort", f"{what} limit")
                if jtype != "continuous":
                    lower = self.scalar(limit, "lower", f"{what} limit", default=0.0)
                    upper = self.scalar(limit, "upper", f"{what} limit", default=0.0)
                    if lower > upper:
                        raise self.fail(f"{what}: lower limit {lower} > upper limit {upper}")
        return Joint(
            name=name,
            type=jtype,  # type: ignore[arg-type]
            parent=ends["parent"],
            child=ends["child"],
            X_PJ=_frozen(self.origin(el, what)),
            axis=_frozen(axis),
            lower=lower,
            upper=upper,
            velocity=velocity,
            effort=effort,
        )

    def tree_order(self, joints: list[Joint], link_names: list[str]) -> tuple[str, list[Joint]]:
        """Root link and joints in depth-first order from it; rejects loops and forests."""
        parent_joint: dict[str, Joint] = {}
        for j in joints:
            if j.child in parent_joint:
                raise self.fail(
                    f"link {j.child!r} is the child of two joints "
                    f"({parent_joint[j.child].name!r}, {j.name!r}): a kinematic loop"
                )
            parent_joint[j.child] = j
        for start in link_names:  # walking up from any link must end at a root
            seen, link = [start], start
            while link in parent_joint:
                link = parent_joint[link].parent
                if link in seen:
                    raise self.fail(f"kinematic loop through links {seen}")
                seen.append(link)
        roots = [n for n in link_names if n not in parent_joint]
        if len(roots) != 1:
            raise self.fail(f"expected one root link, found {roots}")
        children: dict[str, list[Joint]] = {n: [] for n in link_names}
        for j in joints:
            children[j.parent].append(j)
        ordered: list[Joint] = []
        stack = list(reversed(children[roots[0]]))
        while stack:  # depth-first, children in file order
            j = stack.pop()
            ordered.append(j)
            stack.extend(reversed(children[j.child]))
        return roots[0], ordered


def load_robot(path: str | Path) -> RobotModel:
    """Read a URDF (primitive shapes) into a :class:`RobotModel`.

    Raises :class:`ModelError` naming the file for a missing/unparsable file, unknown joint types,
    non-finite numbers, non-unit axes, undefined links, duplicate names, loops or several roots.
    """
    path = Path(path)
    r = _Reader(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise r.fail("file not found") from None
    except (OSError, ET.ParseError) as e:
        raise r.fail(f"cannot read URDF: {e}") from None
    if root.tag != "robot":
        raise r.fail(f"root element is <{root.tag}>, expected <robot>")
    materials = r.materials(root)
    links = [r.link(el, materials) for el in root.findall("link")]
    if not links:
        raise r.fail("no links")
    link_names = [lk.name for lk in links]
    if len(set(link_names)) != len(link_names):
        raise r.fail(f"duplicate link names in {link_names}")
    joints = [r.joint(el, set(link_names)) for el in root.findall("joint")]
    joint_names = [j.name for j in joints]
    if len(set(joint_names)) != len(joint_names):
        raise r.fail(f"duplicate joint names in {joint_names}")
    root_link, ordered = r.tree_order(joints, link_names)
    return RobotModel(
        name=root.get("name", path.stem),
        source=path,
        root_link=root_link,
        links={lk.name: lk for lk in links},
        joints=tuple(ordered),
        arm_joints=tuple(j.name for j in ordered if j.type in ("revolute", "continuous")),
        finger_joints=tuple(j.name for j in ordered if j.type == "prismatic"),
        _joint_by_name={j.name: j for j in ordered},
    )
