"""Contact manifolds between two convex polyhedra that are close but apart (paper §V-A).

A distance query gives one nearest pair of points; a resting block needs all of its contact: a
vertex on a face is one point, an edge on a face the two ends of the overlap, a face on a face
the corners of the overlap polygon. With ``n`` the unit vector from the workpiece's nearest
point to the obstacle's, the planes through the two nearest points perpendicular to ``n``
separate the bodies; each body's *support feature* is its set of vertices within ``eps_contact``
of the other body's plane. Projected onto the plane, the two features are convex sets whose
intersection is the contact region; its corners, lifted back to the mid-plane, are the contact
points.
"""

from __future__ import annotations

import math

import numpy as np

PLANAR_TOL_M = 1e-9
"""Points closer than this in the contact plane are the same point (m)."""
MIN_SEPARATION_FOR_NORMAL_M = 1e-12
"""Below this distance the direction between nearest points is not a usable normal (m)."""
NORMAL_SNAP_RAD = 1e-6
"""A nearest-point direction within this angle of a face normal is that face normal: the
direction between nearest points of parallel faces 0.1 mm apart is only good to ~1e-12."""
NEAREST_POINT_PRECISION_M = 1e-14
"""How far the nearest points may be off in float64 on parts within metres of the origin
(tens of ulps of their coordinates, with a margin); the direction between points d apart is
only good to this over d, so closer than 1e-8 m the snapping angle grows as that."""


def _plane_basis(n: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) spanning the plane perpendicular to unit ``n``."""
    x, y, z = n
    # n × (1, 0, 0) or n × (0, 1, 0), whichever is far from parallel; written out (np.cross
    # costs more than the rest of this function).
    e1 = np.array([0.0, z, -y]) if abs(x) < 0.9 else np.array([-z, 0.0, x])
    e1 /= math.sqrt(e1 @ e1)
    e2 = np.array([y * e1[2] - z * e1[1], z * e1[0] - x * e1[2], x * e1[1] - y * e1[0]])
    return np.array([e1, e2])


Pt = tuple[float, float]


def _cross(o: Pt, a: Pt, b: Pt) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _dedupe(P: list[Pt]) -> list[Pt]:
    """Drop points within :data:`PLANAR_TOL_M` of an earlier one (order kept)."""
    out: list[Pt] = []
    for p in P:
        x, y = p
        for q in out:  # a plain loop: all() over a generator cost more than the comparisons
            if not (abs(x - q[0]) > PLANAR_TOL_M or abs(y - q[1]) > PLANAR_TOL_M):
                break
        else:
            out.append(p)
    return out


def convex_hull_2d(P: list[Pt]) -> list[Pt]:
    """Counter-clockwise hull of 2D points; 1 point or 2 (a segment) for degenerate sets.

    Plain Python: for the handful of corners of a contact feature it beats numpy's call overhead.
    """
    P = sorted(_dedupe(P))
    if len(P) <= 2:
        return P
    span = max(P[-1][0] - P[0][0], max(p[1] for p in P) - min(p[1] for p in P))
    tol = PLANAR_TOL_M * max(span, PLANAR_TOL_M)  # a turn below this area is straight
    lower: list[Pt] = []
    for p in P:
        while len(lower) >= 2 and _cross(lower[-2], lower[-1], p) <= tol:
            lower.pop()
        lower.append(p)
    upper: list[Pt] = []
    for p in reversed(P):
        while len(upper) >= 2 and _cross(upper[-2], upper[-1], p) <= tol:
            upper.pop()
        upper.append(p)
    hull = lower[:-1] + upper[:-1]
    return hull if len(hull) >= 2 else [P[0], P[-1]]


def _clip_polygon(S: list[Pt], Q: list[Pt]) -> list[Pt]:
    """Sutherland–Hodgman: the part of convex CCW polygon S inside convex CCW polygon Q."""
    out = S
    for i in range(len(Q)):
        a, b = Q[i], Q[(i + 1) % len(Q)]
        ex, ey = b[0] - a[0], b[1] - a[1]
        length = math.hypot(ex, ey)
        if length < PLANAR_TOL_M or not out:
            continue
        side = [(ex * (p[1] - a[1]) - ey * (p[0] - a[0])) / length for p in out]
        kept: list[Pt] = []
        for j, p in enumerate(out):
            q, dp, dq = out[(j + 1) % len(out)], side[j], side[(j + 1) % len(out)]
            if dp >= -PLANAR_TOL_M:
                kept.append(p)
            if (dp < -PLANAR_TOL_M) != (dq < -PLANAR_TOL_M):
                t = dp / (dp - dq)
                kept.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        out = _dedupe(kept)
    return out


def _clip_segment(S: list[Pt], Q: list[Pt]) -> list[Pt]:
    """Cyrus–Beck: the part of segment S inside convex CCW polygon Q (0, 1 or 2 points)."""
    (x0, y0), (x1, y1) = S
    dx, dy = x1 - x0, y1 - y0
    lo, hi = 0.0, 1.0
    for i in range(len(Q)):
        a, b = Q[i], Q[(i + 1) % len(Q)]
        ex, ey = b[0] - a[0], b[1] - a[1]
        length = math.hypot(ex, ey)
        if length < PLANAR_TOL_M:
            continue
        # Signed distance inside the edge at S(t) = f0 + t·df; keep where it is ≥ −tol.
        f0 = (ex * (y0 - a[1]) - ey * (x0 - a[0])) / length + PLANAR_TOL_M
        df = (ex * dy - ey * dx) / length
        if abs(df) < 1e-300:
            if f0 < 0:
                return []
        elif df > 0:
            lo = max(lo, -f0 / df)
        else:
            hi = min(hi, -f0 / df)
        if lo > hi:
            return []
    return _dedupe([(x0 + lo * dx, y0 + lo * dy), (x0 + hi * dx, y0 + hi * dy)])


def _segment_overlap(S: list[Pt], T: list[Pt]) -> list[Pt]:
    """Intersection of two 2D segments: their crossing point or the ends of a collinear overlap."""
    (ax, ay), (bx, by) = S
    (cx, cy), (ex, ey) = T
    d1x, d1y, d2x, d2y = bx - ax, by - ay, ex - cx, ey - cy
    l1, l2 = math.hypot(d1x, d1y), math.hypot(d2x, d2y)
    denom = d1x * d2y - d1y * d2x
    if abs(denom) > 1e-9 * l1 * l2:
        rx, ry = cx - ax, cy - ay
        t = (rx * d2y - ry * d2x) / denom
        u = (rx * d1y - ry * d1x) / denom
        if (
            -PLANAR_TOL_M / l1 <= t <= 1 + PLANAR_TOL_M / l1
            and -PLANAR_TOL_M / l2 <= u <= 1 + PLANAR_TOL_M / l2
        ):
            t = min(max(t, 0.0), 1.0)
            return [(ax + t * d1x, ay + t * d1y)]
        return []
    ux, uy = d1x / l1, d1y / l1
    t0, t1 = sorted(((cx - ax) * ux + (cy - ay) * uy, (ex - ax) * ux + (ey - ay) * uy))
    lo, hi = max(0.0, t0), min(l1, t1)
    if hi < lo - PLANAR_TOL_M:
        return []
    return _dedupe([(ax + lo * ux, ay + lo * uy), (ax + max(lo, hi) * ux, ay + max(lo, hi) * uy)])


def convex_intersection_2d(P: list[Pt], Q: list[Pt]) -> list[Pt]:
    """Corners of the intersection of two convex 2D hulls (each a point, segment or polygon)."""
    if len(P) > len(Q):
        P, Q = Q, P
    if len(P) == 1:
        return list(P)  # the caller knows the point lies in both (nearest points coincide)
    if len(Q) == 2:
        return _segment_overlap(P, Q)
    if len(P) == 2:
        return _clip_segment(P, Q)
    return _clip_polygon(P, Q)


def reduce_polygon(P: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` corners of the convex polygon P (CCW), keeping most of its area.

    Greedy: the two farthest corners, then repeatedly the corner farthest outside the polygon
    chosen so far (the largest gain of area for a convex polygon).
    """
    if len(P) <= max_points:
        return P
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    chosen = set(np.unravel_index(np.argmax(D), D.shape))
    while len(chosen) < max_points:
        order = sorted(chosen)
        edges = [(P[order[k]], P[order[(k + 1) % len(order)]]) for k in range(len(order))]
        gains = [
            -1.0 if m in chosen else min(_point_segment_distance(P[m], a, b) for a, b in edges)
            for m in range(len(P))
        ]
        chosen.add(int(np.argmax(gains)))
    return P[sorted(chosen)]


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = np.clip((p - a) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * ab)))


def _surface_height(S_2d: np.ndarray, h: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Height along the normal, at plane points Q (k, 2), of the flat feature (vertex, edge or
    face) whose corners project to ``S_2d`` (m, 2) at heights ``h`` (m,).

    Python floats over the feature's few corners: numpy's per-call overhead cost more than the
    arithmetic (it runs twice for every contact manifold)."""
    S, H = S_2d.tolist(), h.tolist()
    x0, y0 = S[0]
    d1 = [(x - x0) * (x - x0) + (y - y0) * (y - y0) for x, y in S]
    i1 = max(range(len(S)), key=d1.__getitem__)  # the first of equals, as np.argmax
    if d1[i1] < PLANAR_TOL_M**2:
        return np.full(len(Q), float(h.mean()))
    ux, uy = S[i1][0] - x0, S[i1][1] - y0
    area = [abs(ux * (y - y0) - uy * (x - x0)) for x, y in S]
    i2 = max(range(len(S)), key=area.__getitem__)
    if area[i2] < PLANAR_TOL_M * math.sqrt(d1[i1]):
        t = (Q - S_2d[0]) @ np.array([ux, uy]) / d1[i1]  # an edge: linear along it
        return H[0] + t * (H[i1] - H[0])
    # A face: the plane through three corners spanning the largest triangle.
    M = np.array([[ux, uy], [S[i2][0] - x0, S[i2][1] - y0]])
    grad = np.linalg.solve(M, np.array([H[i1] - H[0], H[i2] - H[0]]))
    return H[0] + (Q - S_2d[0]) @ grad


def _snap(n: np.ndarray, face_normals: np.ndarray | None, cos_snap: float) -> np.ndarray:
    if face_normals is None or len(face_normals) == 0:
        return n
    cos = face_normals @ n
    best = int(np.argmax(cos))
    return face_normals[best] if cos[best] >= cos_snap else n


def contact_manifold(
    V_A: np.ndarray,
    V_B: np.ndarray,
    p_A: np.ndarray,
    p_B: np.ndarray,
    eps_contact_m: float,
    max_points: int = 8,
    normals_A: np.ndarray | None = None,
    normals_B: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact points (k, 3), the unit normal (3,) from A towards B, and the gaps (k,) (m).

    ``V_A``, ``V_B``: the vertices (in W) of two convex parts that do not touch; ``p_A``, ``p_B``:
    their nearest points; ``normals_A``, ``normals_B``: optional outward face normals (in W), to
    which a nearly parallel contact normal is snapped. The points lie on the mid-plane between
    the two separating planes; a point's gap is the distance from A's surface to B's along the
    normal there (≥ the parts' distance, larger where the faces are not quite parallel).
    """
    gap = p_B - p_A
    d = float(np.linalg.norm(gap))
    if d < MIN_SEPARATION_FOR_NORMAL_M:
        raise ValueError(f"parts are {d:.3g} m apart: too close for a contact normal")
    cos_snap = math.cos(max(NORMAL_SNAP_RAD, NEAREST_POINT_PRECISION_M / d))
    n = -_snap(-gap / d, normals_B, cos_snap)
    if normals_B is None or not np.any(normals_B @ -n >= cos_snap):
        n = _snap(n, normals_A, cos_snap)
    h_A, h_B = float(p_A @ n), float(p_B @ n)
    S_A = V_A[V_A @ n >= h_B - eps_contact_m]
    S_B = V_B[V_B @ n <= h_A + eps_contact_m]
    E = _plane_basis(n)
    origin = p_A - h_A * n  # p_A projected onto the plane n·x = 0
    A_2d, B_2d = (S_A - origin) @ E.T, (S_B - origin) @ E.T
    # tolist(): the same floats as float() of each element, without a numpy scalar apiece.
    H_A = convex_hull_2d(list(map(tuple, A_2d.tolist())))
    H_B = convex_hull_2d(list(map(tuple, B_2d.tolist())))
    Q = np.array(convex_intersection_2d(H_A, H_B) if H_A and H_B else []).reshape(-1, 2)
    if len(Q) == 0:
        # Rounding put the projected features a hair apart; the nearest points always touch.
        return (0.5 * (p_A + p_B))[None], n, np.array([d])
    Q = reduce_polygon(Q, max_points)
    top_A = _surface_height(A_2d, S_A @ n, Q)
    bottom_B = _surface_height(B_2d, S_B @ n, Q)
    points = origin + Q @ E + np.outer(0.5 * (top_A + bottom_B), n)
    return points, n, bottom_B - top_A
