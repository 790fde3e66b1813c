"""The program generator end to end (§VI): history → path → deformation → commands → check."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from models.geometry import ConvexPart
from models.robot import load_robot
from models.scene import Scene
from operator_site.program.check import CheckResult, Sweeper
from operator_site.program.commands import CommandParams, build_program, park_pose_W
from operator_site.program.deform import Deformer, DeformParams, DeformResult
from operator_site.program.feasibility import (
    Feasibility,
    check_feasibility,
    movable_names,
    parked_through_joints,
)
from operator_site.program.path import WorkpiecePath, path_from_history
from operator_site.simulator import SimParams, StepResult
from protocol import HeldBlock, MotionProgram

REFUSED_RETRY_MAX_SWEEPS = 300
"""A program the check refuses after a deformation stopped unsettled by its sweep cap is made
once more from a deformation allowed this many sweeps, because round an outside corner the capped
path can stop mid-creep where no refinement of the pivot passes the sweep."""


class ProgramRefusedError(ValueError):
    """The generated program failed the check; ``check`` says where and why."""

    def __init__(self, check: CheckResult) -> None:
        super().__init__(f"program refused: {check.reason}")
        self.check = check


class ProgramInfeasibleError(ProgramRefusedError):
    """The program passed the sweep, but the robot cannot do it (:mod:`.feasibility`):
    ``feasibility`` says why and at which command; ``check`` carries the same reason."""

    def __init__(self, feasibility: Feasibility, check: CheckResult) -> None:
        super().__init__(
            replace(check, ok=False, reason=feasibility.reason, segment=feasibility.command)
        )
        self.feasibility = feasibility


@dataclass(frozen=True, eq=False)
class Generated:
    """A checked program with what it was made from."""

    program: MotionProgram
    raw: WorkpiecePath
    deformed: DeformResult
    check: CheckResult


def _holding(
    program: MotionProgram, scene: Scene, workpiece: str, opening_m: float
) -> MotionProgram:
    """``program`` saying that its grasp holds ``workpiece`` between fingers ``opening_m`` apart
    (unchanged for a model without a mass: there is nothing to weigh it against)."""
    model = scene.object(workpiece).model
    if model.mass_kg <= 0:
        return program
    X_GP = program.X_GP
    com_G = X_GP[:3, :3] @ model.com_O + X_GP[:3, 3]
    return replace(program, holds=(HeldBlock(workpiece, model.mass_kg, opening_m, com_G),))


def generate_program(
    program_id: str,
    scene: Scene,
    workpiece: str,
    history: Sequence[StepResult],
    X_GP: np.ndarray,
    attached_O: tuple[ConvexPart, ...] = (),
    sim_params: SimParams | None = None,
    deform_params: DeformParams | None = None,
    command_params: CommandParams | None = None,
    X_WO: dict[str, np.ndarray] | None = None,
    progress: Callable[[float, str], None] | None = None,
    feasible: bool = True,
    grip_opening_m: float | None = None,
) -> Generated:
    """The motion program for the task in ``history``; raises :class:`ProgramRefusedError` if its
    sweep finds a collision or a lost contact, and with ``feasible``
    :class:`ProgramInfeasibleError` if the robot cannot do it (:func:`check_feasibility`: its
    grasp, its reach, a contact it could not verify). ``X_WO`` overrides the scene's object
    poses, as for the simulator (pass the task session's ``X_WO``: the poses the simulation
    used). With ``grip_opening_m`` (the fingers' opening on the block in the grasp ``X_GP``)
    the program says what its grasp holds (:class:`~protocol.HeldBlock`: the model's mass and
    centre of mass), which the work site weighs the grip against before carrying it.
    ``progress(fraction, stage)`` is called as each stage begins (fraction of the work done)."""
    say = progress or (lambda _fraction, _stage: None)
    say(0.05, "reading the path")
    c_O = scene.object(workpiece).model.com_O
    raw = path_from_history(history, workpiece, c_O)
    deform_params = deform_params or DeformParams()
    sweeper = Sweeper(scene, workpiece, sim_params, attached_O, X_WO=X_WO)
    robot = load_robot(scene.robot.urdf_path)
    say(0.15, "deforming the path")
    while True:
        deformer = Deformer(scene, workpiece, deform_params, sim_params, attached_O, X_WO)
        deformed = deformer.deform(raw)
        say(0.55, "fitting robot moves")
        program = parked_through_joints(
            robot,
            build_program(
                program_id, deformed.path, X_GP, command_params, sweeper, park_pose_W(scene)
            ),
            scene.robot.q_home_rad,
            scene.robot.X_WB,
            movable_names(scene),
        )
        if grip_opening_m is not None:
            program = _holding(program, scene, workpiece, grip_opening_m)
        say(0.85, "checking every move for collisions")
        check = sweeper.program(program)
        if check.ok:
            if feasible:  # quick (tens of ms): no progress stage of its own
                verdict = check_feasibility(
                    scene, workpiece, program, attached_O, X_WO, robot=robot
                )
                if not verdict.ok:
                    raise ProgramInfeasibleError(verdict, check)
            return Generated(program, raw, deformed, check)
        if deformed.settled or deform_params.max_sweeps >= REFUSED_RETRY_MAX_SWEEPS:
            raise ProgramRefusedError(check)
        deform_params = replace(deform_params, max_sweeps=REFUSED_RETRY_MAX_SWEEPS)
        say(0.15, f"{check.reason}: deforming the path further")
