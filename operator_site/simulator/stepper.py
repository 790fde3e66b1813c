"""The task simulator (§V): a workpiece dragged by a virtual spring bumps, slides and settles.

One step: contact points from the last pose → contact forces from the LCP of §V-A → spatial
velocity from first-order dynamics (equation 1) → a move along X(s) for s ∈ [0, Δt] chosen by
minimising the barrier potential U(s) (§V-B) with golden-section search, after collision samples
close enough together that nothing can be tunnelled through (§VII-B).

Frames: W world; O the workpiece's object frame; the workpiece turns about its centre of mass c.
Velocities and forces are in W; ω turns the workpiece about c.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from models.geometry import ConvexPart
from models.scene import Scene
from models.transforms import orthonormalize, so3_exp, so3_log
from operator_site.simulator.barrier import barrier, capture_barrier
from operator_site.simulator.contacts import contact_manifold
from operator_site.simulator.lcp import solve_lcp
from operator_site.simulator.params import POINTS_PER_PAIR_RANGE, REST_GAP_FRACTION, SimParams
from operator_site.simulator.world import SimWorld

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
MAX_LIFT_DOUBLINGS = 12
"""A workpiece starting too close to something is lifted by ε_b·2^k, k ≤ this (≈ 0.4 m)."""
REST_DISPLACEMENT_M = 1e-12
"""A step that would move no point of the workpiece further than this is no step: the pose and
contacts stay as they are and no query is made (a settled block costs next to nothing)."""
REST_ENERGY_FRACTION = 1e-12
"""Nor is a step that would lower the spring's energy by less than this fraction of it: the line
search compares energies whose float64 rounding is a few 1e-16 of them, and a smaller change is
noise to it."""
STRETCH_ROUNDING = 64 * np.finfo(np.float64).eps
"""The spring's stretch, a difference of coordinates (or of rotations), is good to this fraction
of their size: each is rounded to an ulp, and a few operations make them."""
MAX_FLOOR_HALVINGS = 20
"""A step whose chosen pose turns out under the floor is halved at most this many times (then
not taken): see :meth:`Simulator._verified_move`."""
FULL_MANIFOLD_POINTS = POINTS_PER_PAIR_RANGE[1]
"""Contact points per pair when a step blocked at once is planned again with the whole contact
polygons (:meth:`Simulator.step`)."""
MAX_COLLISION_SAMPLES = 10_000
"""Collision samples along one step at most: parameters that would need more (a tiny tunnelling
fraction against a fast, long step) are refused when the simulator is made."""


def spring_step_factor(params: SimParams) -> float:
    """φ(x) = (1 − e^(−x))/x with x = Δt·d_t·k_t (= Δt·d_r·k_r): the dragger spring's force
    scaled so that one explicit step of equation (1) moves the free workpiece exactly as far as
    the spring's first-order dynamics do over Δt, a fraction 1 − e^(−x) of the way to the
    target. Unscaled, a step moves it x times the way: past the target for x > 1, swinging
    about it for ever for x ≥ 2, although first-order dynamics never overshoot."""
    x = params.step_gain
    return -math.expm1(-x) / x


BARRIER_RESOLUTION = 0.5
"""The line search resolves a step to at least this fraction of ε_b, whatever
``golden_rel_tol``: a coarser search cannot find the barrier's minimum, and a workpiece whose
first obstacle is nearer than its resolution would stop dead short of it."""


def _golden_fraction(params: SimParams, sweep_m: float) -> float:
    """The golden-section search's final bracket as a fraction of Δt for a step that would
    sweep ``sweep_m``: ``golden_rel_tol``, or finer where that would not resolve
    :data:`BARRIER_RESOLUTION` × ε_b of the sweep (``sweep_m`` > 0: a step that moves)."""
    return min(params.golden_rel_tol, BARRIER_RESOLUTION * params.eps_barrier_m / sweep_m)


@dataclass(frozen=True, eq=False)
class Contact:
    """The contact between the workpiece and one obstacle object.

    ``points_W`` (k, 3): contact points; ``normals_W`` (k, 3): unit normals pointing into the
    workpiece (the direction the obstacle pushes it); ``gaps_m`` (k,): the separation at each
    point; ``distance_m``: the smallest distance.
    """

    object: str
    points_W: np.ndarray
    normals_W: np.ndarray
    gaps_m: np.ndarray
    distance_m: float
    captured: bool = False
    reduced: bool = False
    """Some pair's contact polygon may have had more corners than ``max_points_per_pair``
    (it had at least that many points), so that some were dropped."""


@dataclass(frozen=True, eq=False)
class StepResult:
    """What one step did: the new pose, the contacts there, and its costs."""

    time_s: float
    X_WO: np.ndarray
    contacts: tuple[Contact, ...]
    s_fraction: float
    """How much of the nominal step Δt was taken (1: unobstructed)."""
    queries: int
    """Narrow-phase distance queries this step."""
    min_distance_m: float
    """Smallest distance to any nearby obstacle after the step (inf when none is near)."""
    speed_limited: bool
    lcp_ok: bool = True


@dataclass
class SimState:
    """What changes: pose, target, captures, time and history (the model is :class:`SimWorld`)."""

    X_WO: np.ndarray
    X_WD: np.ndarray
    time_s: float = 0.0
    capturable: set[str] = field(default_factory=set)
    held: set[str] = field(default_factory=set)
    contacts: tuple[Contact, ...] = ()
    history: list[StepResult] = field(default_factory=list)
    barrier_K: float = 0.0
    """K of equation (6) (J), set with the target (:meth:`Simulator.set_target`)."""
    resting: bool = False
    """The last step did not move and no input has changed since: the next will not either."""


@dataclass(frozen=True, eq=False)
class _Plan:
    """A step's velocity and what the line search needs of it."""

    v: np.ndarray
    w: np.ndarray
    lcp_ok: bool
    limited: bool
    sweep_m: float
    """How far the fastest point of the workpiece would move over the whole step."""


class Simulator:
    """First-order contact simulation of one workpiece among fixed obstacles."""

    def __init__(
        self,
        scene: Scene,
        workpiece: str,
        params: SimParams | None = None,
        X_WO: dict[str, np.ndarray] | None = None,
        attached_O: tuple[ConvexPart, ...] = (),
    ) -> None:
        """``attached_O``: convex parts that move with the workpiece (the gripper's fingers)."""
        self.params = params or SimParams()
        self.scene = scene
        poses = {o.name: o.X_WO for o in scene.objects} | (X_WO or {})
        self.world = SimWorld(scene, workpiece, poses, attached_O)
        p = self.params
        # A step sweeps at most max_speed·Δt, plus ε_b for each object whose barrier pushes.
        n_objects = len(set(self.world.obstacle_object))
        sweep_m = p.max_speed_mps * p.dt_s + n_objects * p.eps_barrier_m
        samples = math.ceil(sweep_m / (p.tunnel_fraction * self.world.thinnest_obstacle_m))
        if samples > MAX_COLLISION_SAMPLES:
            lowest = sweep_m / (MAX_COLLISION_SAMPLES * self.world.thinnest_obstacle_m)
            raise ValueError(
                f"SimParams.tunnel_fraction {p.tunnel_fraction:g} would take {samples} collision "
                f"samples a step in this scene (at most {MAX_COLLISION_SAMPLES}): it must be in "
                f"[{lowest:.3g}, 1] at max_speed_mps {p.max_speed_mps:g} and dt_s {p.dt_s:g}"
            )
        self._spring_factor = spring_step_factor(p)
        cuts = math.ceil(math.log(_golden_fraction(p, sweep_m)) / math.log(GOLDEN)) + 1
        pairs = len(self.world.wp_parts) * len(self.world.obstacle_object)
        search = samples + cuts + 2
        verified = 1 + MAX_FLOOR_HALVINGS
        self.max_queries_per_step = (3 * search + 1 + 2 * verified) * pairs
        """A bound on :attr:`StepResult.queries`: the collision samples, the golden-section
        cuts and its two first points, for the push out of ε_b, the move and the move planned
        again with the whole contact polygons (after the contacts at its start again); and the
        contacts where the push and the move end (and at each halving of one found under the
        floor), each at most one query per pair of parts."""
        model = scene.object(workpiece).model
        self.c_O = model.com_O.copy()
        self.r_max_m = float(np.max(np.linalg.norm(self.world.wp_vertices_O - self.c_O, axis=1)))
        X0 = self._lift_clear(np.array(poses[workpiece], dtype=np.float64))
        self.state = SimState(X_WO=X0, X_WD=X0.copy())
        self.state.contacts = self._contacts(X0, self._near(X0, 0.0))

    def _lift_clear(self, X_WO: np.ndarray) -> np.ndarray:
        """``X_WO`` raised straight up until the workpiece is ε_b clear of everything.

        A model from a scene file or from vision has blocks exactly on the table (distance 0),
        where the barrier would never let them move; the lift is the least power-of-two
        multiple of ε_b that clears them (it settles back to ε_b on the first steps).
        """
        eps_b = self.params.eps_barrier_m
        near = self._near(X_WO, 0.0)
        X = X_WO.copy()
        for k in range(MAX_LIFT_DOUBLINGS + 1):
            pairs = self.world.distances(X, near) if len(near) else []
            if min((pair.distance_m for pair in pairs), default=math.inf) >= eps_b:
                return X
            X = X_WO.copy()
            X[2, 3] += eps_b * 2**k
        raise ValueError(
            f"workpiece {self.world.workpiece!r} is stuck inside another object: "
            f"lifting it {eps_b * 2**MAX_LIFT_DOUBLINGS:.3f} m did not free it"
        )

    # ------------------------------------------------------------------------------ inputs

    @property
    def X_WO(self) -> np.ndarray:
        """The workpiece's current pose."""
        return self.state.X_WO.copy()

    @property
    def history(self) -> list[StepResult]:
        return self.state.history

    def set_target(self, X_WD: np.ndarray) -> None:
        """Where the dragger wants the workpiece's frame O to be (the spring's other end)."""
        X_WD = np.asarray(X_WD, dtype=np.float64)
        if X_WD.shape != (4, 4) or not np.all(np.isfinite(X_WD)):
            raise ValueError("target must be a finite 4×4 pose")
        self.state.X_WD = X_WD.copy()
        self.state.resting = False
        # K of equation (6) (SimParams.barrier_gain), from the spring's pull now (its moment
        # counted at the workpiece's reach), fixed until the target moves again: U_v plus the
        # barriers is then one function for the whole approach, which every step lowers, so
        # that no sequence of steps can come back to a pose. §V-B's K, from the step's work,
        # vanishes as the workpiece settles and lets the spring press it onto the floor.
        p = self.params
        f, m = self._spring(self.state.X_WO)
        pull_N = float(np.linalg.norm(f) + np.linalg.norm(m) / self.r_max_m)
        self.state.barrier_K = (
            p.barrier_gain * pull_N * p.eps_barrier_m / (1.0 / REST_GAP_FRACTION - 1.0)
        )

    def capture(self, name: str) -> None:
        """Hold contact with ``name`` once the workpiece touches it (now, if it already does)."""
        self.scene.object(name)
        self.state.capturable.add(name)
        self.state.resting = False
        X = self.state.X_WO
        self.state.contacts = self._contacts(X, self._near(X, 0.0))

    def release(self, name: str) -> None:
        """Stop holding contact with ``name``."""
        self.state.capturable.discard(name)
        self.state.held.discard(name)
        self.state.resting = False
        X = self.state.X_WO
        self.state.contacts = self._contacts(X, self._near(X, 0.0))

    # ------------------------------------------------------------------------------ forces

    def _spring_stretch(self, X_WO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far the dragger spring is stretched at ``X_WO``: c_D − c (m) and the rotation
        vector from R to R_D (rad), both in W."""
        R, R_D = X_WO[:3, :3], self.state.X_WD[:3, :3]
        c = X_WO[:3, :3] @ self.c_O + X_WO[:3, 3]
        c_D = R_D @ self.c_O + self.state.X_WD[:3, 3]
        return c_D - c, so3_log(R_D @ R.T)

    def _spring(self, X_WO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The dragger spring's force and moment on the workpiece, scaled by
        :func:`spring_step_factor` for the step."""
        p, phi = self.params, self._spring_factor
        dc, dr = self._spring_stretch(X_WO)
        return phi * p.k_t * dc, phi * p.k_r * dr

    def _pull_rounding(self, X_WO: np.ndarray, v: np.ndarray, w: np.ndarray) -> float:
        """How far rounding can take the spring's power f·v + m·w at ``X_WO`` (W): its stretch
        is a difference of coordinates and of rotations, each good to
        :data:`STRETCH_ROUNDING` of their size."""
        p, X_WD = self.params, self.state.X_WD
        size_m = float(np.linalg.norm(X_WO[:3, 3]) + np.linalg.norm(X_WD[:3, 3])) + self.r_max_m
        return (
            self._spring_factor
            * STRETCH_ROUNDING
            * (p.k_t * size_m * float(np.linalg.norm(v)) + p.k_r * float(np.linalg.norm(w)))
        )

    def _spring_energy(self, X_WO: np.ndarray) -> float:
        """The spring's energy at ``X_WO``, scaled like its force (J)."""
        p = self.params
        dc, dr = self._spring_stretch(X_WO)
        return 0.5 * self._spring_factor * (p.k_t * dc @ dc + p.k_r * dr @ dr)

    def _velocity(
        self, X_WO: np.ndarray, contacts: tuple[Contact, ...]
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """v, ω (W, about the centre of mass) after contact forces; False if the LCP failed."""
        p = self.params
        f_a, m_a = self._spring(X_WO)
        ok = True
        if contacts:
            c = X_WO[:3, :3] @ self.c_O + X_WO[:3, 3]
            P = np.vstack([k.points_W for k in contacts]) - c
            N = np.vstack([k.normals_W for k in contacts])
            T = np.cross(P, N)  # moment arm of a unit force along each normal
            A = p.d_t * N @ N.T + p.d_r * T @ T.T
            # A point with room to spare may approach by that room within the step (less ε_b),
            # so that a face within ε_c but not quite flush can still turn flush.
            room = np.concatenate([k.gaps_m for k in contacts]) - p.eps_barrier_m
            b = p.d_t * N @ f_a + p.d_r * T @ m_a + np.maximum(room, 0.0) / p.dt_s
            result = solve_lcp(A, b)
            ok = result.ok
            f_a = f_a + N.T @ result.c
            m_a = m_a + T.T @ result.c
        return p.d_t * f_a, p.d_r * m_a, ok

    # ------------------------------------------------------------------------------ motion

    def _pose_at(self, X0: np.ndarray, v: np.ndarray, w: np.ndarray, s: float) -> np.ndarray:
        R = so3_exp(w * s) @ X0[:3, :3]
        c = X0[:3, :3] @ self.c_O + X0[:3, 3] + v * s
        X = np.eye(4)
        X[:3, :3] = R
        X[:3, 3] = c - R @ self.c_O
        return X

    def _near(self, X_WO: np.ndarray, sweep_m: float) -> np.ndarray:
        lo, hi = self.world.workpiece_box(X_WO, sweep_m + self.params.eps_capture_m)
        return self.world.candidates(lo, hi)

    def _object_distances(
        self, obstacles: Iterable[int], distances_m: Iterable[float]
    ) -> dict[str, float]:
        """The least of ``distances_m`` (to the obstacle parts ``obstacles``) per object."""
        d: dict[str, float] = {}
        for i, distance_m in zip(obstacles, distances_m, strict=True):
            name = self.world.obstacle_object[i]
            d[name] = min(d.get(name, math.inf), distance_m)
        return d

    def _potential(self, distances_m: dict[str, float], gain: float) -> float:
        """Σ U_i over obstacle objects at ``distances_m`` (excluding U_v); ``inf`` closer than
        the hard floor."""
        p, total = self.params, 0.0
        floor = p.floor_m
        for name, d in distances_m.items():
            if d <= floor:
                return math.inf
            if name in self.state.held:
                total += capture_barrier(d, p.eps_barrier_m, p.eps_capture_m, gain)
            else:
                total += barrier(d, p.eps_barrier_m, gain)
            if total == math.inf:
                return total
        return total

    def _contacts(
        self, X_WO: np.ndarray, near: np.ndarray, max_points: int | None = None
    ) -> tuple[Contact, ...]:
        """The contacts at ``X_WO`` with the obstacles' parts ``near``, at most ``max_points``
        points per pair of parts (default ``max_points_per_pair``)."""
        p = self.params
        max_points = max_points or p.max_points_per_pair
        pairs = self.world.distances(X_WO, near) if len(near) else []
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        V_wp = [part.vertices_O @ R.T + t for part in self.world.wp_parts]
        N_wp = [part.normals_O @ R.T for part in self.world.wp_parts]
        by_object: dict[str, list] = {}
        dist = self._object_distances(
            (pair.obstacle for pair in pairs), (pair.distance_m for pair in pairs)
        )
        for name, d in dist.items():
            if name in self.state.capturable and d < p.eps_contact_m:
                self.state.held.add(name)
        for pair in pairs:
            name = self.world.obstacle_object[pair.obstacle]
            # A captured object holds the workpiece itself within ε_o; the fingers riding with
            # it only ever touch (ε_c): a finger above a captured bar is not a contact to keep.
            own = pair.wp_part < self.world.n_own_parts
            reach = p.eps_capture_m if own and name in self.state.held else p.eps_contact_m
            if pair.distance_m >= reach or pair.distance_m <= 0:
                continue
            points, n, gaps = contact_manifold(
                V_wp[pair.wp_part],
                self.world.obstacle_vertices_W[pair.obstacle],
                pair.p_wp,
                pair.p_obstacle,
                p.eps_contact_m,
                max_points,
                N_wp[pair.wp_part],
                self.world.obstacle_normals_W[pair.obstacle],
            )
            by_object.setdefault(name, []).append((points, -n, gaps, pair.distance_m))
        return tuple(
            Contact(
                name,
                np.vstack([x[0] for x in items]),
                np.vstack([np.tile(x[1], (len(x[0]), 1)) for x in items]),
                np.concatenate([x[2] for x in items]),
                min(x[3] for x in items),
                name in self.state.held,
                any(len(x[0]) >= max_points for x in items),
            )
            for name, items in by_object.items()
        )

    def step(self) -> StepResult:
        """Advance one time step Δt and return what happened: the barrier's push out of ε_b,
        then the move the spring and the contacts make."""
        p, st = self.params, self.state
        if st.resting and st.history:
            st.time_s += p.dt_s
            result = dataclasses.replace(st.history[-1], time_s=st.time_s, queries=0)
            st.history.append(result)
            return result
        X0, contacts = st.X_WO, st.contacts
        queries0 = self.world.queries
        st.time_s += p.dt_s
        plan = self._plan(X0, contacts)
        push = self._push(contacts)
        pushed = False
        if push is not None:
            s_push, X_pushed, contacts_pushed = self._verified_move(
                X0, push.v, push.w, self._search(X0, push, contacts)
            )
            if s_push > 0.0:
                X0, contacts, pushed = X_pushed, contacts_pushed, True
                plan = self._plan(X0, contacts)
        s_best, X1 = 0.0, X0
        if not self._still(X0, plan):
            s_best = self._search(X0, plan, contacts)
            if s_best == 0.0 and any(c.reduced for c in contacts):
                # Dropped corners of a contact polygon are not in the LCP, which may then drive
                # one into its obstacle: blocked at once, the step would block again for ever.
                # Planned with the whole polygons, the LCP sees every corner.
                contacts = self._contacts(X0, self._near(X0, 0.0), FULL_MANIFOLD_POINTS)
                plan = self._plan(X0, contacts)
                if not self._still(X0, plan):
                    s_best = self._search(X0, plan, contacts)
            s_best, X1, contacts = self._verified_move(X0, plan.v, plan.w, s_best)
        st.X_WO, st.contacts = X1, contacts
        # Nothing moved and nothing changed: the next step would find the same.
        st.resting = s_best == 0.0 and not pushed
        d_min = min((c.distance_m for c in st.contacts), default=math.inf)
        result = StepResult(
            time_s=st.time_s,
            X_WO=X1.copy(),
            contacts=st.contacts,
            s_fraction=s_best / p.dt_s,
            queries=self.world.queries - queries0,
            min_distance_m=d_min,
            speed_limited=plan.limited,
            lcp_ok=plan.lcp_ok,
        )
        st.history.append(result)
        return result

    def _still(self, X0: np.ndarray, plan: _Plan) -> bool:
        """Whether ``plan`` is no step: it would move no point of the workpiece further than
        :data:`REST_DISPLACEMENT_M`, or lower the spring's energy by less than
        :data:`REST_ENERGY_FRACTION` of it."""
        if plan.sweep_m < REST_DISPLACEMENT_M:
            return True
        f, m = self._spring(X0)
        drop_J = float(f @ plan.v + m @ plan.w) * self.params.dt_s
        return drop_J <= REST_ENERGY_FRACTION * self._spring_energy(X0)

    def _plan(self, X0: np.ndarray, contacts: tuple[Contact, ...]) -> _Plan:
        """The step's velocity from ``X0`` with ``contacts``: spring, LCP, speed limit."""
        p = self.params
        v, w, lcp_ok = self._velocity(X0, contacts)
        speed = float(np.linalg.norm(v) + np.linalg.norm(w) * self.r_max_m)
        limited = speed > p.max_speed_mps
        if limited:
            v, w = v * (p.max_speed_mps / speed), w * (p.max_speed_mps / speed)
            speed = p.max_speed_mps
        return _Plan(v, w, lcp_ok, limited, speed * p.dt_s)

    def _push(self, contacts: tuple[Contact, ...]) -> _Plan | None:
        """The barrier's push out of ε_b (§V-B) along each nearer obstacle's normal, fast
        enough to restore ε_b in one step if the line search lets it; None if nothing is
        nearer by more than :data:`REST_DISPLACEMENT_M`.

        A move along the LCP's velocity keeps gaps only to first order, and turning about a
        contact brings it nearer by the second; the push is a move of its own, before it:
        inside it, the search could take the push only as far as the turn, and a workpiece
        turning on a contact at the floor would creep."""
        p = self.params
        v = np.zeros(3)
        for contact in contacts:
            if p.eps_barrier_m - contact.distance_m >= REST_DISPLACEMENT_M:
                n = contact.normals_W.mean(axis=0)
                v += (p.eps_barrier_m - contact.distance_m) / p.dt_s * n / np.linalg.norm(n)
        if not v.any():
            return None
        return _Plan(v, np.zeros(3), True, False, float(np.linalg.norm(v)) * p.dt_s)

    def _search(self, X0: np.ndarray, plan: _Plan, contacts: tuple[Contact, ...]) -> float:
        """The line search's s along ``plan`` from ``X0``, whose contacts are ``contacts`` (Δt
        where nothing is near)."""
        p = self.params
        near = self._near(X0, plan.sweep_m)
        if not len(near):
            return p.dt_s
        gain = self.state.barrier_K
        s = self._line_search(X0, plan.v, plan.w, near, plan.sweep_m, gain)
        # A step found that would move no point further than REST_DISPLACEMENT_M is no step
        # (its U differs from staying put by rounding alone).
        return s if plan.sweep_m * s / p.dt_s >= REST_DISPLACEMENT_M else 0.0

    def _verified_move(
        self, X0: np.ndarray, v: np.ndarray, w: np.ndarray, s: float
    ) -> tuple[float, np.ndarray, tuple[Contact, ...]]:
        """The pose s along the step and its contacts, the step halved while that pose is under
        the floor or outside a capture (at most :data:`MAX_FLOOR_HALVINGS` times, then no step
        at all: the last pose and contacts, unchanged).

        The line search weighs the distances of the poses it samples; the pose it chooses is
        built again (its rotation orthonormalised) and may differ from the one weighed by a
        rounding, so its contacts are a second query. (A capturable object within ε_c of a pose
        not taken is held all the same: the pose taken is nearer the last one, itself about as
        near.)"""
        floor = self.params.floor_m
        held = set(self.state.held)
        for _ in range(MAX_FLOOR_HALVINGS + 1):
            if s == 0.0:
                break
            X1 = self._pose_at(X0, v, w, s)
            X1[:3, :3] = orthonormalize(X1[:3, :3])
            contacts = self._contacts(X1, self._near(X1, 0.0))
            clear = min((c.distance_m for c in contacts), default=math.inf) > floor
            if clear and held <= {c.object for c in contacts}:
                return s, X1, contacts
            s *= 0.5
        # No step: the pose stays bit for bit. Rebuilt and queried again it would move by ulps,
        # and at a floor of nanometres such a move can cross it.
        return 0.0, X0, self.state.contacts

    def _line_search(
        self,
        X0: np.ndarray,
        v: np.ndarray,
        w: np.ndarray,
        near: np.ndarray,
        sweep_m: float,
        gain: float,
    ) -> float:
        """argmin over s ∈ [0, Δt] of U(s) = U_v(s) + Σ U_i(d_i(s)) (§V-B), U_v the spring's
        energy along the step.

        §V-B takes U_v linear in s (the work at the step's start rate), which makes a whole step
        best wherever no barrier acts. In contact the step's direction is not the spring's:
        turning about a contact, the spring's energy along it may be least well before Δt, a
        whole step then overshoots, and at large steps the workpiece rocks for ever. With the
        spring's own energy every step taken lowers U; its slope at s = 0 is the linear U_v's
        (the contact forces do no work along the LCP's velocity), and in free space the
        exact-rate step never passes the spring's minimum, so a free pull is unchanged."""
        p = self.params
        cache: dict[float, float] = {}
        springs: dict[float, float] = {}
        E0 = self._spring_energy(X0)

        parts = near.tolist()

        def U(s: float) -> float:
            if s not in cache:
                X = self._pose_at(X0, v, w, s)
                springs[s] = self._spring_energy(X) - E0
                nearest_m = self.world.distances_m(X, near).min(axis=0).tolist()
                distances_m = self._object_distances(parts, nearest_m)
                cache[s] = self._potential(distances_m, gain) + springs[s]
            return cache[s]

        # Collision samples no further apart than a fraction of the thinnest obstacle.
        n = max(1, math.ceil(sweep_m / (p.tunnel_fraction * self.world.thinnest_obstacle_m)))
        hi = p.dt_s
        for k in range(1, n + 1):
            s = p.dt_s * k / n
            if U(s) == math.inf:
                hi = s
                break
        else:
            X1 = self._pose_at(X0, v, w, p.dt_s)
            f, m = self._spring(X1)
            if U(p.dt_s) == springs[p.dt_s] and f @ v + m @ w >= -self._pull_rounding(X1, v, w):
                # No barrier to speak of at the end, the spring still pulls on (or is at its
                # target, where what is left of its pull is rounding): least there.
                return p.dt_s
        lo = 0.0
        a, b = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
        tol = p.dt_s * _golden_fraction(p, sweep_m)
        while hi - lo > tol:
            if U(a) <= U(b):  # ties (both inf: past a wall) shrink towards s = 0
                hi, b = b, a
                a = hi - GOLDEN * (hi - lo)
            else:
                lo, a = a, b
                b = lo + GOLDEN * (hi - lo)
        # The best point evaluated; s = 0 (stay) is always admissible.
        candidates = [(u, s) for s, u in cache.items() if u < math.inf]
        best_u, best_s = min(candidates, default=(math.inf, 0.0))
        return best_s if best_u <= U(0.0) else 0.0
