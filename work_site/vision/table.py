"""Pose hypotheses from two image lines under the table prior (§IV-A, with the work site's
knowledge that blocks rest on the table).

A block resting on one of its faces has only three free pose parameters: its position on the
table and its yaw. A corner of the block where two horizontal edges meet (a corner of its top
face, or of its bottom face on the table) lies at a known height above the table, so the image
junction of the two edges' lines, cast back onto the plane at that height, gives the corner's 3D
position, and the two lines cast onto the same plane give the edges' directions. The angle
between them must equal the model's corner angle (a strong filter); the first edge's direction
then gives the yaw. So one junction of two lines yields a complete pose, with no indexing and no
iterative fit, and it needs no third and fourth line: this finds blocks whose faces are shaded
almost alike, where chains of four connected lines are rare.

Where only one of the two edges is horizontal (a top corner's vertical edge, a wedge's sloping
face meeting its ridge), the horizontal one alone gives the yaw, and the other edge's image
line must point where that pose projects it: the same one-junction pose, for the corners
whose second horizontal edge is faint or hidden.

All candidate poses are scored at once (vectorised over candidates, edges and sample points) by
the image gradient along their predicted edges, the cheap early rejection before the full test.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from models.transforms import invert_pose
from work_site.vision.model import VisionModel, hull_facets

HEIGHT_TOL_M = 1e-6
"""Corners whose heights above the table differ by less than this share a back-projection."""
SUPPORT_OFFSETS_PX = (-1.5, 0.0, 1.5)
"""Offsets across an edge at which :func:`batch_support` looks for the gradient."""


@dataclass(frozen=True)
class RestCorners:
    """Every corner of a horizontal edge and another edge of every model in every resting
    orientation.

    ``model`` (c,) index into the models; ``R_WO0`` (c, 3, 3) the resting rotation at yaw 0;
    ``lift_m`` (c,) height of O's origin above the table at rest; ``corner`` (c, 3) the corner
    in the rest frame (O rotated by ``R_WO0``, z measured from the table); ``heading`` (c,) the
    yaw (rad) of the first edge, horizontal, leaving the corner; ``second`` (c, 3) the unit
    direction of the second edge leaving it, in the rest frame; ``level`` (c,) whether the
    second edge is horizontal too; ``turn`` (c,) then the signed angle (rad, about +z) from
    the first edge to the second (NaN otherwise). Both orders of each pair of horizontal edges
    are listed.
    """

    model: np.ndarray
    R_WO0: np.ndarray
    lift_m: np.ndarray
    corner: np.ndarray
    heading: np.ndarray
    second: np.ndarray
    level: np.ndarray
    turn: np.ndarray


def rest_rotations(vertices_O: np.ndarray, com_O: np.ndarray, margin_m: float = 2e-3):
    """Rotations ``R_WO`` (yaw 0) that rest the object on a hull facet whose support polygon
    contains the centre of mass at least ``margin_m`` inside, facet normal pointing down."""
    out = []
    for n, d in hull_facets(vertices_O):
        on = vertices_O[np.abs(vertices_O @ n - d) < 1e-9]
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        poly = np.column_stack([on @ e1, on @ e2]).astype(np.float32)
        hull = cv2.convexHull(poly)
        c = (float(com_O @ e1), float(com_O @ e2))
        if cv2.pointPolygonTest(hull, c, True) < margin_m:
            continue
        z = -n
        out.append(np.array([e1, np.cross(z, e1), z]))
    return out


def rest_corners(models: Sequence[VisionModel], coms_O: Sequence[np.ndarray]) -> RestCorners:
    """The :class:`RestCorners` of ``models`` (with their centres of mass ``coms_O``)."""
    rows = []
    for mi, (m, com) in enumerate(zip(models, coms_O, strict=True)):
        for R0 in rest_rotations(m.vertices_O, np.asarray(com, dtype=np.float64)):
            lift = -float((m.vertices_O @ R0.T)[:, 2].min())
            E = m.edges_O @ R0.T + np.array([0.0, 0.0, lift])  # (e, 2, 3) rest frame
            horiz = np.abs(E[:, 0, 2] - E[:, 1, 2]) < 1e-9
            # Two horizontal edges first, then a horizontal and another.
            for level in (True, False):
                for i in np.flatnonzero(horiz):
                    for j in np.flatnonzero(horiz == level):
                        if i == j:
                            continue
                        for ei in (0, 1):
                            v = E[i, ei]
                            d = np.linalg.norm(E[j] - v, axis=1)
                            if d.min() > 1e-9:
                                continue
                            a = E[i, 1 - ei] - v
                            b = E[j, 1 - int(np.argmin(d))] - v
                            b = b / np.linalg.norm(b)
                            heading = np.arctan2(a[1], a[0])
                            turn = _wrap(np.arctan2(b[1], b[0]) - heading) if level else np.nan
                            if level and abs(np.sin(turn)) < 0.1:
                                continue  # collinear edges make no corner
                            if not _known(rows, mi, m.symmetries, R0, v, heading, b):
                                rows.append((mi, R0, lift, v, heading, b, turn))
    if not rows:
        return RestCorners(
            np.zeros(0, int), np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 3)),
            np.zeros(0), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0),
        )  # fmt: skip
    turn = np.array([r[6] for r in rows])
    return RestCorners(
        model=np.array([r[0] for r in rows], dtype=np.int64),
        R_WO0=np.array([r[1] for r in rows]),
        lift_m=np.array([r[2] for r in rows]),
        corner=np.array([r[3] for r in rows]),
        heading=np.array([r[4] for r in rows]),
        second=np.array([r[5] for r in rows]),
        level=~np.isnan(turn),
        turn=turn,
    )


def _known(rows, mi, symmetries, R0, v, heading, second) -> bool:
    """Whether a listed corner of model ``mi`` gives the same poses as this one, up to the
    model's symmetries: from any junction both give ``R = Rz(ψ)·A`` and ``t = P − Rz(ψ)·w`` with
    ``A = Rz(−heading)·R0`` and ``w = Rz(−heading)·v``, so they agree when the ``w`` and the
    second edges (turned likewise) agree and the ``A`` differ by a symmetry."""
    A = _rz(-heading) @ R0
    w = _rz(-heading) @ v
    b = _rz(-heading) @ second
    for mj, R1, _, v1, h1, b1, _ in rows:
        if mj != mi or np.linalg.norm(_rz(-h1) @ b1 - b) > 1e-9:
            continue
        if np.linalg.norm(_rz(-h1) @ v1 - w) > 1e-9:
            continue
        A1 = _rz(-h1) @ R1
        if any(np.linalg.norm(A1 @ S - A) < 1e-6 for S in symmetries):
            return True
    return False


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def back_project_to_plane(
    uv: np.ndarray, K: np.ndarray, X_WC: np.ndarray, z_W: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 2) px cast onto the world plane ``z = z_W``: (n, 3) points and (n,) bool
    for rays that meet the plane in front of the camera."""
    rays_C = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T
    rays_W = rays_C @ X_WC[:3, :3].T
    c = X_WC[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (z_W - c[2]) / rays_W[:, 2]
    ok = np.isfinite(lam) & (lam > 0)
    lam = np.where(ok, lam, 0.0)
    return c + lam[:, None] * rays_W, ok


def table_hypotheses(
    corners: RestCorners,
    junctions: Sequence[tuple[int, int, int, int, np.ndarray]],
    segs: np.ndarray,
    K: np.ndarray,
    X_WC: np.ndarray,
    table_z: float,
    angle_tol_rad: float = np.deg2rad(8.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses from image junctions: ``(model (h,), X_WO (h, 4, 4), segs (h, 2))``, where
    ``segs`` are the two image segments of the junction each pose came from."""
    if len(junctions) == 0 or len(corners.model) == 0:
        return np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros((0, 2), int)
    a = np.array([j[0] for j in junctions])
    b = np.array([j[2] for j in junctions])
    X = np.array([j[4] for j in junctions])
    ends = segs.reshape(-1, 2, 2)
    # The far end of each segment from the junction: the edge leaves the corner that way.
    far_a = ends[a, 1 - np.array([j[1] for j in junctions])]
    far_b = ends[b, 1 - np.array([j[3] for j in junctions])]
    models, poses, pairs = [], [], []

    def add(c: np.ndarray, yaw: np.ndarray, P: np.ndarray, pair: np.ndarray) -> None:
        """The poses of corners ``c`` at image junctions cast to ``P`` (n, 3), turned by
        ``yaw`` (n,); ``pair`` (n, 2) the junctions' segments."""
        cs, sn = np.cos(yaw), np.sin(yaw)
        Rz = np.zeros((len(c), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = cs, -sn, sn, cs
        Rz[:, 2, 2] = 1.0
        X_WO = np.tile(np.eye(4), (len(c), 1, 1))
        X_WO[:, :3, :3] = Rz @ corners.R_WO0[c]
        rot_v = np.einsum("nij,nj->ni", Rz, corners.corner[c])
        X_WO[:, 0, 3] = P[:, 0] - rot_v[:, 0]
        X_WO[:, 1, 3] = P[:, 1] - rot_v[:, 1]
        X_WO[:, 2, 3] = table_z + corners.lift_m[c]
        models.append(corners.model[c])
        poses.append(X_WO)
        pairs.append(pair)

    X_CW = invert_pose(X_WC)
    R_CW, t_CW = X_CW[:3, :3], X_CW[:3, 3]
    cos_tol = np.cos(angle_tol_rad)
    heights = np.unique(np.round(corners.corner[:, 2] / HEIGHT_TOL_M).astype(np.int64))
    for hk in heights:
        h = hk * HEIGHT_TOL_M
        at_h = np.abs(corners.corner[:, 2] - h) < 2 * HEIGHT_TOL_M
        P, ok0 = back_project_to_plane(X, K, X_WC, table_z + h)
        Pa, ok1 = back_project_to_plane(far_a, K, X_WC, table_z + h)
        Pb, ok2 = back_project_to_plane(far_b, K, X_WC, table_z + h)
        ok = ok0 & ok1 & ok2
        da, db = Pa - P, Pb - P
        psi_a = np.arctan2(da[:, 1], da[:, 0])
        psi_b = np.arctan2(db[:, 1], db[:, 0])
        turn = _wrap(psi_b - psi_a)  # (n,)
        # (junction, corner) pairs whose angles agree
        sel = np.flatnonzero(at_h & corners.level)
        diff = np.abs(_wrap(turn[:, None] - corners.turn[sel][None, :]))
        ji, ck = np.nonzero((diff < angle_tol_rad) & ok[:, None])
        if len(ji):
            c = sel[ck]
            # Bisect the angle error: the yaw that best aligns both edges.
            yaw = psi_a[ji] - corners.heading[c] + 0.5 * _wrap(turn[ji] - corners.turn[c])
            add(c, yaw, P[ji], np.column_stack([a[ji], b[ji]]))
        # One horizontal edge: either line may be it; the other must lie along the second
        # edge's image at the pose the first gives.
        sel = np.flatnonzero(at_h & ~corners.level)
        if len(sel) == 0:
            continue
        # The second edge's image direction leaving the junction: d/ds of P + s·d projected,
        # d = Rz(ψ)·e, which is cos ψ·A + sin ψ·B + C in the camera's frame.
        e = corners.second[sel]
        A = np.column_stack([e[:, 0], e[:, 1], np.zeros(len(e))]) @ R_CW.T
        B = np.column_stack([-e[:, 1], e[:, 0], np.zeros(len(e))]) @ R_CW.T
        C = e[:, 2:3] * R_CW[:, 2]
        P_C = P @ R_CW.T + t_CW
        for psi, far, first, other in ((psi_a, far_b, a, b), (psi_b, far_a, b, a)):
            seen = far - X
            yaw = psi[:, None] - corners.heading[sel][None, :]  # (n, m)
            cs, sn = np.cos(yaw), np.sin(yaw)
            d_C = [cs * A[:, k] + sn * B[:, k] + C[:, k] for k in range(3)]
            # Times z² > 0: the direction, not the length, is compared.
            dx = d_C[0] * P_C[:, 2:3] - P_C[:, 0:1] * d_C[2]
            dy = d_C[1] * P_C[:, 2:3] - P_C[:, 1:2] * d_C[2]
            du = K[0, 0] * dx + K[0, 1] * dy
            dv = K[1, 1] * dy
            along = du * seen[:, 0:1] + dv * seen[:, 1:2]
            size = np.hypot(du, dv) * np.linalg.norm(seen, axis=1, keepdims=True)
            agree = (along > cos_tol * size) & (size > 0) & ok[:, None] & (P_C[:, 2:3] > 0)
            ji, ck = np.nonzero(agree)
            if len(ji):
                add(sel[ck], yaw[ji, ck], P[ji], np.column_stack([first[ji], other[ji]]))
    if not models:
        return np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros((0, 2), int)
    return np.concatenate(models), np.concatenate(poses), np.vstack(pairs)


def batch_support(
    model: VisionModel,
    on_face: np.ndarray,
    X_CO: np.ndarray,
    K: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    gradient_min: float,
    gradient_angle_rad: float,
    points_per_edge: int = 6,
    coarse_min: float | None = None,
) -> np.ndarray:
    """Cheap support of many poses ``X_CO`` (n, 4, 4) of one model at once, (n,): the fraction
    of points along the predicted edges where the image gradient, within ±1.5 px across the
    edge, is strong and at right angles to it. An edge counts as seen when one of its faces
    faces the camera (exact for convex parts; occlusion by other objects is ignored here).

    ``coarse_min``: first sample only two of each edge's points (those at 1/4 and 3/4 of 6 per
    edge) for all poses, and the rest only for poses whose support there reaches
    ``coarse_min``; the others get that coarse support. Poses sampled in full get exactly the
    support without it."""
    n = len(X_CO)
    if n == 0:
        return np.zeros(0)
    R, t = X_CO[:, :3, :3], X_CO[:, :3, 3]
    n_e = len(model.edges_O)
    # Edge end points in C, (n, 3, 2e), by one matrix product: [k, j, p] = R_k[j]·e_p + t_k[j]
    # (products of many 3×3 matrices with small arrays are slow in numpy; this is one call).
    E = (R.reshape(3 * n, 3) @ model.edges_O.reshape(-1, 3).T).reshape(n, 3, 2 * n_e)
    E += t[:, :, None]
    planes = np.vstack(model.planes_O)
    nC = (R.reshape(3 * n, 3) @ planes[:, :3].T).reshape(n, 3, -1)  # face normals in C
    dC = planes[:, 3][None, :] + np.einsum("nif,ni->nf", nC, t)  # n·x ≤ d inside, in C
    # A face faces the camera (at C's origin) when the origin is outside its plane: d < 0.
    facing = dC < 0  # (n, f)
    seen = facing.astype(np.float64) @ on_face.T.astype(np.float64) > 0  # (n, e)
    z = E[:, 2]  # (n, 2e)
    in_front = z > 1e-3
    seen &= in_front[:, 0::2] & in_front[:, 1::2]  # both ends (rows alternate a, b)
    iz = 1.0 / np.where(in_front, z, 1.0)
    x, y = E[:, 0] * iz, E[:, 1] * iz
    u = (K[0, 0] * x + K[0, 1] * y + K[0, 2]).reshape(n, n_e, 2)
    v = (K[1, 0] * x + K[1, 1] * y + K[1, 2]).reshape(n, n_e, 2)
    du, dv = u[:, :, 1] - u[:, :, 0], v[:, :, 1] - v[:, :, 0]
    L = np.sqrt(du * du + dv * dv)
    h, w = gx.shape
    on_image = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    inside = on_image[:, :, 0] & on_image[:, :, 1]
    use = seen & (L >= 4.0) & inside
    k = points_per_edge
    n_used = use.sum(axis=1)
    count = n_used * k
    # Sample only the edges that count: about half of all edges are hidden or off the image.
    ci, ei = np.nonzero(use)
    if len(ci) == 0:
        return np.zeros(n)
    du, dv, Lu = du[ci, ei], dv[ci, ei], L[ci, ei]
    nx, ny = -dv / Lu, du / Lu  # the edges' unit normals
    u0, v0 = u[ci, ei, 0], v[ci, ei, 0]
    ts = (np.arange(k) + 0.5) / k
    cos2 = np.float32(np.cos(gradient_angle_rad) ** 2)
    g2 = np.float32(gradient_min**2)
    offsets = np.array(SUPPORT_OFFSETS_PX)[:, None, None]

    def hits_at(rows: np.ndarray | None, t: np.ndarray) -> np.ndarray:
        """Points along used edges ``rows`` (None: all) at fractions ``t`` where the gradient
        agrees. The points are laid out (offset, t, edge): rows of many points for remap."""
        sel = slice(None) if rows is None else rows
        tq = t[None, :, None]
        nxr, nyr = nx[sel], ny[sel]
        # Sums in float64 stored straight as the float32 that remap wants (as a cast would
        # round them), and in-place float32 arithmetic after: these arrays are large.
        X = np.empty((len(offsets), len(t), len(nxr)), np.float32)
        Y = np.empty_like(X)
        np.add(u0[sel] + tq * du[sel], offsets * nxr, out=X)  # (3, t, r)
        np.add(v0[sel] + tq * dv[sel], offsets * nyr, out=Y)
        sx, sy = sample_gradient_xy(gx, gy, X, Y)
        # mag > min and |cos| > cos_min, without roots or divisions
        mag2 = sx * sx
        mag2 += sy * sy
        dot = sx * nxr.astype(np.float32)
        dot += sy * nyr.astype(np.float32)
        dot *= dot
        ok = mag2 > g2
        mag2 *= cos2
        ok &= dot > mag2
        good = ok[0] | ok[1] | ok[2] if len(ok) == 3 else ok.any(axis=0)
        return good.sum(axis=0)

    all_rows = None
    if coarse_min is None or k != 6:
        hits = np.bincount(ci, weights=hits_at(all_rows, ts), minlength=n)
        return np.where(count > 0, hits / np.maximum(count, 1), 0.0)
    first = np.array([1, 4])
    coarse_hits = np.bincount(ci, weights=hits_at(all_rows, ts[first]), minlength=n)
    coarse = np.where(n_used > 0, coarse_hits / np.maximum(2 * n_used, 1), 0.0)
    full = coarse >= coarse_min
    rows = np.flatnonzero(full[ci])
    rest = np.array([0, 2, 3, 5])
    hits = coarse_hits + np.bincount(ci[rows], weights=hits_at(rows, ts[rest]), minlength=n)
    return np.where(full, np.where(count > 0, hits / np.maximum(count, 1), 0.0), coarse)


def sample_gradient(
    gx: np.ndarray, gy: np.ndarray, pts: np.ndarray, width: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of both gradient images at points (m, 2) px, 0 outside the image;
    any number of points (``cv2.remap`` maps must stay below 32767 rows)."""
    return sample_gradient_xy(gx, gy, pts[:, 0], pts[:, 1], width)


def sample_gradient_xy(
    gx: np.ndarray, gy: np.ndarray, x: np.ndarray, y: np.ndarray, width: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_gradient` at points given as two arrays of coordinates of any (equal)
    shape; the samples have that shape."""
    m = x.size
    if m == 0:
        return np.zeros(x.shape, np.float32), np.zeros(x.shape, np.float32)
    cols = x.shape[-1] if x.ndim else 1
    if m <= width or (x.ndim > 1 and width <= cols < 32767 and m // cols < 32767):
        # The points' own rows, if long, else one row as long as the points: no padding
        # (remap's cost grows with the map, padding included).
        cols = cols if m > width else m
        mx = np.asarray(x, dtype=np.float32).reshape(-1, cols)
        my = np.asarray(y, dtype=np.float32).reshape(-1, cols)
    else:
        rows = -(-m // width)
        mx = np.full(rows * width, -10.0, dtype=np.float32)
        my = np.full(rows * width, -10.0, dtype=np.float32)
        mx[:m] = x.ravel()
        my[:m] = y.ravel()
        mx, my = mx.reshape(rows, width), my.reshape(rows, width)
    sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR).ravel()[:m]
    sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR).ravel()[:m]
    return sx.reshape(x.shape), sy.reshape(x.shape)
