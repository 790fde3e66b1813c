"""Straight image edges with sub-pixel least-squares fits (§IV-B: "Image lines are determined
through a least-squares fit to each pixel along an edge").

OpenCV 5 headless has a line segment detector (``cv2.createLineSegmentDetector``, LSD) but no
``ximgproc``; LSD finds and roughly places the segments, and what it lacks we add here:

- a refit of each segment to the sub-pixel maxima of the image gradient across it (total least
  squares, weighted by edge strength), which is what the paper's line fit does;
- merging of collinear fragments that LSD splits at noise or junctions;
- splitting of a segment LSD grew across a shallow corner (two edges a few degrees apart, as
  a block's side seen nearly edge-on makes): one line fitted to both misplaces each.

Segments are (n, 4) float64 rows ``(x0, y0, x1, y1)`` in pixels, pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class LineParams:
    """Tuning of the line extraction (pixels unless named otherwise)."""

    min_length_px: float = 6.0
    refine: bool = True
    profile_half_px: float = 2.0
    profile_step_px: float = 0.25
    sample_step_px: float = 1.0
    end_margin_px: float = 1.5
    merge_angle_rad: float = np.deg2rad(1.5)
    merge_offset_px: float = 0.75
    merge_gap_px: float = 4.0
    lsd_scale: float = 1.0
    lsd_quant: float = 2.0
    lsd_smooth_px: float = 0.0
    """Standard deviation (px) of a Gaussian the image is smoothed with before LSD (0: none;
    LSD's own smoothing is off at ``lsd_scale`` 1)."""
    kink_px: float = 0.35
    """A refined segment whose sub-pixel edge points stray further than this from its line is
    split in two where two lines fit them best, if those fit at least twice as closely and
    bend by more than noise explains (a corner LSD grew across; 0: never split)."""


FAINT_LINE_PARAMS = LineParams(lsd_quant=1.0, lsd_smooth_px=0.75)
"""A second, more sensitive pass (smoothed, finer gradient quantisation) for the faint edges
LSD's default pass misses under dim or flat light: a block's own face-to-face edges, a block
against one of the same shade."""


_LSD: dict[tuple[float, float], cv2.LineSegmentDetector] = {}


def _lsd(scale: float, quant: float) -> cv2.LineSegmentDetector:
    if (scale, quant) not in _LSD:
        _LSD[scale, quant] = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, scale, 0.6, quant)
    return _LSD[scale, quant]


def check_grey_image(image: np.ndarray) -> np.ndarray:
    """The image as a 2-D uint8 array; ValueError with the reason if it cannot be one."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {a.shape}")
    if a.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit image, got dtype {a.dtype}")
    return a


def detect_lines(
    image: np.ndarray,
    params: LineParams | None = None,
    gradients: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Straight edge segments of a grey uint8 image, (n, 4) float64 px, longest first.
    ``gradients``: the image's Scharr derivatives ``(gx, gy)`` (float32) if already known."""
    params = params or LineParams()
    img = check_grey_image(image)
    if min(img.shape) < 4:
        return np.zeros((0, 4))
    if params.lsd_smooth_px > 0.0:
        img = cv2.GaussianBlur(img, (0, 0), params.lsd_smooth_px)
    found = _lsd(params.lsd_scale, params.lsd_quant).detect(img)[0]
    if found is None:
        return np.zeros((0, 4))
    segs = np.asarray(found, dtype=np.float64).reshape(-1, 4)
    segs = segs[_lengths(segs) >= 0.5 * params.min_length_px]
    if len(segs) == 0:
        return segs
    segs = merge_collinear(segs, params)
    if params.refine:
        gx, gy = gradients if gradients is not None else image_gradients(img)
        segs = refine_segments(segs, gx, gy, params)
    segs = segs[_lengths(segs) >= params.min_length_px]
    return segs[np.argsort(-_lengths(segs))]


def _lengths(segs: np.ndarray) -> np.ndarray:
    return np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])


def image_gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Scharr derivatives ``(gx, gy)`` (float32) of a grey image."""
    f = img.astype(np.float32)
    # Scharr is the most rotation-invariant 3×3 derivative; the edge peak is then symmetric.
    return cv2.Scharr(f, cv2.CV_32F, 1, 0), cv2.Scharr(f, cv2.CV_32F, 0, 1)


def refine_segments(
    segs: np.ndarray, gx: np.ndarray, gy: np.ndarray, params: LineParams
) -> np.ndarray:
    """Refit every segment to the sub-pixel gradient maxima across it (weighted total least
    squares); end points are kept where they project onto the new line. Vectorised over all
    segments: one ``remap`` per derivative image."""
    if len(segs) == 0:
        return segs
    offsets = np.arange(
        -params.profile_half_px, params.profile_half_px + 1e-9, params.profile_step_px
    )
    a0, b0 = segs[:, :2], segs[:, 2:]
    d = b0 - a0
    length = np.linalg.norm(d, axis=1)
    ok_seg = length >= 2 * params.end_margin_px + 2
    u = d / np.maximum(length, 1e-9)[:, None]
    n = np.column_stack([-u[:, 1], u[:, 0]])
    counts = np.where(
        ok_seg,
        np.floor((length - 2 * params.end_margin_px) / params.sample_step_px).astype(int) + 1,
        0,
    )
    if counts.sum() == 0:
        return segs.copy()
    sid = np.repeat(np.arange(len(segs)), counts)
    first = np.cumsum(counts) - counts
    ts = params.end_margin_px + (np.arange(counts.sum()) - first[sid]) * params.sample_step_px
    base = a0[sid] + ts[:, None] * u[sid]  # (m, 2)
    ns = n[sid]
    # The profiles' points (m, k), each coordinate straight into its map
    mx = (base[:, :1] + offsets * ns[:, :1]).astype(np.float32)
    my = (base[:, 1:] + offsets * ns[:, 1:]).astype(np.float32)
    sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    prof = np.abs(sx * ns[:, :1] + sy * ns[:, 1:]).astype(np.float64)  # (m, k)
    j = np.argmax(prof, axis=1)
    rows = np.arange(len(prof))
    inner = (j > 0) & (j < len(offsets) - 1)
    jj = np.clip(j, 1, len(offsets) - 2)
    jm, jc, jp = prof[rows, jj - 1], prof[rows, j], prof[rows, jj + 1]
    denom = jm - 2 * jc + jp
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(denom < 0, 0.5 * (jm - jp) / denom, 0.0)
    off = offsets[j] + np.clip(delta, -0.5, 0.5) * params.profile_step_px
    P = base + off[:, None] * ns
    w = jc
    # Drop samples whose peak is weak (another edge, a junction, or the line's end).
    # Per segment, its samples' median (np.median's: the mean of the middle two of an even
    # count): sort by strength within each segment's run, then pick the middle.
    ws = w[np.lexsort((w, sid))]
    med = np.zeros(len(segs))
    has = np.flatnonzero(counts)
    mid_lo = first[has] + (counts[has] - 1) // 2
    mid_hi = first[has] + counts[has] // 2
    med[has] = (ws[mid_lo] + ws[mid_hi]) / 2
    keep = inner & (w > 0.5 * med[sid])
    wk = np.where(keep, w, 0.0)
    n_seg = len(segs)
    W = np.bincount(sid, wk, n_seg)
    good = ok_seg & (np.bincount(sid, keep.astype(float), n_seg) >= 3) & (W > 0)
    Wd = np.maximum(W, 1e-12)
    cx = np.bincount(sid, wk * P[:, 0], n_seg) / Wd
    cy = np.bincount(sid, wk * P[:, 1], n_seg) / Wd
    dx, dy = P[:, 0] - cx[sid], P[:, 1] - cy[sid]
    sxx = np.bincount(sid, wk * dx * dx, n_seg)
    syy = np.bincount(sid, wk * dy * dy, n_seg)
    sxy = np.bincount(sid, wk * dx * dy, n_seg)
    # Principal axis of the weighted scatter: the fitted line's direction.
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    v = np.column_stack([np.cos(theta), np.sin(theta)])
    c = np.column_stack([cx, cy])
    ta = np.sum((a0 - c) * v, axis=1)
    tb = np.sum((b0 - c) * v, axis=1)
    out = segs.copy()
    new = np.column_stack([c + ta[:, None] * v, c + tb[:, None] * v])
    out[good] = new[good]
    if params.kink_px <= 0.0:
        return out
    normal = np.column_stack([-v[:, 1], v[:, 0]])
    res = np.einsum("mk,mk->m", P - c[sid], normal[sid])
    stray = np.bincount(sid[keep], np.abs(res[keep]) > params.kink_px, n_seg) > 0
    tested = np.flatnonzero(stray & good)
    if len(tested) == 0:
        return out
    # Each tested segment's kept edge points, in order along it, one run after another.
    member = np.zeros(n_seg, bool)
    member[tested] = True
    take = keep & member[sid]
    first_piece, second_piece, split = _split_at_corners(P[take], sid[take], out)
    out[split] = first_piece
    return np.vstack([out, second_piece])


KINK_MIN_SAMPLES = 8
"""Edge points on each side of a split, at least: a shorter piece is no line."""
KINK_SIGNIFICANCE = 3.0
"""A corner's bend must exceed this many standard errors of the two pieces' directions."""


def _split_at_corners(
    points: np.ndarray, owner: np.ndarray, segs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments of ``segs`` (n, 4) split in two where they turn a corner, all at once.

    ``points`` (m, 2) are edge points, ``owner`` (m,) the segment of each, each segment's in a
    run, in order along it. A segment is split where two total least squares lines fit its
    points best (least summed squared distances), if they fit at least twice as closely as
    one line (the farthest point from them), each piece has :data:`KINK_MIN_SAMPLES` points,
    and the two bend by more than :data:`KINK_SIGNIFICANCE` standard errors of their
    directions. Returns the first pieces (s, 4), the second pieces (s, 4), and the indices
    (s,) of the segments split."""
    none = np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0, int)
    segments, start, count = np.unique(owner, return_index=True, return_counts=True)
    enough = count >= 2 * KINK_MIN_SAMPLES
    if not enough.any():
        return none
    if not enough.all():  # the others drop out: fewer points than two lines need
        kept = np.repeat(enough, count)
        points, owner = points[kept], owner[kept]
        segments, start, count = segments[enough], start[enough], count[enough]
        start = np.cumsum(count) - count
    g = np.repeat(np.arange(len(segments)), count)  # each point's run
    j = np.arange(len(points)) - start[g]  # its place in its run
    # Scatter of every prefix of each run from running sums (about the run's mean, for
    # conditioning): every split's two fits at once.
    mean = np.add.reduceat(points, start) / count[:, None]
    x, y = (points - mean[g]).T
    running = np.cumsum(np.column_stack([np.ones_like(x), x, y, x * x, y * y, x * y]), axis=0)
    before = np.vstack([np.zeros((1, 6)), running])[start]  # sums of the earlier runs
    head = running - before[g]  # sums of points j' <= j of the run
    total = head[start + count - 1]
    tail = total[g] - head
    splittable = (j >= KINK_MIN_SAMPLES - 1) & (j <= count[g] - KINK_MIN_SAMPLES - 1)
    sse = np.where(splittable, _tls_sse(head) + _tls_sse(tail), np.inf)
    # The least per run, the first of equals: sort by run, then sse, then place.
    order = np.lexsort((j, sse, g))
    best = order[start]  # the last point of each run's first piece
    k = j[best] + 1  # points in the first piece
    c1, d1 = _tls_from_sums(head[best])
    c2, d2 = _tls_from_sums(tail[best])
    c0, d0 = _tls_from_sums(total)
    in_second = j >= k[g]
    c_piece = np.where(in_second[:, None], c2[g], c1[g])
    d_piece = np.where(in_second[:, None], d2[g], d1[g])
    q = np.column_stack([x, y])
    r = _cross(d_piece, q - c_piece)
    r0 = _cross(d0[g], q - c0[g])
    along = np.einsum("mi,mi->m", q - c_piece, d_piece)
    far, far0 = (np.maximum.reduceat(np.abs(d), start) for d in (r, r0))
    piece = 2 * g + in_second  # each piece's statistics: (run, first or second)
    n_piece = np.bincount(piece, minlength=2 * len(segments)).reshape(-1, 2)
    across2 = np.bincount(piece, r * r, 2 * len(segments)).reshape(-1, 2)
    along2 = np.bincount(piece, along * along, 2 * len(segments)).reshape(-1, 2)
    # Each direction's standard error: its points' spread across over their spread along.
    se = np.sqrt(across2 / n_piece / np.maximum(along2, 1e-12))
    bend = np.arccos(np.minimum(np.abs(np.einsum("si,si->s", d1, d2)), 1.0))
    split = (far <= 0.5 * far0) & (bend >= KINK_SIGNIFICANCE * np.hypot(se[:, 0], se[:, 1]))
    if not split.any():
        return none
    s = np.flatnonzero(split)
    corner = 0.5 * (q[best[s]] + q[best[s] + 1])
    shift = np.tile(mean[s], 2)  # back from about each run's mean
    seg = segs[segments[s]] - shift
    c1, d1, c2, d2 = c1[s], d1[s], c2[s], d2[s]
    first = np.hstack([_on_line(c1, d1, seg[:, :2]), _on_line(c1, d1, corner)])
    second = np.hstack([_on_line(c2, d2, corner), _on_line(c2, d2, seg[:, 2:])])
    return first + shift, second + shift, segments[s]


def _scatter(m: np.ndarray) -> tuple[np.ndarray, ...]:
    """Count (at least 1), Σx, Σy and the centred second moments vxx, vyy, vxy of point sets
    given by their sums (k, 6): count, Σx, Σy, Σx², Σy², Σxy."""
    cnt, sx, sy, sxx, syy, sxy = m.T
    cnt = np.maximum(cnt, 1.0)
    return cnt, sx, sy, sxx - sx * sx / cnt, syy - sy * sy / cnt, sxy - sx * sy / cnt


def _tls_sse(m: np.ndarray) -> np.ndarray:
    """Squared residual of the total least squares line of point sets given by their sums
    (k, 6) as in :func:`_scatter` (no points: 0)."""
    _, _, _, vxx, vyy, vxy = _scatter(m)
    return 0.5 * (vxx + vyy) - np.sqrt(0.25 * (vxx - vyy) ** 2 + vxy * vxy)


def _tls_from_sums(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least squares lines of point sets given by their sums (k, 6) as in
    :func:`_scatter`: a point on each (k, 2) and its unit direction (k, 2)."""
    cnt, sx, sy, vxx, vyy, vxy = _scatter(m)
    theta = 0.5 * np.arctan2(2 * vxy, vxx - vyy)
    return np.column_stack([sx / cnt, sy / cnt]), np.column_stack([np.cos(theta), np.sin(theta)])


def _cross(d: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distances of points ``p`` (m, 2) from lines through the origin along unit
    ``d`` (m, 2)."""
    return d[:, 0] * p[:, 1] - d[:, 1] * p[:, 0]


def _on_line(centre: np.ndarray, direction: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The feet of points ``p`` (k, 2) on the lines through ``centre`` (k, 2) along unit
    ``direction`` (k, 2)."""
    t = np.einsum("ki,ki->k", p - centre, direction)
    return centre + t[:, None] * direction


def _mergeable(segs: np.ndarray, params: LineParams) -> np.ndarray:
    """(n, n) bool: segment ``j`` may be joined to segment ``i`` (tested in ``i``'s frame:
    parallel, on its line, and with a small gap), the test :func:`merge_collinear` makes."""
    a = segs[:, :2]
    d = segs[:, 2:] - a
    L = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = d / L[:, None]
    n = np.column_stack([-u[:, 1], u[:, 0]])
    lo = np.maximum(L, 1e-9)
    cosang = np.abs(u @ d.T) / lo[None, :]
    P0 = segs[None, :, :2] - a[:, None, :]  # (i, j, 2)
    P1 = segs[None, :, 2:] - a[:, None, :]
    off = np.maximum(np.abs(np.einsum("ijk,ik->ij", P0, n)), np.abs(np.einsum("ijk,ik->ij", P1, n)))
    t0 = np.einsum("ijk,ik->ij", P0, u)
    t1 = np.einsum("ijk,ik->ij", P1, u)
    gap = np.maximum(np.minimum(t0, t1) - L[:, None], -np.maximum(t0, t1))
    with np.errstate(invalid="ignore"):
        ok = (
            (cosang > np.cos(params.merge_angle_rad))
            & (off < params.merge_offset_px)
            & (gap < params.merge_gap_px)
        )
    np.fill_diagonal(ok, False)
    return ok


def _mergeable_into(segs: np.ndarray, j: int, params: LineParams) -> np.ndarray:
    """Column ``j`` of :func:`_mergeable` alone: may segment ``j`` be joined to each segment
    (tested in that segment's frame, with the arithmetic of :func:`merge_collinear`'s own
    test)? (n,) bool, False at ``j``."""
    a = segs[:, :2]
    d = segs[:, 2:] - a
    L = np.hypot(d[:, 0], d[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ux, uy = d[:, 0] / L, d[:, 1] / L
    nx, ny = -uy, ux
    dj = segs[j, 2:] - segs[j, :2]
    lo = max(float(np.hypot(dj[0], dj[1])), 1e-9)
    cosang = np.abs(dj[0] * ux + dj[1] * uy) / lo
    p0x, p0y = segs[j, 0] - a[:, 0], segs[j, 1] - a[:, 1]
    p1x, p1y = segs[j, 2] - a[:, 0], segs[j, 3] - a[:, 1]
    off = np.maximum(np.abs(p0x * nx + p0y * ny), np.abs(p1x * nx + p1y * ny))
    t0, t1 = p0x * ux + p0y * uy, p1x * ux + p1y * uy
    gap = np.maximum(np.minimum(t0, t1) - L, -np.maximum(t0, t1))
    with np.errstate(invalid="ignore"):
        ok = (
            (cosang > np.cos(params.merge_angle_rad))
            & (off < params.merge_offset_px)
            & (gap < params.merge_gap_px)
        )
    ok[j] = False
    return ok


def merge_collinear(segs: np.ndarray, params: LineParams) -> np.ndarray:
    """Join segments that lie on one line with a small gap between them (greedy, longest
    first); the joined segment spans both.

    Each pass first tests all pairs at once (:func:`_mergeable`), and again, for all
    segments at once, each segment that grows (:func:`_mergeable_into`); a segment is
    processed one by one only if it has a live partner there. Most segments have none, so
    passes are cheap."""
    if len(segs) < 2:
        return segs
    order = np.argsort(-_lengths(segs))
    segs = segs[order].copy()
    alive = np.ones(len(segs), dtype=bool)
    changed = True
    while changed:
        changed = False
        partner = _mergeable(segs, params)
        maybe = partner.any(axis=1).tolist()  # a partner, live or not: the cheap first test
        for i in range(len(segs)):
            if not maybe[i] or not alive[i] or not (partner[i] & alive).any():
                continue
            a, b = segs[i, :2], segs[i, 2:]
            L = np.linalg.norm(b - a)
            if L < 1e-9:
                continue
            u = (b - a) / L
            n = np.array([-u[1], u[0]])
            others = np.flatnonzero(alive)
            others = others[others != i]
            if len(others) == 0:
                break
            S = segs[others]
            du = S[:, 2:] - S[:, :2]
            lo = np.linalg.norm(du, axis=1)
            cosang = np.abs(du @ u) / np.maximum(lo, 1e-9)
            off0 = np.abs((S[:, :2] - a) @ n)
            off1 = np.abs((S[:, 2:] - a) @ n)
            t0 = (S[:, :2] - a) @ u
            t1 = (S[:, 2:] - a) @ u
            tmin, tmax = np.minimum(t0, t1), np.maximum(t0, t1)
            gap = np.maximum(tmin - L, -tmax)
            ok = (
                (cosang > np.cos(params.merge_angle_rad))
                & (np.maximum(off0, off1) < params.merge_offset_px)
                & (gap < params.merge_gap_px)
            )
            for j in others[ok]:
                t = [0.0, L, *((segs[j, :2] - a) @ u, (segs[j, 2:] - a) @ u)]
                lo_t, hi_t = min(t), max(t)
                segs[i] = np.concatenate([a + lo_t * u, a + hi_t * u])
                alive[j] = False
                changed = True
                a, b = segs[i, :2], segs[i, 2:]
                L = np.linalg.norm(b - a)
            if ok.any():
                # Segment i grew: segments after it may now join it where they did not before.
                partner[:, i] = _mergeable_into(segs, i, params)
                maybe = [m or q for m, q in zip(maybe, partner[:, i].tolist(), strict=True)]
    return segs[alive]
