"""What vision needs of an object model: edges, convex parts as half-spaces, symmetries.

All geometry is float64 in metres, in the object frame O unless a name says otherwise. Camera
frame C follows OpenCV (x right, y down, z forward), ``K`` is the 3×3 intrinsic matrix (px).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import cache, cached_property

import numpy as np

from models.geometry import axis_rotations
from models.scene import ObjectModel

EDGE_SAMPLES = 12
"""Points per model edge at which visibility is tested (ray casting against the parts)."""
_EDGE_TS = (np.arange(EDGE_SAMPLES) + 0.5) / EDGE_SAMPLES  # their fractions along the edge
VISIBILITY_EPS_M = 2e-5
"""A surface point counts as hidden only if a part is entered this far (m) before reaching it."""
CULL_MARGIN = 1e-6
"""Slack (px, and m) of the tests that set aside occluders which cannot hide anything."""


@dataclass(frozen=True, eq=False)
class VisionModel:
    """One object as vision sees it.

    ``edges_O``: (m, 2, 3) feature edges. ``planes_O``: one (k, 4) array per convex part, rows
    ``(n, d)`` with ``n·x ≤ d`` inside. ``vertices_O``: (v, 3) all part vertices.
    ``symmetries``: (s, 3, 3) rotations ``R`` with ``R·shape = shape`` (identity first).
    """

    name: str
    edges_O: np.ndarray
    planes_O: tuple[np.ndarray, ...]
    vertices_O: np.ndarray
    symmetries: np.ndarray
    parts_vertices_O: tuple[np.ndarray, ...]

    @cached_property
    def edge_faces(self) -> np.ndarray:
        """(e, f) bool: edge ``e`` lies on face ``f`` of the parts (faces stacked over the
        parts in :attr:`planes_O` order)."""
        planes = np.vstack(self.planes_O)
        dist = np.abs(self.edges_O @ planes[:, :3].T - planes[:, 3])  # (e, 2, f)
        return np.all(dist < 1e-7, axis=1)

    @property
    def size_m(self) -> float:
        """Bounding-box diagonal (m)."""
        return float(np.linalg.norm(self.vertices_O.max(0) - self.vertices_O.min(0)))


def vision_model(model: ObjectModel) -> VisionModel:
    """The :class:`VisionModel` of a loaded object model."""
    planes = tuple(np.column_stack([p.normals_O, p.offsets_m]) for p in model.parts)
    V = np.vstack([p.vertices_O for p in model.parts])
    # The union's outer vertices (drop points shared by parts or buried in another part).
    V = np.unique(np.round(V, 9), axis=0)
    return VisionModel(
        name=model.name,
        edges_O=np.asarray(model.feature_edges_O, dtype=np.float64),
        planes_O=planes,
        vertices_O=V,
        symmetries=model.symmetries,
        parts_vertices_O=tuple(p.vertices_O for p in model.parts),
    )


def project(p_C: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of points (..., 3) in C to pixels (..., 2)."""
    z = p_C[..., 2:3]
    uv = p_C[..., :2] / z
    return uv @ K[:2, :2].T + K[:2, 2]


def transform(X_AB: np.ndarray, p_B: np.ndarray) -> np.ndarray:
    """Points (..., 3) in B expressed in A."""
    return p_B @ X_AB[:3, :3].T + X_AB[:3, 3]


def planes_in(X_CO: np.ndarray, planes_O: np.ndarray) -> np.ndarray:
    """Half-space rows ``(n, d)`` (k, 4) moved from O into C."""
    n_C = planes_O[:, :3] @ X_CO[:3, :3].T
    d_C = planes_O[:, 3] + n_C @ X_CO[:3, 3]
    return np.column_stack([n_C, d_C])


def parts_in(X_AO: np.ndarray, model: VisionModel) -> list[tuple[np.ndarray, np.ndarray]]:
    """``model``'s convex parts at pose ``X_AO``: (vertices (n, 3), face normals (k, 3)) in A,
    the form :class:`~work_site.vision.verification.Surroundings` weighs."""
    return [
        (transform(X_AO, V), P[:, :3] @ X_AO[:3, :3].T)
        for V, P in zip(model.parts_vertices_O, model.planes_O, strict=True)
    ]


def occluded(points_C: np.ndarray, occluders_C: list[np.ndarray]) -> np.ndarray:
    """For points (n, 3) in C: is the ray from the camera centre to the point blocked by any of
    the convex parts (each (k, 4) half-spaces in C) before it gets there? (n,) bool.

    All parts at once: the planes are stacked and each part's entry and exit are reduced over
    its own rows (``reduceat``), so the cost is a few array operations whatever the count."""
    hidden = np.zeros(len(points_C), dtype=bool)
    if len(occluders_C) == 0 or len(points_C) == 0:
        return hidden
    planes = np.concatenate(occluders_C)  # (P, 4)
    starts = list(itertools.accumulate((len(q) for q in occluders_C[:-1]), initial=0))
    dist = np.sqrt(np.sum(points_C * points_C, axis=1))  # as np.linalg.norm, fewer calls
    eps_t = (VISIBILITY_EPS_M / np.maximum(dist, 1e-9))[:, None]
    # Ray x(t) = t·p for t in [0, 1]; inside a part where t·(n·p) ≤ d for each of its faces.
    den = points_C @ planes[:, :3].T  # (n, P)
    num = planes[:, 3]  # broadcast along the rows
    # t where den = 0 is never used (the two wheres below): divide by 1 there, not by 0
    t = num / np.where(den == 0, 1.0, den)
    t_enter = np.maximum.reduceat(np.where(den < 0, t, 0.0), starts, axis=1)  # (n, parts)
    t_exit = np.minimum.reduceat(np.where(den > 0, t, np.inf), starts, axis=1)
    parallel_out = np.logical_or.reduceat((den == 0) & (num < 0), starts, axis=1)
    hit = (t_enter < t_exit - eps_t) & (t_enter < 1.0 - eps_t) & ~parallel_out
    return np.any(hit, axis=1)


@dataclass(frozen=True)
class Occluders:
    """Convex parts that may hide others, in C: ``planes`` one (k, 4) half-space array per
    part, ``boxes_px`` (parts, 4) the bounding box ``(u_min, v_min, u_max, v_max)`` of each
    part's image (infinite where the part reaches behind the camera). Knowing the boxes, most
    parts are set aside at once for any one object: see :meth:`relevant`."""

    planes: list[np.ndarray]
    boxes_px: np.ndarray
    _stacked: np.ndarray = field(init=False, repr=False)
    _starts: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        stacked = np.vstack(self.planes) if self.planes else np.zeros((0, 4))
        starts = np.cumsum([0] + [len(q) for q in self.planes[:-1]]).astype(np.intp)
        object.__setattr__(self, "_stacked", stacked)
        object.__setattr__(self, "_starts", starts)

    @staticmethod
    def of_parts(vertices_C: list[np.ndarray], planes_C: list[np.ndarray], K: np.ndarray):
        """The occluders of convex parts given by their vertices and half-spaces in C."""
        boxes = np.tile([-np.inf, -np.inf, np.inf, np.inf], (len(planes_C), 1))
        for k, V in enumerate(vertices_C):
            if np.all(V[:, 2] > 1e-9):  # wholly in front: its image is its vertices' hull
                uv = project(V, K)
                boxes[k] = [*uv.min(0), *uv.max(0)]
        return Occluders(list(planes_C), boxes)

    def __add__(self, other: list[np.ndarray] | Occluders) -> Occluders:
        """These and more parts: ``other``'s, or parts whose images are not known."""
        if isinstance(other, Occluders):
            return Occluders(self.planes + other.planes, np.vstack([self.boxes_px, other.boxes_px]))
        extra = np.tile([-np.inf, -np.inf, np.inf, np.inf], (len(other), 1))
        return Occluders(self.planes + list(other), np.vstack([self.boxes_px, extra]))

    @staticmethod
    def joined(parts: list[Occluders]) -> Occluders:
        """The parts of all of ``parts``, in order."""
        planes = [q for o in parts for q in o.planes]
        boxes = np.vstack([o.boxes_px for o in parts]) if parts else np.zeros((0, 4))
        return Occluders(planes, boxes)

    def relevant(self, points_C: np.ndarray, K: np.ndarray) -> list[np.ndarray]:
        """The parts that may hide some point of the convex hull of ``points_C`` (n, 3): a
        part hides a point only where it covers the point's image, and never when one of its
        faces has both the camera and all the points on its outer side. Exact: the parts set
        aside hide nothing that :func:`occluded` would find hidden."""
        if not self.planes:
            return []
        keep = np.ones(len(self.planes), dtype=bool)
        if np.all(points_C[:, 2] > 1e-9):  # the hull's image is the points' images' hull
            uv = project(points_C, K)
            lo, hi = uv.min(0) - CULL_MARGIN, uv.max(0) + CULL_MARGIN
            b = self.boxes_px
            keep = (b[:, 0] <= hi[0]) & (b[:, 2] >= lo[0]) & (b[:, 1] <= hi[1]) & (b[:, 3] >= lo[1])
        P = self._stacked
        outside = np.all(points_C @ P[:, :3].T > P[:, 3] + CULL_MARGIN, axis=0) & (P[:, 3] < 0)
        keep &= ~np.logical_or.reduceat(outside, self._starts)
        return [q for q, k in zip(self.planes, keep.tolist(), strict=True) if k]


def visible_edges(
    model: VisionModel,
    X_CO: np.ndarray,
    K: np.ndarray,
    occluders_C: list[np.ndarray] | Occluders | None = None,
    min_fraction: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected visible parts of the model's edges under pose ``X_CO``.

    Returns ``(edge_ids (e,), segments_px (e, 4), visible_fraction (e,))`` for edges at least
    ``min_fraction`` visible; each segment spans the edge's visible samples (hidden-edge removal by
    the faces' orientation for a convex model, else by ray casting against its own parts, and by
    ray casting against ``occluders_C``).
    """
    edges_C = transform(X_CO, model.edges_O)  # (m, 2, 3)
    if isinstance(occluders_C, Occluders):
        occluders_C = occluders_C.relevant(edges_C.reshape(-1, 3), K)
    if len(model.planes_O) == 1:
        # A convex object hides exactly those of its edges whose faces all face away from the
        # camera (at C's origin, outside a face's plane when its offset is negative): only the
        # others need rays cast, and only against the other objects.
        P = model.planes_O[0]  # the offsets of planes_in(X_CO, P), alone
        d_C = P[:, 3] + (P[:, :3] @ X_CO[:3, :3].T) @ X_CO[:3, 3]
        cand = np.flatnonzero(model.edge_faces[:, d_C < 0].any(axis=1))
        occ = []
    else:
        occ = [planes_in(X_CO, P) for P in model.planes_O]
        cand = np.arange(len(edges_C))
    occ += list(occluders_C or [])
    ts = _EDGE_TS
    E = edges_C[cand]
    if not occ and min_fraction <= 1.0 and E[..., 2].min(initial=np.inf) > 1e-3:
        # Nothing to cast rays against and all in front: every sample is visible.
        a = E[:, 0]
        d = E[:, 1] - a  # the ends as the general case writes them (t 0 and 1): the same bits
        segs = project(np.stack([a + 0.0 * d, a + 1.0 * d], axis=1), K).reshape(-1, 4)
        return cand, segs, np.ones(len(cand))
    samples = E[:, 0, None, :] + ts[None, :, None] * (E[:, 1] - E[:, 0])[:, None, :]
    flat = samples.reshape(-1, 3)
    vis = flat[:, 2] > 1e-3
    if occ:
        vis &= ~occluded(flat, occ)
    vis = vis.reshape(len(E), EDGE_SAMPLES)
    frac = vis.sum(axis=1) / EDGE_SAMPLES
    keep = np.flatnonzero(frac >= min_fraction)
    if len(keep) == 0:
        return keep, np.zeros((0, 4)), np.zeros(0)
    half = 0.5 / EDGE_SAMPLES
    first = np.argmax(vis[keep], axis=1)  # first and last visible sample of each kept edge
    last = EDGE_SAMPLES - 1 - np.argmax(vis[keep, ::-1], axis=1)
    t0 = np.where(first == 0, 0.0, ts[first] - half)[:, None]
    t1 = np.where(last == EDGE_SAMPLES - 1, 1.0, ts[last] + half)[:, None]
    a = E[keep, 0]
    d = E[keep, 1] - a
    segs = project(np.stack([a + t0 * d, a + t1 * d], axis=1), K).reshape(-1, 4)
    return cand[keep], segs, frac[keep]


def convex_overlap_depth(
    A: np.ndarray,
    B: np.ndarray,
    normals_A: np.ndarray | None = None,
    normals_B: np.ndarray | None = None,
) -> float:
    """Penetration depth (m) of the convex hulls of two vertex sets (0 if they are apart).

    Separating-axis test over both hulls' facet normals and the cross products of their edge
    directions (the edge directions of a hull are among the cross products of its facet normals,
    and extra axes never create a false overlap). Pass the facet normals if known: finding
    them is the slow part.
    """
    na = _unit_rows(normals_A if normals_A is not None else [n for n, _ in hull_facets(A)])
    nb = _unit_rows(normals_B if normals_B is not None else [n for n, _ in hull_facets(B)])
    # All axes at once; repeated axes do not change the smallest overlap.
    ia, ja = _pairs(len(na))
    ib, jb = _pairs(len(nb))
    ea = _unit_rows(_cross(na[ia], na[ja]))
    eb = _unit_rows(_cross(nb[ib], nb[jb]))
    axes = np.vstack([na, nb, _unit_rows(_cross(ea[:, None, :], eb[None, :, :]).reshape(-1, 3))])
    pa, pb = A @ axes.T, B @ axes.T
    depth = float(np.min(np.minimum(pa.max(0), pb.max(0)) - np.maximum(pa.min(0), pb.min(0))))
    return max(depth, 0.0)


def overlap_exceeds(
    A: np.ndarray, B: np.ndarray, normals_A: np.ndarray, normals_B: np.ndarray, limit_m: float
) -> bool:
    """Whether ``convex_overlap_depth(A, B, normals_A, normals_B) > limit_m`` (``limit_m`` ≥ 0).
    The facet normals are tried first: when they alone separate the hulls to within
    ``limit_m``, the edge axes (most of the work) cannot raise the depth, which is a minimum
    over axes; only otherwise is the whole test run."""
    axes = np.vstack([_unit_rows(normals_A), _unit_rows(normals_B)])
    pa, pb = A @ axes.T, B @ axes.T
    if np.min(np.minimum(pa.max(0), pb.max(0)) - np.maximum(pa.min(0), pb.min(0))) <= limit_m:
        return False
    return convex_overlap_depth(A, B, normals_A, normals_B) > limit_m


@cache
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)``, made once per ``n``."""
    return np.triu_indices(n, 1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of 3-vectors in the last axis (broadcast), by components: the same
    arithmetic without its axis juggling, which costs more than the products here."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _unit_rows(v) -> np.ndarray:
    """The rows of ``v`` (k, 3) at least 1e-9 long, scaled to unit length."""
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(v, axis=1)
    keep = norm >= 1e-9
    return v[keep] / norm[keep, None]


def hull_facets(V: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Facets of the convex hull of ``V`` as (outward unit normal, offset), brute force."""
    out: list[tuple[np.ndarray, float]] = []
    c = V.mean(0)
    for i, j, k in itertools.combinations(range(len(V)), 3):
        n = np.cross(V[j] - V[i], V[k] - V[i])
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n = n / norm
        s = (V - V[i]) @ n
        if np.all(s <= 1e-9) or np.all(s >= -1e-9):
            if (c - V[i]) @ n > 0:
                n = -n
            if not any(n @ m > 1 - 1e-9 for m, _ in out):
                out.append((n, float(n @ V[i])))
    return out


def containments(A: VisionModel, B: VisionModel, tol_m: float = 1e-9) -> list[np.ndarray]:
    """Poses ``X_BA`` that put all of ``A`` inside one convex part of ``B`` with faces on the
    part's faces (A rotated by one of the cube's 24 rotations, then pushed into a corner of the
    part's bounding box). A found object may really be part of a bigger one: an L block's bar
    looks like a tall block lying down, its end like a cube."""
    out: list[np.ndarray] = []
    rots = axis_rotations()
    for V_P, planes in zip(B.parts_vertices_O, B.planes_O, strict=True):
        lo, hi = V_P.min(0), V_P.max(0)
        for R in rots:
            V = A.vertices_O @ R.T
            mn, mx = V.min(0), V.max(0)
            if np.any(mx - mn > hi - lo + tol_m):
                continue
            for corner in itertools.product((0, 1), repeat=3):
                c = np.array(corner, dtype=bool)
                t = np.where(c, hi - mx, lo - mn)
                W = V + t
                if np.max(W @ planes[:, :3].T - planes[:, 3]) > 1e-7:
                    continue
                X = np.eye(4)
                X[:3, :3] = R
                X[:3, 3] = t
                if not any(np.allclose(X, Y, atol=1e-9) for Y in out):
                    out.append(X)
    return out
