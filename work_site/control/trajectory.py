"""Spatially-linear Cartesian moves (§III-A): a straight line in position and the shortest arc in
orientation, timed by one trapezoidal profile so that both arrive together."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from models.transforms import make_pose, so3_exp, so3_log


class _Trapezoid:
    """A path parameter s from 0 to 1 on a trapezoidal (or, short, triangular) profile; the
    subclass, a frozen dataclass, has the fields ``duration_s`` and ``_profile``."""

    duration_s: float
    _profile: tuple[float, float, float]

    def _set_profile(self, v: float, a: float) -> None:
        """Time s with rate at most ``v`` (1/s) and acceleration at most ``a`` (1/s²)."""
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


@dataclass(frozen=True)
class LinearMove(_Trapezoid):
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
        self._set_profile(v, a)

    @property
    def _rotvec(self) -> np.ndarray:
        return so3_log(self.X_start[:3, :3].T @ self.X_goal[:3, :3])

    def pose_at(self, t_s: float) -> np.ndarray:
        """The commanded pose at time ``t_s``."""
        s = self.s_at(t_s)
        p = self.X_start[:3, 3] + s * (self.X_goal[:3, 3] - self.X_start[:3, 3])
        R = self.X_start[:3, :3] @ so3_exp(s * self._rotvec)
        return make_pose(R, p)


@dataclass(frozen=True)
class JointMove(_Trapezoid):
    """From joints ``q_start`` to ``q_goal`` (rad) on the straight line in joint space, no joint
    faster than ``w_max_rps`` nor accelerating more than ``alpha_max_rps2``: the empty hand's
    way to where a straight TCP move cannot take it."""

    q_start: np.ndarray
    q_goal: np.ndarray
    w_max_rps: float
    alpha_max_rps2: float
    duration_s: float = field(init=False)
    _profile: tuple[float, float, float] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("w_max_rps", "alpha_max_rps2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"JointMove.{name} must be finite and > 0, got {value}")
        turn = float(np.max(np.abs(np.asarray(self.q_goal) - np.asarray(self.q_start))))
        if turn > 0:
            self._set_profile(self.w_max_rps / turn, self.alpha_max_rps2 / turn)
        else:
            self._set_profile(math.inf, math.inf)

    def q_at(self, t_s: float) -> np.ndarray:
        """The commanded joints (rad) at time ``t_s``."""
        return self.q_start + self.s_at(t_s) * (self.q_goal - self.q_start)
