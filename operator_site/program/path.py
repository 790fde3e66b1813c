"""The workpiece path of §VI: the simulator's history as nodes, with the required contacts marked.

Each step of the task simulation is a *node*: the workpiece pose ``X_WO`` and its contacts
(object names and normals). A contact is *required* where the operator asked for it: the final
contact state (the task's goal), and every stretch where the operator held a capture object
(Fig. 13 bottom). Everything else the workpiece touched on the way is unwanted (Fig. 12).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from operator_site.program.poses import centres
from operator_site.simulator import StepResult

SAME_POSE_TOL_M = 1e-9
"""Consecutive history poses whose points all lie within this of each other are one node (a
workpiece at rest adds a step per 50 ms but no path)."""


@dataclass(frozen=True, eq=False)
class NodeContact:
    """Contact of the workpiece with ``object`` at a node: ``normals_W`` (k, 3) unit normals
    pointing into the workpiece, ``distance_m`` the smallest separation."""

    object: str
    normals_W: np.ndarray
    distance_m: float


@dataclass(frozen=True, eq=False)
class PathNode:
    """One node: pose ``X_WO`` (4, 4), its contacts, and the objects it must stay in contact
    with (``required``); ``fixed`` nodes are never moved (path ends, ends of required
    stretches)."""

    X_WO: np.ndarray
    contacts: tuple[NodeContact, ...]
    required: frozenset[str]
    fixed: bool = False


@dataclass(frozen=True, eq=False)
class WorkpiecePath:
    """The workpiece's path: nodes in order, and the workpiece's centre of mass ``c_O`` (3,)
    (the point whose travel measures path length)."""

    workpiece: str
    nodes: tuple[PathNode, ...]
    c_O: np.ndarray

    def __len__(self) -> int:
        return len(self.nodes)

    @property
    def poses(self) -> np.ndarray:
        """All node poses, (n, 4, 4)."""
        return np.array([node.X_WO for node in self.nodes])

    @property
    def centres_W(self) -> np.ndarray:
        """The centre of mass at each node, (n, 3)."""
        return centres(self.poses, self.c_O)

    def length_m(self) -> float:
        """Distance travelled by the centre of mass along the piecewise-linear path (m)."""
        C = self.centres_W
        return float(np.sum(np.linalg.norm(np.diff(C, axis=0), axis=1)))

    def stretches(self) -> list[tuple[int, int, frozenset[str]]]:
        """Maximal runs ``(first, last, objects)`` of nodes with the same non-empty required
        set (inclusive indices)."""
        runs: list[tuple[int, int, frozenset[str]]] = []
        for i, node in enumerate(self.nodes):
            if runs and runs[-1][2] == node.required and runs[-1][1] == i - 1:
                runs[-1] = (runs[-1][0], i, node.required)
            elif node.required:
                runs.append((i, i, node.required))
        return runs


def mark_fixed(nodes: Sequence[PathNode]) -> tuple[PathNode, ...]:
    """``nodes`` with the path's ends and the first and last node of every run of equal,
    non-empty required sets marked fixed (§VI-A: "path endpoints are kept fixed, as are the
    endpoints of any required contact motions")."""
    n = len(nodes)
    fixed = np.zeros(n, dtype=bool)
    fixed[[0, n - 1]] = True
    for i in range(n):
        if nodes[i].required and (i == 0 or nodes[i - 1].required != nodes[i].required):
            fixed[i] = True
        if nodes[i].required and (i == n - 1 or nodes[i + 1].required != nodes[i].required):
            fixed[i] = True
    return tuple(
        PathNode(node.X_WO, node.contacts, node.required, bool(fixed[i]) or node.fixed)
        for i, node in enumerate(nodes)
    )


def path_from_history(
    history: Sequence[StepResult], workpiece: str, c_O: np.ndarray
) -> WorkpiecePath:
    """The workpiece path of a simulation ``history`` (a :attr:`Simulator.history`; put the
    start state first, as ``TaskSession.path_history`` does, or the path starts one step late).

    Steps that did not move the workpiece are dropped; a node's required contacts are its
    captured ones, and the last node's whole contact state is required (the goal).
    """
    if not history:
        raise ValueError("the simulator's history is empty: the operator has not moved anything")
    kept: list[StepResult] = []
    for step in history:
        if kept and np.max(np.abs(step.X_WO - kept[-1].X_WO)) <= SAME_POSE_TOL_M:
            kept[-1] = step  # same pose: keep the latest contact state
            continue
        kept.append(step)
    nodes = []
    for k, step in enumerate(kept):
        contacts = tuple(
            NodeContact(c.object, np.asarray(c.normals_W, dtype=np.float64), c.distance_m)
            for c in step.contacts
        )
        if k == len(kept) - 1:
            required = frozenset(c.object for c in step.contacts)
        else:
            required = frozenset(c.object for c in step.contacts if c.captured)
        nodes.append(PathNode(np.array(step.X_WO, dtype=np.float64), contacts, required))
    return WorkpiecePath(workpiece, mark_fixed(nodes), np.asarray(c_O, dtype=np.float64))


def unwanted_contact_nodes(path: WorkpiecePath) -> list[int]:
    """Nodes between the path's ends touching something they are not required to touch (the
    ends are where the workpiece starts and rests, fixed by the task)."""
    return [
        i
        for i, node in enumerate(path.nodes[1:-1], start=1)
        if any(c.object not in node.required for c in node.contacts)
    ]


def lost_contact_nodes(path: WorkpiecePath) -> list[int]:
    """Nodes missing one of their required contacts."""
    return [
        i
        for i, node in enumerate(path.nodes)
        if not node.required <= {c.object for c in node.contacts}
    ]
