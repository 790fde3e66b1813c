"""Path deformation (§VI-A, after Quinlan's elastic bands): straighten the operator's path and
pull it off unwanted contacts while keeping the required ones.

Each free node feels
  1. a tension towards each neighbour, in position and orientation (orientation weighted by the
     simulator's characteristic length, so a turn counts like the travel of a point at that
     radius): constant in magnitude, and proportional to the distance for neighbours closer than
     a minimum (§VII-C: constant tension alone makes close nodes unstable);
  2. a repulsion in translation from each unwanted obstacle part within a range, growing
     linearly as the gap closes, with its component along the path removed (nodes must not
     slide along it) — except for parts the node already touches: where the path runs straight
     into an obstacle's normal (an approach from above onto a bar's edge) removing it would
     leave the node stuck in the unwanted contact;
  3. on a node with required contacts, a small holding force towards each required object, so
     that it slides along it rather than drifting to the capture barrier ε_o;
and is moved by the contact step (:mod:`operator_site.program.contact_step`) with these as the
applied force and moment, so it never collides and never loses a required contact. Path ends
and the ends of required-contact stretches are fixed.

Differences from the paper, each for speed or stability: all nodes move together (Jacobi; the
paper moves them in succession), so that tension is one vectorised computation and nodes far
from every obstacle move without any distance query; a node whose motion reverses has its
mobility halved until it stops overshooting; and the path is deformed coarse to fine (spacing
40, 20, 10 mm by default), because constant tension shortens a path by at most one step per
sweep. Between sweeps nodes are inserted where the path has stretched (dragged there by the
contact step where the straight midpoint is not admissible) and removed where it has shrunk.
A coarse level ends when a sweep no longer shortens the path by a fifth of its spacing; at the
finest, the sweeps repeat until no node moves more than ``settle_m``, or until the path stops
getting shorter (``patience_sweeps``; reported as not settled: round a corner in contact, nodes
keep sliding slowly along the path, where any spacing is an equilibrium).
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from models.geometry import ConvexPart
from models.scene import Scene
from operator_site.program.contact_step import (
    EMPTY_PROBE,
    ContactStepper,
    Probe,
    away_normal,
    held_towards,
)
from operator_site.program.path import NodeContact, PathNode, WorkpiecePath
from operator_site.program.poses import centres, exp_batch, interpolate, log_batch
from operator_site.simulator import SimParams
from operator_site.simulator.params import refuse_out_of_range
from operator_site.simulator.world import PairDistance, SimWorld

REST_FRACTION = 0.1
"""A near node whose applied push would move it less than this fraction of ``settle_m`` is left
where it is for the sweep."""
COINCIDENT_FRACTION = 0.2
"""A node closer than this fraction of the spacing to its kept predecessor is dropped even at a
corner (two nodes jammed together make the proportional tension between them stiff)."""
DRAG_STEPS = 3
"""Contact steps taken to drag a node into a gap whose straight midpoint is not admissible."""
DRAG_FORCE_N = 10.0
"""The pull on a dragged node (N): strong, so each step goes its full length unless blocked."""
MAX_NODES = 5000
"""Nodes a deformation may hold: a path that would need more at its spacing is refused, and
the sweeps stop (``node cap``) if insertions take it past this. Each sweep costs up to a
contact step per node."""

RANGES: dict[str, tuple[float, float, str]] = {
    "spacing_m": (1e-5, 0.1, "nodes 10 µm to 10 cm apart"),
    "insert_factor": (1.1, 4.0, "a node is inserted where two are this many spacings apart"),
    "tension_n": (1e-3, 1e3, "N"),
    "tension_min_fraction": (1e-3, 1.0, "of the spacing"),
    "step_fraction": (
        1e-3,
        0.5,
        "above a half, two neighbours could move a node bent back on itself further than "
        "the spacing in one sweep",
    ),
    "repulsion_n": (1e-3, 1e3, "N"),
    "repulsion_range_m": (1e-5, 0.1, "m"),
    "hold_n": (1e-3, 1e3, "N"),
    "max_step_fraction": (1e-3, 1.0, "of the spacing"),
    "settle_coarse_fraction": (1e-3, 1.0, "of the level's spacing"),
    "settle_m": (1e-9, 1e-2, "m"),
    "progress_m": (1e-9, 1e-2, "m"),
    "coarse_spacing_m": (1e-5, 1.0, "m"),
}
"""Each float knob of :class:`DeformParams`: accepted range (inclusive) and why."""
INT_RANGES: dict[str, tuple[int, int]] = {
    "max_sweeps": (0, 100_000),
    "max_sweeps_coarse": (0, 10_000),
    "patience_sweeps": (1, 10_000),
}
"""Each integer knob's accepted range (inclusive): the sweeps, and so the cost, are bounded."""


@dataclass(frozen=True)
class DeformParams:
    """Knobs of the deformation (SI). Forces are in N and become displacements through the
    simulator's damping d_t (equation 1) over one step Δt, scaled so that a node pulled by
    ``tension_n`` moves ``step_fraction`` of the spacing per sweep: at the finest level with the
    defaults one newton moves a node 2.5 mm, whatever the simulator's d_t and Δt. Only the
    ratios of tension, repulsion and holding shape the path."""

    spacing_m: float = 0.01
    """Target node spacing (centre travel plus turn × characteristic length). A node is removed
    when its neighbours are closer than this, and one is inserted where two are more than
    ``insert_factor`` × this apart."""
    insert_factor: float = 1.5
    tension_n: float = 1.0
    """Constant tension towards each neighbour (N)."""
    tension_min_fraction: float = 0.5
    """Neighbours closer than this fraction of the spacing pull with tension × distance / that
    distance (§VII-C: constant tension alone makes close nodes unstable)."""
    step_fraction: float = 0.25
    """One neighbour's tension moves a node this fraction of the spacing per sweep (the
    mobility d_t·Δt is scaled to it). With two neighbours a node bent back on itself moves at
    most half the spacing: damped enough that all-at-once sweeps do not oscillate."""
    repulsion_n: float = 3.0
    """Repulsion at zero gap (N); it falls linearly to 0 at ``repulsion_range_m``. Three times
    the tension: a node bearing a right-angle bend (net tension √2 N) still keeps half the range
    clear."""
    repulsion_range_m: float = 0.01
    hold_n: float = 0.5
    """Holding force towards each required object (N)."""
    max_step_fraction: float = 0.5
    """No point of a node moves further than this fraction of the spacing per sweep (longer
    moves near obstacles are checked at intermediate poses, so nothing is tunnelled through)."""
    max_sweeps: int = 45
    """Sweeps allowed over all levels together. It bounds the cost: a path round an outside
    corner does not settle, its nodes in contact creep on until ``patience_sweeps`` stops them,
    and the last of that creep changes the program's targets by millimetres. A program the
    check refuses after a capped deformation is made again with more sweeps
    (``generate.REFUSED_RETRY_MAX_SWEEPS``)."""
    max_sweeps_coarse: int = 15
    """Sweeps allowed at each level but the finest (they only prepare it)."""
    settle_coarse_fraction: float = 0.2
    """A coarse level is done when a sweep shortened the path by less than this fraction of the
    level's spacing (it only prepares the next level, whose sweeps shorten by half as much).
    Its nodes' displacements are no measure: on a gently bent path they are a fraction of a
    step while the path still shortens by centimetres a sweep."""
    settle_m: float = 3e-4
    """The path has settled when no point of any node moved further than this in a sweep (m)."""
    patience_sweeps: int = 10
    """… or, at the finest level, stop when the path has not become ``progress_m`` shorter in
    this many sweeps since it last had more nodes than ever before (nodes jostling round a
    corner in contact never settle; §VII-B notes the same sticking for captures going round
    corners). The result then says it stopped on ``no progress``."""
    progress_m: float = 5e-4
    coarse_spacing_m: float = 0.04
    """Coarse to fine: the path is first deformed with about this spacing, then with half of
    it, and so on down to ``spacing_m``; at each level the spacing, the step limit and the
    mobility are that multiple of the defaults. Constant tension shortens a path by at most one
    step per sweep, so a coarse path first makes the big moves in few sweeps; finer levels then
    add the detail."""

    @property
    def levels(self) -> tuple[float, ...]:
        """The levels' multiples of ``spacing_m``, coarse to fine (powers of two, last 1)."""
        k = max(0, math.ceil(math.log2(self.coarse_spacing_m / self.spacing_m) - 1e-9))
        return tuple(float(2**i) for i in range(k, -1, -1))

    def __post_init__(self) -> None:
        refuse_out_of_range("DeformParams", self, RANGES)
        for name, (lo, hi) in INT_RANGES.items():
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi):
                raise ValueError(
                    f"DeformParams.{name} must be an integer in [{lo}, {hi}], got {value!r}"
                )


@dataclass
class DeformResult:
    """The settled path and what it took."""

    path: WorkpiecePath
    sweeps: int
    stopped: str
    """Why the sweeps stopped: ``settled`` (no node moved ``settle_m``), ``no progress`` (the
    path stopped getting shorter, ``patience_sweeps``), ``sweep cap`` (``max_sweeps``) or
    ``node cap`` (insertions took the path past :data:`MAX_NODES`)."""
    elapsed_s: float
    probes: int
    """Distance probes made (each one query per nearby pair of convex parts)."""
    history_m: list[float] = field(default_factory=list)
    """Path length after each sweep (m)."""

    @property
    def settled(self) -> bool:
        """Whether the sweeps stopped because the path settled."""
        return self.stopped == "settled"


@dataclass
class _Node:
    X: np.ndarray
    required: frozenset[str]
    fixed: bool
    probe: Probe | None = None  # at X; None: not yet queried
    gain: float = 1.0  # this node's mobility factor, halved when its motion reverses
    last: np.ndarray | None = None  # its last centre displacement (m)
    touching: bool = True  # in contact in the history (before it has a probe)


def _metric_vectors(X: np.ndarray, c_O: np.ndarray, char_m: float) -> np.ndarray:
    """(n − 1, 6): from each node to the next, centre travel (m) and turn × ``char_m`` (m)."""
    C = centres(X, c_O)
    R = X[:, :3, :3]
    turn = log_batch(R[1:] @ np.swapaxes(R[:-1], -1, -2))
    return np.hstack([C[1:] - C[:-1], char_m * turn])


class Deformer:
    """Deforms workpiece paths in one scene (the world and its broad phase built once)."""

    def __init__(
        self,
        scene: Scene,
        workpiece: str,
        params: DeformParams | None = None,
        sim_params: SimParams | None = None,
        attached_O: tuple[ConvexPart, ...] = (),
        X_WO: dict[str, np.ndarray] | None = None,
    ) -> None:
        """``attached_O``: the gripper's fingers as parts of the workpiece (see grasp.py);
        ``X_WO``: object poses overriding the scene's (the task session's model)."""
        self.params = params or DeformParams()
        self.sim_params = sim_params or SimParams()
        self.scene = scene
        self.world = SimWorld(
            scene, workpiece, {o.name: o.X_WO for o in scene.objects} | (X_WO or {}), attached_O
        )
        self.c_O = scene.object(workpiece).model.com_O.astype(np.float64)
        reach = self.params.repulsion_range_m
        self.stepper = ContactStepper(self.world, self.c_O, self.sim_params, reach)
        self.char_m = self.sim_params.char_length_m
        self._level = 1.0

    # ------------------------------------------------------------------------ public API

    def deform(self, path: WorkpiecePath) -> DeformResult:
        """The settled deformation of ``path`` (its nodes are respaced first)."""
        t0 = time.perf_counter()
        probes0 = self.stepper.probes
        p = self.params
        nodes = [
            _Node(n.X_WO.copy(), n.required, n.fixed, touching=bool(n.contacts)) for n in path.nodes
        ]
        X = np.array([node.X for node in nodes])
        metric_m = float(np.sum(np.linalg.norm(_metric_vectors(X, self.c_O, self.char_m), axis=1)))
        if metric_m / p.spacing_m > MAX_NODES:
            raise ValueError(
                f"DeformParams.spacing_m {p.spacing_m:g} m would put {metric_m / p.spacing_m:.0f} "
                f"nodes on this {metric_m:.3g} m path (at most {MAX_NODES}): for it, spacing_m "
                f"must be at least {metric_m / MAX_NODES:.3g} m"
            )
        lengths: list[float] = []
        sweeps = 0
        levels = p.levels
        for level in levels:
            self._level = level
            nodes = self._decimate(nodes) if level == levels[0] else self._remove_close(nodes)
            for node in nodes:
                node.gain, node.last = 1.0, None
            stopped = "sweep cap"
            first_fine, most_nodes = len(lengths), len(nodes)
            finest = level == levels[-1]
            cap = p.max_sweeps if finest else sweeps + p.max_sweeps_coarse
            before_m = self._length(nodes)
            while sweeps < min(cap, p.max_sweeps):
                sweeps += 1
                moved = self._sweep(nodes)
                nodes = self._insert(self._remove_close(nodes))
                lengths.append(self._length(nodes))
                if len(nodes) > most_nodes:
                    # Nodes inserted add detail and lengthen the path: progress is measured from
                    # the most nodes the level has had (not from each insertion of nodes
                    # jostling round a corner, which would never let the patience run out).
                    most_nodes, first_fine = len(nodes), len(lengths) - 1
                if len(nodes) > MAX_NODES:
                    stopped = "node cap"
                    break
                if not finest:
                    if before_m - lengths[-1] < p.settle_coarse_fraction * p.spacing_m * level:
                        break
                    before_m = lengths[-1]
                elif moved < p.settle_m:
                    stopped = "settled"
                    break
                else:
                    fine, k = lengths[first_fine:], p.patience_sweeps
                    if len(fine) > k and min(fine[-k:]) > min(fine[:-k]) - p.progress_m:
                        stopped = "no progress"
                        break
            if stopped == "node cap":
                break
        out = WorkpiecePath(path.workpiece, tuple(self._finish(n) for n in nodes), self.c_O)
        return DeformResult(
            out, sweeps, stopped, time.perf_counter() - t0, self.stepper.probes - probes0, lengths
        )

    def _length(self, nodes: list[_Node]) -> float:
        """The path's length: its centres' polyline (m)."""
        C = centres(np.array([n.X for n in nodes]), self.c_O)
        return float(np.sum(np.linalg.norm(np.diff(C, axis=0), axis=1)))

    def node_contacts(self, X_WO: np.ndarray, required: frozenset[str]) -> tuple[NodeContact, ...]:
        """The contact state at ``X_WO``: objects within ε_c (ε_o if required), with normals."""
        probe = self.stepper.probe(X_WO)
        return self._contacts_of(X_WO, probe, required)

    # ------------------------------------------------------------------------ internals

    def _contacts_of(
        self, X_WO: np.ndarray, probe: Probe, required: frozenset[str]
    ) -> tuple[NodeContact, ...]:
        names, _, N, _ = self.stepper.contacts(X_WO, probe, required)
        out = []
        for name in dict.fromkeys(names):
            rows = np.array([k for k, m in enumerate(names) if m == name])
            normals = np.unique(np.round(N[rows], 9), axis=0)
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
            out.append(NodeContact(name, normals, probe.distance_m(name)))
        return tuple(out)

    def _finish(self, node: _Node) -> PathNode:
        probe = node.probe if node.probe is not None else self.stepper.probe(node.X)
        return PathNode(
            node.X, self._contacts_of(node.X, probe, node.required), node.required, node.fixed
        )

    def _near_mask(self, X: np.ndarray, grow_m: float) -> np.ndarray:
        """Nodes whose workpiece box, grown by ``grow_m``, overlaps an obstacle's box (n,)."""
        V = np.einsum("nij,vj->nvi", X[:, :3, :3], self.world.wp_vertices_O) + X[:, None, :3, 3]
        lo, hi = V.min(axis=1) - grow_m, V.max(axis=1) + grow_m
        W_lo, W_hi = self.world.lo_W, self.world.hi_W
        overlap = np.all((W_lo[None] <= hi[:, None]) & (W_hi[None] >= lo[:, None]), axis=2)
        return overlap.any(axis=1)

    def _tension(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tension force (n, 3) N and moment (n, 3) N·m on every node from its neighbours."""
        p = self.params
        E = _metric_vectors(X, self.c_O, self.char_m)  # node k → k+1
        L = np.linalg.norm(E, axis=1, keepdims=True)
        s_m = p.spacing_m * self._level
        U = p.tension_n * E / np.maximum(L, p.tension_min_fraction * s_m)
        W = np.zeros((len(X), 6))
        W[:-1] += U  # pulled towards the next node
        W[1:] -= U  # … and towards the previous one
        return W[:, :3], W[:, 3:] * self.char_m

    def _sweep(self, nodes: list[_Node]) -> float:
        """Move every free node once; the largest displacement of any point (m)."""
        p, sp = self.params, self.sim_params
        s_m = p.spacing_m * self._level
        # Forces become displacements through the simulator's d_t·Δt (equation 1), scaled so
        # that one neighbour's tension moves a node step_fraction of the spacing per sweep.
        # Repulsion and holding get the finest level's scale: they balance the tension as
        # forces, whatever the simulator's d_t and Δt.
        L_fine = p.step_fraction * p.spacing_m / (sp.d_t * sp.dt_s * p.tension_n)
        L = L_fine * self._level
        n = len(nodes)
        if n < 3:
            return 0.0
        X = np.array([node.X for node in nodes])
        C_all = centres(X, self.c_O)
        F, M = self._tension(X)
        gain = L * np.array([node.gain for node in nodes])
        F, M = F * gain[:, None], M * gain[:, None]
        free = np.array([not node.fixed for node in nodes])
        max_step = p.max_step_fraction * s_m
        near = self._near_mask(X, p.repulsion_range_m + max_step) | np.array(
            [bool(node.required) for node in nodes]
        )
        # Far from everything: a free step, all at once (no obstacle within reach of the step).
        far = np.flatnonzero(free & ~near)
        if len(far):
            v, w = sp.d_t * F[far] * sp.dt_s, sp.d_r * M[far] * sp.dt_s
            reach = np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1) * self.stepper.r_max_m
            scale = np.minimum(1.0, max_step / np.maximum(reach, 1e-300))
            R = exp_batch(w * scale[:, None]) @ X[far, :3, :3]
            C = C_all[far] + v * scale[:, None]
            for k, i in enumerate(far):
                Xi = np.eye(4)
                Xi[:3, :3] = R[k]
                Xi[:3, 3] = C[k] - R[k] @ self.c_O
                nodes[i].X, nodes[i].probe = Xi, EMPTY_PROBE
        for i in np.flatnonzero(free & near):
            node = nodes[i]
            probe = node.probe if node.probe is not None else self.stepper.probe(node.X)
            tangent = C_all[i + 1] - C_all[i - 1]
            tangent /= max(float(np.linalg.norm(tangent)), 1e-300)
            # Only the tension scales with the level: repulsion and holding act over millimetres
            # whatever the spacing, and a coarse mobility would make them overshoot.
            f = F[i] + node.gain * L_fine * self._repulsion(probe, node.required, tangent)
            # A node whose push (holding force aside) would move it less than a tenth of the
            # settling distance stays: it would only press on its contacts, at the price of a
            # contact LCP.
            push_m = sp.dt_s * (
                sp.d_t * float(np.linalg.norm(f))
                + sp.d_r * float(np.linalg.norm(M[i])) * self.stepper.r_max_m
            )
            if push_m < REST_FRACTION * p.settle_m and probe.nearest:
                node.probe = probe
                continue
            f = held_towards(f, probe, node.required, node.gain * L_fine * p.hold_n)
            node.X, node.probe, _ = self.stepper.displace(
                node.X, probe, f, M[i], node.required, max_step
            )
        # A node whose motion reverses is overshooting (repulsion and close-range tension are
        # stiff): halve its mobility; one that keeps going regains it.
        X1 = np.array([node.X for node in nodes])
        dC = centres(X1, self.c_O) - C_all
        for i in np.flatnonzero(free):
            node = nodes[i]
            if node.last is not None and node.last @ dC[i] < 0:
                node.gain *= 0.5
            else:
                node.gain = min(1.0, node.gain * 1.25)
            node.last = dC[i]
        turn = np.linalg.norm(log_batch(X1[:, :3, :3] @ np.swapaxes(X[:, :3, :3], -1, -2)), axis=1)
        return float(np.max(np.linalg.norm(dC, axis=1) + turn * self.stepper.r_max_m))

    def _repulsion(self, probe: Probe, required: frozenset[str], tangent: np.ndarray) -> np.ndarray:
        """Repulsion (3,) N from unwanted obstacles within range, normal to the path."""
        p = self.params
        f = np.zeros(3)
        # Per obstacle part (not per object): a block wedged between two bars of the frame is
        # pushed off both, even when the nearer one pushes along the path.
        nearest: dict[int, PairDistance] = {}
        for pair in probe.pairs:
            if pair.obstacle not in nearest or pair.distance_m < nearest[pair.obstacle].distance_m:
                nearest[pair.obstacle] = pair
        touching = np.zeros(3)
        for i, pair in nearest.items():
            if self.world.obstacle_object[i] in required or pair.distance_m >= p.repulsion_range_m:
                continue
            push = p.repulsion_n * (1.0 - pair.distance_m / p.repulsion_range_m) * away_normal(pair)
            if pair.distance_m < self.sim_params.eps_contact_m:
                touching += push
            else:
                f += push
        # The tangential part is removed so that nodes do not slide along the path (§VI-A);
        # but a node in an unwanted contact keeps it: where the path runs into an obstacle's
        # normal (an approach from above onto a bar's edge), it is the only way out.
        return f - (f @ tangent) * tangent + touching

    def _remove_close(self, nodes: list[_Node]) -> list[_Node]:
        """Drop free nodes whose neighbours are closer than the spacing (never two in a row),
        unless the pose halfway between those neighbours is not admissible (a node at a convex
        corner holds the path round it)."""
        if len(nodes) < 3:
            return nodes
        spacing = self.params.spacing_m * self._level
        X = np.array([node.X for node in nodes])
        step = np.linalg.norm(_metric_vectors(X, self.c_O, self.char_m), axis=1)
        out = [nodes[0]]
        gap = 0.0  # metric length from the last kept node to the current one
        for i in range(1, len(nodes) - 1):
            gap += step[i - 1]
            # Bounded by the triangle inequality: the kept neighbours are at most this apart.
            if not nodes[i].fixed and gap + step[i] < spacing:
                # A node (nearly) on top of its kept neighbour adds nothing that neighbour
                # does not hold; any other must not be holding the path round a corner.
                coincident = gap < COINCIDENT_FRACTION * spacing
                if coincident or not (
                    self._touching(nodes[i]) and not self._midpoint_ok(out[-1], nodes[i + 1])
                ):
                    continue
            out.append(nodes[i])
            gap = 0.0
        out.append(nodes[-1])
        return out

    def _decimate(self, nodes: list[_Node]) -> list[_Node]:
        """The history thinned to the spacing: every node closer than the spacing to the last
        kept one is dropped (fixed nodes are kept); then each chord between kept nodes whose
        midpoint is not admissible gets back the dropped node halfway along it, recursively
        (the operator's path went round something there)."""
        spacing = self.params.spacing_m * self._level
        X = np.array([node.X for node in nodes])
        step = np.linalg.norm(_metric_vectors(X, self.c_O, self.char_m), axis=1)
        keep = [0]
        gap = 0.0
        for i in range(1, len(nodes)):
            gap += step[i - 1]
            if nodes[i].fixed or i == len(nodes) - 1 or gap >= spacing:
                keep.append(i)
                gap = 0.0
        out = [0]
        todo = list(itertools.pairwise(keep))[::-1]
        while todo:
            a, b = todo.pop()
            if b - a > 1 and not self._midpoint_ok(nodes[a], nodes[b]):
                m = (a + b) // 2
                todo += [(m, b), (a, m)]
                continue
            out.append(b)
        return [nodes[i] for i in out]

    def _touching(self, node: _Node) -> bool:
        """Whether ``node`` is close enough to something to be holding the path round it."""
        if node.probe is None:
            return node.touching
        d = min((pair.distance_m for pair in node.probe.nearest.values()), default=np.inf)
        return d < self.sim_params.eps_capture_m

    def _midpoint_ok(self, a: _Node, b: _Node) -> bool:
        mid = interpolate(a.X, b.X, np.array([0.5]), self.c_O)[0]
        return self.stepper.admissible(self.stepper.probe(mid), a.required & b.required)

    def _insert(self, nodes: list[_Node]) -> list[_Node]:
        """Put a node halfway between neighbours further apart than the insertion distance,
        where that pose is admissible."""
        p = self.params
        X = np.array([node.X for node in nodes])
        gaps = np.linalg.norm(_metric_vectors(X, self.c_O, self.char_m), axis=1)
        wide = np.flatnonzero(gaps > p.insert_factor * p.spacing_m * self._level)
        if len(wide) == 0:
            return nodes
        mids = interpolate(X[wide], X[wide + 1], np.full(len(wide), 0.5), self.c_O)
        out: list[_Node] = []
        k = 0
        for i, node in enumerate(nodes):
            out.append(node)
            if k < len(wide) and wide[k] == i:
                required = node.required & nodes[i + 1].required
                probe = self.stepper.probe(mids[k])
                new = (
                    _Node(mids[k], required, False, probe)
                    if self.stepper.admissible(probe, required)
                    else self._drag(node, mids[k], required, gaps[i])
                )
                if new is not None:
                    new.gain = min(node.gain, nodes[i + 1].gain)
                    out.append(new)
                k += 1
        return out

    def _drag(
        self, start: _Node, X_goal: np.ndarray, required: frozenset[str], gap_m: float
    ) -> _Node | None:
        """A node made by dragging a copy of ``start`` towards ``X_goal`` with the contact step
        (where the straight midpoint is not admissible: round a corner, over an edge)."""
        p = self.params
        X = start.X
        probe = start.probe if start.probe is not None else self.stepper.probe(X)
        travelled = 0.0
        for _ in range(DRAG_STEPS):
            e = _metric_vectors(np.array([X, X_goal]), self.c_O, self.char_m)[0]
            norm = float(np.linalg.norm(e))
            if norm < 1e-9:
                break
            f = DRAG_FORCE_N * e[:3] / norm
            m = DRAG_FORCE_N * e[3:] / norm * self.char_m
            f = held_towards(f, probe, required, p.hold_n)
            X, probe, step = self.stepper.displace(
                X, probe, f, m, required, 0.5 * gap_m / DRAG_STEPS
            )
            travelled += step
        if travelled < 0.1 * gap_m:
            return None
        return _Node(X, required, False, probe)
