"""The task simulator (§V): first-order contact dynamics with barrier potentials and captures.

Create a :class:`Simulator` for a scene and a workpiece, :meth:`~Simulator.set_target` the
dragger's pose, :meth:`~Simulator.capture` / :meth:`~Simulator.release` objects, and
:meth:`~Simulator.step`; each step returns the new pose with its contacts, and
:attr:`~Simulator.history` keeps the workpiece's path for the program generator (§VI).
"""

from operator_site.simulator.lcp import LcpResult, solve_lcp
from operator_site.simulator.params import SimParams
from operator_site.simulator.stepper import Contact, Simulator, StepResult

__all__ = ["Contact", "LcpResult", "SimParams", "Simulator", "StepResult", "solve_lcp"]
