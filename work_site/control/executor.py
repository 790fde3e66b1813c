"""Runs motion programs from the wire (§VI-B): checked whole before any motion, then executed
command by command with a report for each step; a stop takes effect within one control period.

What runs today: ``guarded_grasp`` (open, approach from above, descend, close the coupled
fingers until they stop on the block at the finger motor's force limit, check something is
between them), ``move`` (a spatially-linear move of the workpiece frame P, i.e. the gripper TCP
at ``X_WP · X_GP⁻¹``) and ``open_gripper``/``release``. Guarded moves and contact moves (force
thresholds, impedance) are refused, with that reason, until issue 5 brings them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.transforms import invert_pose
from protocol import MotionProgram
from work_site.control.controller import MAX_TCP_SPEED_MPS, TaskController
from work_site.control.kinematics import ik_tcp

SUPPORTED_KINDS = ("guarded_grasp", "move", "open_gripper", "release")
WORKSPACE_MIN_W = np.array([0.10, -0.45, 0.02])
"""Lowest corner of the box every TCP target must lie in (m). z: the fingertips hang 15 mm
below the TCP, so 0.02 m keeps them 5 mm above the table."""
WORKSPACE_MAX_W = np.array([0.75, 0.45, 0.50])
GRIPPER_OPEN_M = 0.08

Report = Callable[[str, int, str, str], None]
"""report(program_id, command_index, status, message)."""


def check_program(program: MotionProgram, controller: TaskController) -> str:
    """Why ``program`` must not run ("" if it may): unsupported commands, targets outside the
    workspace or unreachable, speeds above the limit. Checked whole, before any motion."""
    if not program.commands:
        return "empty program"
    X_PG = invert_pose(program.X_GP)
    q = controller.world.q_target.copy()
    for i, cmd in enumerate(program.commands):
        where = f"command {i} ({cmd.kind})"
        if cmd.kind not in SUPPORTED_KINDS:
            return f"{where}: not supported by this work site yet"
        if cmd.kind not in ("move", "guarded_grasp"):
            continue
        if not (math.isfinite(cmd.speed_mps) and 0 < cmd.speed_mps <= MAX_TCP_SPEED_MPS):
            return f"{where}: speed {cmd.speed_mps} m/s not in (0, {MAX_TCP_SPEED_MPS}] m/s"
        X_WG = cmd.X_WP @ X_PG
        p = X_WG[:3, 3]
        if np.any(p < WORKSPACE_MIN_W) or np.any(p > WORKSPACE_MAX_W):
            return (
                f"{where}: gripper target {np.round(p, 3).tolist()} m is outside the "
                f"workspace {WORKSPACE_MIN_W.tolist()}–{WORKSPACE_MAX_W.tolist()} m"
            )
        result = ik_tcp(X_WG, q, controller.robot, controller.X_WB, controller.geometry)
        if not result.ok:
            return f"{where}: {result.reason}"
        q = result.q
    return ""


@dataclass(frozen=True)
class MoveTo:
    """A straight TCP move to ``X_WG`` at ``speed_mps``."""

    X_WG: np.ndarray
    speed_mps: float


@dataclass(frozen=True)
class SetFingers:
    """Drive each finger to ``each_m`` (0: closed) with the finger motors' force limit; done
    when the fingers have stopped (a grip: something is between them) or arrived."""

    each_m: float


@dataclass(frozen=True)
class CheckGrip:
    """Fail unless the fingers stopped at least ``min_opening_m`` apart (a block between)."""

    min_opening_m: float


FINGERS_STILL_M = 2e-6
"""Fingers moving less than this per control period have stopped (m)."""
FINGERS_STILL_TICKS = 5
FINGERS_MAX_TICKS = 150
GRASP_APPROACH_M = 0.06
"""The grasp approaches from this far above the grasp pose, straight down (m)."""
GRASP_DESCENT_MPS = 0.03
MIN_GRIP_OPENING_M = 0.005


def expand(program: MotionProgram, index: int) -> list:
    """The primitive actions of command ``index``."""
    cmd = program.commands[index]
    if cmd.kind in ("open_gripper", "release"):
        return [SetFingers(GRIPPER_OPEN_M / 2)]
    X_WG = cmd.X_WP @ invert_pose(program.X_GP)
    if cmd.kind == "move":
        return [MoveTo(X_WG, cmd.speed_mps)]
    if cmd.kind == "guarded_grasp":
        above = X_WG.copy()
        above[2, 3] += GRASP_APPROACH_M
        return [
            SetFingers(GRIPPER_OPEN_M / 2),
            MoveTo(above, cmd.speed_mps),
            MoveTo(X_WG, min(cmd.speed_mps, GRASP_DESCENT_MPS)),
            SetFingers(0.0),
            CheckGrip(MIN_GRIP_OPENING_M),
        ]
    raise ValueError(f"command {index}: {cmd.kind} is not supported by this work site yet")


@dataclass
class Execution:
    """One program being executed; :meth:`tick` advances it by one control period."""

    program: MotionProgram
    controller: TaskController
    report: Report
    index: int = -1
    finished: bool = False

    def __post_init__(self) -> None:
        self._actions: list = []
        self._fingers_last = -1.0
        self._fingers_still = 0
        self._fingers_ticks = 0

    def tick(self) -> None:
        """One control period: advance the current action; start the next when it is done."""
        if self.finished:
            return
        c = self.controller
        if c.move is not None:
            result = c.tick()
            if result.status == "failed":
                self._finish("failed", f"command {self.index}: {result.reason}")
                return
            if result.status == "moving":
                return
        elif self._actions and isinstance(self._actions[0], SetFingers):
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
                if self.index >= 0:
                    self.report(self.program.program_id, self.index, "done", "")
                self.index += 1
                if self.index >= len(self.program.commands):
                    self._finish("done", "program complete")
                    return
                self._actions = expand(self.program, self.index)
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
                self._actions.pop(0)
                continue
            if isinstance(action, MoveTo):
                try:
                    c.start_move(action.X_WG, action.speed_mps)
                except ValueError as e:
                    self._finish("failed", f"command {self.index}: {e}")
            else:
                c.world.finger_target_m = action.each_m
                self._fingers_last, self._fingers_still, self._fingers_ticks = -1.0, 0, 0
            return

    def stop(self, reason: str) -> None:
        """Stop now: hold the arm where it is."""
        if not self.finished:
            self.controller.stop()
            self._finish("stopped", reason)

    def _finish(self, status: str, message: str) -> None:
        self.finished = True
        self.report(self.program.program_id, -1, status, message)
