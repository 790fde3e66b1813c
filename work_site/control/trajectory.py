"""Spatially-linear Cartesian moves (§III-A): a straight line in position and the shortest arc in
orientation, timed by one trapezoidal profile so that both arrive together."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from models.transforms import make_pose, so3_exp, so3_log


@dataclass(frozen=True)
class LinearMove:
    """From ``X_start`` to ``X_goal`` (4×4, same frame) within speed and acceleration limits.

    ``v_max_mps``/``a_max_mps2`` bound the translation, ``w_max_rps``/``alpha_max_rps2`` the
    rotation; the path parameter follows a trapezoid (or triangle, for short moves).
    """

    X_start: np.ndarray
    X_goal: np.ndarray
    v_max_mps: float
    a_max_mps2: float
    w_max_rps: float = 1.0
    alpha_max_rps2: float = 4.0
    duration_s: float = field(init=False)
    _profile: tuple[float, float, float] = field(init=False, repr=False)  # v̂, â, t_acc

    def __post_init__(self) -> None:
        for name in ("v_max_mps", "a_max_mps2", "w_max_rps", "alpha_max_rps2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"LinearMove.{name} must be finite and > 0, got {value}")
        length = float(np.linalg.norm(self.X_goal[:3, 3] - self.X_start[:3, 3]))
        angle = float(np.linalg.norm(self._rotvec))
        # Limits on s ∈ [0, 1]: the tighter of translation and rotation.
        v = min(
            self.v_max_mps / length if length > 0 else math.inf,
            self.w_max_rps / angle if angle > 0 else math.inf,
        )
        a = min(
            self.a_max_mps2 / length if length > 0 else math.inf,
            self.alpha_max_rps2 / angle if angle > 0 else math.inf,
        )
        if math.isinf(v):  # no motion at all
            object.__setattr__(self, "duration_s", 0.0)
            object.__setattr__(self, "_profile", (0.0, 0.0, 0.0))
            return
        if v * v / a >= 1.0:  # triangle: never reaches v
            t_acc = math.sqrt(1.0 / a)
            v = a * t_acc
            duration = 2 * t_acc
        else:
            t_acc = v / a
            duration = 1.0 / v + t_acc
        object.__setattr__(self, "duration_s", duration)
        object.__setattr__(self, "_profile", (v, a, t_acc))

    @property
    def _rotvec(self) -> np.ndarray:
        return so3_log(self.X_start[:3, :3].T @ self.X_goal[:3, :3])

    def s_at(self, t_s: float) -> float:
        """Path parameter in [0, 1] at time ``t_s`` after the start."""
        v, a, t_acc = self._profile
        T = self.duration_s
        if T == 0.0 or t_s >= T:
            return 1.0
        if t_s <= 0.0:
            return 0.0
        if t_s < t_acc:
            return 0.5 * a * t_s * t_s
        if t_s > T - t_acc:
            r = T - t_s
            return 1.0 - 0.5 * a * r * r
        return 0.5 * a * t_acc * t_acc + v * (t_s - t_acc)

    def pose_at(self, t_s: float) -> np.ndarray:
        """The commanded pose at time ``t_s``."""
        s = self.s_at(t_s)
        p = self.X_start[:3, 3] + s * (self.X_goal[:3, 3] - self.X_start[:3, 3])
        R = self.X_start[:3, :3] @ so3_exp(s * self._rotvec)
        return make_pose(R, p)
