"""Runs motion programs from the wire (§VI-B): checked whole before any motion, then executed
command by command with a report for each step; a stop takes effect within one control period.

Commands (targets are workpiece poses ``X_WP``; the gripper TCP goes to ``X_WP · X_GP⁻¹``):
- ``guarded_grasp``: open, approach from above, descend (guarded: touching anything fails),
  close the coupled fingers until they stop on the block, check something is between them,
  lift it clear by :data:`GRASP_LIFT_M` and weigh it (the payload's weight is then removed from
  the wrist force); where the program says what it holds (``holds``), the grip must match it
  (:func:`held_problem`: its width, its weight, where its weight pulls) or the block is set
  back down, the hand withdraws and the program fails;
- ``move``: a spatially-linear move, failing on any force above the command's limit;
- ``guarded_move``: a move that stops when the force against its direction exceeds the
  command's ``force_limit_n``; with ``contacts`` it must end in them, verified by force;
- ``contact_move``: a compliant move (impedance) towards the target biased into its contacts by
  Δp with ``N Δp ≈ −d·1``; when it has settled, the force along each contact normal must reach
  :data:`CONTACT_VERIFY_N` ("contact_verified" report) or the program fails;
- ``open_gripper``/``release``: open the fingers (the payload is forgotten).
Every force is also held under :data:`HARD_FORCE_LIMIT_N`, which no program can raise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import nnls

from models.scene import GRAVITY_W
from models.transforms import invert_pose
from protocol import ContactState, HeldBlock, MotionProgram
from protocol.execution import (
    CONTACT_VERIFY_N,
    GRASP_LIFT_M,
    GUARD_OVERTRAVEL_M,
    TARGET_BIAS_M,
    TARGET_BIAS_MAX_M,
    WORKSPACE_MAX_W,
    WORKSPACE_MIN_W,
    contact_bias_W,
    grasp_approach_W,
    press_caps_n,
)
from protocol.messages import contact_directions, target_bias
from work_site.control.controller import (
    DEFAULT_SURFACE_STIFFNESS_N_PER_M,
    HARD_FORCE_LIMIT_N,
    MAX_TCP_SPEED_MPS,
    Guard,
    Impedance,
    TaskController,
    compliant_projector,
)
from work_site.control.kinematics import Approach, PathFollow, follow_line_tcp, plan_approach
from work_site.world import MOVABLE_MASS_RANGE_KG

GRIPPER_OPEN_M = 0.08
MAX_CONTACT_SPEED_MPS = 0.02
"""Moves in contact (guarded and contact moves) are no faster than this (§VI-B)."""
MIN_TCP_SPEED_MPS = 0.005
"""No command may be slower (m/s): half the speed asked in contact; slower ones only tie the
robot up."""
MAX_PROGRAM_DURATION_S = 600.0
"""A program whose moves, at their speeds, take longer than this is refused (s): it would tie
the robot up."""
MIN_FORCE_LIMIT_N = 1.0
"""No force limit may be lower (N): the contact verification threshold, below which no contact
could be verified nor a block carried."""

Report = Callable[[str, int, str, str], None]
"""report(program_id, command_index, status, message)."""

_MOVING_KINDS = ("guarded_grasp", "move", "guarded_move", "contact_move")


def target_bias_W(normals_W: np.ndarray, d_m: float = TARGET_BIAS_M) -> np.ndarray:
    """This work site's target bias Δp (m, W): :func:`protocol.messages.target_bias` with its
    d, bounded by :data:`TARGET_BIAS_MAX_M`."""
    return target_bias(normals_W, d_m, TARGET_BIAS_MAX_M)


def contact_forces_n(force_W: np.ndarray, normals_W: np.ndarray) -> np.ndarray:
    """Non-negative normal forces ``f`` (N) with ``Σ f_i n_i`` closest to ``force_W``."""
    N = np.asarray(normals_W, dtype=np.float64).reshape(-1, 3)
    return nnls(N.T, np.asarray(force_W, dtype=np.float64))[0]


class CheckCancelledError(Exception):
    """A program's check was abandoned (a stop came meanwhile)."""


def same_program(a: MotionProgram, b: MotionProgram) -> bool:
    """Whether ``a`` and ``b`` have the same grasp and commands (their ids may differ)."""
    if not np.array_equal(a.X_GP, b.X_GP) or len(a.commands) != len(b.commands):
        return False
    return all(
        p.kind == q.kind
        and np.array_equal(p.X_WP, q.X_WP)
        and p.speed_mps == q.speed_mps
        and p.force_limit_n == q.force_limit_n
        and len(p.contacts) == len(q.contacts)
        and all(
            c.object == d.object and np.array_equal(c.normals_W, d.normals_W)
            for c, d in zip(p.contacts, q.contacts, strict=True)
        )
        for p, q in zip(a.commands, b.commands, strict=True)
    )


def movable_objects(controller: TaskController) -> frozenset[str]:
    """The names of the objects a program may push about at this work site."""
    return frozenset(o.name for o in controller.world.scene.movable)


def later_targets_WG(
    program: MotionProgram, index: int, skip: int, movable: frozenset[str] = frozenset()
) -> list[np.ndarray]:
    """The TCP targets of the straight moves of command ``index`` after its first ``skip``, and
    of the commands after it up to the next grasp (whose approach is planned again), in order;
    ``movable`` as for :func:`expand`."""
    after = [a for a in expand(program, index, movable=movable) if isinstance(a, MoveTo)][skip:]
    for k in range(index + 1, len(program.commands)):
        if program.commands[k].kind == "guarded_grasp":
            break
        after += [a for a in expand(program, k, movable=movable) if isinstance(a, MoveTo)]
    return [a.X_WG for a in after]


def program_refusal(
    program: MotionProgram,
    controller: TaskController,
    cancelled: Callable[[], bool] | None = None,
    holding: bool = False,
    start: int = 0,
    approaches: dict[int, Approach] | None = None,
) -> str:
    """Why ``program`` must not run ("" if it may): a contact move with nothing held, targets
    outside the workspace or unreachable, speeds or force limits beyond the work site's, a held
    block it could not grasp or weigh.
    Checked whole, before any motion; raises :class:`CheckCancelledError` as soon as ``cancelled()``
    (asked before each command) holds. Reads the controller's joint targets and kinematics
    only, so it may run on another thread while the arm holds still. A program that resumes a
    stopped one is checked from command ``start`` on, the hand ``holding`` a block or not.
    ``approaches`` (if given) receives each grasp's approach as planned, by command index: the
    execution takes them from there, for planning one can take longer than a control period."""
    if not program.commands:
        return "empty program"
    for held in program.holds:
        low, high = MOVABLE_MASS_RANGE_KG
        if not low <= held.mass_kg <= high:
            return (
                f"holds: the {held.name} weighs {held.mass_kg} kg, not in [{low}, {high}] kg, "
                "the masses this work site grasps and weighs"
            )
        if held.opening_m > GRIPPER_OPEN_M:
            return (
                f"holds: the {held.name} is held {held.opening_m * 1e3:.1f} mm wide, more than "
                f"the fingers open ({GRIPPER_OPEN_M * 1e3:.0f} mm)"
            )
    X_PG = invert_pose(program.X_GP)
    q = np.array(controller.world.q_target, copy=True)
    X_WG_before = controller.robot.tcp_pose_W(q, controller.X_WB)
    movable = movable_objects(controller)
    duration_s = 0.0
    for i, cmd in enumerate(program.commands):
        if i < start:
            continue
        if cancelled is not None and cancelled():
            raise CheckCancelledError(f"cancelled at command {i}")
        where = f"command {i} ({cmd.kind})"
        if cmd.kind in ("open_gripper", "release"):
            holding = False
            continue
        if cmd.kind == "guarded_grasp":
            holding = True
        elif cmd.kind == "contact_move" and not holding:
            return f"{where}: nothing is held (a guarded_grasp must come first)"
        if not np.all(np.isfinite(cmd.X_WP)):
            return f"{where}: target pose has NaN or infinite entries"
        if not (
            math.isfinite(cmd.speed_mps) and MIN_TCP_SPEED_MPS <= cmd.speed_mps <= MAX_TCP_SPEED_MPS
        ):
            return (
                f"{where}: speed {cmd.speed_mps} m/s not in [{MIN_TCP_SPEED_MPS}, "
                f"{MAX_TCP_SPEED_MPS}] m/s"
            )
        if cmd.kind in ("guarded_move", "contact_move") and cmd.speed_mps > MAX_CONTACT_SPEED_MPS:
            return (
                f"{where}: speed {cmd.speed_mps} m/s is above {MAX_CONTACT_SPEED_MPS} m/s, "
                "the limit for moves into contact"
            )
        limit_n = cmd.force_limit_n
        if not (math.isfinite(limit_n) and MIN_FORCE_LIMIT_N <= limit_n <= HARD_FORCE_LIMIT_N):
            return (
                f"{where}: force limit {limit_n} N not in [{MIN_FORCE_LIMIT_N}, "
                f"{HARD_FORCE_LIMIT_N}] N (the work site's own limits)"
            )
        if cmd.kind == "contact_move":
            if not cmd.contacts:
                return f"{where}: a contact move needs the contacts it must keep"
            if cmd.force_limit_n <= CONTACT_VERIFY_N * len(contact_directions(cmd.contacts)):
                return (
                    f"{where}: force limit {cmd.force_limit_n} N leaves no room for its "
                    f"contacts' {CONTACT_VERIFY_N} N each"
                )
        X_WG = cmd.X_WP @ X_PG
        p = X_WG[:3, 3]
        if np.any(p < WORKSPACE_MIN_W) or np.any(p > WORKSPACE_MAX_W):
            return (
                f"{where}: gripper target {np.round(p, 3).tolist()} m is outside the "
                f"workspace {WORKSPACE_MIN_W.tolist()}–{WORKSPACE_MAX_W.tolist()} m"
            )
        # Every pose the command's motions aim at (a grasp's approach from above and lift, a
        # guard's overtravel, a contact move's bias), not only its target: a program refused
        # here never stops half done on a pose it cannot reach.
        for action in expand(program, i, movable=movable):
            if isinstance(action, MoveTo):
                # The whole line, as the controller will follow it: a target reachable only
                # through a joint limit or a swing to another configuration is refused too.
                result = follow_line_tcp(
                    X_WG_before,
                    action.X_WG,
                    q,
                    controller.robot,
                    controller.X_WB,
                    controller.geometry,
                )
                if action.approach:  # the empty hand may go through joint space instead
                    plan = Approach(True)
                    if not result.ok:
                        plan = plan_approach(
                            X_WG_before,
                            q,
                            action.X_WG,
                            later_targets_WG(program, i, 1, movable),
                            controller.robot,
                            controller.X_WB,
                            controller.geometry,
                        )
                        result = PathFollow(plan.ok, plan.q_joint, reason=plan.reason)
                    if approaches is not None:
                        approaches[i] = plan
                if not result.ok:
                    return f"{where}: on the way, {result.reason}"
                q = result.q
                # At least the translation at the command's speed (a lower bound: cheap).
                step_m = math.dist(action.X_WG[:3, 3].tolist(), X_WG_before[:3, 3].tolist())
                duration_s += step_m / action.speed_mps
                X_WG_before = action.X_WG
                if duration_s > MAX_PROGRAM_DURATION_S:
                    return (
                        f"{where}: the program's moves would take more than "
                        f"{MAX_PROGRAM_DURATION_S:g} s, the longest this work site runs"
                    )
    return ""


@dataclass(frozen=True)
class MoveTo:
    """A straight TCP move to ``X_WG`` at ``speed_mps``; with a ``guard``, a touch ends it:
    ``touch_fails`` says whether that is a failure (with that message) or the goal."""

    X_WG: np.ndarray
    speed_mps: float
    force_limit_n: float = HARD_FORCE_LIMIT_N
    guard: Guard | None = None
    impedance: Impedance | None = None
    touch_fails: str = ""
    must_touch: bool = False
    approach: bool = False
    """The empty hand's way to a grasp, its command's first move: through joint space where no
    straight move goes (:func:`~models.kinematics.plan_approach`)."""


@dataclass(frozen=True)
class SetFingers:
    """Drive each finger to ``each_m`` (0: closed) with the finger motors' force limit; done
    when the fingers have stopped (a grip: something is between them) or arrived."""

    each_m: float


@dataclass(frozen=True)
class CheckGrip:
    """Fail unless the fingers stopped at least ``min_opening_m`` apart (a block between); with
    ``held``, open and withdraw to ``above_WG`` unless they stopped at its width."""

    min_opening_m: float
    held: HeldBlock | None = None
    above_WG: np.ndarray | None = None


@dataclass(frozen=True)
class Weigh:
    """Hold still ``ticks`` periods, then take the mean force as the payload's weight; ``empty``:
    only note the wrist's torque (the hand's own, to tell a payload's moment from)."""

    ticks: int
    empty: bool = False


@dataclass(frozen=True)
class CheckHeld:
    """With the block lifted to ``X_WG`` and weighed: unless it is ``held``
    (:func:`held_problem`), set it back down at ``grasped_WG``, open, withdraw to
    ``above_WG``."""

    held: HeldBlock
    X_WG: np.ndarray
    grasped_WG: np.ndarray
    above_WG: np.ndarray


@dataclass(frozen=True)
class Fail:
    """End the program as failed, saying ``message``."""

    message: str


@dataclass(frozen=True)
class LockGrip:
    """Lock the gripped fingers (see ``World.lock_fingers``)."""


@dataclass(frozen=True)
class Settle:
    """Hold still ``ticks`` periods."""

    ticks: int


@dataclass(frozen=True)
class VerifyContacts:
    """Fail unless the force along each of ``contacts``' normals reaches CONTACT_VERIFY_N:
    the force now, or ``at_guard`` the one that stopped the guarded move before (which then
    eases as the servo stops pushing)."""

    contacts: tuple[ContactState, ...]
    at_guard: bool = False


@dataclass(frozen=True)
class ForgetPayload:
    """The fingers are opening: unlock them, nothing is held."""


FINGERS_STILL_M = 2e-6
"""Fingers moving less than this per control period have stopped (m)."""
FINGERS_STILL_TICKS = 5
FINGERS_MAX_TICKS = 150
GRASP_DESCENT_MPS = 0.03
GRASP_TOUCH_N = 3.0
"""Descending to grasp, a force this large means the fingers hit something (N)."""
WEIGH_TICKS = 20
LOCK_SETTLE_TICKS = 10
"""After locking the fingers the wrist reads the coupled grip's false force for a few steps
more: the lift waits this long."""
MIN_GRIP_OPENING_M = 0.005
GRIP_OPENING_TOLERANCE_M = 0.003
"""Fingers stopped farther than this from the held block's width (its model's) hold it across
something else: an edge, a corner, another block (m)."""
HELD_MASS_TOLERANCE = 0.2
"""A held block may weigh this fraction more or less than its model says (wooden blocks differ
in density); beyond it and :data:`WEIGHING_UNCERTAINTY_KG`, the grip holds something else."""
WEIGHING_UNCERTAINTY_KG = 0.01
"""What the wrist sensor's weighing may be off by, whatever the block (about 0.1 N)."""
HELD_COM_TOLERANCE_M = 0.005
"""How far (across the vertical) the held block's centre of mass, from its weight's moment on
the wrist, may lie from where the model puts it in the grasp: vision's error along the block
(its position and its turn times the block's size) and the fingers' slip; beyond it, and
:data:`WRIST_TORQUE_UNCERTAINTY_NM`'s share, the block is held elsewhere along it or turned
from where the model has it, and would be carried off by as much."""
WRIST_TORQUE_UNCERTAINTY_NM = 0.002
"""What the wrist sensor's torque may be off by between two readings (N·m): a light block's
moment says less about where its weight pulls."""
_UP_W = np.array([0.0, 0.0, 1.0])
_G_MPS2 = float(np.linalg.norm(GRAVITY_W))


def held_com_off_m(
    held: HeldBlock, mass_kg: float, moment_W: np.ndarray, X_WG: np.ndarray, p_WS: np.ndarray
) -> float:
    """How far (m, across the vertical) the weighed block's centre of mass lies from the
    model's in the grasp: from the moment ``moment_W`` its weight (``mass_kg``) added on the
    wrist, about the sensor's origin ``p_WS``, the hand at ``X_WG``."""
    weight_n = mass_kg * _G_MPS2
    # moment = r × (0, 0, −W): its x is −W r_y, its y W r_x.
    r_xy = np.array([moment_W[1], -moment_W[0]]) / weight_n
    expected_xy = (X_WG[:3, :3] @ held.com_G + X_WG[:3, 3] - p_WS)[:2]
    return float(np.linalg.norm(r_xy - expected_xy))


def held_problem(
    held: HeldBlock, mass_kg: float, moment_W: np.ndarray, X_WG: np.ndarray, p_WS: np.ndarray
) -> str:
    """Why the weighed grip does not hold ``held`` ("" if it does): its mass ``mass_kg`` against
    the model's (:data:`HELD_MASS_TOLERANCE`), and where its weight pulls, from the moment it
    added on the wrist ``moment_W`` (N·m, about the sensor's origin ``p_WS``, the hand at
    ``X_WG``), against the model's centre of mass in the grasp (horizontally: a vertical offset
    adds no moment)."""
    tolerance_kg = HELD_MASS_TOLERANCE * held.mass_kg + WEIGHING_UNCERTAINTY_KG
    if abs(mass_kg - held.mass_kg) > tolerance_kg:
        return (
            f"holding {mass_kg * 1e3:.0f} g where the {held.name} weighs "
            f"{held.mass_kg * 1e3:.0f} g: the fingers hold something else"
        )
    off_m = held_com_off_m(held, mass_kg, moment_W, X_WG, p_WS)
    if off_m > HELD_COM_TOLERANCE_M + WRIST_TORQUE_UNCERTAINTY_NM / (mass_kg * _G_MPS2):
        return (
            f"the {held.name}'s weight pulls {off_m * 1e3:.0f} mm from where the model puts "
            "it in the grip: the block is held elsewhere along it, or turned from where the "
            "model has it"
        )
    return ""


def default_impedance() -> Impedance:
    """The contact moves' impedance unless told otherwise (see
    :data:`~work_site.control.controller.DEFAULT_SURFACE_STIFFNESS_N_PER_M`)."""
    return Impedance(tangential_stiffness_n_per_m=DEFAULT_SURFACE_STIFFNESS_N_PER_M)


def expand(
    program: MotionProgram,
    index: int,
    impedance: Impedance | None = None,
    movable: frozenset[str] = frozenset(),
) -> list:
    """The primitive actions of command ``index``; contact moves use ``impedance`` (default
    :class:`Impedance`) compliant along their contact normals, and press the ``movable``
    objects sideways more gently (:func:`~protocol.execution.press_caps_n`)."""
    cmd = program.commands[index]
    if cmd.kind in ("open_gripper", "release"):
        return [ForgetPayload(), SetFingers(GRIPPER_OPEN_M / 2)]
    X_WG = cmd.X_WP @ invert_pose(program.X_GP)
    limit = cmd.force_limit_n
    if cmd.kind == "move":
        return [MoveTo(X_WG, cmd.speed_mps, limit)]
    if cmd.kind == "guarded_move":
        here = program.commands[index - 1].X_WP if index > 0 else cmd.X_WP
        direction = cmd.X_WP[:3, 3] - here[:3, 3]
        if np.linalg.norm(direction) > 0:
            against = -direction / np.linalg.norm(direction)
        else:  # no motion: the guard looks along the expected contacts' normals
            against = np.sum([n for _, n in contact_directions(cmd.contacts)] or [_UP_W], axis=0)
            against /= np.linalg.norm(against)
        beyond = X_WG.copy()
        beyond[:3, 3] -= GUARD_OVERTRAVEL_M * against
        guarded = MoveTo(
            beyond,
            cmd.speed_mps,
            HARD_FORCE_LIMIT_N,
            guard=Guard(against, limit),
            must_touch=bool(cmd.contacts),
        )
        return [guarded, VerifyContacts(cmd.contacts, at_guard=True)] if cmd.contacts else [guarded]
    if cmd.kind == "contact_move":
        biased = X_WG.copy()
        directions = contact_directions(cmd.contacts)
        normals = np.array([n for _, n in directions])
        biased[:3, 3] += contact_bias_W(directions, movable)
        caps = press_caps_n(directions, movable)
        return [
            MoveTo(
                biased,
                cmd.speed_mps,
                limit,
                impedance=replace(
                    impedance or default_impedance(),
                    compliant_W=compliant_projector(normals),
                    press_caps=tuple(
                        (n, float(cap))
                        for n, cap in zip(normals, caps, strict=True)
                        if cap < np.inf
                    ),
                ),
            ),
            VerifyContacts(cmd.contacts),
        ]
    if cmd.kind == "guarded_grasp":
        lifted = X_WG.copy()
        lifted[2, 3] += GRASP_LIFT_M
        first, *then = grasp_approach_W(X_WG)
        approach = [MoveTo(first, cmd.speed_mps, limit, approach=True)]
        approach += [MoveTo(X, cmd.speed_mps, limit) for X in then]
        held = program.holds[0] if program.holds else None
        above = [first, *then][-1]  # over the grasp, where the hand withdraws to
        return [
            ForgetPayload(),
            SetFingers(GRIPPER_OPEN_M / 2),
            *approach,
            MoveTo(
                X_WG,
                min(cmd.speed_mps, GRASP_DESCENT_MPS),
                limit,
                guard=Guard(_UP_W, GRASP_TOUCH_N),
                touch_fails="the fingers touched something on the way down to the grasp",
            ),
            *([Weigh(WEIGH_TICKS, empty=True)] if held else []),
            SetFingers(0.0),
            CheckGrip(MIN_GRIP_OPENING_M, held, above),
            LockGrip(),
            Settle(LOCK_SETTLE_TICKS),
            MoveTo(lifted, GRASP_DESCENT_MPS, limit),
            Weigh(WEIGH_TICKS),
            *([CheckHeld(held, lifted, X_WG, above)] if held else []),
        ]
    raise ValueError(f"command {index}: {cmd.kind} is not supported by this work site")


@dataclass
class Execution:
    """One program being executed; :meth:`tick` advances it by one control period."""

    program: MotionProgram
    controller: TaskController
    report: Report
    index: int = -1
    finished: bool = False
    impedance: Impedance = field(default_factory=lambda: default_impedance())
    """The contact moves' impedance (its ``compliant_W`` is set per move)."""
    holding: bool = False
    """Whether the hand holds a block: from a grasp's lock to the next opening (at the start:
    the stopped program's, when this one resumes it)."""
    start: int = 0
    """The command it starts at (that of the stopped program it resumes, else 0)."""
    approaches: dict[int, Approach] = field(default_factory=dict)
    """The grasps' approaches as the check planned them, by command index (see
    :func:`program_refusal`); one missing is planned when its command starts."""
    end_status: str = ""
    """How it finished (done, failed, stopped); "" while it runs."""

    def __post_init__(self) -> None:
        self.index = self.start - 1
        self._actions: list = []
        self._fingers_last = -1.0
        self._fingers_still = 0
        self._fingers_ticks = 0
        self._weighed: list[np.ndarray] = []
        self._torques_W: list[np.ndarray] = []
        self._empty_torque_W = np.zeros(3)
        self._held_torque_W = np.zeros(3)
        self._grip_opening_m = 0.0
        self._settle_ticks = 0

    def tick(self) -> None:
        """One control period: advance the current action; start the next when it is done."""
        if self.finished:
            return
        c = self.controller
        action = self._actions[0] if self._actions else None
        if c.move is not None:
            result = c.tick()
            if result.status == "failed":
                self._finish("failed", f"command {self.index}: {result.reason}")
                return
            if result.status == "moving":
                return
            if isinstance(action, MoveTo):
                if result.status == "guarded" and action.touch_fails:
                    self._finish("failed", f"command {self.index}: {action.touch_fails}")
                    return
                if result.status == "done" and action.must_touch:
                    self._finish(
                        "failed", f"command {self.index}: reached its target without contact"
                    )
                    return
        elif isinstance(action, SetFingers):
            c.tick()
            opening = c.world.robot_snapshot().gripper_opening_m
            moved = abs(opening - self._fingers_last)
            self._fingers_last = opening
            self._fingers_ticks += 1
            self._fingers_still = self._fingers_still + 1 if moved < FINGERS_STILL_M else 0
            if (
                self._fingers_still < FINGERS_STILL_TICKS
                and self._fingers_ticks < FINGERS_MAX_TICKS
            ):
                return
        elif isinstance(action, Settle):
            c.tick()
            self._settle_ticks += 1
            if self._settle_ticks < action.ticks:
                return
        elif isinstance(action, Weigh):
            c.tick()
            self._weighed.append(c.force_W)
            self._torques_W.append(c.sensor.torque_W(c.world.robot_snapshot()))
            if len(self._weighed) < action.ticks:
                return
            torque_W = np.mean(self._torques_W, axis=0)
            if action.empty:
                self._empty_torque_W = torque_W
            else:
                self._held_torque_W = torque_W
                mass = c.sensor.tare(np.mean(self._weighed, axis=0))
                self.report(
                    self.program.program_id, self.index, "started", f"holding {mass * 1e3:.0f} g"
                )
        else:
            c.tick()
        if self._actions:
            self._actions.pop(0)
        self._advance()

    def _advance(self) -> None:
        """Start the next action, through as many commands as have finished."""
        c = self.controller
        while True:
            while not self._actions:
                if self.index >= self.start:
                    self.report(self.program.program_id, self.index, "done", "")
                self.index += 1
                if self.index >= len(self.program.commands):
                    self._finish("done", "program complete")
                    return
                self._actions = expand(self.program, self.index, self.impedance, movable_objects(c))
                self.report(
                    self.program.program_id,
                    self.index,
                    "started",
                    self.program.commands[self.index].kind,
                )
            action = self._actions[0]
            if isinstance(action, CheckGrip):
                opening = c.world.robot_snapshot().gripper_opening_m
                if opening < action.min_opening_m:
                    self._finish(
                        "failed",
                        f"command {self.index}: nothing between the "
                        f"fingers (they closed to {opening * 1e3:.1f} mm)",
                    )
                    return
                self._grip_opening_m = opening
                held = action.held
                if held is not None and abs(opening - held.opening_m) > GRIP_OPENING_TOLERANCE_M:
                    self._give_back(
                        f"the fingers closed to {opening * 1e3:.1f} mm where the {held.name} "
                        f"is {held.opening_m * 1e3:.1f} mm wide: they hold something else",
                        action.above_WG,
                    )
                    continue
            elif isinstance(action, CheckHeld):
                weighed = (
                    action.held,
                    c.sensor.payload_mass_kg,
                    self._held_torque_W - self._empty_torque_W,
                    action.X_WG,
                    c.world.robot_snapshot().X_WF[:3, 3],
                )
                problem = held_problem(*weighed)
                if problem:
                    self._give_back(problem, action.above_WG, action.grasped_WG)
                    continue
                self.report(
                    self.program.program_id,
                    self.index,
                    "started",
                    f"holds the {action.held.name} as modelled: {self._grip_opening_m * 1e3:.1f} "
                    f"mm wide (model {action.held.opening_m * 1e3:.1f}), its weight "
                    f"{held_com_off_m(*weighed) * 1e3:.1f} mm from the model's centre of mass",
                )
            elif isinstance(action, Fail):
                self._finish("failed", f"command {self.index}: {action.message}")
                return
            elif isinstance(action, VerifyContacts):
                force_W = c.guard_force_W if action.at_guard else c.force_W
                problem = self._verify(action.contacts, force_W)
                if problem:
                    c.stop()
                    self._finish("failed", f"command {self.index}: {problem}")
                    return
            elif isinstance(action, ForgetPayload):
                c.world.unlock_fingers()
                c.sensor.clear_payload()
                self.holding = False
            elif isinstance(action, LockGrip):
                c.world.lock_fingers()
                self.holding = True
            elif isinstance(action, MoveTo) and action.approach:
                plan = self.approaches.get(self.index) or plan_approach(
                    c.commanded_tcp_W(),
                    c.world.q_target,
                    action.X_WG,
                    later_targets_WG(self.program, self.index, 1, movable_objects(c)),
                    c.robot,
                    c.X_WB,
                    c.geometry,
                )
                try:
                    if not plan.ok:
                        raise ValueError(f"on the way to the grasp: {plan.reason}")
                    if plan.q_joint is not None:
                        c.start_joint_move(plan.q_joint, action.force_limit_n)
                    else:
                        c.start_move(
                            action.X_WG, action.speed_mps, force_limit_n=action.force_limit_n
                        )
                except ValueError as e:
                    self._finish("failed", f"command {self.index}: {e}")
                return
            elif isinstance(action, MoveTo):
                try:
                    c.start_move(
                        action.X_WG,
                        action.speed_mps,
                        guard=action.guard,
                        impedance=action.impedance,
                        force_limit_n=action.force_limit_n,
                    )
                except ValueError as e:
                    self._finish("failed", f"command {self.index}: {e}")
                return
            elif isinstance(action, SetFingers):
                c.world.finger_target_m = action.each_m
                self._fingers_last, self._fingers_still, self._fingers_ticks = -1.0, 0, 0
                return
            elif isinstance(action, Weigh):
                self._weighed, self._torques_W = [], []
                return
            elif isinstance(action, Settle):
                self._settle_ticks = 0
                return
            self._actions.pop(0)

    def _give_back(
        self, why: str, above_WG: np.ndarray, grasped_WG: np.ndarray | None = None
    ) -> None:
        """The grip is not what the program said it holds: set the block back down where it was
        taken from (``grasped_WG``, if it was lifted: a guarded move, the table ends it), open,
        withdraw to ``above_WG``, then fail saying ``why``."""
        back: list = []
        if grasped_WG is not None:
            down = grasped_WG.copy()
            down[2, 3] -= GUARD_OVERTRAVEL_M
            back.append(MoveTo(down, GRASP_DESCENT_MPS, guard=Guard(_UP_W, GRASP_TOUCH_N)))
        self._actions = [
            *back,
            ForgetPayload(),
            SetFingers(GRIPPER_OPEN_M / 2),
            MoveTo(above_WG, GRASP_DESCENT_MPS),
            Fail(why),
        ]

    def _verify(self, contacts: tuple[ContactState, ...], force_W: np.ndarray) -> str:
        """Report the contacts verified by ``force_W`` (N, W); the reason if one is not ("" if
        all are)."""
        directions = contact_directions(contacts)
        f = contact_forces_n(force_W, np.array([n for _, n in directions]))
        weakest = int(np.argmin(f))
        summary = ", ".join(
            f"{name} {fi:.1f} N along {np.round(n, 2).tolist()}"
            for (name, n), fi in zip(directions, f, strict=True)
        )
        if f[weakest] < CONTACT_VERIFY_N:
            return (
                f"contact with {directions[weakest][0]} not verified: {f[weakest]:.1f} N along "
                f"its normal, below {CONTACT_VERIFY_N} N (wrist force "
                f"{np.round(force_W, 1).tolist()} N; {summary})"
            )
        self.report(self.program.program_id, self.index, "contact_verified", summary)
        return ""

    def stop(self, reason: str) -> None:
        """Stop now: hold the arm where it is, eased off any contact it presses."""
        if not self.finished:
            self.controller.stop(ease=True)
            self._finish("stopped", reason)

    def _finish(self, status: str, message: str) -> None:
        self.finished, self.end_status = True, status
        self.report(self.program.program_id, -1, status, message)
