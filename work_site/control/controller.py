"""The task controller (§III-A, §VI-B): Cartesian moves of the gripper at 100 Hz over 1 kHz joint
servos, with the wrist force watched at every servo step.

Each control period the commanded TCP pose of the current :class:`LinearMove` is turned into
joint targets by the closed-form IK (nearest solution to the last target), with the joint
velocities that carry the move forward as feed-forward (pybullet's servo otherwise lags).

Force: every 1 ms servo step the wrist force (:class:`WristSensor`) is checked against the
move's force limit (never above :data:`HARD_FORCE_LIMIT_N`) and, for a guarded move, against its
guard; either stops the arm within that step. A contact move adds position-based impedance
(admittance): the commanded position is the path's plus an offset δ with ``K δ + B δ̇ = f``,
``f`` the measured external force, ``δ̇`` limited in norm (§VI-B: output-velocity limiting for
stable contact transitions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.robot import RobotModel
from models.transforms import invert_pose
from protocol.execution import NORMAL_STIFFNESS_N_PER_M
from work_site.control.kinematics import (
    BRANCH_JUMP_RAD,
    arm_geometry,
    geometric_jacobian_W,
    ik_tcp,
)
from work_site.control.sensing import WristSensor
from work_site.control.trajectory import JointMove, LinearMove
from work_site.world import World

CONTROL_PERIOD_S = 0.01
"""The task controller's period (§III-A: 100 Hz)."""
MAX_TCP_SPEED_MPS = 0.25
"""No move, however commanded, is faster than this."""
TCP_ACCEL_MPS2 = 0.5
JOINT_MOVE_RPS = 0.5
"""The fastest joint of a joint-space move turns at most this fast (rad/s) ..."""
JOINT_MOVE_ACCEL_RPS2 = 1.0
"""... and speeds up at most this fast (rad/s²)."""
HARD_FORCE_LIMIT_N = 40.0
"""No external force on the hand may exceed this, whatever a program asks (the arm stops)."""
FORCE_WINDOW_STEPS = 4
"""Guards and the admittance look at the mean of this many 1 ms readings: a servo setpoint
change while accelerating and a stop's deceleration each read as a one-step spike that is no
contact, and an even length cancels exactly the period-2 chatter of a block held against a wall
and the table (figures in docs/tuning.md)."""
LIMIT_WINDOW_STEPS = 10
"""The force limit looks at the mean of this many 1 ms readings, one control period: the limit is
about a sustained force, and in contact the stiff 1 kHz servo makes the readings chatter from
step to step at more than period 2, which the guards' shorter window lets through."""

EASE_M = 0.003
"""A safety stop in contact holds the hand this far back from it, along the contact force (m)."""
EASE_S = 0.1
"""How long the hand takes to ease off (s)."""
EASE_WEIGHT_COS = 0.7
"""A force within about 45° of straight down is taken for a payload's weight: no easing off."""
EASE_FROM_N = 1.5
"""A safety stop eases off when the external force exceeds this (N): above a resting block's
weight, which the table carries once the block is set down."""


@dataclass(frozen=True)
class Guard:
    """Stop the move as soon as the external force along ``direction_W`` (unit, W) exceeds
    ``threshold_n``."""

    direction_W: np.ndarray
    threshold_n: float


DEFAULT_SURFACE_STIFFNESS_N_PER_M = 5000.0
"""The work site's contact moves' stiffness along the contact surfaces (N/m); along the normals
it stays §VI-B's low 1,000 N/m. Stiffer than the paper's isotropic impedance because at 1,000 N/m
friction holds the block millimetres behind its path, which round the frame's outside corner
leaves its edge on the corner when the next face's bias begins. `work-site serve
--surface-stiffness 1000` gives the isotropic impedance back."""


@dataclass(frozen=True)
class Impedance:
    """Translational admittance of a contact move: ``stiffness`` (N/m) and ``damping`` (N·s/m),
    along the contact normals (``compliant_W``) or in every direction; the offset moves at most
    ``max_rate_mps``. Updated at every physics step Δt: in free space the offset returns
    without overshoot while K·Δt/B ≤ 1 (:meth:`step_gain`, checked when a move starts); in
    contact, discrete stability needs ``damping > (stiffness + k_env)·Δt/2`` with k_env the
    contacts' stiffness, and the default damping keeps a margin over it for a cube pressed into
    a corner (docs/tuning.md)."""

    stiffness_n_per_m: float = NORMAL_STIFFNESS_N_PER_M
    damping_n_s_per_m: float = 200.0
    max_rate_mps: float = 0.02
    """Twice the contact speed (10 mm/s), so that the offset can back away faster than the path
    presses on and a set-down onto the table stays under its force limit."""
    settled_offset_m: float = 2e-4
    """The move has settled once its offset stays within this of where it was over the last
    ``settled_ticks`` periods (above what the force's ripple moves it while pressed into a
    corner)."""
    settled_ticks: int = 10
    max_settle_s: float = 3.0
    compliant_W: np.ndarray | None = None
    """Projector (3, 3) onto the contact normals' span (:func:`compliant_projector`), along
    which ``stiffness_n_per_m`` holds; across it (along the surfaces) the stiffness is
    ``tangential_stiffness_n_per_m``."""
    tangential_stiffness_n_per_m: float | None = None
    """None: isotropic (§VI-B). Stiffer along the surfaces, friction no longer drags the block
    behind its path, while a contact the model missed still meets a spring, not a rigid arm."""
    max_press_n: float = 10.0
    """The spring along the contact normals presses with at most this force (N): stiffness × 2d,
    twice what it presses with when the model is right, so that where the real contact lies
    further than d past the hand's target (the block turned in the grip, a model off) the hand
    yields rather than pressing on until the move's force limit stops it."""
    press_caps: tuple[tuple[np.ndarray, float], ...] = ()
    """(unit normal, N): along each of these contact normals (into the workpiece) the spring
    presses with at most that force, as :data:`max_press_n` bounds the whole press: a movable
    object is pressed only as hard as verifying the contact needs."""

    def __post_init__(self) -> None:
        for name in (
            "stiffness_n_per_m",
            "damping_n_s_per_m",
            "max_rate_mps",
            "max_press_n",
            "settled_offset_m",
            "max_settle_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Impedance.{name} must be finite and > 0, got {value!r}")
        k_t = self.tangential_stiffness_n_per_m
        if k_t is not None and not (math.isfinite(k_t) and k_t > 0):
            raise ValueError(f"Impedance.tangential_stiffness_n_per_m must be > 0, got {k_t!r}")
        if not (isinstance(self.settled_ticks, int) and self.settled_ticks >= 1):
            raise ValueError(
                f"Impedance.settled_ticks must be an integer ≥ 1, got {self.settled_ticks!r}"
            )

    @property
    def stiffest_n_per_m(self) -> float:
        """The stiffer of its springs, along the normals or across them (N/m)."""
        return max(self.stiffness_n_per_m, self.tangential_stiffness_n_per_m or 0.0)

    def step_gain(self, dt_s: float) -> float:
        """K·Δt/B for the stiffer of its springs: the fraction of the offset one update of
        ``B δ̇ = −K δ`` takes back. Above 1 the offset overshoots zero each update (and swings
        without end from 2); :meth:`TaskController.start_move` refuses it."""
        return self.stiffest_n_per_m * dt_s / self.damping_n_s_per_m


NORMAL_RANK_TOL = 1e-3
"""Singular values of the stacked contact normals below this are not independent directions."""


def compliant_projector(normals_W: np.ndarray) -> np.ndarray:
    """The orthogonal projector (3, 3) onto the span of the rows of ``normals_W``."""
    N = np.asarray(normals_W, dtype=np.float64).reshape(-1, 3)
    if len(N) == 0:
        return np.zeros((3, 3))
    _, sv, Vt = np.linalg.svd(N, full_matrices=False)
    basis = Vt[sv > NORMAL_RANK_TOL * sv[0]]
    return basis.T @ basis


def carried_offset_W(offset_W: np.ndarray, impedance: Impedance) -> np.ndarray:
    """The part of the last contact move's offset δ (m, W) that the next one, with
    ``impedance``, keeps as its offset: the part along its contact normals when it is stiffer
    along the surfaces (isotropic: all of it). The rest becomes part of its path's start, so
    that the hand is not pulled back to where the last target's bias pointed: leaving a
    contact, that is into the surface it leaves."""
    if impedance.compliant_W is None or impedance.tangential_stiffness_n_per_m is None:
        return offset_W
    return impedance.compliant_W @ offset_W


@dataclass(frozen=True)
class TickResult:
    """``status``: "idle", "moving", "done", "guarded" (the guard stopped the move) or "failed"
    (with ``reason``)."""

    status: str
    reason: str = ""


class TaskController:
    """Drives ``world``'s arm through linear TCP moves; call :meth:`tick` every 10 ms."""

    def __init__(self, world: World, robot: RobotModel) -> None:
        self.world, self.robot = world, robot
        self.geometry = arm_geometry(robot)
        self.X_WB = world.scene.robot.X_WB
        self.sensor = WristSensor(robot)
        self.move: LinearMove | JointMove | None = None
        self.t_s = 0.0
        self.steps_per_tick = max(1, round(CONTROL_PERIOD_S / world.time_step_s))
        self.guard: Guard | None = None
        self.impedance: Impedance | None = None
        self.force_limit_n = HARD_FORCE_LIMIT_N
        self.offset_W = np.zeros(3)
        """The impedance offset δ (m, W) added to the path's position."""
        self.force_W = np.zeros(3)
        """Mean external force over the last control period (N, W; payload weight removed)."""
        self.force_peak_n = 0.0
        """Largest 1 ms force reading along the guard (or in norm) since the move started."""
        self.guard_force_W = np.zeros(3)
        """The force (N, W) that tripped the last guard."""
        self._window: list[np.ndarray] = []
        self._offsets: list[np.ndarray] = []
        self._settle_s = 0.0
        self._ease_q: np.ndarray | None = None
        """Where a safety stop eases the arm to, over ``_ease_ticks`` more periods."""
        self._ease_ticks = 0

    def commanded_tcp_W(self) -> np.ndarray:
        """The TCP pose the joint targets command (``X_WG``)."""
        return self.robot.tcp_pose_W(self.world.q_target, self.X_WB)

    def measured_tcp_W(self) -> np.ndarray:
        """The TCP pose of the measured joint angles."""
        return self.robot.tcp_pose_W(self.world.robot_joint_positions()[0], self.X_WB)

    def start_move(
        self,
        X_WG_goal: np.ndarray,
        speed_mps: float,
        *,
        guard: Guard | None = None,
        impedance: Impedance | None = None,
        force_limit_n: float = HARD_FORCE_LIMIT_N,
    ) -> None:
        """Begin a straight TCP move to ``X_WG_goal``; ValueError if it cannot be done.

        ``guard`` stops it on contact; ``impedance`` makes it compliant; ``force_limit_n``
        (capped at :data:`HARD_FORCE_LIMIT_N`) fails it on any larger external force.
        """
        if not (math.isfinite(speed_mps) and 0 < speed_mps <= MAX_TCP_SPEED_MPS):
            raise ValueError(f"speed {speed_mps} m/s not in (0, {MAX_TCP_SPEED_MPS}]")
        if not (math.isfinite(force_limit_n) and force_limit_n > 0):
            raise ValueError(f"force limit {force_limit_n} N must be finite and > 0")
        dt_s = self.world.time_step_s
        if impedance is not None and impedance.step_gain(dt_s) > 1.0:
            k = impedance.stiffest_n_per_m
            raise ValueError(
                f"impedance stiffness {k:g} N/m with damping {impedance.damping_n_s_per_m:g} "
                f"N·s/m would overshoot at the {dt_s * 1e3:g} ms physics step: the damping must "
                f"be at least stiffness × step, {k * dt_s:g} N·s/m"
            )
        goal = ik_tcp(X_WG_goal, self.world.q_target, self.robot, self.X_WB, self.geometry)
        if not goal.ok:
            raise ValueError(f"target cannot be reached: {goal.reason}")
        start = self.commanded_tcp_W()
        self._ease_q, self._ease_ticks = None, 0
        if impedance is None:
            self.offset_W = np.zeros(3)
        else:  # compliant moves chain: the path goes on from where the hand is commanded
            self.offset_W = carried_offset_W(self.offset_W, impedance)
            start[:3, 3] -= self.offset_W
        self.move = LinearMove(
            start, np.array(X_WG_goal, dtype=np.float64), speed_mps, TCP_ACCEL_MPS2
        )
        self.t_s = 0.0
        self.guard, self.impedance = guard, impedance
        self.force_limit_n = min(force_limit_n, HARD_FORCE_LIMIT_N)
        self.force_peak_n = 0.0
        self._offsets, self._settle_s = [], 0.0

    def start_joint_move(
        self, q_goal: np.ndarray, force_limit_n: float = HARD_FORCE_LIMIT_N
    ) -> None:
        """Begin a straight move in joint space to ``q_goal`` (rad, within the limits) at
        :data:`JOINT_MOVE_RPS`: the empty hand's way where no straight TCP move goes; fails on
        any external force above ``force_limit_n`` (capped at :data:`HARD_FORCE_LIMIT_N`)."""
        q_goal = np.asarray(q_goal, dtype=np.float64)
        if q_goal.shape != (6,) or not np.all(np.isfinite(q_goal)):
            raise ValueError(f"joint target must be 6 finite angles, got {q_goal!r}")
        if np.any(q_goal < self.robot.q_lower) or np.any(q_goal > self.robot.q_upper):
            raise ValueError(f"joint target {np.round(q_goal, 3).tolist()} is outside the limits")
        if not (math.isfinite(force_limit_n) and force_limit_n > 0):
            raise ValueError(f"force limit {force_limit_n} N must be finite and > 0")
        self._ease_q, self._ease_ticks = None, 0
        self.offset_W = np.zeros(3)
        self.move = JointMove(
            self.world.q_target.copy(), q_goal, JOINT_MOVE_RPS, JOINT_MOVE_ACCEL_RPS2
        )
        self.t_s = 0.0
        self.guard, self.impedance = None, None
        self.force_limit_n = min(force_limit_n, HARD_FORCE_LIMIT_N)
        self.force_peak_n = 0.0
        self._offsets, self._settle_s = [], 0.0

    def stop(self, ease: bool = False) -> None:
        """Hold where the arm is now (within one control period). ``ease`` (a safety stop):
        in contact, hold :data:`EASE_M` back along the contact force instead, so that the hand
        does not go on pressing (a position servo holding the measured pose leans on it)."""
        q = self.world.robot_joint_positions()[0]
        self._ease_q, self._ease_ticks = None, 0
        size_n = float(np.linalg.norm(self.force_W))
        # A force pointing mostly down is a held block's weight, not a contact pushing back.
        if ease and size_n > EASE_FROM_N and self.force_W[2] > -EASE_WEIGHT_COS * size_n:
            X_WG = self.robot.tcp_pose_W(q, self.X_WB)
            X_WG[:3, 3] += EASE_M * self.force_W / size_n
            eased = ik_tcp(X_WG, q, self.robot, self.X_WB, self.geometry)
            if eased.ok:  # reached over EASE_S: a jump would jolt the hand
                self._ease_q, self._ease_ticks = eased.q, max(1, round(EASE_S / CONTROL_PERIOD_S))
        self.world.q_target = q
        self.world.q_dot_target = np.zeros(6)
        self.move = None
        self.guard = self.impedance = None
        self.offset_W = np.zeros(3)

    def _physics(
        self,
        q_goal: np.ndarray | None = None,
        q_dot_goal: np.ndarray | None = None,
        J: np.ndarray | None = None,
    ) -> TickResult | None:
        """The servo steps of one period towards joint setpoint ``q_goal`` with rates
        ``q_dot_goal`` (holding still without them), watching the force at each step; a result
        if the arm was stopped. With an impedance, the offset δ advances at every step and
        moves the setpoint through the flange Jacobian ``J``.

        The servo setpoints are interpolated over the period, because a rate setpoint stepped
        every 10 ms jerks the hand into a large one-step wrist force. The admittance runs at the
        servo rate, because at 100 Hz against stiff contacts it falls into a 2-period limit
        cycle.
        """
        total = np.zeros(3)
        n = self.steps_per_tick
        q0, q_dot0 = self.world.q_target.copy(), self.world.q_dot_target.copy()
        offset0 = self.offset_W.copy()
        for i in range(1, n + 1):
            if q_goal is not None:
                q = q0 + (q_goal - q0) * (i / n)
                if self.impedance is not None and J is not None:
                    self._admittance(self.world.time_step_s)
                    twist = np.concatenate([self.offset_W - offset0, np.zeros(3)])
                    q = q + np.linalg.lstsq(J, twist, rcond=None)[0]
                self.world.q_target = q
                self.world.q_dot_target = q_dot0 + (q_dot_goal - q_dot0) * (i / n)
            self.world.step(1)
            f = self.sensor.force_W(self.world.robot_snapshot())
            total += f
            self._window.append(f)
            del self._window[:-LIMIT_WINDOW_STEPS]
            if self.move is None:
                continue
            mean_W = np.mean(self._window[-FORCE_WINDOW_STEPS:], axis=0)
            size = float(np.linalg.norm(np.mean(self._window, axis=0)))
            along = float(mean_W @ self.guard.direction_W) if self.guard else size
            self.force_peak_n = max(self.force_peak_n, along)
            if size > self.force_limit_n:
                self.stop()
                return TickResult(
                    "failed",
                    f"external force {size:.1f} N exceeds the limit of {self.force_limit_n:.1f} N",
                )
            if self.guard is not None and along > self.guard.threshold_n:
                self.guard_force_W = mean_W
                self.stop()
                return TickResult("guarded", f"contact force {along:.1f} N")
        self.force_W = total / self.steps_per_tick
        return None

    def _admittance(self, dt_s: float) -> None:
        """Advance the impedance offset by ``dt_s``: ``B δ̇ = f − K δ`` with ``f`` the last
        window's mean force, ``|δ̇|`` limited."""
        imp = self.impedance
        window = self._window[-FORCE_WINDOW_STEPS:]
        f_W = np.mean(window, axis=0) if window else np.zeros(3)
        P = np.eye(3) if imp.compliant_W is None else imp.compliant_W
        k_surface = (
            imp.stiffness_n_per_m
            if imp.tangential_stiffness_n_per_m is None
            else imp.tangential_stiffness_n_per_m
        )
        along = P @ self.offset_W
        press_W = imp.stiffness_n_per_m * along
        press_n = float(np.linalg.norm(press_W))
        if press_n > imp.max_press_n:
            press_W *= imp.max_press_n / press_n
        for n_W, cap_n in imp.press_caps:
            excess_n = float(press_W @ n_W) - cap_n
            if excess_n > 0.0:
                press_W = press_W - excess_n * n_W
        spring_W = press_W + k_surface * (self.offset_W - along)
        rate = (f_W - spring_W) / imp.damping_n_s_per_m
        speed = float(np.linalg.norm(rate))
        if speed > imp.max_rate_mps:
            rate *= imp.max_rate_mps / speed
        self.offset_W = self.offset_W + rate * dt_s

    def tick(self) -> TickResult:
        """One control period: the next setpoint, then the physics steps of the period."""
        if self.move is None:
            if self._ease_q is not None and self._ease_ticks > 0:
                q = self.world.q_target
                q_goal = q + (self._ease_q - q) / self._ease_ticks
                self._ease_ticks -= 1
                self._physics(q_goal, np.zeros(6))
            else:
                self._physics()
            return TickResult("idle")
        self.t_s += CONTROL_PERIOD_S
        if isinstance(self.move, JointMove):
            q = self.move.q_at(self.t_s)
            q_dot = (self.move.q_at(self.t_s + CONTROL_PERIOD_S) - q) / CONTROL_PERIOD_S
            stopped = self._physics(q, q_dot)
            if stopped is not None:
                return stopped
            if self.t_s < self.move.duration_s:
                return TickResult("moving")
            self.world.q_dot_target = np.zeros(6)
            self.move = None
            return TickResult("done")
        X = self.move.pose_at(self.t_s)
        X[:3, 3] += self.offset_W
        result = ik_tcp(X, self.world.q_target, self.robot, self.X_WB, self.geometry)
        if not result.ok:
            self.stop()
            return TickResult("failed", f"on the way: {result.reason}")
        jump_rad = np.abs(result.q - self.world.q_target)
        if np.max(jump_rad) > BRANCH_JUMP_RAD:
            # The nearest solution left the continuous one (a joint at its limit): commanding
            # it would swing the arm through space in one period.
            j = int(np.argmax(jump_rad))
            self.stop()
            return TickResult(
                "failed",
                f"on the way: {self.robot.arm_joints[j]} would swing {jump_rad[j]:.2f} rad at "
                "once to another arm configuration",
            )
        # Feed-forward joint rates from the path's velocity (finite difference over a period).
        X_next = self.move.pose_at(self.t_s + CONTROL_PERIOD_S)
        X_next[:3, 3] += self.offset_W
        X_WF = X @ invert_pose(self.geometry.X_FG)
        X_WF_next = X_next @ invert_pose(self.geometry.X_FG)
        v_F = (X_WF_next[:3, 3] - X_WF[:3, 3]) / CONTROL_PERIOD_S
        dR = X_WF_next[:3, :3] @ X_WF[:3, :3].T
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (
            2 * CONTROL_PERIOD_S
        )
        J = geometric_jacobian_W(result.q, self.robot, self.X_WB)
        q_dot = np.linalg.lstsq(J, np.concatenate([v_F, w]), rcond=None)[0]
        stopped = self._physics(result.q, q_dot, J)
        if stopped is not None:
            return stopped
        if self.t_s < self.move.duration_s:
            return TickResult("moving")
        self.world.q_dot_target = np.zeros(6)
        if self.impedance is not None:
            self._settle_s += CONTROL_PERIOD_S
            self._offsets.append(self.offset_W.copy())
            del self._offsets[: -self.impedance.settled_ticks]
            spread = max(float(np.linalg.norm(d - self.offset_W)) for d in self._offsets)
            if (
                len(self._offsets) < self.impedance.settled_ticks
                or spread > self.impedance.settled_offset_m
            ):
                limit_s = self.impedance.max_settle_s
                if self._settle_s > limit_s:
                    self.stop()
                    return TickResult("failed", f"contact did not settle in {limit_s} s")
                return TickResult("moving")
        self.move = None
        self.guard = None
        return TickResult("done")
