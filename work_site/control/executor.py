"""Runs motion programs from the wire (§VI-B): checked whole before any motion, then executed
command by command with a report for each step; a stop takes effect within one control period.

What runs today: ``move`` (a spatially-linear move of the workpiece frame P, i.e. the gripper
TCP at ``X_WP · X_GP⁻¹``) and ``open_gripper``/``release``. Programs with guarded grasps,
guarded moves or contact moves are refused, with that reason, until issue 5 brings them.
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

SUPPORTED_KINDS = ("move", "open_gripper", "release")
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
        if cmd.kind != "move":
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


@dataclass
class Execution:
    """One program being executed; :meth:`tick` advances it by one control period."""

    program: MotionProgram
    controller: TaskController
    report: Report
    index: int = -1
    finished: bool = False

    def tick(self) -> None:
        """One control period: advance the current command; start the next when it is done."""
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
        else:
            c.tick()  # an idle period: the fingers move, the arm holds
        if self.index >= 0:
            self.report(self.program.program_id, self.index, "done", "")
        self.index += 1
        if self.index >= len(self.program.commands):
            self._finish("done", "program complete")
            return
        cmd = self.program.commands[self.index]
        self.report(self.program.program_id, self.index, "started", cmd.kind)
        if cmd.kind == "move":
            try:
                c.start_move(cmd.X_WP @ invert_pose(self.program.X_GP), cmd.speed_mps)
            except ValueError as e:
                self._finish("failed", f"command {self.index}: {e}")
        else:  # open_gripper / release
            c.world.finger_target_m = GRIPPER_OPEN_M / 2

    def stop(self, reason: str) -> None:
        """Stop now: hold the arm where it is."""
        if not self.finished:
            self.controller.stop()
            self._finish("stopped", reason)

    def _finish(self, status: str, message: str) -> None:
        self.finished = True
        self.report(self.program.program_id, -1, status, message)
