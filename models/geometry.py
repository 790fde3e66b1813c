"""Polyhedral geometry of object models: convex parts, their checks, mass properties, feature edges.

An object is a union of convex parts that may touch but not interpenetrate. Each part is a closed,
consistently oriented polyhedron with planar polygonal faces listed counter-clockwise when seen
from outside (so face normals point out of the part).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from models.errors import ModelError

PLANARITY_TOL_M = 1e-7
"""Largest distance of a face vertex from its face's plane (m)."""
CONVEXITY_TOL_M = 1e-7
"""Largest distance a vertex may lie outside any face plane of its own part (m)."""
INTERPENETRATION_TOL_M = 1e-6
"""Depth by which two parts of one object may overlap before the model is refused (m)."""
FEATURE_CREASE_MIN_ANGLE_RAD = np.deg2rad(5.0)
"""Surfaces meeting at less than this bend are treated as smooth (no feature edge)."""
_EDGE_PROBE_RADIUS_M = 1e-5
_EDGE_PROBE_COUNT = 720
_COLLINEAR_TOL_M = 1e-7


@dataclass(frozen=True, eq=False)
class ConvexPart:
    """One convex piece of an object, in the object frame O.

    ``vertices_O``: (n, 3) float64 m. ``faces``: tuple of vertex-index tuples, counter-clockwise
    seen from outside. ``normals_O``: (k, 3) outward unit normals, ``offsets_m``: (k,) with
    ``normals_O[i] · x = offsets_m[i]`` on face i.
    """

    vertices_O: np.ndarray
    faces: tuple[tuple[int, ...], ...]
    normals_O: np.ndarray
    offsets_m: np.ndarray

    def signed_distance_upper_bound(self, p_O: np.ndarray) -> np.ndarray:
        """``max_i(n_i·p − d_i)`` per point (m, 3): < 0 inside, else a lower bound of distance."""
        return np.max(p_O @ self.normals_O.T - self.offsets_m, axis=-1)

    def triangles(self) -> np.ndarray:
        """Fan triangulation of the faces as vertex indices, (t, 3) int."""
        return np.array([(f[0], f[i], f[i + 1]) for f in self.faces for i in range(1, len(f) - 1)])


def make_convex_part(vertices_O: np.ndarray, faces: list[list[int]], source: str) -> ConvexPart:
    """Check a polyhedron and build a :class:`ConvexPart`; ``source`` names it in errors.

    Raises :class:`ModelError` if it has non-finite or unused vertices, degenerate or non-planar
    faces, is not closed and consistently oriented, is inside out, or is not convex.
    """
    V = np.asarray(vertices_O, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 4:
        raise ModelError(f"{source}: expected at least 4 vertices of 3 coordinates, got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise ModelError(f"{source}: vertex coordinates contain NaN or infinity")
    if len(faces) < 4:
        raise ModelError(f"{source}: a closed polyhedron needs at least 4 faces, got {len(faces)}")
    directed: dict[tuple[int, int], int] = {}
    normals, offsets = [], []
    for fi, face in enumerate(faces):
        if len(face) < 3 or len(set(face)) != len(face):
            raise ModelError(f"{source}: face {fi} {list(face)} is degenerate")
        if min(face) < 0 or max(face) >= len(V):
            raise ModelError(f"{source}: face {fi} refers to a vertex that does not exist")
        P = V[list(face)]
        # Newell's method: robust normal of a planar polygon, length = 2 × area.
        n = np.sum(np.cross(P, np.roll(P, -1, axis=0)), axis=0)
        area2 = np.linalg.norm(n)
        if area2 < 1e-14:
            raise ModelError(f"{source}: face {fi} has zero area")
        n /= area2
        d = float(np.mean(P @ n))
        if np.max(np.abs(P @ n - d)) > PLANARITY_TOL_M:
            raise ModelError(f"{source}: face {fi} is not planar")
        normals.append(n)
        offsets.append(d)
        for a, b in zip(face, face[1:] + face[:1], strict=True):
            if (a, b) in directed:
                raise ModelError(
                    f"{source}: edge {a}-{b} is used twice in the same direction "
                    "(faces inconsistently oriented or non-manifold)"
                )
            directed[(a, b)] = fi
    open_edges = [e for e in directed if (e[1], e[0]) not in directed]
    if open_edges:
        raise ModelError(
            f"{source}: mesh is not closed ({len(open_edges)} open edges, "
            f"e.g. {open_edges[0][0]}-{open_edges[0][1]})"
        )
    used = {i for f in faces for i in f}
    if len(used) != len(V):
        raise ModelError(f"{source}: {len(V) - len(used)} vertices are not used by any face")
    N, d = np.array(normals), np.array(offsets)
    part = ConvexPart(V, tuple(tuple(int(i) for i in f) for f in faces), N, d)
    if mass_properties([part])[0] <= 0:
        raise ModelError(f"{source}: faces are oriented inwards (negative volume)")
    if np.max(V @ N.T - d) > CONVEXITY_TOL_M:
        raise ModelError(f"{source}: part is not convex (a vertex lies outside a face plane)")
    return part


def mass_properties(parts: list[ConvexPart]) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (m³), centroid (3,) and inertia about the centroid per unit density (3, 3)."""
    canonical = np.array([[2.0, 1.0, 1.0], [1.0, 2.0, 1.0], [1.0, 1.0, 2.0]]) / 120.0
    volume, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for part in parts:
        T = part.vertices_O[part.triangles()]  # (t, 3 vertices, 3)
        dets = np.linalg.det(T)  # 6 × signed volume of each tetrahedron with the origin
        volume += dets.sum() / 6.0
        first += (dets[:, None] * T.sum(axis=1)).sum(axis=0) / 24.0
        # Covariance of each tetrahedron: det(A) A C Aᵀ with A's columns the three vertices.
        second += np.einsum(
            "t,tia,ab,tjb->ij", dets, T.transpose(0, 2, 1), canonical, T.transpose(0, 2, 1)
        )
    if volume <= 0:
        return volume, np.zeros(3), np.zeros((3, 3))
    c = first / volume
    C = second - volume * np.outer(c, c)
    return volume, c, np.trace(C) * np.eye(3) - C


def check_no_interpenetration(parts: list[ConvexPart], source: str) -> None:
    """Refuse parts of one object that overlap by more than :data:`INTERPENETRATION_TOL_M`.

    Separating-axis test over face normals and edge cross products of each pair.
    """
    for i in range(len(parts)):
        for j in range(i + 1, len(parts)):
            depth = _overlap_depth(parts[i], parts[j])
            if depth > INTERPENETRATION_TOL_M:
                raise ModelError(
                    f"{source}: convex parts {i} and {j} interpenetrate by "
                    f"{depth * 1e3:.3f} mm (parts may touch, not overlap)"
                )


def _edge_directions(part: ConvexPart) -> np.ndarray:
    E = {tuple(sorted((a, b))) for f in part.faces for a, b in zip(f, f[1:] + f[:1], strict=True)}
    D = np.array([part.vertices_O[b] - part.vertices_O[a] for a, b in E])
    return D / np.linalg.norm(D, axis=1, keepdims=True)


def _overlap_depth(a: ConvexPart, b: ConvexPart) -> float:
    axes = [a.normals_O, b.normals_O]
    cross = np.cross(_edge_directions(a)[:, None, :], _edge_directions(b)[None, :, :]).reshape(
        -1, 3
    )
    norms = np.linalg.norm(cross, axis=1)
    axes.append(cross[norms > 1e-9] / norms[norms > 1e-9, None])
    A = np.vstack(axes)
    pa, pb = a.vertices_O @ A.T, b.vertices_O @ A.T
    overlap = np.minimum(pa.max(0), pb.max(0)) - np.maximum(pa.min(0), pb.min(0))
    return float(max(overlap.min(), 0.0))


def feature_edges(parts: list[ConvexPart]) -> np.ndarray:
    """Edges of the union of ``parts`` where its surface really creases, (m, 2, 3) m in O.

    Part edges are split where other parts' face planes cross them; each piece is classified by
    probing a small circle around its midpoint for points inside the union: a flat surface fills
    half the circle, a crease more or less by at least :data:`FEATURE_CREASE_MIN_ANGLE_RAD`.
    Collinear pieces that touch are merged, so an edge shared by two parts counts once.
    """
    pieces: list[tuple[np.ndarray, np.ndarray]] = []
    for k, part in enumerate(parts):
        others = [p for i, p in enumerate(parts) if i != k]
        edges = {
            tuple(sorted((a, b))) for f in part.faces for a, b in zip(f, f[1:] + f[:1], strict=True)
        }
        for ia, ib in sorted(edges):
            a, b = part.vertices_O[ia], part.vertices_O[ib]
            ts = [0.0, 1.0]
            for o in others:
                denom = o.normals_O @ (b - a)
                ok = np.abs(denom) > 1e-12
                t = (o.offsets_m[ok] - o.normals_O[ok] @ a) / denom[ok]
                ts.extend(t[(t > 1e-9) & (t < 1 - 1e-9)].tolist())
            ts = np.unique(np.round(ts, 12))
            for t0, t1 in itertools.pairwise(ts):
                p0, p1 = a + t0 * (b - a), a + t1 * (b - a)
                if _is_crease(parts, p0, p1):
                    pieces.append((p0, p1))
    return _merge_collinear(pieces)


def _is_crease(parts: list[ConvexPart], p0: np.ndarray, p1: np.ndarray) -> bool:
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    e1 = np.cross(u, [0.5773, 0.5774, 0.5775])
    if np.linalg.norm(e1) < 1e-3:
        e1 = np.cross(u, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    # Offset the probe angles so that no probe lies exactly in a face plane.
    ang = (np.arange(_EDGE_PROBE_COUNT) + 0.5) * (2 * np.pi / _EDGE_PROBE_COUNT) + 0.1234
    P = 0.5 * (p0 + p1) + _EDGE_PROBE_RADIUS_M * (
        np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2
    )
    inside = np.zeros(len(P), dtype=bool)
    for part in parts:
        inside |= part.signed_distance_upper_bound(P) < 0
    filled = inside.mean() * 2 * np.pi
    bend = abs(filled - np.pi)
    return bool(FEATURE_CREASE_MIN_ANGLE_RAD < bend < np.pi - FEATURE_CREASE_MIN_ANGLE_RAD / 2)


def _merge_collinear(pieces: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    merged: list[list[np.ndarray]] = []
    remaining = [list(p) for p in pieces]
    while remaining:
        a, b = remaining.pop()
        u = (b - a) / np.linalg.norm(b - a)
        grew = True
        while grew:
            grew = False
            for i, (c, d) in enumerate(remaining):
                on_line = all(np.linalg.norm(np.cross(q - a, u)) < _COLLINEAR_TOL_M for q in (c, d))
                if not on_line:
                    continue
                ta, tb = 0.0, float(u @ (b - a))
                tc, td = sorted((float(u @ (c - a)), float(u @ (d - a))))
                if tc <= tb + _COLLINEAR_TOL_M and td >= ta - _COLLINEAR_TOL_M:
                    lo, hi = min(ta, tc), max(tb, td)
                    a, b = a + lo * u, a + hi * u
                    remaining.pop(i)
                    grew = True
                    break
        merged.append([a, b])
    if not merged:
        return np.zeros((0, 2, 3))
    return np.array(merged)


def read_obj(path: Path) -> tuple[np.ndarray, list[list[int]]]:
    """Vertices (n, 3) and polygonal faces (0-based) of a Wavefront OBJ file."""
    vertices, faces = [], []
    try:
        text = path.read_text()
    except OSError as e:
        raise ModelError(f"{path}: cannot read mesh ({e.strerror})") from e
    for lineno, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        try:
            if words[0] == "v":
                vertices.append([float(w) for w in words[1:4]])
            elif words[0] == "f":
                faces.append([int(w.split("/")[0]) - 1 for w in words[1:]])
        except ValueError as e:
            raise ModelError(f"{path}:{lineno}: cannot parse {line.strip()!r}") from e
    return np.array(vertices, dtype=np.float64).reshape(-1, 3), faces


def write_obj(path: Path, vertices: np.ndarray, faces: list[list[int]], comment: str) -> None:
    """Write a polygonal OBJ (faces 1-based, counter-clockwise from outside)."""
    lines = [f"# {comment}"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


SYMMETRY_TURN_ORDERS = (2, 3, 4, 5, 6, 8)
"""Rotations by a 1/n turn about one of O's axes, n among these, composed with the 24 rotations
that map the axes onto themselves, are the candidate symmetries of a shape."""
SYMMETRY_TOL_M = 1e-6
"""A rotation maps a shape onto itself when every corner lands this close to a corner."""


def axis_rotations() -> np.ndarray:
    """The 24 rotations that map the coordinate axes onto themselves (a cube's), (24, 3, 3),
    identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.array(out)


def _candidate_symmetries() -> np.ndarray:
    """(c, 3, 3): the axis rotations, then the 1/n turns about O's axes composed with them,
    each rotation once, identity first."""
    turns = []
    for axis in range(3):
        for n in SYMMETRY_TURN_ORDERS:
            for k in range(1, n):
                a = 2.0 * np.pi * k / n
                c, s = np.cos(a), np.sin(a)
                i, j = [q for q in range(3) if q != axis]
                R = np.eye(3)
                R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
                turns.append(R)
    axes = axis_rotations()
    C = np.concatenate([axes, np.einsum("tij,ajk->taik", np.array(turns), axes).reshape(-1, 3, 3)])
    _, first = np.unique(np.round(C, 9).reshape(len(C), 9), axis=0, return_index=True)
    return C[np.sort(first)]


_CANDIDATE_SYMMETRIES = _candidate_symmetries()


def shape_symmetries(corners_O: np.ndarray, tol_m: float = SYMMETRY_TOL_M) -> np.ndarray:
    """The rotations about O's origin that map the corner set ``corners_O`` (n, 3) onto itself,
    (s, 3, 3), identity first: a cube's 24, a square-section block's 8, a hexagonal prism's 12.
    A rotation that is not among the candidates (1/n turns about O's axes and the axis
    permutations) is not found."""
    moved = np.einsum("cij,nj->cni", _CANDIDATE_SYMMETRIES, corners_O)  # (c, n, 3)
    d = np.linalg.norm(moved[:, :, None, :] - corners_O[None, None, :, :], axis=3).min(axis=2)
    return _CANDIDATE_SYMMETRIES[np.all(d < tol_m, axis=1)]


def convex_gap_2d(A: np.ndarray, B: np.ndarray) -> float:
    """The distance between the convex hulls of point sets ``A`` and ``B`` (each (n, 2), n ≥ 1:
    polygons, segments or points), 0 where they meet: a vertex of one inside the other, or two
    edges crossing; else the nearest vertex of either to an edge of the other."""

    def hull(P: np.ndarray) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64).reshape(-1, 2)
        if len(P) <= 2:
            return P
        return cv2.convexHull(P.astype(np.float32)).reshape(-1, 2).astype(np.float64)

    def edges(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (H, np.roll(H, -1, axis=0)) if len(H) > 2 else (H[:1], H[-1:])

    def inside(P: np.ndarray, H: np.ndarray) -> bool:
        if len(H) < 3:
            return False
        e0, e1 = edges(H)
        d = e1 - e0
        cross = d[None, :, 0] * (P[:, None, 1] - e0[None, :, 1]) - d[None, :, 1] * (
            P[:, None, 0] - e0[None, :, 0]
        )
        return bool(np.any(np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)))

    def vertex_to_edges(P: np.ndarray, H: np.ndarray) -> float:
        e0, e1 = edges(H)
        d = e1 - e0
        length2 = np.maximum(np.sum(d * d, axis=1), 1e-300)
        t = np.clip(np.einsum("ijk,jk->ij", P[:, None, :] - e0[None], d) / length2, 0.0, 1.0)
        closest = e0[None] + t[..., None] * d[None]
        return float(np.min(np.linalg.norm(P[:, None, :] - closest, axis=2)))

    def crossing(H: np.ndarray, G: np.ndarray) -> bool:
        (a, b), (p, q) = edges(H), edges(G)

        def side(u, v, w):
            return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (
                w[..., 0] - u[..., 0]
            )

        a, b, p, q = a[:, None], b[:, None], p[None], q[None]
        return bool(
            np.any((side(a, b, p) * side(a, b, q) < 0) & (side(p, q, a) * side(p, q, b) < 0))
        )

    HA, HB = hull(A), hull(B)
    if inside(HA, HB) or inside(HB, HA) or crossing(HA, HB):
        return 0.0
    return min(vertex_to_edges(HA, HB), vertex_to_edges(HB, HA))
