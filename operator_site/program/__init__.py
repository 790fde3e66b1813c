"""The program generator (§VI): from the operator's simulated task to a robot motion program.

:func:`generate_program` runs it end to end: the simulator's history becomes a
:class:`WorkpiecePath` with its required contacts marked (:mod:`.path`), the path is deformed
after Quinlan (:mod:`.deform`, moving each node with the contact step of :mod:`.contact_step`),
fitted with few spatially-linear moves (:mod:`.commands`) and swept against the model before
sending (:mod:`.check`); :func:`check_feasibility` asks whether the robot can do it at all
(:mod:`.feasibility`: its grasp, its reach, contacts it can verify by force).
:func:`pick_and_place` is the straight program without deformation.
"""

from operator_site.program.check import CheckResult, Sweeper, check_program
from operator_site.program.commands import (
    CommandParams,
    build_program,
    fit_targets,
    park_pose_W,
    program_to_json,
    target_bias,
)
from operator_site.program.deform import Deformer, DeformParams, DeformResult
from operator_site.program.feasibility import Feasibility, check_feasibility
from operator_site.program.generate import (
    Generated,
    ProgramInfeasibleError,
    ProgramRefusedError,
    generate_program,
)
from operator_site.program.path import (
    NodeContact,
    PathNode,
    WorkpiecePath,
    lost_contact_nodes,
    path_from_history,
    unwanted_contact_nodes,
)
from operator_site.program.pick_place import choose_grasp_yaw, pick_and_place

__all__ = [
    "CheckResult",
    "CommandParams",
    "DeformParams",
    "DeformResult",
    "Deformer",
    "Feasibility",
    "Generated",
    "NodeContact",
    "PathNode",
    "ProgramInfeasibleError",
    "ProgramRefusedError",
    "Sweeper",
    "WorkpiecePath",
    "build_program",
    "check_feasibility",
    "check_program",
    "choose_grasp_yaw",
    "fit_targets",
    "generate_program",
    "lost_contact_nodes",
    "park_pose_W",
    "path_from_history",
    "pick_and_place",
    "program_to_json",
    "target_bias",
    "unwanted_contact_nodes",
]
