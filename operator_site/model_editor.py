"""The operator's model of the work site (§IV-C): the fixed environment plus the recognised objects
the operator accepted, made physically consistent before any task uses it.

Vision's poses carry millimetre errors: a block may sink into the table, float above it, tilt, or
overlap its neighbour. The paper took them as they came; here each accepted object is first
pushed sideways out of any other object it overlaps, then settled onto its support by the task
simulator (lowered flat onto its nearest face), and every correction is reported so the page can
show it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import fcl
import numpy as np

from models.scene import Scene, SceneObject
from models.transforms import make_pose, so3_exp, so3_log
from operator_site.simulator import SimParams, Simulator
from operator_site.simulator.world import fcl_convex

SETTLE_DROP_M = 0.02
"""Settling pulls an object's spring this far below it (it stops on its support)."""
SETTLE_MAX_STEPS = 400
SEPARATION_MARGIN_M = 0.5e-3
"""Overlapping objects are pushed this much further apart than their overlap (m)."""
MAX_SEPARATION_ROUNDS = 20
UNSETTLED_MM = 5.0
"""A settle that moves an object further than this is reported as a warning (m·1e-3)."""
CONFLICT_OVERLAP_M = UNSETTLED_MM * 1e-3
"""Two recognitions overlapping deeper than this are not pushed apart but refused: more than
vision's pose error explains (a block seen as another, or one seen where another is), and
pushing one aside would put it where nothing is."""


@dataclass(frozen=True)
class Correction:
    """How far object ``name`` moved (mm) and turned (°) to make the model consistent, and why."""

    name: str
    moved_mm: float
    turned_deg: float
    why: str


def _turn_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(so3_log(R_a.T @ R_b))))


class WorkSiteModel:
    """The fixed objects of ``scene`` and the accepted movable ones, by name, with their poses."""

    def __init__(self, scene: Scene, accepted: dict[str, np.ndarray] | None = None) -> None:
        self.base = scene
        self.poses: dict[str, np.ndarray] = {}
        self.scores: dict[str, float] = {}
        for name, X in (accepted or {}).items():
            self.accept(name, X)

    @property
    def fixed(self) -> tuple[SceneObject, ...]:
        return tuple(o for o in self.base.objects if o.fixed)

    def accept(self, name: str, X_WO: np.ndarray, score: float = 1.0) -> None:
        """Add (or move) the movable object ``name`` at ``X_WO``."""
        obj = self.base.object(name)  # KeyError naming the known objects
        if obj.fixed:
            raise ValueError(f"{name!r} is part of the fixed environment, not a recognition")
        X = np.asarray(X_WO, dtype=np.float64)
        if X.shape != (4, 4) or not np.all(np.isfinite(X)):
            raise ValueError(f"{name}: the pose must be a finite 4×4 matrix")
        self.poses[name] = self._upright(name, X)
        self.scores[name] = float(score)

    def _upright(self, name: str, X_WO: np.ndarray) -> np.ndarray:
        """Of the poses a symmetric block looks the same in, the one with its frame's z axis
        most nearly up: vision cannot tell a box from itself upside down, but grasps from
        above are planned in the block's frame."""
        best = X_WO.copy()
        for S in self.symmetries(name):
            R = X_WO[:3, :3] @ S
            if R[2, 2] > best[2, 2] + 1e-9:
                best = make_pose(R, X_WO[:3, 3])
        return best

    def symmetries(self, name: str) -> list[np.ndarray]:
        """The rotations (in O) that map ``name``'s shape onto itself, identity first."""
        return list(self.base.object(name).model.symmetries)

    def remove(self, name: str) -> None:
        """Take ``name`` out of the model (KeyError if it is not in it)."""
        if name not in self.poses:
            raise KeyError(f"{name!r} is not in the model (it has: {', '.join(self.poses)})")
        del self.poses[name]
        self.scores.pop(name, None)

    def scene(self) -> Scene:
        """The scene the simulator should see: the environment and the accepted objects."""
        objects = list(self.fixed)
        for obj in self.base.movable:
            if obj.name in self.poses:
                objects.append(dataclasses.replace(obj, X_WO=self.poses[obj.name].copy()))
        return dataclasses.replace(self.base, objects=tuple(objects))

    # ------------------------------------------------------------------------------ consistency

    def _fcl_objects(self, name: str) -> list[fcl.CollisionObject]:
        X = self.poses[name] if name in self.poses else self.base.object(name).X_WO
        tf = fcl.Transform(X[:3, :3], X[:3, 3])
        return [
            fcl.CollisionObject(fcl_convex(part), tf) for part in self.base.object(name).model.parts
        ]

    def _overlap(self, a: str, b: str) -> tuple[float, np.ndarray]:
        """Deepest penetration of ``a`` into ``b`` (m, 0 if apart) and the horizontal unit
        direction that moves ``a`` out of it."""
        request = fcl.CollisionRequest(num_max_contacts=8, enable_contact=True)
        deepest, away = 0.0, np.zeros(3)
        centre = self.poses[a][:3, 3] - (
            self.poses[b][:3, 3] if b in self.poses else self.base.object(b).X_WO[:3, 3]
        )
        for oa in self._fcl_objects(a):
            for ob in self._fcl_objects(b):
                result = fcl.CollisionResult()
                if not fcl.collide(oa, ob, request, result):
                    continue
                for contact in result.contacts:
                    n = np.array(contact.normal, dtype=np.float64)
                    n[2] = 0.0  # sideways only: up and down are the settle's job
                    size = float(np.linalg.norm(n))
                    if size < 1e-9 or contact.penetration_depth <= deepest:
                        continue
                    n /= size
                    deepest = float(contact.penetration_depth)
                    away = n if n @ centre >= 0 else -n
        return deepest, away

    def _separate(self) -> dict[str, str]:
        """Push accepted objects sideways out of each other and out of the fixed objects'
        sides (not the table: settling lifts out of that); the reasons, by object."""
        why: dict[str, str] = {}
        others = [o.name for o in self.fixed if o.name != "table"]
        for _ in range(MAX_SEPARATION_ROUNDS):
            moved = False
            names = sorted(self.poses, key=lambda n: -self.scores.get(n, 0.0))
            for i, a in enumerate(names):
                # The less certain of two overlapping recognitions is the one that moves.
                for b in [*names[:i], *others]:
                    depth, away = self._overlap(a, b)
                    if depth > CONFLICT_OVERLAP_M:
                        raise ValueError(
                            f"{a} and {b} overlap by {depth * 1e3:.0f} mm, more than vision's "
                            f"error explains: one of them is not where vision put it (remove "
                            f"one, or accept a later frame)"
                        )
                    if depth > 0.0 and np.any(away):
                        self.poses[a][:3, 3] += (depth + SEPARATION_MARGIN_M) * away
                        why[a] = f"overlapped {b} by {depth * 1e3:.1f} mm"
                        moved = True
            if not moved:
                return why
        raise ValueError("recognised objects still overlap after separating them; remove one")

    def _settle(self, name: str, params: SimParams) -> None:
        """Lower ``name`` flat onto whatever is under it with the task simulator."""
        X = self.poses[name]
        R = X[:3, :3]
        model = self.base.object(name).model
        # The face pointing most nearly down becomes exactly down (vision's tilt removed).
        normals_W = np.vstack([part.normals_O for part in model.parts]) @ R.T
        n = normals_W[int(np.argmin(normals_W[:, 2]))]
        axis = np.cross(n, [0.0, 0.0, -1.0])
        angle = math.atan2(float(np.linalg.norm(axis)), float(-n[2]))
        R_flat = (so3_exp(axis / np.linalg.norm(axis) * angle) if angle > 1e-12 else np.eye(3)) @ R
        sim = Simulator(self.scene(), name, params, X_WO={name: make_pose(R_flat, X[:3, 3])})
        target = make_pose(R_flat, X[:3, 3] - [0.0, 0.0, SETTLE_DROP_M])
        sim.set_target(target)
        for _ in range(SETTLE_MAX_STEPS):
            if sim.step().s_fraction == 0.0 or sim.state.resting:
                break
        self.poses[name] = sim.X_WO

    def make_consistent(self, params: SimParams | None = None) -> list[Correction]:
        """Separate overlapping objects, then settle each (lowest first) onto its support;
        what moved, by how much, and why."""
        params = params or SimParams()
        before = {n: X.copy() for n, X in self.poses.items()}
        why = self._separate()
        for name in sorted(self.poses, key=lambda n: self._bottom_z(n)):
            self._settle(name, params)
        out = []
        for name, X0 in before.items():
            X = self.poses[name]
            moved = float(np.linalg.norm(X[:3, 3] - X0[:3, 3])) * 1e3
            turned = _turn_deg(X0[:3, :3], X[:3, :3])
            reason = why.get(name, "settled onto its support")
            if moved > UNSETTLED_MM:
                reason += f" (moved {moved:.1f} mm: check the recognition)"
            out.append(Correction(name, moved, turned, reason))
        return out

    def _bottom_z(self, name: str) -> float:
        X = self.poses[name]
        V = np.vstack([p.vertices_O for p in self.base.object(name).model.parts])
        return float((V @ X[:3, :3].T + X[:3, 3])[:, 2].min())
