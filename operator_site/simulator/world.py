"""The simulator's geometry: the workpiece and the fixed obstacles as convex parts, with a broad
phase so that a step only queries obstacles the workpiece can reach. Distances are exact
(:mod:`.polytope`); python-fcl answers overlaps' depths (EPA)."""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np

from models.geometry import ConvexPart
from models.scene import Scene
from operator_site.simulator.polytope import (
    Polytope,
    PolytopeGroup,
    SeparatingFaces,
    distances_over_faces,
    posed_distances_and_faces,
)


def fcl_convex(part: ConvexPart) -> fcl.Convex:
    """A python-fcl convex geometry for ``part`` (faces flattened as ``[k, i0, …, ik-1, …]``)."""
    flat: list[int] = []
    for face in part.faces:
        flat += [len(face), *face]
    return fcl.Convex(part.vertices_O, len(part.faces), np.array(flat, dtype=np.int64))


def thickness_m(vertices: np.ndarray, normals: np.ndarray) -> float:
    """The thinnest extent of a convex part across its own face normals (m)."""
    extent = vertices @ normals.T
    return float(np.min(extent.max(axis=0) - extent.min(axis=0)))


@dataclass(frozen=True)
class PairDistance:
    """Distance (m) between workpiece part ``wp_part`` and obstacle part ``obstacle``, with the
    nearest points in W (``p_wp``, ``p_obstacle``); distance ≤ 0 means they collide."""

    distance_m: float
    obstacle: int
    wp_part: int
    p_wp: np.ndarray
    p_obstacle: np.ndarray


class SimWorld:
    """Fixed obstacles (every object but the workpiece) and the workpiece's parts in fcl."""

    def __init__(
        self,
        scene: Scene,
        workpiece: str,
        X_WO: dict[str, np.ndarray] | None = None,
        attached_O: tuple[ConvexPart, ...] = (),
    ):
        """``attached_O``: more convex parts moving with the workpiece (the gripper's fingers),
        in its frame O."""
        X_WO = X_WO or {}
        wp = scene.object(workpiece)
        self.workpiece = wp.name
        self.wp_parts = (*wp.model.parts, *attached_O)
        self.n_own_parts = len(wp.model.parts)
        """``wp_parts[:n_own_parts]`` are the workpiece's; the rest ride with it (fingers)."""
        self.wp_vertices_O = np.vstack([p.vertices_O for p in self.wp_parts])
        self._wp_objects = [
            fcl.CollisionObject(fcl_convex(p), fcl.Transform()) for p in self.wp_parts
        ]
        self._wp_polytopes = [Polytope.of(p) for p in self.wp_parts]
        self.obstacle_names: list[str] = []
        self.obstacle_object: list[str] = []
        self.obstacle_vertices_W: list[np.ndarray] = []
        self.obstacle_normals_W: list[np.ndarray] = []
        self._obstacles: list[fcl.CollisionObject] = []
        self._obstacle_polytopes: list[Polytope] = []
        thinnest = np.inf
        lo, hi = [], []
        for obj in scene.objects:
            if obj.name == self.workpiece:
                continue
            X = X_WO.get(obj.name, obj.X_WO)
            R, t = X[:3, :3], X[:3, 3]
            for part in obj.model.parts:
                V_W = part.vertices_O @ R.T + t
                self._obstacles.append(fcl.CollisionObject(fcl_convex(part), fcl.Transform(R, t)))
                self._obstacle_polytopes.append(Polytope.of(part).moved(R, t))
                self.obstacle_object.append(obj.name)
                self.obstacle_vertices_W.append(V_W)
                self.obstacle_normals_W.append(part.normals_O @ R.T)
                lo.append(V_W.min(axis=0))
                hi.append(V_W.max(axis=0))
                thinnest = min(thinnest, thickness_m(part.vertices_O, part.normals_O))
        self.lo_W = np.array(lo).reshape(-1, 3)
        self.hi_W = np.array(hi).reshape(-1, 3)
        self.thinnest_obstacle_m = float(thinnest)
        self._group_key = b""
        self._group: PolytopeGroup | None = None
        self._faces: list[SeparatingFaces | None] = [None] * len(self.wp_parts)
        """Per workpiece part, the faces that held its nearest pairs with ``_group`` last."""
        self._collide_request = fcl.CollisionRequest(num_max_contacts=4, enable_contact=True)
        self.queries = 0
        """Narrow-phase distance queries made so far (one per pair of convex parts)."""

    def candidates(self, lo_W: np.ndarray, hi_W: np.ndarray) -> np.ndarray:
        """Indices of obstacle parts whose bounding boxes overlap the box [lo_W, hi_W]."""
        overlap = np.all((self.lo_W <= hi_W) & (self.hi_W >= lo_W), axis=1)
        return np.flatnonzero(overlap)

    def workpiece_box(self, X_WO: np.ndarray, grow_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box of the workpiece at ``X_WO``, grown by ``grow_m`` on every side."""
        V = self.wp_vertices_O @ X_WO[:3, :3].T + X_WO[:3, 3]
        return V.min(axis=0) - grow_m, V.max(axis=0) + grow_m

    def _group_of(self, obstacles: np.ndarray) -> PolytopeGroup:
        key = obstacles.tobytes()
        if key != self._group_key:  # the broad phase's answer seldom changes between queries
            self._group_key = key
            self._group = PolytopeGroup.of(tuple(self._obstacle_polytopes[i] for i in obstacles))
            self._faces = [None] * len(self.wp_parts)
        return self._group

    def distances(self, X_WO: np.ndarray, obstacles: np.ndarray) -> list[PairDistance]:
        """Distances from every workpiece part at ``X_WO`` to each listed obstacle part."""
        if len(obstacles) == 0:
            return []
        group = self._group_of(obstacles)
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        out = []
        for k, part in enumerate(self._wp_polytopes):
            pairs, self._faces[k] = posed_distances_and_faces(part, R, t, group)
            for i, (d, p_wp, p_obstacle) in zip(obstacles, pairs, strict=True):
                out.append(PairDistance(d, int(i), k, p_wp, p_obstacle))
        self.queries += len(self._wp_objects) * len(obstacles)
        return out

    def distances_m(self, X_WO: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """The distances alone (m), (workpiece parts, ``obstacles``): as :meth:`distances`, but
        first over the faces that held the nearest pairs at the last query, which a pose near
        it (a line search's next) mostly keeps."""
        out = np.empty((len(self._wp_polytopes), len(obstacles)))
        if len(obstacles) == 0:
            return out
        group = self._group_of(obstacles)
        R, t = X_WO[:3, :3], X_WO[:3, 3]
        for k, part in enumerate(self._wp_polytopes):
            faces = self._faces[k]
            d = None if faces is None else distances_over_faces(part, R, t, group, faces)
            if d is None:
                pairs, self._faces[k] = posed_distances_and_faces(part, R, t, group)
                d = np.array([pair[0] for pair in pairs])
            out[k] = d
        self.queries += len(self._wp_objects) * len(obstacles)
        return out

    def penetration(self, X_WO: np.ndarray, obstacles: np.ndarray) -> tuple[float, np.ndarray]:
        """The deepest overlap of any workpiece part at ``X_WO`` with the listed obstacle parts:
        fcl's EPA depth (m, 0 when nothing overlaps) and the unit direction (3,) in W that moves
        the workpiece out of it (zero when nothing overlaps)."""
        tf = fcl.Transform(X_WO[:3, :3], X_WO[:3, 3])
        deepest, escape = 0.0, np.zeros(3)
        for wp in self._wp_objects:
            wp.setTransform(tf)
            for i in obstacles:
                result = fcl.CollisionResult()
                if not fcl.collide(wp, self._obstacles[i], self._collide_request, result):
                    continue
                for c in result.contacts:
                    if c.penetration_depth > deepest:
                        # fcl's normal points from the workpiece into the obstacle.
                        deepest, escape = float(c.penetration_depth), -np.asarray(c.normal)
        self.queries += len(self._wp_objects) * len(obstacles)
        norm = float(np.linalg.norm(escape))
        return deepest, escape / norm if norm > 0.0 else escape
