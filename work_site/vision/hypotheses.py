"""Pose hypotheses (§IV-A): from the model index's matches of grouped image lines, from corners
resting on the table, and from bigger models grown around an object already found; each with
its initial pose ``X_CO`` and the soft prior that keeps a fit resting on the table.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.geometry import axis_rotations
from models.transforms import invert_pose
from work_site.vision.index import (
    GroupParams,
    Groups,
    IndexParams,
    ModelIndex,
    find_junctions,
    group_segments,
)
from work_site.vision.model import VisionModel, transform
from work_site.vision.params import RecognizerParams
from work_site.vision.pose import fit_pose
from work_site.vision.pose_sets import PoseSet
from work_site.vision.table import RestCorners, batch_support, table_hypotheses


def initial_pose(
    R_view: np.ndarray,
    junctions_canonical_px: np.ndarray,
    junctions_image_px: np.ndarray,
    K: np.ndarray,
    index_params: IndexParams,
) -> np.ndarray:
    """``X_CO`` that makes the indexed view's group land on the image group: rotate in the
    image plane, scale to depth, then tilt the view onto the ray through the group."""
    return initial_poses(
        R_view[None], junctions_canonical_px[None], junctions_image_px[None], K, index_params
    )[0]


def initial_poses(
    R_view: np.ndarray,
    junctions_canonical_px: np.ndarray,
    junctions_image_px: np.ndarray,
    K: np.ndarray,
    index_params: IndexParams,
) -> np.ndarray:
    """:func:`initial_pose` of many hypotheses at once: ``R_view`` (h, 3, 3), junctions
    (h, j, 2) each; returns (h, 4, 4). The image group is the indexed one under the 2-D
    similarity ``a·z + t`` (least squares, complex numbers; ``a`` is scale·rotation)."""
    h = len(R_view)
    f = index_params.canonical_f_px
    src = junctions_canonical_px / f
    Kinv = np.linalg.inv(K)
    J = junctions_image_px
    dst = J @ Kinv[:2, :2].T + Kinv[:2, 2]  # K's last row is (0, 0, 1)
    zs = src[..., 0] + 1j * src[..., 1]  # (h, j)
    zd = dst[..., 0] + 1j * dst[..., 1]
    ms, md = zs.mean(axis=1, keepdims=True), zd.mean(axis=1, keepdims=True)
    den = np.sum(np.abs(zs - ms) ** 2, axis=1)
    num = np.sum(np.conj(zs - ms) * (zd - md), axis=1)
    a = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0 + 0j)
    t = md[:, 0] - a * ms[:, 0]
    Z = index_params.view_distance_m / np.maximum(np.abs(a), 1e-9)
    alpha = np.angle(a)
    ca, sa = np.cos(alpha), np.sin(alpha)
    Rz = np.zeros((h, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = ca, -sa, sa, ca, 1.0
    ray = np.column_stack([t.real, t.imag, np.ones(h)])
    b = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    # The smallest rotation taking +z to b: about v = z × b = (−b_y, b_x, 0), by atan2(|v|, b_z).
    sv = np.hypot(b[:, 0], b[:, 1])
    kx = np.where(sv < 1e-12, 0.0, -b[:, 1] / np.maximum(sv, 1e-300))
    ky = np.where(sv < 1e-12, 0.0, b[:, 0] / np.maximum(sv, 1e-300))
    ang = np.arctan2(sv, b[:, 2])
    Kx = np.zeros((h, 3, 3))
    Kx[:, 0, 2], Kx[:, 1, 2], Kx[:, 2, 0], Kx[:, 2, 1] = ky, -kx, -ky, kx
    R_tilt = (
        np.eye(3) + np.sin(ang)[:, None, None] * Kx + (1 - np.cos(ang))[:, None, None] * Kx @ Kx
    )
    X = np.tile(np.eye(4), (h, 1, 1))
    X[:, :3, :3] = R_tilt @ Rz @ R_view
    X[:, :3, 3] = Z[:, None] * ray
    return X


def index_hypotheses(
    index: ModelIndex,
    group_params: GroupParams,
    segs: np.ndarray,
    params: RecognizerParams,
    limit: int | None = None,
    junctions: list | None = None,
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """(image group segments, junctions, index entry), most probable first; at most
    ``limit`` of them. ``junctions``: :func:`find_junctions` of ``segs`` if known."""
    groups = group_segments(segs, group_params, index.params.ratio_weight, junctions)
    # Each chain is listed in both directions, and so is every model chain in the index:
    # the reversed chain finds the reversed entries at the same distances and gives the
    # same pose. Look up one direction only.
    one_way = groups.segs[:, 0] < groups.segs[:, 3]
    groups = Groups(groups.segs[one_way], groups.junctions[one_way], groups.vectors[one_way])
    if len(groups.segs) == 0:
        return []
    ids, d2 = index.query(groups.vectors)
    if ids.shape[1] == 0:
        return []
    sigma = index.params.kernel_sigma
    # Kernel density of the models at the group's vector: a group that lies where model
    # views put many vectors is likely an object's; accidental groups of clutter fall in
    # sparse places. The neighbour's share of the density says which model it points to.
    w = np.exp(-d2 / (2 * sigma**2))
    prob = w / (w.sum(axis=1, keepdims=True) + params.kernel_prior)
    rank = w * prob
    order = np.argsort(-rank, axis=None)
    out = []
    seen: set[tuple] = set()
    for flat in order:
        g, k = divmod(int(flat), ids.shape[1])
        if rank[g, k] < 1e-4:
            break
        e = int(ids[g, k])
        key = (int(index.model[e]), tuple(sorted(groups.segs[g].tolist())),
               tuple(index.edges[e].tolist()))  # fmt: skip
        if key in seen:
            continue
        seen.add(key)
        out.append((groups.segs[g], groups.junctions[g], e))
        if limit is not None and len(out) >= limit:
            break
    return out


def index_stream(
    hyps: list[tuple],
    index: ModelIndex,
    models: Sequence[VisionModel],
    facets: dict[str, tuple[np.ndarray, np.ndarray]],
    table_z: float,
    K: np.ndarray,
    X_WC: np.ndarray,
    params: RecognizerParams,
    max_height_m: float = 0.0,
) -> tuple[list[tuple], list[tuple]]:
    """Indexed hypotheses ``(model, group's segments, (index entry, initial X_CO))`` in
    their order, all initial poses computed at once, in two lists: those that show the object
    standing on one of its faces roughly at table height (with the table prior), and the
    others whose lowest point lies between the table and ``max_height_m`` above it, in any
    orientation (blocks on blocks, leaning). Those below the table or above that height are
    dropped (most accidental matches fail this at no cost)."""
    if not hyps:
        return [], []
    p = params
    idx = index
    entries = np.array([e for _, _, e in hyps])
    X = initial_poses(
        idx.R_CO[idx.view[entries]], idx.junctions[entries],
        np.array([g_junc for _, g_junc, _ in hyps]), K, idx.params,
    )  # fmt: skip
    resting = np.ones(len(hyps), dtype=bool)
    free = np.zeros(len(hyps), dtype=bool)
    if p.table_prior:
        X_WO = X_WC @ X
        mods = idx.model[entries]
        for mi, m in enumerate(models):
            sel = np.flatnonzero(mods == mi)
            if len(sel) == 0:
                continue
            up = X_WO[sel, 2, :3]  # world z of O's axes: n_W[:, 2] = N_O · up
            tilt_ok = -(facets[m.name][0] @ up.T).min(axis=0) >= np.cos(p.prefilter_tilt_rad)
            height = (m.vertices_O @ up.T).min(axis=0) + X_WO[sel, 2, 3] - table_z
            resting[sel] = tilt_ok & (np.abs(height) <= p.prefilter_height_m)
            free[sel] = (
                ~resting[sel]
                & (height >= -p.prefilter_height_m)
                & (height <= max_height_m + p.prefilter_height_m)
            )

    def items(ok: np.ndarray) -> list[tuple]:
        return [
            (models[int(idx.model[e])], g_segs, (e, X[k]))
            for k, (g_segs, _, e) in enumerate(hyps)
            if ok[k]
        ]

    return items(resting), items(free)


def table_stream(
    corners: RestCorners,
    models: Sequence[VisionModel],
    group_params: GroupParams,
    table_z: float,
    segs: np.ndarray,
    K: np.ndarray,
    X_WC: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    params: RecognizerParams,
    junctions: list | None = None,
) -> list[tuple]:
    """Table hypotheses ``(model, junction's two segments, X_CO)``, best supported first,
    only those with enough cheap support (see :mod:`work_site.vision.table`), each pose once."""
    p = params
    if not p.table_hypotheses:
        return []
    if junctions is None:
        junctions = find_junctions(segs, group_params)
    mod, X_WO, pairs = table_hypotheses(
        corners, junctions, segs, K, X_WC, table_z, p.table_angle_tol_rad
    )
    if len(mod) == 0:
        return []
    X_CO = invert_pose(X_WC) @ X_WO
    score = np.zeros(len(mod))
    for mi, m in enumerate(models):
        sel = np.flatnonzero(mod == mi)
        score[sel] = batch_support(
            m, m.edge_faces, X_CO[sel], K, gx, gy,
            p.gradient_min, p.gradient_angle_rad, coarse_min=p.table_coarse_min,
        )  # fmt: skip
    order = np.argsort(-score, kind="stable")
    order = order[score[order] >= p.quick_support_min]
    # Many junctions of one block give the same pose: count each pose once against the cap,
    # looking at the best supported a cap's worth at a time.
    cap = p.max_table_hypotheses
    if cap < 1:
        return []
    same = PoseSet(p.same_pose_m, p.same_pose_rad)
    kept: list[np.ndarray] = []
    n_kept = 0
    for start in range(0, len(order), cap):
        chunk = order[start : start + cap]
        new = np.zeros(len(chunk), dtype=bool)
        for mi in np.unique(mod[chunk]):
            of_m = np.flatnonzero(mod[chunk] == mi)
            new[of_m] = same.add_new(models[int(mi)], X_CO[chunk[of_m]])
        kept.append(chunk[new])
        n_kept += int(new.sum())
        if n_kept >= cap:
            break
    order = np.concatenate(kept)[:cap] if kept else order
    return [(models[int(mod[i])], pairs[i], X_CO[i]) for i in order]


def initial_fit(
    model: VisionModel,
    index: ModelIndex,
    entry: int,
    X: np.ndarray,
    g_segs: np.ndarray,
    segs: np.ndarray,
    K: np.ndarray,
    X_WC: np.ndarray,
    table_z: float,
    params: RecognizerParams,
    prior=None,
    max_height_m: float = 0.0,
) -> np.ndarray | None:
    """``X_CO`` fitted to the hypothesis' four correspondences (index ``entry``'s model edges,
    image lines ``segs[g_segs]``) from the initial ``X``, or None if it cannot be right: the
    lines do not fit, or the object's lowest point would be far below the table or more than
    ``max_height_m`` above it (0: resting on it). ``prior``: see :func:`resting_prior`."""
    p = params
    edges = model.edges_O[index.edges[entry]]
    fit = fit_pose(
        X, edges, segs[g_segs], K, iterations=p.fit_iterations, tol=p.fit_tol, prior=prior
    )
    if fit.rms_px > p.init_rms_max_px or fit.X_CO[2, 3] <= 0.05:
        return None
    height = transform(X_WC @ fit.X_CO, model.vertices_O)[:, 2].min() - table_z
    if not -p.early_table_tol_m <= height <= max_height_m + p.early_table_tol_m:
        return None
    return fit.X_CO


def resting_prior(
    model: VisionModel,
    facet_normals_O: np.ndarray,
    X_WC: np.ndarray,
    table_z: float,
    params: RecognizerParams,
):
    """The fits' soft prior that ``model`` rests on a face on the table: a function of
    ``X_CO`` giving residuals (px-equivalents) and their Jacobian (see
    :func:`~work_site.vision.pose.fit_pose`), or None when the prior is off. Applied softly,
    so that the lines still decide. ``facet_normals_O``: the model's hull facet normals."""
    if not params.table_prior:
        return None
    p = params
    N_O = facet_normals_O
    R_WC = X_WC[:3, :3]
    g = R_WC[2]  # world z of a camera-frame vector

    V_O = model.vertices_O
    a, b = p.table_prior_px_per_m, p.table_prior_px_per_rad
    gx, gy, gz = g.tolist()
    z_C, z_table = float(X_WC[2, 3]), table_z
    # rows of b·R_WCᵀ applied to down × e_x and down × e_y (see below), as plain floats
    r0, r1, r2 = (b * R_WC).tolist()

    def prior(X_CO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # The update rotates by ω about O's origin in C and shifts by v in C (pose.py):
        # a vertex moves by ω × Q + v, a normal turns by (R_WC ω) × n_W. Small vectors
        # are plain floats: this runs at every evaluation of every fit.
        R_CO = X_CO[:3, :3]
        R_WO = R_WC @ R_CO
        dx, dy, dz = (R_WO @ N_O[(N_O @ R_WO[2]).argmin()]).tolist()  # n_W facing down
        Q = V_O @ R_CO.T
        z = (Q + X_CO[:3, 3]) @ g + z_C
        k = z.argmin()
        qx, qy, qz = Q[k].tolist()
        r = np.array([a * (z[k].item() - z_table), b * dx, b * dy])
        # down × e_x = (0, d_z, −d_y); down × e_y = (−d_z, 0, d_x); R_WCᵀ takes them to C
        J = np.array(
            [
                [a * (qy * gz - qz * gy), a * (qz * gx - qx * gz), a * (qx * gy - qy * gx),
                 a * gx, a * gy, a * gz],
                [dz * r1[0] - dy * r2[0], dz * r1[1] - dy * r2[1], dz * r1[2] - dy * r2[2],
                 0.0, 0.0, 0.0],
                [dx * r2[0] - dz * r0[0], dx * r2[1] - dz * r0[1], dx * r2[2] - dz * r0[2],
                 0.0, 0.0, 0.0],
            ]
        )  # fmt: skip
        return r, J

    return prior


def turned_poses(model: VisionModel) -> np.ndarray:
    """``X_OT`` (k, 4, 4): the model turned about its bounding-box centre by each of the
    cube's rotations that give a pose different from the model's own (up to its
    symmetries)."""
    c = 0.5 * (model.vertices_O.min(0) + model.vertices_O.max(0))
    out: list[np.ndarray] = []
    for S in axis_rotations():
        if any(np.allclose(S, Q, atol=1e-9) for Q in model.symmetries):
            continue
        if any(np.allclose(S @ Q, X[:3, :3], atol=1e-9) for X in out for Q in model.symmetries):
            continue
        X = np.eye(4)
        X[:3, :3] = S
        X[:3, 3] = c - S @ c
        out.append(X)
    return np.array(out).reshape(-1, 4, 4)


def grown_poses(
    whole: VisionModel,
    X_CB_all: np.ndarray,
    X_WC: np.ndarray,
    K: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    table_z: float,
    tested: PoseSet,
    params: RecognizerParams,
    max_height_m: float = 0.0,
) -> np.ndarray:
    """Poses ``X_CB`` (k, 4, 4) of the bigger model ``whole`` around a part found in the image,
    to test in full, best supported first: of the candidate poses ``X_CB_all`` (n, 4, 4), those
    whose lowest point is near the table top (or up to ``max_height_m`` above it), not tested
    before (all are recorded in ``tested``) and with enough cheap support, at most
    ``params.grown_max_tests``."""
    p = params
    X_WB = X_WC @ X_CB_all
    z_W = X_WB[:, 2, :3] @ whole.vertices_O.T + X_WB[:, 2, 3:]  # (k, v)
    height = z_W.min(1) - table_z
    X_CB_all = X_CB_all[
        (height >= -p.early_table_tol_m) & (height <= max_height_m + p.early_table_tol_m)
    ]
    # Cheap support of all of them at once (no occlusion): most poses of a bigger model
    # around a found part hang over empty table and fail here.
    support = batch_support(
        whole, whole.edge_faces, X_CB_all, K, gx, gy, p.gradient_min, p.gradient_angle_rad
    )
    fresh = tested.add_new(whole, X_CB_all)
    # The right pose, if any, is among the best supported.
    order = np.argsort(-support, kind="stable")
    order = order[fresh[order] & (support[order] >= p.grow_support_min)]
    return X_CB_all[order[: p.grown_max_tests]]
