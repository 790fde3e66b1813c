"""The robot as vision sees it: each link's visual shapes as convex parts, so that at a known
joint state its image lines are set aside and it hides what is behind it, as the fixed
environment does. Without it, an arm in view (a gripper's fingers look like a plank) is the
source of false objects."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from models.robot import RobotModel, Shape
from work_site.vision.model import VisionModel

CYLINDER_SIDES = 24
"""Sides of the prism standing for a cylinder: its outline is then within r·(1 − cos(π/24)),
under 1 % of the radius, of the true one."""
SPHERE_RINGS = 6
"""Latitude rings (and twice as many meridians) of the polyhedron standing for a sphere."""
COPLANAR_COS = 1.0 - 1e-9
"""Hull triangles whose normals agree this well lie on one face: the edge between them is not
a feature edge."""


def shape_vertices_V(shape: Shape) -> np.ndarray:
    """Vertices (n, 3) of a convex polyhedron standing for ``shape``, in its frame V."""
    if shape.kind == "box":
        half = np.asarray(shape.size, dtype=np.float64) / 2
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
        return signs * half
    if shape.kind == "cylinder":
        r, length = shape.size
        a = 2 * np.pi * np.arange(CYLINDER_SIDES) / CYLINDER_SIDES
        ring = np.column_stack([r * np.cos(a), r * np.sin(a)])
        return np.vstack(
            [np.column_stack([ring, np.full(len(a), z)]) for z in (-length / 2, length / 2)]
        )
    if shape.kind == "sphere":
        (r,) = shape.size
        lat = np.pi * (np.arange(1, SPHERE_RINGS) / SPHERE_RINGS - 0.5)
        lon = 2 * np.pi * np.arange(2 * SPHERE_RINGS) / (2 * SPHERE_RINGS)
        la, lo = np.meshgrid(lat, lon)
        pts = np.column_stack(
            [np.cos(la.ravel()) * np.cos(lo.ravel()), np.cos(la.ravel()) * np.sin(lo.ravel()),
             np.sin(la.ravel())]
        )  # fmt: skip
        return r * np.vstack([pts, [[0, 0, -1.0], [0, 0, 1.0]]])
    raise ValueError(f"robot shape kind {shape.kind!r} has no convex stand-in")


def convex_part(V: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The convex hull of points ``V`` (n, 3): its vertices, half-space rows ``(n, d)`` with
    ``n·x ≤ d`` inside, one per face, and its feature edges (m, 2, 3)."""
    hull = ConvexHull(V)
    normals, offsets = hull.equations[:, :3], -hull.equations[:, 3]
    edge_tris: dict[tuple[int, int], list[int]] = {}
    for t, tri in enumerate(hull.simplices):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            edge_tris.setdefault((min(a, b), max(a, b)), []).append(t)
    edges = [
        V[[a, b]]
        for (a, b), tris in edge_tris.items()
        if len(tris) == 2 and normals[tris[0]] @ normals[tris[1]] < COPLANAR_COS
    ]
    faces = np.unique(np.round(np.column_stack([normals, offsets]), 12), axis=0)
    return V[hull.vertices], faces, np.array(edges).reshape(-1, 2, 3)


class RobotParts:
    """The links of ``robot`` (based at ``X_WB``) as :class:`VisionModel` s, one per link with
    visual shapes, placed by :meth:`at`."""

    def __init__(self, robot: RobotModel, X_WB: np.ndarray) -> None:
        self.robot = robot
        self.X_WB = np.asarray(X_WB, dtype=np.float64)
        self.links: list[tuple[str, VisionModel]] = []
        for link in robot.links.values():
            if not link.visuals:
                continue
            parts = []
            for shape in link.visuals:
                V = shape_vertices_V(shape) @ shape.X_LV[:3, :3].T + shape.X_LV[:3, 3]
                parts.append(convex_part(V))
            self.links.append(
                (
                    link.name,
                    VisionModel(
                        name=f"robot:{link.name}",
                        edges_O=np.vstack([e for _, _, e in parts]),
                        planes_O=tuple(P for _, P, _ in parts),
                        vertices_O=np.vstack([v for v, _, _ in parts]),
                        symmetries=np.eye(3)[None],
                        parts_vertices_O=tuple(v for v, _, _ in parts),
                    ),
                )
            )

    def at(
        self, q_rad: np.ndarray, finger_opening_m: float
    ) -> list[tuple[VisionModel, np.ndarray]]:
        """Every link's model and pose ``X_WL`` at joint state ``q_rad`` (6,) and finger
        opening (m)."""
        poses = self.robot.link_poses_W(np.asarray(q_rad), finger_opening_m, self.X_WB)
        return [(model, poses[name]) for name, model in self.links]
