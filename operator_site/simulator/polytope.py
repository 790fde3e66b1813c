"""Exact distance between two convex polytopes, by their features.

GJK (python-fcl's) converges to a tolerance it does not let its caller set; near contact it can
answer a distance several times the true one, and a block then steps under the barrier it was
meant to keep. Two separated convex polytopes have their nearest points on a vertex of one and
inside a face of the other, or on an edge of each (a vertex is an edge's end, and parallel faces
or edges also reach the minimum at such a pair). Every candidate below is a pair of points on the
two bodies, so the smallest is the distance itself, to rounding, and the plane between its points
certifies it. Where no candidate certifies itself (the bodies overlap, or touch too closely for a
direction), separating axes decide (face normals and edge-by-edge cross products), which for
convex polytopes also give the exact penetration depth and its direction.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, fields

import numpy as np
from scipy.spatial import ConvexHull

from models.geometry import ConvexPart

PARALLEL_AXIS_SIN = 1e-9
"""Edge pairs more nearly parallel than this (sine of their angle) give no separating axis of
their own: their cross product is all rounding, and a face normal already separates them."""

CERTIFICATE_SLACK_M = 1e-12
"""How far rounding may bring a separating plane's gap below the distance it certifies (m): tens
of ulps of coordinates within a metre of the origin."""


@dataclass(frozen=True)
class Polytope:
    """A convex part's features in one frame: ``vertices`` (n, 3) m; ``edges`` (m, 2) vertex
    indices; ``normals`` (k, 3) outward unit face normals and ``offsets`` (k,) m with
    ``normals[i] · x = offsets[i]`` on face i; ``planes`` (s + k, 3) and ``plane_offsets``
    (s + k,) m: first each face's sides as half-planes (outward in the face's plane, < 0 inside),
    face i's starting at row ``side_starts[i]``, then the faces' own planes; edge j runs from
    ``edge_starts[j]`` along ``edge_vectors[j]`` (m, 3) m, of squared length ``edge_length2[j]``
    (m²); ``face_sides`` (k, w, 3) and ``face_side_offsets`` (k, w) m: face i's sides again,
    padded to the widest face with sides that hold every point (normal 0, offset 1)."""

    vertices: np.ndarray
    edges: np.ndarray
    edge_starts: np.ndarray
    edge_vectors: np.ndarray
    edge_length2: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    planes: np.ndarray
    plane_offsets: np.ndarray
    side_starts: np.ndarray
    face_sides: np.ndarray
    face_side_offsets: np.ndarray

    @classmethod
    def of(cls, part: ConvexPart) -> Polytope:
        """``part``'s features in its own frame, found once per part (parts do not change: a
        simulator world is built for every drag and every program, from the same parts); the
        arrays are read-only."""
        known = _OF_PART.get(part)
        if known is None:
            found = cls._features(part)
            known = _OF_PART[part] = cls(*(_read_only(getattr(found, f.name)) for f in fields(cls)))
        return known

    @classmethod
    def _features(cls, part: ConvexPart) -> Polytope:
        V = part.vertices_O
        ring = [(a, b) for f in part.faces for a, b in zip(f, f[1:] + f[:1], strict=True)]
        edges = sorted({(min(a, b), max(a, b)) for a, b in ring})
        side_n, side_d, starts = [], [], []
        for face, n in zip(part.faces, part.normals_O, strict=True):
            starts.append(len(side_n))
            for a, b in zip(face, face[1:] + face[:1], strict=True):
                # Counter-clockwise seen from outside: (b − a) × n points out of the face.
                m = np.cross(V[b] - V[a], n)
                m /= np.linalg.norm(m)
                side_n.append(m)
                side_d.append(float(m @ V[a]))
        E = np.array(edges, dtype=np.int64)
        D = V[E[:, 1]] - V[E[:, 0]]
        ends = [*starts[1:], len(side_n)]
        sides, side_offsets = _padded(
            [np.array(side_n[a:b]) for a, b in zip(starts, ends, strict=True)],
            [np.array(side_d[a:b]) for a, b in zip(starts, ends, strict=True)],
        )
        return cls(
            V,
            E,
            V[E[:, 0]],
            D,
            np.einsum("ij,ij->i", D, D),
            part.normals_O,
            part.offsets_m,
            np.vstack([np.array(side_n), part.normals_O]),
            np.concatenate([side_d, part.offsets_m]),
            np.array(starts, dtype=np.int64),
            sides,
            side_offsets,
        )

    def moved(self, R: np.ndarray, t: np.ndarray) -> Polytope:
        """These features after the motion x ↦ R x + t."""
        normals, planes, sides = self.normals @ R.T, self.planes @ R.T, self.face_sides @ R.T
        return Polytope(
            self.vertices @ R.T + t,
            self.edges,
            self.edge_starts @ R.T + t,
            self.edge_vectors @ R.T,
            self.edge_length2,
            normals,
            self.offsets + normals @ t,
            planes,
            self.plane_offsets + planes @ t,
            self.side_starts,
            sides,
            self.face_side_offsets + sides @ t,
        )


_OF_PART: weakref.WeakKeyDictionary[ConvexPart, Polytope] = weakref.WeakKeyDictionary()


def _read_only(a: np.ndarray) -> np.ndarray:
    """A copy of ``a`` that cannot be written (the part's own arrays stay as they are)."""
    a = a.copy()
    a.setflags(write=False)
    return a


def _padded(sides: list[np.ndarray], offsets: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Faces' side planes, (s_i, 3) normals and (s_i,) offsets each, stacked as (k, w, 3) and
    (k, w), w the most sides of any, the rest sides that hold every point: 0 · x − 1 < 0."""
    width = max(len(n) for n in sides)
    N = np.zeros((len(sides), width, 3))
    D = np.ones((len(sides), width))
    for i, (n, d) in enumerate(zip(sides, offsets, strict=True)):
        N[i, : len(n)], D[i, : len(d)] = n, d
    return N, D


def _separation(A: Polytope, B: Polytope) -> tuple[float, np.ndarray]:
    """The largest gap between the two bodies' projections over the separating axes (m; < 0: the
    smallest overlap, the penetration depth) and its axis, a unit vector from A towards B."""
    dA = A.edge_vectors / np.sqrt(A.edge_length2)[:, None]
    dB = B.edge_vectors / np.sqrt(B.edge_length2)[:, None]
    cross = np.cross(dA[:, None, :], dB[None, :, :]).reshape(-1, 3)
    norms = np.linalg.norm(cross, axis=1)
    keep = norms > PARALLEL_AXIS_SIN
    axes = np.vstack([A.normals, B.normals, cross[keep] / norms[keep, None]])
    pA, pB = A.vertices @ axes.T, B.vertices @ axes.T
    gap_AB = pB.min(axis=0) - pA.max(axis=0)  # along +axis: A below, B above
    gap_BA = pA.min(axis=0) - pB.max(axis=0)
    flip = gap_BA > gap_AB
    gaps = np.where(flip, gap_BA, gap_AB)
    k = int(np.argmax(gaps))
    return float(gaps[k]), -axes[k] if flip[k] else axes[k]


def _edge_edge(A: Polytope, B: Polytope) -> tuple[float, np.ndarray, np.ndarray]:
    """The nearest pair of points on an edge of A and an edge of B: (distance m, A's, B's)
    (Ericson, Real-Time Collision Detection §5.1.9, for every pair at once)."""
    p1, d1, a = A.edge_starts, A.edge_vectors, A.edge_length2[:, None]
    p2, d2, e = B.edge_starts, B.edge_vectors, B.edge_length2[None, :]
    b = d1 @ d2.T
    # c = d1·(p1 − p2) and f = d2·(p1 − p2) for every pair, without the (m, n, 3) differences.
    c = np.einsum("ij,ij->i", d1, p1)[:, None] - d1 @ p2.T
    f = p1 @ d2.T - np.einsum("ij,ij->i", d2, p2)[None, :]
    denom = a * e - b * b
    # Parallel edges (denom 0): any s is nearest somewhere; s = 0 and the clamps below find it.
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 0.0, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = np.where(
        t < 0.0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s)
    )
    t = np.clip(t, 0.0, 1.0)
    w = (p1[:, None, :] - p2[None, :, :]) + s[..., None] * d1[:, None, :] - t[..., None] * d2[None]
    dist2 = np.einsum("ijk,ijk->ij", w, w)
    i, j = np.unravel_index(int(np.argmin(dist2)), dist2.shape)
    q = p1[i] + s[i, j] * d1[i]
    return float(np.sqrt(dist2[i, j])), q, q - w[i, j]


def certified(V_A: np.ndarray, V_B: np.ndarray, d: float, p_A: np.ndarray, p_B: np.ndarray) -> bool:
    """Whether points p_A and p_B, d apart, are the nearest points of the hulls of V_A and V_B
    (n, 3) to :data:`CERTIFICATE_SLACK_M`: the planes through them perpendicular to p_B − p_A
    separate the hulls by d, so that the hulls are no nearer than d; being on them, the points
    show they are no further."""
    if not 0.0 < d < np.inf:
        return False
    n = (p_B - p_A) / d
    return float(np.min(V_B @ n) - np.max(V_A @ n)) >= d - CERTIFICATE_SLACK_M


@dataclass(frozen=True)
class PolytopeGroup:
    """Polytopes in one frame stacked, so that one array operation serves them all: their
    ``vertices`` (N, 3), member g's from row ``vertex_starts[g]``, each row's member in
    ``vertex_member``; their faces' ``normals`` (F, 3), g's from ``face_starts[g]``, each face's
    member in ``face_member``; ``planes`` (S + F, 3) and ``plane_offsets`` (S + F,):
    every face's sides (face i's from row ``side_starts[i]``), then every face's own plane;
    ``offsets`` (F,) the faces' own planes' offsets; ``face_sides`` (F, w, 3) and
    ``face_side_offsets`` (F, w) every face's sides padded as :class:`Polytope`'s are."""

    members: tuple[Polytope, ...]
    vertices: np.ndarray
    vertex_starts: np.ndarray
    vertex_member: np.ndarray
    normals: np.ndarray
    face_starts: np.ndarray
    face_member: np.ndarray
    planes: np.ndarray
    plane_offsets: np.ndarray
    side_starts: np.ndarray
    offsets: np.ndarray
    face_sides: np.ndarray
    face_side_offsets: np.ndarray

    @classmethod
    def of(cls, members: tuple[Polytope, ...]) -> PolytopeGroup:
        """The stack of ``members`` (at least one)."""
        n_sides = [len(m.planes) - len(m.normals) for m in members]
        side_base = np.cumsum([0, *n_sides[:-1]])
        n_vertices = [len(m.vertices) for m in members]
        n_faces = [len(m.normals) for m in members]
        return cls(
            members,
            np.vstack([m.vertices for m in members]),
            np.cumsum([0, *n_vertices[:-1]]),
            np.repeat(np.arange(len(members)), n_vertices),
            np.vstack([m.normals for m in members]),
            np.cumsum([0, *n_faces[:-1]]),
            np.repeat(np.arange(len(members)), n_faces),
            np.vstack(
                [m.planes[:k] for m, k in zip(members, n_sides, strict=True)]
                + [m.normals for m in members]
            ),
            np.concatenate(
                [m.plane_offsets[:k] for m, k in zip(members, n_sides, strict=True)]
                + [m.offsets for m in members]
            ),
            np.concatenate([m.side_starts + b for m, b in zip(members, side_base, strict=True)]),
            np.concatenate([m.offsets for m in members]),
            *_padded(
                [n for m in members for n in m.face_sides],
                [d for m in members for d in m.face_side_offsets],
            ),
        )


def polytope_distance(A: Polytope, B: Polytope) -> tuple[float, np.ndarray, np.ndarray]:
    """The distance (m) between convex polytopes A and B, and their nearest points (3,) each.

    Overlapping bodies get minus their penetration depth; the points are then A's vertex deepest
    into B along the separating axis and where the depth's translation of A takes it.
    """
    return posed_distances(A, np.eye(3), np.zeros(3), PolytopeGroup.of((B,)))[0]


def _vertex_face_table(
    V: np.ndarray, planes: np.ndarray, offsets: np.ndarray, side_starts: np.ndarray, n_faces: int
) -> tuple[np.ndarray, np.ndarray]:
    """For vertices V (n, 3) and faces given as :class:`Polytope` stacks them (``planes``,
    ``offsets``, ``side_starts``, the last ``n_faces`` rows the faces' own planes): each vertex's
    distance to each face's plane where it projects inside the face (inf elsewhere) and its
    signed height over the plane, both (n, n_faces) m."""
    H = V @ planes.T - offsets
    n_sides = len(planes) - n_faces
    inside = np.maximum.reduceat(H[:, :n_sides], side_starts, axis=1) < 0.0
    height = H[:, n_sides:]
    return np.where(inside, np.abs(height), np.inf), height


def posed_distances(
    A_O: Polytope, R_WO: np.ndarray, p_WO: np.ndarray, group_W: PolytopeGroup
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """:func:`polytope_distance` of ``A_O`` moved to the pose (``R_WO``, ``p_WO``) and each
    member of ``group_W``, points in W. The vertex–face pairs of all members are found at once;
    a member whose nearest pair they do not certify gets the edge pairs and separating axes."""
    return posed_distances_and_faces(A_O, R_WO, p_WO, group_W)[0]


@dataclass(frozen=True)
class SeparatingFaces:
    """For each member of a group, the face whose plane held the nearest pair of points at a
    query, gathered for :func:`distances_over_faces`: ``complete`` whether every member has
    one (none where an edge pair was nearest, or they overlapped); the members ``on`` (g,)
    whose own face it was, with those faces' ``normals`` (g, 3), ``offsets`` (g,) m,
    ``sides`` (g, w, 3) and ``side_offsets`` (g, w) m in W (as :class:`Polytope`'s); and the
    members ``off`` whose nearest pair lay on A's face ``off_faces`` (A's numbering)."""

    complete: bool
    on: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    sides: np.ndarray
    side_offsets: np.ndarray
    off: tuple[int, ...]
    off_faces: tuple[int, ...]

    @classmethod
    def of(cls, group: PolytopeGroup, on_member: np.ndarray, face: np.ndarray) -> SeparatingFaces:
        """From ``on_member`` (M,) bool and ``face`` (M,) (−1: none) per member of ``group``."""
        on = np.flatnonzero(on_member & (face >= 0))
        f = face[on]
        off = np.flatnonzero(~on_member & (face >= 0))
        return cls(
            bool(np.all(face >= 0)),
            on,
            group.normals[f],
            group.offsets[f],
            group.face_sides[f],
            group.face_side_offsets[f],
            tuple(int(g) for g in off),
            tuple(int(k) for k in face[off]),
        )


def posed_distances_and_faces(
    A_O: Polytope, R_WO: np.ndarray, p_WO: np.ndarray, group_W: PolytopeGroup
) -> tuple[list[tuple[float, np.ndarray, np.ndarray]], SeparatingFaces]:
    """:func:`posed_distances`, and the faces whose planes held each member's nearest pair, for
    :func:`distances_over_faces` at nearby poses."""
    V_AW = A_O.vertices @ R_WO.T + p_WO
    G = group_W
    # A's vertices over the members' faces: (vertices of A) × (faces of all members).
    d_AB, h_AB = _vertex_face_table(V_AW, G.planes, G.plane_offsets, G.side_starts, len(G.normals))
    v_AB = np.argmin(d_AB, axis=0)
    cols = np.arange(len(v_AB))
    d_AB, h_AB = d_AB[v_AB, cols], h_AB[v_AB, cols]
    # The members' vertices over A's faces, in A's frame: (vertices of all) × (faces of A).
    V_BO = (G.vertices - p_WO) @ R_WO
    d_BA, h_BA = _vertex_face_table(
        V_BO, A_O.planes, A_O.plane_offsets, A_O.side_starts, len(A_O.normals)
    )
    f_BA = np.argmin(d_BA, axis=1)
    rows = np.arange(len(f_BA))
    d_BA, h_BA = d_BA[rows, f_BA], h_BA[rows, f_BA]
    # Each member's nearest vertex–face pair: sorted by member, then distance, a member's first
    # entry is its nearest.
    f = np.lexsort((d_AB, G.face_member))[G.face_starts]
    v = np.lexsort((d_BA, G.vertex_member))[G.vertex_starts]
    from_A = (d_AB[f] <= d_BA[v])[:, None]
    q_A = V_AW[v_AB[f]]
    q_B = G.vertices[v]
    p_A = np.where(from_A, q_A, q_B - h_BA[v, None] * (A_O.normals[f_BA[v]] @ R_WO.T))
    p_B = np.where(from_A, q_A - h_AB[f, None] * G.normals[f], q_B)
    d = np.where(from_A[:, 0], d_AB[f], d_BA[v])
    # All members' pairs checked at once, as :func:`certified` does one.
    finite = np.isfinite(d) & (d > 0.0)
    n = (p_B - p_A) / np.where(finite, d, 1.0)[:, None]
    top_A = np.max(V_AW @ n.T, axis=0)
    bottom_B = np.minimum.reduceat(
        np.einsum("ij,ij->i", G.vertices, n[G.vertex_member]), G.vertex_starts
    )
    ok = finite & (bottom_B - top_A >= d - CERTIFICATE_SLACK_M)
    faces = SeparatingFaces.of(
        G, from_A[:, 0], np.where(ok, np.where(from_A[:, 0], f, f_BA[v]), -1)
    )
    results = [
        (float(d[g]), p_A[g], p_B[g])
        if ok[g]
        else _by_edges_and_axes(A_O, R_WO, p_WO, V_AW, B, (float(d[g]), p_A[g], p_B[g]))
        for g, B in enumerate(G.members)
    ]
    return results, faces


def distances_over_faces(
    A_O: Polytope,
    R_WO: np.ndarray,
    p_WO: np.ndarray,
    group_W: PolytopeGroup,
    faces: SeparatingFaces,
) -> np.ndarray | None:
    """The distances (M,) m of :func:`posed_distances` where, for every member, the face in
    ``faces`` still holds the nearest pair: the body on the face's other side lies wholly at
    least its nearest vertex's height above the face's plane, and where that vertex projects
    inside the face it is the nearest point, so the height is the distance. None where a
    member has no face or its nearest vertex falls outside it (or touches): then the whole
    query is due. Nearby poses (a line search's) mostly keep their faces, at a fraction of the
    whole query's cost."""
    if not faces.complete:
        return None
    G = group_W
    d = np.empty(len(G.members))
    if len(faces.on):
        # A's vertices over members' faces, in W.
        V_AW = A_O.vertices @ R_WO.T + p_WO
        H = V_AW @ faces.normals.T - faces.offsets
        j = H.argmin(axis=0)
        h = H[j, np.arange(len(j))]
        sides = np.einsum("kwi,ki->kw", faces.sides, V_AW[j]) - faces.side_offsets
        if not ((sides < 0.0).all() and (h > 0.0).all()):
            return None
        d[faces.on] = h
    for g, f in zip(faces.off, faces.off_faces, strict=True):
        # The member's vertices over A's face, in A's frame.
        V = (G.members[g].vertices - p_WO) @ R_WO
        h = V @ A_O.normals[f] - A_O.offsets[f]
        j = int(h.argmin())
        if not (h[j] > 0.0 and (A_O.face_sides[f] @ V[j] - A_O.face_side_offsets[f] < 0.0).all()):
            return None
        d[g] = h[j]
    return d


def _by_edges_and_axes(
    A_O: Polytope,
    R_WO: np.ndarray,
    p_WO: np.ndarray,
    V_AW: np.ndarray,
    B_W: Polytope,
    nearest: tuple[float, np.ndarray, np.ndarray],
) -> tuple[float, np.ndarray, np.ndarray]:
    """The distance where the nearest vertex–face pair, ``nearest``, did not certify itself: the
    edge pairs join it, and if the nearest of all does not certify itself either, the bodies
    overlap or touch too closely for a direction, which separating axes decide."""
    A_W = A_O.moved(R_WO, p_WO)
    nearest = min(nearest, _edge_edge(A_W, B_W), key=lambda c: c[0])
    if certified(V_AW, B_W.vertices, *nearest):
        return nearest
    sep, axis = _separation(A_W, B_W)
    if sep > 0.0:
        return nearest
    p = V_AW[int(np.argmax(V_AW @ axis))]
    return sep, p, p + sep * axis


def _point_triangle_m(T: np.ndarray) -> float:
    """Distance from the origin to triangle T (3, 3)."""
    a, b, c = T
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    p = (a @ n) * n  # the origin projected onto the triangle's plane
    inside = all(np.cross(v1 - v0, p - v0) @ n >= 0.0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return abs(float(a @ n))
    best = np.inf
    for v0, v1 in ((a, b), (b, c), (c, a)):
        d = v1 - v0
        s = np.clip(-(v0 @ d) / (d @ d), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(v0 + s * d)))
    return best


def reference_distance_m(V_A: np.ndarray, V_B: np.ndarray) -> float:
    """Signed distance between the hulls of V_A and V_B (n, 3), slowly and independently of
    :func:`polytope_distance`, for tests and benchmarks: from the origin to the hull of
    {a − b} (Qhull), outside by its nearest triangle, inside by minus its nearest facet plane."""
    M = (V_A[:, None, :] - V_B[None, :, :]).reshape(-1, 3)
    hull = ConvexHull(M)
    planes = hull.equations  # n·x + c ≤ 0 inside, n outward
    if np.all(planes[:, 3] < 0.0):
        return float(np.max(planes[:, 3]))
    return min(_point_triangle_m(M[s]) for s in hull.simplices)
