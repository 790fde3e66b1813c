"""One contact-constrained displacement of a workpiece pose under an applied wrench (§VI-A).

The path deformation moves each node "using the contact simulation algorithm of Sections V-A
and V-B, with the combined tension and repulsive forces assuming the role of the applied force
and moment". This is that algorithm as a function of a pose rather than of a simulator's state,
built from the simulator's own parts (:class:`SimWorld` distances, :func:`contact_manifold`,
:func:`solve_lcp`, equation (1)): contact points from the pose → the frictionless contact LCP →
spatial velocity → a step along it. The step is accepted at its full length or the longest of
a few halvings that keeps every object at least the barrier floor away and every required
(captured) object within ε_o; a node never ends in collision nor loses a required contact.
The simulator's golden-section search over the barrier potential is replaced by this
backtracking: a deformation step is not a time step, and one distance query per node is what
keeps a 300-node path within its time budget.

Frames: W world, O the workpiece; the workpiece turns about its centre of mass ``c_O``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from models.transforms import orthonormalize, so3_exp
from operator_site.simulator import SimParams, solve_lcp
from operator_site.simulator.contacts import contact_manifold
from operator_site.simulator.world import PairDistance, SimWorld

BACKTRACK_HALVINGS = 4
"""A blocked step is retried at 1/2, 1/4, … of its length this many times before the node stays."""


@dataclass(frozen=True, eq=False)
class Probe:
    """The obstacle parts near a pose: ``nearest`` maps each object within reach to its nearest
    pair (distance, nearest points), ``pairs`` every queried pair."""

    pairs: tuple[PairDistance, ...]
    nearest: dict[str, PairDistance]

    def distance_m(self, name: str) -> float:
        """Distance to object ``name`` (inf when it is out of reach)."""
        pair = self.nearest.get(name)
        return pair.distance_m if pair is not None else math.inf


EMPTY_PROBE = Probe((), {})


def away_normal(pair: PairDistance) -> np.ndarray:
    """Unit vector (3,) from the obstacle's nearest point to the workpiece's (the direction the
    obstacle would push)."""
    gap = pair.p_wp - pair.p_obstacle
    return gap / max(float(np.linalg.norm(gap)), 1e-300)


def held_towards(f_W: np.ndarray, probe: Probe, names: Iterable[str], hold_n: float) -> np.ndarray:
    """``f_W`` (N, W) less ``hold_n`` along :func:`away_normal` of each named object's nearest
    pair in ``probe``: the pull that keeps a workpiece on the contacts it must keep. Summed in
    sorted name order: a set of names iterates in the order of Python's per-process string
    hash, and the sum's rounding, amplified over the deformation's sweeps, would change the
    program from one run to the next."""
    for name in sorted(names):
        pair = probe.nearest.get(name)
        if pair is not None:
            f_W = f_W - hold_n * away_normal(pair)
    return f_W


class ContactStepper:
    """Contact-constrained displacements of one workpiece among a scene's fixed obstacles."""

    def __init__(self, world: SimWorld, c_O: np.ndarray, params: SimParams, reach_m: float) -> None:
        """``reach_m``: obstacles up to this far away are queried (≥ ε_o; the repulsion range)."""
        self.world = world
        self.params = params
        self.c_O = np.asarray(c_O, dtype=np.float64)
        self.reach_m = max(float(reach_m), params.eps_capture_m)
        self.r_max_m = float(np.max(np.linalg.norm(world.wp_vertices_O - self.c_O, axis=1)))
        self.floor_m = params.floor_m
        self.sample_m = params.tunnel_fraction * world.thinnest_obstacle_m
        """Longer moves are also checked at intermediate poses this far apart (§VII-B)."""
        self.probes = 0
        """Poses probed so far (each is one distance query per nearby pair of parts)."""
        self._clamped: dict[tuple[str, ...], np.ndarray] = {}
        """The LCP's last clamped set for each list of contact points' objects: nodes of a path
        in the same contacts mostly clamp the same points, so pivoting is rarely needed."""

    # ------------------------------------------------------------------------------ queries

    def probe(self, X_WO: np.ndarray) -> Probe:
        """Distances from the workpiece at ``X_WO`` to every obstacle part within reach."""
        lo, hi = self.world.workpiece_box(X_WO, self.reach_m)
        near = self.world.candidates(lo, hi)
        if len(near) == 0:
            return EMPTY_PROBE
        self.probes += 1
        pairs = tuple(self.world.distances(X_WO, near))
        nearest: dict[str, PairDistance] = {}
        for pair in pairs:
            name = self.world.obstacle_object[pair.obstacle]
            if name not in nearest or pair.distance_m < nearest[name].distance_m:
                nearest[name] = pair
        return Probe(pairs, nearest)

    def penetration(self, X_WO: np.ndarray, name: str) -> tuple[float, np.ndarray]:
        """Deepest overlap (m, ≥ 0) of the workpiece at ``X_WO`` with object ``name`` and the
        unit direction in W that moves the workpiece out of it (:meth:`SimWorld.penetration`)."""
        lo, hi = self.world.workpiece_box(X_WO, 0.0)
        near = self.world.candidates(lo, hi)
        mine = near[[self.world.obstacle_object[i] == name for i in near]]
        return self.world.penetration(X_WO, mine)

    def admissible(self, probe: Probe, required: frozenset[str]) -> bool:
        """Nothing closer than the barrier floor, every required object within ε_o."""
        if any(pair.distance_m <= self.floor_m for pair in probe.nearest.values()):
            return False
        return all(probe.distance_m(name) < self.params.eps_capture_m for name in required)

    def contacts(
        self, X_WO: np.ndarray, probe: Probe, required: frozenset[str]
    ) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
        """Contact objects (one name per point), points (k, 3), normals into the workpiece
        (k, 3) and gaps (k,): pairs within ε_c, or within ε_o of a required object."""
        p = self.params
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        names: list[str] = []
        P, N, G = [], [], []
        posed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # a part's vertices and normals in W
        for pair in probe.pairs:
            name = self.world.obstacle_object[pair.obstacle]
            own = pair.wp_part < self.world.n_own_parts  # fingers only touch (see the stepper)
            reach = p.eps_capture_m if own and name in required else p.eps_contact_m
            if not 0 < pair.distance_m < reach:
                continue
            if pair.wp_part not in posed:  # once per part, not per obstacle it touches
                part = self.world.wp_parts[pair.wp_part]
                posed[pair.wp_part] = (part.vertices_O @ R.T + t, part.normals_O @ R.T)
            V_W, normals_W = posed[pair.wp_part]
            points, n, gaps = contact_manifold(
                V_W,
                self.world.obstacle_vertices_W[pair.obstacle],
                pair.p_wp,
                pair.p_obstacle,
                p.eps_contact_m,
                p.max_points_per_pair,
                normals_W,
                self.world.obstacle_normals_W[pair.obstacle],
            )
            names += [name] * len(points)
            P.append(points)
            N.append(np.tile(-n, (len(points), 1)))
            G.append(gaps)
        if not P:
            return [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        return names, np.vstack(P), np.vstack(N), np.concatenate(G)

    # ------------------------------------------------------------------------------ motion

    def pose_at(self, X0: np.ndarray, dc_W: np.ndarray, dtheta_W: np.ndarray) -> np.ndarray:
        """``X0`` with its centre moved by ``dc_W`` and turned by ``dtheta_W`` about it."""
        R = orthonormalize(so3_exp(dtheta_W) @ X0[:3, :3])
        X = np.eye(4)
        X[:3, :3] = R
        X[:3, 3] = X0[:3, :3] @ self.c_O + X0[:3, 3] + dc_W - R @ self.c_O
        return X

    def velocity(
        self,
        X_WO: np.ndarray,
        probe: Probe,
        f_W: np.ndarray,
        m_W: np.ndarray,
        required: frozenset[str],
    ) -> tuple[np.ndarray, np.ndarray]:
        """v, ω (W, about the centre of mass) of equation (1) under the applied ``f_W`` (N) and
        ``m_W`` (N·m) plus the contact forces of the LCP of §V-A at ``X_WO``."""
        p = self.params
        names, P, N, gaps = self.contacts(X_WO, probe, required)
        if len(P):
            c = X_WO[:3, :3] @ self.c_O + X_WO[:3, 3]
            T = np.cross(P - c, N)
            A = p.d_t * N @ N.T + p.d_r * T @ T.T
            # As in the simulator: a point with room to spare may approach by it (less ε_b).
            room = np.maximum(gaps - p.eps_barrier_m, 0.0) / p.dt_s
            key = tuple(names)
            result = solve_lcp(
                A, p.d_t * N @ f_W + p.d_r * T @ m_W + room, clamped_guess=self._clamped.get(key)
            )
            if result.clamped is not None:
                self._clamped[key] = result.clamped
            f_W = f_W + N.T @ result.c
            m_W = m_W + T.T @ result.c
        v, w = p.d_t * f_W, p.d_r * m_W
        for pair in probe.nearest.values():
            if pair.distance_m < p.eps_barrier_m:  # the barrier's push back out to ε_b (§V-B)
                v = v + (p.eps_barrier_m - pair.distance_m) / p.dt_s * away_normal(pair)
        return v, w

    def displace(
        self,
        X0: np.ndarray,
        probe0: Probe,
        f_W: np.ndarray,
        m_W: np.ndarray,
        required: frozenset[str],
        max_step_m: float,
    ) -> tuple[np.ndarray, Probe, float]:
        """Move ``X0`` one step Δt under the wrench (``f_W``, ``m_W``) with contacts.

        Returns the new pose, its probe and the largest displacement of any point of the
        workpiece (m; 0 when it stayed). No point moves further than ``max_step_m``.
        """
        v, w = self.velocity(X0, probe0, f_W, m_W, required)
        dt = self.params.dt_s
        reach = (float(np.linalg.norm(v)) + float(np.linalg.norm(w)) * self.r_max_m) * dt
        if reach <= 0.0:
            return X0, probe0, 0.0
        scale = min(1.0, max_step_m / reach)
        for _ in range(BACKTRACK_HALVINGS + 1):
            X1 = self.pose_at(X0, v * dt * scale, w * dt * scale)
            probe1 = self.probe(X1)
            if self.admissible(probe1, required) and self._clear_between(
                X0, v * dt * scale, w * dt * scale, reach * scale
            ):
                return X1, probe1, reach * scale
            scale *= 0.5
        return X0, probe0, 0.0

    def _clear_between(
        self, X0: np.ndarray, dc_W: np.ndarray, dtheta_W: np.ndarray, length_m: float
    ) -> bool:
        """No collision at poses along the move spaced at most ``sample_m`` (no tunnelling)."""
        n = math.ceil(length_m / self.sample_m)
        for k in range(1, n):
            probe = self.probe(self.pose_at(X0, dc_W * k / n, dtheta_W * k / n))
            if any(pair.distance_m <= self.floor_m for pair in probe.nearest.values()):
                return False
        return True
