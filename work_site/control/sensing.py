"""The wrist force sensor, read as the force the world exerts on the gripper and what it holds.

pybullet reports the sensor joint's reaction ``wrench_S``: the force the flange exerts on the
sensor's child link, in the sensor frame S. Held still in free space it carries the weight of
everything beyond the sensor (``m_hand``, the model's masses of those links), so the external
force on the hand, in W, is ``−R_WS f_S − m_hand g_W`` (checked by applying known forces in
tests/test_control_force.py).

The held block's weight is measured once it hangs free and removed until the fingers open
(§VI-B: payload gravity compensated in the wrench). The fingers' gear coupling must be off while
holding (see ``World.lock_fingers``): pybullet leaves its force out of this reaction.
"""

from __future__ import annotations

import numpy as np

from models.robot import FT_SENSOR_JOINT, RobotModel
from models.scene import GRAVITY_W
from work_site.world import RobotSnapshot


class WristSensor:
    """External force on the hand (N, in W), with the hand's and the payload's weight removed."""

    def __init__(self, robot: RobotModel) -> None:
        self.hand_mass_kg = robot.mass_beyond_kg(FT_SENSOR_JOINT)
        self._hand_weight_W = self.hand_mass_kg * np.asarray(GRAVITY_W, dtype=np.float64)
        self.payload_W = np.zeros(3)
        """The held payload's weight (N, in W), as last measured by :meth:`tare`."""

    def force_W(self, snapshot: RobotSnapshot) -> np.ndarray:
        """External force on hand + payload (N, W), payload weight removed."""
        R_WS = snapshot.X_WF[:3, :3]  # the sensor joint is fixed at the flange, unrotated
        return -R_WS @ snapshot.wrench_S[:3] - self._hand_weight_W - self.payload_W

    def torque_W(self, snapshot: RobotSnapshot) -> np.ndarray:
        """Torque on hand + payload about the sensor's origin (N·m, W), their weights included:
        what two readings in one orientation of the hand differ by is what changed between them
        (a block taken up: its weight's moment)."""
        return -snapshot.X_WF[:3, :3] @ snapshot.wrench_S[3:]

    def tare(self, force_W: np.ndarray) -> float:
        """Take ``force_W`` (mean :meth:`force_W`, held still and free of contact) as the
        payload's weight; returns the payload's mass (kg)."""
        self.payload_W = self.payload_W + np.asarray(force_W, dtype=np.float64)
        return self.payload_mass_kg

    @property
    def payload_mass_kg(self) -> float:
        """The held payload's mass as last weighed (kg; 0 when nothing is held)."""
        return float(-self.payload_W[2] / np.linalg.norm(GRAVITY_W))

    def clear_payload(self) -> None:
        """The fingers have opened: nothing is held."""
        self.payload_W = np.zeros(3)
