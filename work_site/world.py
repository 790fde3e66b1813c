"""The work site's reality: a pybullet world with the arm, gripper, wrist sensor and blocks.

This stands in for the real robot and blocks. Everything outside this module talks to it in our
frames (poses ``X_WO`` of URDF link frames); pybullet's inertial-frame poses and ``xyzw``
quaternions are converted here and nowhere else.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p

from models.geometry import mass_properties, write_obj
from models.robot import FT_SENSOR_JOINT
from models.scene import GRAVITY_W, Scene, SceneObject
from models.transforms import (
    R_to_quat_wxyz,
    invert_pose,
    make_pose,
    quat_wxyz_to_R,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
)

ARM_JOINTS = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6")
FINGER_JOINTS = ("finger_left", "finger_right")
FLANGE_LINK = "flange"
ARM_MAX_FORCE_N = 300.0
FINGER_MAX_FORCE_N = 40.0
FINGER_OPEN_SPEED_MPS = 0.05
"""The fastest each finger opens (m/s), as a parallel gripper's drive does. Unlimited, the
fingers spring open within a few 1 ms steps: a pad that lets go a step before the other leaves
the whole grip on the block for that step, and a block gripped a fraction of a degree askew
is thrown centimetres from where it was set down. Closing and squeezing are left to the force
limit: limited as well, the slower grasp changed how a held cube pressed the L-block it was set
on, dragging the L-block along (docs/tuning.md)."""
FINGER_COUPLING_MAX_FORCE_N = 200.0
FINGER_LOCK_MAX_FORCE_N = 200.0
MOVABLE_MASS_RANGE_KG = (0.005, 1.0)
"""Masses of movable objects a scene may give (kg): what the gripper holds and the wrist weighs
well within the hard force limit; lighter bodies, against the arm's, make the solver stiff."""
FINGER_PAD_FRICTION = 2.0
"""Rubber finger pads: pybullet multiplies it with the wood's default 0.5, at which a carried
block slides in the grip."""
FINGER_PAD_FRICTION_ANCHOR = True
"""pybullet's friction anchors on the pads (positional friction correction) while the fingers
close and hold: without them its velocity-level friction lets the held cube creep about the
grip axis under loads far below the slip torque. Off while the fingers open."""
BLOCK_FRICTION_ANCHOR = True
"""The same for the movable blocks' contacts: without them a block resting on the table turns
by itself, the wedge (its weight off its base's centre) over half a degree a minute, and the
world drifts from what vision saw while the operator plans."""
SERVO_POSITION_GAIN = 0.3
"""pybullet's joint servo gain (its default is 0.1): higher tracks the TCP line more closely, but
a servo that closes its whole error in one 1 ms step rings against the stiff contacts, and the
wrist force with it."""
ENV_CONTACT_STIFFNESS_N_PER_M = 1e4
"""Contact stiffness of the fixed environment (table, frame): wood backed by a robot that is
not infinitely stiff. pybullet's default rigid contact answers a touch with a spike within one
1 ms step, which no force guard can catch."""
ENV_CONTACT_DAMPING_N_S_PER_M = 100.0
"""Damping of those contacts: enough that a touch does not bounce."""
PAD_CONTACT_STIFFNESS_N_PER_M = 2e5
"""Contact stiffness of the finger pads (rubber; per contact point, four a pad). Rigid pads
hold the cube on two diagonally opposite corners, a hinge about which it turns in contact
moves; compliant, each pad presses on all four corners of its overlap with the cube. Softer
still, a held block lags the gripper when it turns about the vertical, and the lag stays."""
PAD_CONTACT_DAMPING_N_S_PER_M = 100.0
"""Damping of the pads' contacts: about critical for the held cube on four such points."""


FINGER_OVERCLOSE_TOL_M = 2e-4
"""Closed on nothing, the coupled fingers settle a hair past zero, a little further with closed
fingertips pressed onto the table, where the gear constraint gives."""


def _opening(sum_m: float) -> float:
    """The finger opening from the two finger positions; a closure past zero within
    FINGER_OVERCLOSE_TOL_M reads as closed, beyond it is a fault in the model."""
    if sum_m < -FINGER_OVERCLOSE_TOL_M:
        raise RuntimeError(f"gripper fingers closed past each other ({sum_m:.3g} m)")
    return max(float(sum_m), 0.0)


def pose_from_pybullet(position, quat_xyzw) -> np.ndarray:
    """A 4×4 pose from pybullet's position and ``xyzw`` quaternion."""
    return make_pose(quat_wxyz_to_R(quat_xyzw_to_wxyz(quat_xyzw)), position)


def pose_to_pybullet(X: np.ndarray) -> tuple[list[float], list[float]]:
    """pybullet's (position, ``xyzw`` quaternion) from a 4×4 pose."""
    return X[:3, 3].tolist(), quat_wxyz_to_xyzw(R_to_quat_wxyz(X[:3, :3])).tolist()


@dataclass(frozen=True)
class RobotSnapshot:
    """What the arm reports: joint angles (rad), flange pose, finger opening (m), sensor wrench."""

    q: np.ndarray
    X_WF: np.ndarray
    gripper_opening_m: float
    wrench_S: np.ndarray


def check_object_mass(obj: SceneObject) -> None:
    """ValueError naming the range when movable ``obj``'s mass is outside
    :data:`MOVABLE_MASS_RANGE_KG`."""
    low, high = MOVABLE_MASS_RANGE_KG
    mass = obj.model.mass_kg
    if not obj.fixed and not low <= mass <= high:
        raise ValueError(
            f"object {obj.name!r}: mass {mass} kg is not in [{low}, {high}] kg, the movable "
            "masses this work site grasps and weighs"
        )


def check_scene(scene: Scene) -> None:
    """ValueError naming the object and the limit when a scene's values are out of range."""
    for obj in scene.objects:
        check_object_mass(obj)


class World:
    """A pybullet simulation of a scene, stepped explicitly (no real-time mode).

    Uses its own physics client (``DIRECT`` unless ``gui``); every pybullet call names it.
    """

    def __init__(self, scene: Scene, *, time_step_s: float = 1e-3, gui: bool = False) -> None:
        if not 0 < time_step_s <= 0.01:
            raise ValueError(f"time_step_s must be in (0, 0.01] s, got {time_step_s}")
        self.scene = scene
        self.time_step_s = time_step_s
        self.time_s = 0.0
        self.cid = p.connect(p.GUI if gui else p.DIRECT)
        p.setGravity(*GRAVITY_W, physicsClientId=self.cid)
        p.setTimeStep(time_step_s, physicsClientId=self.cid)
        # Polyhedral contacts (SAT, not GJK): a face on a face gives the corners of their overlap
        # at every step, where GJK gives one arbitrary point a step and false depths at edges.
        p.setPhysicsEngineParameter(enableSAT=1, physicsClientId=self.cid)
        self.bodies: dict[str, int] = {}
        self._X_OI: dict[str, np.ndarray] = {}  # inertial frame in the object frame
        with tempfile.TemporaryDirectory(prefix="telerobot-meshes-") as tmp:
            for obj in scene.objects:
                body = self._create_body(obj, Path(tmp))
                self.bodies[obj.name] = body
                info = p.getDynamicsInfo(body, -1, physicsClientId=self.cid)
                self._X_OI[obj.name] = pose_from_pybullet(info[3], info[4])
                self.set_object_pose(obj.name, obj.X_WO)
        self.robot = self._load_robot()

    def _create_body(self, obj: SceneObject, tmp: Path) -> int:
        """A pybullet body whose collision shape is the model's convex parts, exactly.

        With polyhedral (SAT) features pybullet clips the polyhedra themselves and leaves out
        the collision margin, so the parts are not shrunk by it.
        """
        check_object_mass(obj)
        model = obj.model
        collision_files, visual_files = [], []
        for k, part in enumerate(model.parts):
            for files, V, kind in (
                (collision_files, part.vertices_O, "c"),
                (visual_files, part.vertices_O, "v"),
            ):
                path = tmp / f"{obj.name}_{k}_{kind}.obj"
                write_obj(path, V, [list(f) for f in part.faces], f"{obj.name} part {k}")
                files.append(str(path))
        n = len(model.parts)
        collision = p.createCollisionShapeArray(
            [p.GEOM_MESH] * n,
            fileNames=collision_files,
            flags=[p.URDF_INITIALIZE_SAT_FEATURES] * n,
            physicsClientId=self.cid,
        )
        visual = p.createVisualShapeArray(
            [p.GEOM_MESH] * n, fileNames=visual_files, physicsClientId=self.cid
        )
        _, com_O, inertia_per_density = mass_properties(list(model.parts))
        density = model.mass_kg / model.volume_m3
        moments, R_OI = np.linalg.eigh(density * inertia_per_density)
        if np.linalg.det(R_OI) < 0:
            R_OI[:, 2] *= -1
        _, quat_OI = pose_to_pybullet(make_pose(R_OI))
        body = p.createMultiBody(
            baseMass=0.0 if obj.fixed else model.mass_kg,
            baseCollisionShapeIndex=collision,
            baseVisualShapeIndex=visual,
            baseInertialFramePosition=com_O.tolist(),
            baseInertialFrameOrientation=quat_OI,
            physicsClientId=self.cid,
        )
        if not obj.fixed:
            p.changeDynamics(
                body,
                -1,
                localInertiaDiagonal=moments.tolist(),
                frictionAnchor=BLOCK_FRICTION_ANCHOR,
                physicsClientId=self.cid,
            )
        else:
            p.changeDynamics(
                body,
                -1,
                contactStiffness=ENV_CONTACT_STIFFNESS_N_PER_M,
                contactDamping=ENV_CONTACT_DAMPING_N_S_PER_M,
                physicsClientId=self.cid,
            )
        p.changeVisualShape(body, -1, rgbaColor=list(model.rgba), physicsClientId=self.cid)
        return body

    def _load_robot(self) -> int:
        placement = self.scene.robot
        position, quat = pose_to_pybullet(placement.X_WB)
        robot = p.loadURDF(
            str(placement.urdf_path),
            position,
            quat,
            useFixedBase=True,
            flags=p.URDF_USE_INERTIA_FROM_FILE | p.URDF_INITIALIZE_SAT_FEATURES,
            physicsClientId=self.cid,
        )
        joints, links = {}, {}
        for j in range(p.getNumJoints(robot, physicsClientId=self.cid)):
            info = p.getJointInfo(robot, j, physicsClientId=self.cid)
            joints[info[1].decode()] = j
            links[info[12].decode()] = j
        missing = [n for n in (*ARM_JOINTS, *FINGER_JOINTS, FT_SENSOR_JOINT) if n not in joints]
        if missing or FLANGE_LINK not in links:
            raise ValueError(
                f"{placement.urdf_path}: robot lacks joints {missing} or link {FLANGE_LINK!r}"
            )
        self.arm_joints = [joints[n] for n in ARM_JOINTS]
        self.finger_joints = [joints[n] for n in FINGER_JOINTS]
        self.ft_joint = joints[FT_SENSOR_JOINT]
        self.flange_link = links[FLANGE_LINK]
        p.enableJointForceTorqueSensor(robot, self.ft_joint, True, physicsClientId=self.cid)
        for j, q in zip(self.arm_joints, placement.q_home_rad, strict=True):
            p.resetJointState(robot, j, float(q), physicsClientId=self.cid)
        self.q_target = np.array(placement.q_home_rad, dtype=np.float64)
        self.q_dot_target = np.zeros(6)
        self.finger_target_m = 0.02
        for j in self.finger_joints:
            p.resetJointState(robot, j, self.finger_target_m, physicsClientId=self.cid)
        # A parallel gripper's fingers are coupled: two independently servoed fingers that both
        # saturate on a block leave it free to drift sideways between them.
        left, right = self.finger_joints
        gear = p.createConstraint(
            robot,
            left,
            robot,
            right,
            jointType=p.JOINT_GEAR,
            jointAxis=[0, 1, 0],
            parentFramePosition=[0, 0, 0],
            childFramePosition=[0, 0, 0],
            physicsClientId=self.cid,
        )
        p.changeConstraint(
            gear,
            gearRatio=-1,
            maxForce=FINGER_COUPLING_MAX_FORCE_N,
            erp=0.2,
            physicsClientId=self.cid,
        )
        self._gear = gear
        self.robot = robot
        self.fingers_locked = False
        self._fingers_opening = False
        self.unlock_fingers()
        for finger in self.finger_joints:
            p.changeDynamics(
                robot,
                finger,
                lateralFriction=FINGER_PAD_FRICTION,
                contactStiffness=PAD_CONTACT_STIFFNESS_N_PER_M,
                contactDamping=PAD_CONTACT_DAMPING_N_S_PER_M,
                frictionAnchor=FINGER_PAD_FRICTION_ANCHOR,
                physicsClientId=self.cid,
            )
        return robot

    def lock_fingers(self) -> None:
        """Hold the right finger where it is, uncoupled, while the left one keeps squeezing.

        pybullet leaves the gear constraint's force out of the wrist sensor joint's reaction,
        which a grip then shows as a false force. A held block needs no centring, so the grip
        is then one locked jaw and one pushing jaw (it holds against side forces up to the
        pushing motor's limit), and the sensor reads the held block's weight.
        """
        right = self.finger_joints[1]
        self._right_locked_m = p.getJointState(self.robot, right, physicsClientId=self.cid)[0]
        p.changeConstraint(self._gear, maxForce=0.0, physicsClientId=self.cid)
        self.fingers_locked = True

    def unlock_fingers(self) -> None:
        """Couple the fingers again (the right one follows the left through the gear)."""
        p.changeConstraint(
            self._gear, maxForce=FINGER_COUPLING_MAX_FORCE_N, physicsClientId=self.cid
        )
        p.setJointMotorControl2(
            self.robot,
            self.finger_joints[1],
            p.VELOCITY_CONTROL,
            force=0.0,
            physicsClientId=self.cid,
        )
        self.fingers_locked = False

    def set_object_pose(self, name: str, X_WO: np.ndarray) -> None:
        """Place object ``name`` so that its URDF link frame is at ``X_WO``; zero its velocity."""
        position, quat = pose_to_pybullet(X_WO @ self._X_OI[name])
        body = self.bodies[name]
        p.resetBasePositionAndOrientation(body, position, quat, physicsClientId=self.cid)
        p.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=self.cid)

    def object_pose(self, name: str) -> np.ndarray:
        """``X_WO``: the pose of object ``name``'s URDF link frame in W."""
        position, quat = p.getBasePositionAndOrientation(
            self.bodies[name], physicsClientId=self.cid
        )
        return pose_from_pybullet(position, quat) @ invert_pose(self._X_OI[name])

    def object_poses(self) -> dict[str, np.ndarray]:
        """``X_WO`` of every object, by name."""
        return {name: self.object_pose(name) for name in self.bodies}

    def step(self, n: int = 1) -> None:
        """Advance the simulation by ``n`` time steps, servoing the joints to their targets."""
        p.setJointMotorControlArray(
            self.robot,
            self.arm_joints,
            p.POSITION_CONTROL,
            targetPositions=self.q_target.tolist(),
            targetVelocities=self.q_dot_target.tolist(),
            positionGains=[SERVO_POSITION_GAIN] * 6,
            forces=[ARM_MAX_FORCE_N] * 6,
            physicsClientId=self.cid,
        )
        # One motor drives the left finger; the gear constraint mirrors it on the right.
        # pybullet keeps a motor's speed limit until it is given another: inf lifts it.
        left = self.finger_joints[0]
        opening = (
            self.finger_target_m > p.getJointState(self.robot, left, physicsClientId=self.cid)[0]
        )
        if opening != self._fingers_opening:
            # Opening pads let go with pybullet's velocity-level friction: their anchors
            # would hand the shear they hold back to the block as they leave it.
            for finger in self.finger_joints:
                p.changeDynamics(
                    self.robot,
                    finger,
                    frictionAnchor=FINGER_PAD_FRICTION_ANCHOR and not opening,
                    physicsClientId=self.cid,
                )
            self._fingers_opening = opening
        p.setJointMotorControl2(
            self.robot,
            left,
            p.POSITION_CONTROL,
            targetPosition=self.finger_target_m,
            force=FINGER_MAX_FORCE_N,
            maxVelocity=FINGER_OPEN_SPEED_MPS if opening else math.inf,
            physicsClientId=self.cid,
        )
        if self.fingers_locked:
            p.setJointMotorControl2(
                self.robot,
                self.finger_joints[1],
                p.POSITION_CONTROL,
                targetPosition=self._right_locked_m,
                force=FINGER_LOCK_MAX_FORCE_N,
                physicsClientId=self.cid,
            )
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.cid)
        self.time_s += n * self.time_step_s

    def robot_snapshot(self) -> RobotSnapshot:
        """The arm's joint angles, flange pose, gripper opening and wrist wrench right now.

        ``wrench_S`` is pybullet's joint reaction at the sensor joint, ``[fx, fy, fz, tx, ty, tz]``
        in N and N·m in the sensor frame S (the ft_sensor joint frame).
        """
        arm = p.getJointStates(self.robot, self.arm_joints, physicsClientId=self.cid)
        fingers = p.getJointStates(self.robot, self.finger_joints, physicsClientId=self.cid)
        sensor = p.getJointState(self.robot, self.ft_joint, physicsClientId=self.cid)
        flange = p.getLinkState(
            self.robot, self.flange_link, computeForwardKinematics=True, physicsClientId=self.cid
        )
        return RobotSnapshot(
            q=np.array([s[0] for s in arm]),
            X_WF=pose_from_pybullet(flange[4], flange[5]),
            gripper_opening_m=_opening(sum(s[0] for s in fingers)),
            wrench_S=np.array(sensor[2], dtype=np.float64),
        )

    def robot_joint_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Arm joint angles (6,) rad and finger positions (2,) m, for rendering elsewhere."""
        arm = p.getJointStates(self.robot, self.arm_joints, physicsClientId=self.cid)
        fingers = p.getJointStates(self.robot, self.finger_joints, physicsClientId=self.cid)
        return np.array([s[0] for s in arm]), np.array([s[0] for s in fingers])

    def set_robot_joint_positions(self, q: np.ndarray, fingers_m: np.ndarray) -> None:
        """Teleport the arm (6,) rad and fingers (2,) m, as a renderer mirroring another world."""
        for j, v in zip(self.arm_joints + self.finger_joints, [*q, *fingers_m], strict=True):
            p.resetJointState(self.robot, j, float(v), physicsClientId=self.cid)

    def close(self) -> None:
        """Disconnect the physics client (idempotent)."""
        if self.cid >= 0 and p.isConnected(physicsClientId=self.cid):
            p.disconnect(physicsClientId=self.cid)
        self.cid = -1
