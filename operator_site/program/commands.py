"""Robot motion commands from a settled workpiece path (§VI-B).

The path becomes as few spatially-linear moves as fit it: from each target, the next is the
furthest node such that every node between lies within the tolerance of the straight move
(centre position and rotation), no fixed node (path end, end of a required stretch) is skipped,
and the move passes the sweep of :mod:`operator_site.program.check`. Each target carries its
contact state (object names and normals). The program is a guarded grasp at the start, the
moves (``contact_move`` at a slow speed where the target is in contact; moves leaving a contact
are slow too), a release at the goal and a departure straight up that leaves the gripper clear
of the workpiece (Fig. 12: the deformed path already approaches the goal from its open side
and from above, so the last move does not snag).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from models.robot import TCP_LINK, load_robot
from models.scene import Scene
from models.transforms import invert_pose
from operator_site.program.check import Sweeper
from operator_site.program.contact_step import away_normal, held_towards
from operator_site.program.path import NodeContact, PathNode, WorkpiecePath
from operator_site.program.poses import interpolate, log_batch
from protocol import ContactState, MotionCommand, MotionProgram
from protocol.execution import SAFE_TCP_HEIGHT_M, TARGET_BIAS_M
from protocol.messages import (
    MAX_CONTACT_NORMALS,
    MAX_CONTACTS,
    SAME_CONTACT_DIRECTION_RAD,
    contact_directions,
    target_bias,
)

REFINE_STEP_M = 0.002
"""Point travel per contact step when a move in contact is refined round a corner (m)."""
MAX_REFINE_STEPS = 200
REFINE_STALL_STEPS = 10
"""A drag that has not come :data:`REFINE_STALL_FRACTION` of a step closer to the segment's end
in this many steps is stuck and given up: a drag jammed round an outside corner rocks on the
spot rather than getting on, and would spend the rest of :data:`MAX_REFINE_STEPS` doing so."""
REFINE_STALL_FRACTION = 0.1
REFINE_FORCE_N = 10.0
"""Pull towards the segment's end while refining (N): each step goes its full length."""
REFINE_HOLD_N = 0.5
"""Holding force onto each contact kept along the segment (N)."""
MAX_BISECTIONS = 6
"""A move the drag cannot refine is halved at most this deep (at most 2^6 = 64 moves)."""
CLEAR_ROUNDS = 4
"""Pushes out of nearby objects tried on a midpoint before the bisection gives up."""
CORNER_CLEARANCE_M = 0.003
"""Round an outside corner, the targets just past it are held this far off the new face (m):
see :func:`clear_outside_corners`."""
CORNER_REJOIN_M = 0.01
"""… until the workpiece's centre has gone this far past the corner; the next target comes
back onto the face (m)."""


@dataclass(frozen=True)
class CommandParams:
    """How a settled path becomes commands (SI)."""

    position_tol_m: float = 0.002
    """Every node lies within this of the move that replaces it (centre of mass)."""
    angle_tol_rad: float = 0.02
    """… and its rotation within this angle of the move's."""
    free_speed_mps: float = 0.1
    contact_speed_mps: float = 0.01
    """Speed of moves ending in or leaving contact (§VI-B: "the robot's speed is lowered")."""
    force_limit_n: float = 10.0
    """Force limit of moves in free space and of the grasp (N)."""
    contact_force_per_direction_n: float = 10.0
    """A move in contact may meet this much force per distinct contact normal, plus
    ``force_limit_n`` (N): the impedance presses each contact with about stiffness × d = 5 N, and
    the work site verifies each by a force along it; twice that, because round an outside corner
    the pivot meets friction and the real block's small turn in the grip on top of it. Capped at
    ``max_force_limit_n``."""
    max_force_limit_n: float = 40.0
    """The work site's own limit (``HARD_FORCE_LIMIT_N``), which it refuses any command to
    exceed: four contact directions would otherwise ask more."""
    departure_m: float = 0.06
    """After the release the gripper rises this far (clears the 30 mm frame bars)."""
    target_bias_m: float = TARGET_BIAS_M
    """d of §VI-B: the impedance target is biased this far into each contact normal (the work
    site applies its own d, and presses movable objects sideways more gently:
    :func:`protocol.execution.contact_bias_W`; :func:`program_to_json` shows this bias for
    reference)."""


def park_pose_W(scene: Scene) -> np.ndarray:
    """``X_WG`` where the gripper parks after a program: the robot's home configuration's,
    above the table by the robot's base, out of the camera's view of the frame."""
    robot = load_robot(scene.robot.urdf_path)
    return robot.link_poses_W(scene.robot.q_home_rad, 0.0, scene.robot.X_WB)[TCP_LINK]


def contact_states(node: PathNode) -> tuple[ContactState, ...]:
    """The protocol's contact states of a node (distinct normals per object, ≤ 16 of each)."""
    out = []
    for contact in node.contacts[:MAX_CONTACTS]:
        normals = np.unique(np.round(contact.normals_W, 6), axis=0)[:MAX_CONTACT_NORMALS]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        out.append(ContactState(object=contact.object, normals_W=normals))
    return tuple(out)


def contact_direction_count(contacts: tuple[ContactState, ...]) -> int:
    """Distinct (object, normal) directions among ``contacts``, as the work site counts them."""
    return len(contact_directions(contacts))


def _force_limit(contacts: tuple[ContactState, ...], params: CommandParams) -> float:
    n = contact_direction_count(contacts)
    wanted = params.force_limit_n + params.contact_force_per_direction_n * n
    return min(wanted, params.max_force_limit_n)


def _fits(path: WorkpiecePath, a: int, b: int, params: CommandParams) -> bool:
    """Whether every node strictly between ``a`` and ``b`` is within tolerance of the move."""
    if b - a < 2:
        return True
    X = path.poses[a : b + 1]
    C = path.centres_W[a : b + 1]
    chord = C[-1] - C[0]
    L2 = float(chord @ chord)
    if L2 > 1e-18:
        t = np.clip((C[1:-1] - C[0]) @ chord / L2, 0.0, 1.0)
    else:  # a turn on the spot: parameter by angle
        angles = np.linalg.norm(log_batch(X[1:-1, :3, :3] @ X[0, :3, :3].T), axis=1)
        total = max(float(np.linalg.norm(log_batch((X[-1, :3, :3] @ X[0, :3, :3].T)[None]))), 1e-12)
        t = np.clip(angles / total, 0.0, 1.0)
    Y = interpolate(X[0], X[-1], t, path.c_O)
    C_fit = Y[:, :3, :3] @ path.c_O + Y[:, :3, 3]
    if np.max(np.linalg.norm(C[1:-1] - C_fit, axis=1)) > params.position_tol_m:
        return False
    dR = Y[:, :3, :3] @ np.swapaxes(X[1:-1, :3, :3], -1, -2)
    return bool(np.max(np.linalg.norm(log_batch(dR), axis=1)) <= params.angle_tol_rad)


def fit_targets(
    path: WorkpiecePath, params: CommandParams | None = None, sweeper: Sweeper | None = None
) -> list[int]:
    """Indices of the nodes that become move targets (the first and last always are)."""
    params = params or CommandParams()
    n = len(path)
    targets = [0]
    while targets[-1] < n - 1:
        a = targets[-1]
        b = a + 1
        while b + 1 < n and not path.nodes[b].fixed and _fits(path, a, b + 1, params):
            b += 1
        while (
            sweeper is not None
            and b > a + 1
            and not _sweep_ok(path.nodes[a], path.nodes[b], sweeper)
        ):
            b -= 1
        targets.append(b)
    return targets


def _objects(node: PathNode) -> frozenset[str]:
    return frozenset(c.object for c in node.contacts)


def _sweep_ok(a: PathNode, b: PathNode, sweeper: Sweeper) -> bool:
    at_a, at_b = _objects(a), _objects(b)
    return sweeper.segment(a.X_WO, b.X_WO, at_a | at_b, at_a & at_b).ok


def _node_at(sweeper: Sweeper, X_WO: np.ndarray, required: frozenset[str]) -> PathNode:
    """A node at ``X_WO`` with its contact state (objects within ε_c, or ε_o if required)."""
    st = sweeper.stepper
    probe = st.probe(X_WO)
    names, _, N, _ = st.contacts(X_WO, probe, required)
    contacts = []
    for name in dict.fromkeys(names):
        rows = [k for k, m in enumerate(names) if m == name]
        contacts.append(NodeContact(name, N[rows], probe.distance_m(name)))
    return PathNode(X_WO, tuple(contacts), required)


def _pushed_clear(sweeper: Sweeper, X_WO: np.ndarray) -> np.ndarray | None:
    """``X_WO`` translated out of every object it overlaps or nearly touches, to ε_b from it
    (the barrier's rest distance); None if that takes more than :data:`CLEAR_ROUNDS` pushes."""
    st = sweeper.stepper
    X = X_WO.copy()
    for _ in range(CLEAR_ROUNDS):
        probe = st.probe(X)
        close = {n: p for n, p in probe.nearest.items() if p.distance_m <= st.floor_m}
        if not close:
            return X
        for name, pair in close.items():
            if pair.distance_m > 0.0:
                X[:3, 3] += (st.params.eps_barrier_m - pair.distance_m) * away_normal(pair)
            else:
                depth, escape = st.penetration(X, name)
                X[:3, 3] += (depth + st.params.eps_barrier_m) * escape
    return X if st.admissible(st.probe(X), frozenset()) else None


def _bisect(a: PathNode, b: PathNode, sweeper: Sweeper, depth: int) -> list[PathNode] | None:
    """Waypoints from ``a`` to ``b`` (``b`` last) found by halving the move and pushing each
    midpoint clear of what it cuts into, until every piece passes the sweep; None if it takes
    more than ``depth`` halvings."""
    if _sweep_ok(a, b, sweeper):
        return [b]
    if depth == 0:
        return None
    X = _pushed_clear(sweeper, interpolate(a.X_WO, b.X_WO, np.array([0.5]), sweeper.c_O)[0])
    if X is None:
        return None
    mid = _node_at(sweeper, X, _objects(a) & _objects(b))
    first = _bisect(a, mid, sweeper, depth - 1)
    second = None if first is None else _bisect(mid, b, sweeper, depth - 1)
    return None if first is None or second is None else first + second


def refine_segment(
    a: PathNode, b: PathNode, sweeper: Sweeper, step_m: float = REFINE_STEP_M
) -> list[PathNode] | None:
    """Waypoints from ``a`` to ``b`` (``b`` last) whose moves all pass the sweep. First by
    dragging the workpiece from ``a`` towards ``b`` with the contact step, so that it slides
    round what it touches (a straight move round a corner in contact cuts the corner), the
    waypoints then merged as far as the sweep allows; where the drag gets stuck, by halving
    the move (:func:`_bisect`). None if both fail."""
    return _drag_refine(a, b, sweeper, step_m) or _bisect(a, b, sweeper, MAX_BISECTIONS)


def _drag_refine(
    a: PathNode, b: PathNode, sweeper: Sweeper, step_m: float
) -> list[PathNode] | None:
    st = sweeper.stepper
    kept = _objects(a) & _objects(b)
    X, probe = a.X_WO, st.probe(a.X_WO)
    c_b = b.X_WO[:3, :3] @ st.c_O + b.X_WO[:3, 3]
    poses = []
    closest, closest_at = math.inf, 0  # nearest approach to b so far (m) and its step
    for k in range(MAX_REFINE_STEPS):
        c = X[:3, :3] @ st.c_O + X[:3, 3]
        turn = log_batch((b.X_WO[:3, :3] @ X[:3, :3].T)[None])[0]
        e = np.concatenate([c_b - c, st.params.char_length_m * turn])
        norm = float(np.linalg.norm(e))
        if norm < step_m:
            break
        if norm < closest - REFINE_STALL_FRACTION * step_m:
            closest, closest_at = norm, k
        elif k - closest_at >= REFINE_STALL_STEPS:
            return None
        f = REFINE_FORCE_N * e[:3] / norm
        m = REFINE_FORCE_N * e[3:] / norm * st.params.char_length_m
        f = held_towards(f, probe, kept, REFINE_HOLD_N)
        X, probe, moved = st.displace(X, probe, f, m, kept, step_m)
        if moved == 0.0:
            return None
        poses.append(X)
    else:
        return None
    chain = [a, *(_node_at(sweeper, X, kept) for X in poses), b]
    out, i = [], 0
    while i < len(chain) - 1:
        j = i + 1
        while j + 1 < len(chain) and _sweep_ok(chain[i], chain[j + 1], sweeper):
            j += 1
        if not _sweep_ok(chain[i], chain[j], sweeper):
            return None
        out.append(chain[j])
        i = j
    return out


def plan_targets(
    path: WorkpiecePath, params: CommandParams | None = None, sweeper: Sweeper | None = None
) -> list[PathNode]:
    """The move targets after the start: :func:`fit_targets`, with any move between adjacent
    nodes that fails the sweep replaced by :func:`refine_segment`'s waypoints (kept as they are
    when that fails too: the check then refuses the program)."""
    indices = fit_targets(path, params, sweeper)
    out: list[PathNode] = []
    for a, b in itertools.pairwise(indices):
        na, nb = path.nodes[a], path.nodes[b]
        if sweeper is not None and b == a + 1 and not _sweep_ok(na, nb, sweeper):
            waypoints = refine_segment(na, nb, sweeper)
            if waypoints is not None:
                out += waypoints
                continue
        out.append(nb)
    return out


def _left_directions(a: PathNode, b: PathNode) -> list[tuple[str, np.ndarray]]:
    """The contact directions of ``a`` that ``b`` has nothing of the same object near: the
    contacts the move from ``a`` to ``b`` leaves."""
    cos_same = float(np.cos(SAME_CONTACT_DIRECTION_RAD))
    at_b = contact_directions(contact_states(b))
    return [
        (name, n)
        for name, n in contact_directions(contact_states(a))
        if all(o != name or float(n @ m) < cos_same for o, m in at_b)
    ]


def _turned_directions(a: PathNode, b: PathNode) -> np.ndarray:
    """The contact directions (k, 3) at ``b`` that ``a`` does not have while ``a`` has one of the
    same object that ``b`` lost: the workpiece went round an outside corner of that object
    between them (a face sliding over an edge became a vertex on the next face). Empty if
    none."""
    lost = {name for name, _ in _left_directions(a, b)}
    turned = [n for name, n in _left_directions(b, a) if name in lost]
    return np.array(turned).reshape(-1, 3)


def clear_outside_corners(
    start: PathNode, targets: list[PathNode], sweeper: Sweeper
) -> list[PathNode]:
    """``targets`` with each turn round an outside corner made as leave, turn, come back: the
    workpiece first backs straight off the corner by :data:`CORNER_CLEARANCE_M` along the new
    face's normals, the targets from the turn until the centre has gone
    :data:`CORNER_REJOIN_M` further and its contact state is steady (the next target keeps
    every contact direction it has) are moved as far off the new face, and the next target
    comes back onto it with its contact. Kept as they are where a moved move fails the sweep.

    Why: the simulated workpiece passes the corner by a fraction of a millimetre before the
    new face's contact begins, and the robot biases its target into that face from then on
    (§VI-B). The real block in the grip is a millimetre or two off the simulated one, so its
    edge is often still on the corner: the new bias then pushes it back round the corner and
    it jams there. Off the face, the block passes the corner clear of both faces. A path
    that pivots the block on the corner can reach the new face while the corner's edge still
    lies on the block's face: a target there asks the robot to press and verify a contact the
    path leaves at once, which a block a millimetre off finds with a fraction of a newton."""
    chain = [start, *targets]
    out: list[PathNode] = []
    i = 1
    while i < len(chain):
        normals = _turned_directions(chain[i - 1], chain[i]) if i < len(chain) - 1 else []
        if not len(normals):
            out.append(chain[i])
            i += 1
            continue
        away = normals.sum(axis=0)
        away *= CORNER_CLEARANCE_M / np.linalg.norm(away)
        c_turn = chain[i].X_WO[:3, :3] @ sweeper.c_O + chain[i].X_WO[:3, 3]
        j = i
        while j < len(chain) - 1:
            X = chain[j].X_WO
            past_m = float(np.linalg.norm(X[:3, :3] @ sweeper.c_O + X[:3, 3] - c_turn))
            if past_m >= CORNER_REJOIN_M and not _left_directions(chain[j], chain[j + 1]):
                break
            j += 1
        moved = []
        for node in chain[i - 1 : j]:  # from the last target on the corner: back off first
            X = node.X_WO.copy()
            X[:3, 3] += away
            moved.append(_node_at(sweeper, X, frozenset()))
        legs = itertools.pairwise([chain[i - 1], *moved, chain[j]])
        if all(_sweep_ok(a, b, sweeper) for a, b in legs):
            out += [*moved, chain[j]]
        else:
            out += chain[i : j + 1]
        i = j + 1
    return out


def build_program(
    program_id: str,
    path: WorkpiecePath,
    X_GP: np.ndarray,
    params: CommandParams | None = None,
    sweeper: Sweeper | None = None,
    park_X_WG: np.ndarray | None = None,
) -> MotionProgram:
    """The motion program for a settled ``path`` with grasp ``X_GP`` (workpiece in gripper);
    with ``park_X_WG`` the gripper ends there (:func:`park_pose_W`), out of the camera's view
    and of the next program's way."""
    params = params or CommandParams()
    first = path.nodes[0]
    commands = [
        MotionCommand(  # the work site descends onto the block at its own slower grasp speed
            kind="guarded_grasp",
            X_WP=first.X_WO,
            speed_mps=params.free_speed_mps,
            force_limit_n=params.force_limit_n,
            contacts=contact_states(first),
        )
    ]
    targets = plan_targets(path, params, sweeper)
    if sweeper is not None:
        targets = clear_outside_corners(first, targets, sweeper)
    prev = first
    for node in targets:
        contacts = contact_states(node)
        slow = bool(contacts) or bool(prev.contacts)
        commands.append(
            MotionCommand(
                kind="contact_move" if contacts else "move",
                X_WP=node.X_WO,
                speed_mps=params.contact_speed_mps if slow else params.free_speed_mps,
                force_limit_n=_force_limit(contacts, params),
                contacts=contacts,
            )
        )
        prev = node
    last = path.nodes[-1]
    up = last.X_WO.copy()
    up[2, 3] += params.departure_m
    commands += [
        MotionCommand("release", last.X_WO, 0.0, params.force_limit_n, contact_states(last)),
        MotionCommand("move", up, params.free_speed_mps, params.force_limit_n, ()),
    ]
    X_GP = np.asarray(X_GP, dtype=np.float64)
    if park_X_WG is not None:
        # Up to the height the hand travels at, then to the park: a straight line from low
        # beside the placed block may sweep the open fingers through its neighbours.
        X_WG_up = up @ invert_pose(X_GP)
        if X_WG_up[2, 3] < SAFE_TCP_HEIGHT_M:
            X_WG_up[2, 3] = SAFE_TCP_HEIGHT_M
            commands.append(
                MotionCommand(
                    "move", X_WG_up @ X_GP, params.free_speed_mps, params.force_limit_n, ()
                )
            )
        park = np.asarray(park_X_WG, dtype=np.float64) @ X_GP  # the gripper's target as X_WP
        commands.append(
            MotionCommand("move", park, params.free_speed_mps, params.force_limit_n, ())
        )
    return MotionProgram(program_id=program_id, X_GP=X_GP, commands=tuple(commands))


def program_to_json(
    program: MotionProgram, target_bias_m: float = CommandParams.target_bias_m
) -> dict:
    """A readable JSON form of ``program``: poses as position (m) and rotation matrix, what its
    grasp holds, contact normals per object, and each target's impedance bias Δp (§VI-B) for
    reference."""

    def pose(X: np.ndarray) -> dict:
        X = np.asarray(X)
        return {"p_m": np.round(X[:3, 3], 6).tolist(), "R": np.round(X[:3, :3], 9).tolist()}

    commands = []
    for cmd in program.commands:
        normals = [c.normals_W for c in cmd.contacts]
        N = np.vstack(normals) if normals else np.zeros((0, 3))
        commands.append(
            {
                "kind": cmd.kind,
                "X_WP": pose(cmd.X_WP),
                "speed_mps": cmd.speed_mps,
                "force_limit_n": cmd.force_limit_n,
                "contacts": [
                    {"object": c.object, "normals_W": np.round(c.normals_W, 6).tolist()}
                    for c in cmd.contacts
                ],
                "target_bias_m": np.round(target_bias(N, target_bias_m), 6).tolist(),
            }
        )
    return {
        "type": program.TYPE,
        "program_id": program.program_id,
        "X_GP": pose(program.X_GP),
        "holds": [
            {
                "name": h.name,
                "mass_kg": h.mass_kg,
                "opening_m": h.opening_m,
                "com_G_m": np.round(h.com_G, 6).tolist(),
            }
            for h in program.holds
        ],
        "commands": commands,
    }
