"""Verification of a pose hypothesis against the image (§IV-A, §VII-A): predicted edges matched
to image lines, the image gradient's direction along every predicted edge, the outline against
the background, a final residual bound, and plausibility (resting on the table inside the work
area, no interpenetration with accepted objects or the fixed environment).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from work_site.vision.model import (
    VisionModel,
    convex_overlap_depth,
    overlap_exceeds,
    project,
    transform,
    visible_edges,
)
from work_site.vision.params import PART_MARGIN_PX, RecognizerParams
from work_site.vision.pose import fit_pose
from work_site.vision.table import SUPPORT_OFFSETS_PX, sample_gradient, sample_gradient_xy


def match_segments(
    model_segs: np.ndarray, image_segs: np.ndarray, tol_px: float, angle_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (model row, image row): each image segment to the nearest projected model edge
    that is parallel within ``angle_rad``, within ``tol_px`` at both its ends, and overlaps it
    along its length by at least half the image segment."""
    if len(model_segs) == 0 or len(image_segs) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    a = model_segs[:, :2]
    d = model_segs[:, 2:] - a
    Lm = np.maximum(np.sqrt(np.einsum("mk,mk->m", d, d)), 1e-9)
    u = d / Lm[:, None]
    n = np.column_stack([-u[:, 1], u[:, 0]])
    p, q = image_segs[:, :2], image_segs[:, 2:]
    di = q - p
    Li = np.maximum(np.sqrt(np.einsum("ik,ik->i", di, di)), 1e-9)
    # (m, i) arrays, by matrix products: rows of A = [n; u] applied to the end points − a
    cos = np.abs(u @ di.T) / Li
    A = np.vstack([n, u])
    Aa = np.concatenate([np.einsum("mk,mk->m", n, a), np.einsum("mk,mk->m", u, a)])[:, None]
    Pp, Pq = A @ p.T - Aa, A @ q.T - Aa
    m = len(a)
    dp, dq = np.abs(Pp[:m]), np.abs(Pq[:m])
    tp, tq = Pp[m:], Pq[m:]
    overlap = np.minimum(np.maximum(tp, tq), Lm[:, None]) - np.maximum(np.minimum(tp, tq), 0.0)
    ok = (cos > np.cos(angle_rad)) & (dp < tol_px) & (dq < tol_px) & (overlap >= 0.5 * Li[None, :])
    cost = np.where(ok, dp + dq, np.inf)
    best = np.argmin(cost, axis=0)
    has = ok.any(axis=0)  # the best cost is finite
    return best[has], np.flatnonzero(has)


@dataclass(frozen=True)
class Verification:
    """How well a pose is supported by the image (fractions of visible projected edge length)."""

    length_fraction: float
    gradient_fraction: float
    silhouette_fraction: float
    matched: list[int]
    covered_px: float
    extra_fraction: float = 1.0  # gradient agreement outside the part it was grown around
    edges_px: np.ndarray | None = field(default=None, compare=False, repr=False)
    """The visible projected edges it weighed (e, 4), when it was made in full."""

    @property
    def score(self) -> float:
        """The reported score: mean of matched-length and gradient-agreement fractions."""
        return 0.5 * (self.length_fraction + self.gradient_fraction)


def fit_and_verify(
    model: VisionModel,
    X,
    segs,
    K,
    gx,
    gy,
    occluders_C,
    params: RecognizerParams,
    prior=None,
    grown: bool = False,
):
    """Predict further correspondences from the pose ``X`` (``X_CO``), refit and verify:
    ``(X_CO, rms_px, Verification, matched model edges)``, or None if the pose does not hold.

    ``prior``: the fit's soft prior (see :func:`~work_site.vision.pose.fit_pose`), or None.
    ``grown``: ``X`` is a bigger model placed around a part already fitted, so it is
    nearly right already and verification before refitting tells most phantoms apart."""
    p = params
    # Visible edges are recomputed only when the pose has moved (the quick support and
    # the first round see the same pose, and so do rounds whose refit was skipped).
    seen_at, vis = X, visible_edges(model, X, K, occluders_C)
    first = None
    if not grown:
        # The first round's matching before the quick support: of the hypotheses that
        # fail, most fail it, and it costs less (the same outcome either way).
        first = match_segments(vis[1], segs, p.match_tol_px[0], p.match_angle_rad)
        if len(np.unique(first[0])) < 4:
            return None
    q_min = p.grown_quick_support_min if grown else p.quick_support_min
    if quick_support(model, X, K, gx, gy, occluders_C, p, vis[1]) < q_min:
        return None
    if grown:
        need = (p.grown_pre_length_min, p.grown_pre_score_min, p.grown_pre_gradient_min)
        v0 = verify(model, X, K, segs, gx, gy, occluders_C, p, vis[1], need, outline=False)
        if v0.length_fraction < need[0] or v0.score < need[1] or v0.gradient_fraction < need[2]:
            return None
    mi = mj = np.zeros(0, int)
    fit = earlier = None
    earlier_proj = None  # the visible edges at the earlier fit's pose, once known
    pairs = None
    for r in range(p.refine_rounds):
        tol = p.match_tol_px[min(r, len(p.match_tol_px) - 1)]
        if seen_at is not X:
            seen_at, vis = X, visible_edges(model, X, K, occluders_C)
        ids, proj, _ = vis
        if r == 0 and first is not None:
            mi, mj = first
        else:
            mi, mj = match_segments(proj, segs, tol, p.match_angle_rad)
        if len(np.unique(mi)) < 4:
            return None
        now = (ids[mi].tobytes(), mj.tobytes())
        if now == pairs:
            continue  # the same correspondences as the last fit: it would not move
        pairs = now
        if fit is not None:
            earlier = fit
            earlier_proj = proj if seen_at is fit.X_CO else None
        fit = fit_pose(
            X, model.edges_O[ids[mi]], segs[mj], K, iterations=p.fit_iterations,
            tol=p.fit_tol, prior=prior,
        )  # fmt: skip
        X = fit.X_CO
    if fit is None:
        return None
    n_edges = len(np.unique(mi))
    if fit.rms_px > p.final_rms_max_px or n_edges < p.min_matched_edges_few:
        return None
    # Fewer edges than min_matched_edges pass only if the image supports them strongly.
    few = n_edges < p.min_matched_edges
    need = (
        min(p.min_length_fraction, p.candidate_min_length_fraction),
        min(p.few_edges_min_score if few else p.min_score, p.candidate_min_score),
        0.0,
    )
    proj = vis[1] if seen_at is X else None
    v = verify(model, X, K, segs, gx, gy, occluders_C, p, proj, need)
    if (
        p.keep_better_earlier_fit
        and earlier is not None
        and (v.length_fraction < p.min_length_fraction or v.score < p.min_score)
    ):
        # The last refit, to lines matched within the tightest tolerance, can pull a pose
        # off when a neighbour's lines come that close: the one before may verify better.
        v1 = verify(model, earlier.X_CO, K, segs, gx, gy, occluders_C, p, earlier_proj, need)
        if v1.score > v.score and earlier.rms_px <= p.final_rms_max_px:
            X, fit, v = earlier.X_CO, earlier, v1
    if v.length_fraction < need[0] or v.score < need[1]:
        return None
    return X, fit.rms_px, v, n_edges


def quick_support(
    model: VisionModel, X_CO, K, gx, gy, occluders_C, params: RecognizerParams, proj=None
) -> float:
    """Cheap test of a pose before any refinement: the fraction of points along its
    predicted visible edges where the image gradient, within ±1.5 px across the edge, is
    strong and at right angles to it. ``proj``: the visible edges if already known."""
    p = params
    if proj is None:
        _, proj, _ = visible_edges(model, X_CO, K, occluders_C)
    h, w = gx.shape
    proj = _clip_segments(proj, w, h)
    d = proj[:, 2:] - proj[:, :2]
    L = np.linalg.norm(d, axis=1)
    keep = L >= 4.0
    if not keep.any():
        return 0.0
    proj, d, L = proj[keep], d[keep], L[keep]
    u = d / L[:, None]
    nx, ny = -u[:, 1:], u[:, :1]  # (e, 1) each
    k = 6  # points per edge
    t = (np.arange(k) + 0.5) / k
    off = np.array(SUPPORT_OFFSETS_PX)[:, None, None]
    # Points at 6 fractions along each edge, at 3 offsets across it: (3, e, k)
    X = (proj[:, :1] + t * d[:, :1])[None] + off * nx[None]
    Y = (proj[:, 1:2] + t * d[:, 1:])[None] + off * ny[None]
    sx, sy = sample_gradient_xy(gx, gy, X, Y)
    mag = np.hypot(sx, sy)
    cos = np.abs(sx * nx + sy * ny) / np.maximum(mag, 1e-9)
    best = np.any((mag > p.gradient_min) & (cos > np.cos(p.gradient_angle_rad)), axis=0)
    return np.count_nonzero(best) / best.size  # as best.mean()


def verify(
    model: VisionModel,
    X_CO,
    K,
    segs,
    gx,
    gy,
    occluders_C,
    params: RecognizerParams,
    proj=None,
    need=None,
    part_px=None,
    outline: bool = True,
) -> Verification:
    """Fractions of the visible projected edge length matched by image lines and with the
    image gradient across them, plus the image segments matched. ``proj``: the visible
    edges if already known. ``need``: minima ``(length, score, gradient)`` fractions; a
    pose below one of them is returned as soon as that is known, without the rest
    (fractions not computed are 0). ``part_px``: the outline of the smaller object this
    pose was grown around, for :attr:`Verification.extra_fraction`. ``outline``: False
    when the silhouette and extra fractions are not wanted (returned as 0 and 1)."""
    p = params
    if proj is None:
        _, proj, _ = visible_edges(model, X_CO, K, occluders_C)
    edges_px = proj
    h, w = gx.shape
    # Clip to the image: an edge beyond the border is unseen, not missing.
    proj = _clip_segments(proj, w, h)
    L = np.linalg.norm(proj[:, 2:] - proj[:, :2], axis=1)
    keep = L >= 4.0
    proj, L = proj[keep], L[keep]
    if len(proj) == 0 or L.sum() < 20:
        return Verification(0.0, 0.0, 0.0, [], 0.0)
    a = proj[:, :2]
    u = (proj[:, 2:] - a) / L[:, None]
    # Gradient direction agreement sampled every 1.5 px along every visible edge.
    counts = np.maximum(np.ceil((L - 2.0) / 1.5), 0).astype(int)  # len(arange(1, L−1, 1.5))
    e = np.repeat(np.arange(len(proj)), counts)
    ts = 1.0 + 1.5 * (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))
    P = (a[e] + ts[:, None] * u[e]).astype(np.float32)
    N = np.column_stack([-u[e, 1], u[e, 0]])
    sx, sy = sample_gradient(gx, gy, P)
    mag = np.hypot(sx, sy)
    cosang = np.abs(sx * N[:, 0] + sy * N[:, 1]) / np.maximum(mag, 1e-9)
    good = (mag > p.gradient_min) & (cosang > np.cos(p.gradient_angle_rad))
    frac_grad = np.count_nonzero(good) / len(good) if len(good) else 0.0  # as np.mean
    if need is not None and frac_grad < need[2]:
        return Verification(0.0, frac_grad, 0.0, [], 0.0)
    mi, mj = match_segments(proj, segs, p.verify_tol_px, p.verify_angle_rad)
    covered = 0.0
    if len(mi):
        # Each matched image segment as an interval along its edge; the union per edge.
        ta = np.sum((segs[mj, :2] - a[mi]) * u[mi], axis=1)
        tb = np.sum((segs[mj, 2:] - a[mi]) * u[mi], axis=1)
        lo = np.clip(np.minimum(ta, tb), 0.0, L[mi])
        hi = np.clip(np.maximum(ta, tb), 0.0, L[mi])
        covered = _covered_length(mi, lo, hi, L)
    frac_len = float(covered / L.sum())
    if not outline or (
        need is not None and (frac_len < need[0] or 0.5 * (frac_len + frac_grad) < need[1])
    ):
        return Verification(frac_len, frac_grad, 0.0, mj.tolist(), float(covered))
    # The outline against the background must show in the image almost everywhere: a
    # hypothesis that explains one block and hangs over empty table fails here.
    uv = project(transform(X_CO, model.vertices_O), K).astype(np.float32)
    hull = cv2.convexHull(uv).reshape(-1, 2).astype(np.float64)
    on_hull = _distance_to_polygon(P.astype(np.float64), hull) < 1.0
    n_hull = np.count_nonzero(on_hull)
    frac_sil = np.count_nonzero(good[on_hull]) / n_hull if n_hull else 0.0
    frac_extra = 1.0
    if part_px is not None:
        # What the bigger model adds to the part it was grown around must show too, where
        # it can be seen at all.
        extra = _outside_convex(P.astype(np.float64), part_px, PART_MARGIN_PX)
        frac_extra = float(np.mean(good[extra])) if extra.any() else 1.0
    return Verification(
        frac_len, frac_grad, frac_sil, mj.tolist(), float(covered), frac_extra, edges_px
    )


@dataclass(frozen=True, eq=False)
class Surroundings:
    """Where an object may be: resting on the table top (height ``table_z``, m) inside the work
    area (``work_area_xy``: lowest and highest x, y in W), not interpenetrating the fixed
    environment's parts ``fixed_parts_W``: (vertices (n, 3), face normals (k, 3)) in W."""

    table_z: float
    work_area_xy: tuple[np.ndarray, np.ndarray]
    fixed_parts_W: list[tuple[np.ndarray, np.ndarray]]
    # The fixed parts' bounding spheres, once for every test
    fixed_centres: list[np.ndarray] = field(init=False, repr=False)
    fixed_radii: list[float] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "fixed_centres", [b.mean(0) for b, _ in self.fixed_parts_W])
        object.__setattr__(self, "fixed_radii", [_radius(b) for b, _ in self.fixed_parts_W])

    def plausible(
        self,
        parts_W: list[tuple],
        accepted: list[list[tuple]],
        params: RecognizerParams,
        environment: bool = True,
        max_height_m: float = 0.0,
    ) -> bool:
        """Rests on the table (its lowest point within ``table_tol_m`` of the top, or up to
        ``max_height_m`` above it: on something else) inside the work area; interpenetrates
        nothing accepted (nor the fixed environment, if ``environment``). Parts are (vertices
        (n, 3), face normals (k, 3)) in W."""
        p = params
        V = np.vstack([v for v, _ in parts_W])
        height = V[:, 2].min() - self.table_z
        if not -p.table_tol_m <= height <= max_height_m + p.table_tol_m:
            return False
        c = V[:, :2].mean(0)
        lo, hi = self.work_area_xy
        if np.any(c < lo) or np.any(c > hi):
            return False
        others = [q for parts in accepted for q in parts]
        # Bounding spheres first: only parts whose spheres meet can interpenetrate.
        centres = [b.mean(0) for b, _ in others]
        radii = [_radius(b) for b, _ in others]
        if environment:
            others += self.fixed_parts_W
            centres += self.fixed_centres
            radii += self.fixed_radii
        if not others:
            return True
        centres, radii = np.array(centres), np.array(radii)
        for a, na in parts_W:
            ca = a.mean(0)
            near = np.sqrt(np.sum((centres - ca) ** 2, axis=1)) <= _radius(a) + radii
            for k in np.flatnonzero(near):
                b, nb = others[k]
                if overlap_exceeds(a, b, na, nb, p.max_penetration_m):
                    return False
        return True

    def supported_by(
        self, parts_W: list[tuple], others: list[list[tuple]], params: RecognizerParams
    ) -> bool:
        """Held up: its lowest point within ``table_tol_m`` of the table top, or something of
        ``others`` (objects) or of the fixed parts under it: moved down by ``table_tol_m`` it
        would dig into that by at least half the move (a block on a block, across an edge of
        one, on the frame; a block only beside another digs in no deeper)."""
        tol = params.table_tol_m
        V = np.vstack([v for v, _ in parts_W])
        if V[:, 2].min() - self.table_z <= tol:
            return True
        down = np.array([0.0, 0.0, tol])
        for b, nb in [q for parts in others for q in parts] + self.fixed_parts_W:
            for a, na in parts_W:
                if np.linalg.norm(a.mean(0) - b.mean(0)) > _radius(a) + _radius(b) + tol:
                    continue
                before = convex_overlap_depth(a, b, na, nb)
                if convex_overlap_depth(a - down, b, na, nb) >= before + tol / 2:
                    return True
        return False


def _radius(V: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(V - V.mean(0), axis=1)))


def _covered_length(edge: np.ndarray, lo: np.ndarray, hi: np.ndarray, L: np.ndarray) -> float:
    """Total length of the union, per edge, of intervals ``[lo, hi]`` (m,) on edges ``edge``
    (m,) of lengths ``L`` (e,), with ``0 ≤ lo ≤ hi ≤ L[edge]``. The edges are laid end to end
    with gaps, so one sort and one running maximum do all of them."""
    start = np.cumsum(L + 1.0) - (L + 1.0)
    lo, hi = lo + start[edge], hi + start[edge]
    order = np.argsort(lo, kind="stable")
    lo, hi = lo[order], hi[order]
    reach = np.maximum.accumulate(hi)  # the furthest any earlier interval reaches
    before = np.concatenate([[-np.inf], reach[:-1]])
    return float(np.sum(np.maximum(hi - np.maximum(lo, before), 0.0)))


def _outside_convex(P: np.ndarray, poly: np.ndarray, margin: float) -> np.ndarray:
    """(n,) bool: points (n, 2) farther than ``margin`` outside the line of some edge of the
    convex polygon (k, 2), either orientation."""
    A = poly
    D = np.roll(poly, -1, axis=0) - A
    area2 = float(np.sum(A[:, 0] * D[:, 1] - A[:, 1] * D[:, 0]))
    # Outward normals: (d_y, −d_x) for counter-clockwise polygons in x-right, y-up terms.
    n = np.column_stack([D[:, 1], -D[:, 0]]) * np.sign(area2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.any(np.einsum("nkj,kj->nk", P[:, None, :] - A[None], n) > margin, axis=1)


def _distance_to_polygon(P: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (px) of points (n, 2) to the boundary of the closed polygon (k, 2)."""
    A = poly
    B = np.roll(poly, -1, axis=0)
    D = B - A
    den = np.maximum(np.sum(D * D, axis=1), 1e-18)
    W = P[:, None, :] - A[None]  # (n, k, 2)
    t = np.clip(np.einsum("nkj,kj->nk", W, D) / den, 0.0, 1.0)
    R = W - t[..., None] * D[None]
    return np.sqrt(np.min(np.einsum("nkj,nkj->nk", R, R), axis=1))


def _clip_segments(segs: np.ndarray, w: int, h: int) -> np.ndarray:
    """Segments (n, 4) clipped to the image rectangle (Liang–Barsky, all at once); fully
    outside → zero length at the first end point."""
    x, y = segs[:, 0::2], segs[:, 1::2]
    if len(segs) == 0 or (x.min() >= 0 and y.min() >= 0 and x.max() <= w - 1 and y.max() <= h - 1):
        return segs  # the usual case: nothing reaches beyond the image
    x0, y0, x1, y1 = segs.T
    dx, dy = x1 - x0, y1 - y0
    # The four boundaries at once: inside where q − t·p ≥ 0 for each row (p, q).
    pp = np.stack([-dx, dx, -dy, dy])
    qq = np.stack([x0, w - 1 - x0, y0, h - 1 - y0])
    par = pp == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        r = qq / np.where(par, 1.0, pp)
    t0 = np.maximum(np.max(np.where(pp < 0, r, 0.0), axis=0), 0.0)
    t1 = np.minimum(np.min(np.where(pp > 0, r, 1.0), axis=0), 1.0)
    gone = np.any(par & (qq < 0), axis=0) | (t0 >= t1)
    t0 = np.where(gone, 0.0, t0)
    t1 = np.where(gone, 0.0, t1)
    return np.column_stack([x0 + t0 * dx, y0 + t0 * dy, x0 + t1 * dx, y0 + t1 * dy])
