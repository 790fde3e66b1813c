"""Recognition and location of known objects in one grey image (§IV-A), with verification
better than the paper's "50 % of visible edge length" (§VII-A).

Pipeline: lines → groups → index look-up → probability-ranked hypotheses; for each hypothesis in
turn, an initial pose from the group's junctions and the indexed view, Lowe's least-squares fit,
prediction of further edge correspondences and refitting; then verification: matched visible
edge length, agreement of the image gradient's direction along every predicted edge, a final
residual bound, no interpenetration with accepted objects or the fixed environment, and the
object resting on the table inside the work area.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from models.scene import CameraModel, ObjectModel, Scene, load_scene
from models.transforms import invert_pose
from work_site.vision.index import (
    GroupParams,
    IndexParams,
    ModelIndex,
    find_junctions,
    group_segments,
    load_or_build_index,
)
from work_site.vision.lines import LineParams, check_grey_image, detect_lines
from work_site.vision.model import (
    VisionModel,
    containments,
    convex_overlap_depth,
    hull_facets,
    planes_in,
    project,
    transform,
    visible_edges,
    vision_model,
)
from work_site.vision.pose import fit_pose
from work_site.vision.table import batch_support, edge_faces, rest_corners, table_hypotheses

ENV_MATCH_TOL_PX = 1.5
"""Image lines this close to a projected edge of the fixed environment are its own."""


@dataclass(frozen=True)
class RecognizerParams:
    """Tuning of hypothesis testing and verification (pixels, radians, metres)."""

    max_hypotheses: int = 400
    refine_rounds: int = 3
    match_tol_px: tuple[float, ...] = (8.0, 3.0, 1.5)
    match_angle_rad: float = np.deg2rad(5.0)
    fit_iterations: int = 12
    fit_tol: float = 1e-7  # rad and m: a fit stops at steps this small (1 µm ≪ the 1 mm goal)
    init_rms_max_px: float = 4.0
    final_rms_max_px: float = 1.0
    min_matched_edges: int = 5
    verify_tol_px: float = 1.5
    verify_angle_rad: float = np.deg2rad(4.0)
    gradient_min: float = 60.0
    gradient_angle_rad: float = np.deg2rad(20.0)
    min_score: float = 0.6
    min_length_fraction: float = 0.45
    min_silhouette_fraction: float = 0.65
    grown_min_silhouette_fraction: float = 0.8
    table_tol_m: float = 0.006
    early_table_tol_m: float = 0.03
    same_pose_m: float = 0.004
    same_pose_rad: float = np.deg2rad(4.0)
    max_penetration_m: float = 0.002
    max_per_model: int | None = 1
    kernel_prior: float = 0.05
    time_budget_s: float | None = None
    confident_score: float = 0.85
    quick_support_min: float = 0.5
    grow_support_min: float = 0.4  # batch support (no occlusion) of a bigger model grown
    # around a found part, before its full test; true ones measured ≥ 0.45 on 40 scenes
    prefilter_tilt_rad: float = np.deg2rad(30.0)
    prefilter_height_m: float = 0.06
    table_prior: bool = True
    table_prior_px_per_m: float = 1000.0
    table_prior_px_per_rad: float = 60.0
    table_hypotheses: bool = True
    max_table_hypotheses: int = 200
    table_angle_tol_rad: float = np.deg2rad(8.0)


@dataclass(frozen=True)
class Verification:
    """How well a pose is supported by the image (fractions of visible projected edge length)."""

    length_fraction: float
    gradient_fraction: float
    silhouette_fraction: float
    matched: list[int]
    covered_px: float

    @property
    def score(self) -> float:
        """The reported score: mean of matched-length and gradient-agreement fractions."""
        return 0.5 * (self.length_fraction + self.gradient_fraction)


@dataclass(frozen=True)
class Recognition:
    """One recognised object: model name, pose ``X_WO``, score in [0, 1] and diagnostics."""

    model: str
    X_WO: np.ndarray
    score: float
    rms_px: float = 0.0
    length_fraction: float = 0.0
    gradient_fraction: float = 0.0
    matched_segments: tuple[int, ...] = field(default=(), repr=False)

    def __iter__(self):
        """Unpacks as ``(model, X_WO, score)``, the triple the work-site server publishes."""
        return iter((self.model, self.X_WO, self.score))


def check_camera(camera: CameraModel) -> None:
    """ValueError if ``camera`` cannot project: singular or non-finite ``K``, bad pose."""
    K = np.asarray(camera.K, dtype=np.float64)
    X = np.asarray(camera.X_WC, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError("camera K must be a finite 3×3 matrix")
    if abs(np.linalg.det(K)) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("camera K is singular (fx and fy must be > 0)")
    if X.shape != (4, 4) or not np.all(np.isfinite(X)):
        raise ValueError("camera X_WC must be a finite 4×4 pose")


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[complex, complex]:
    """Least-squares 2-D similarity ``dst ≈ a·src + t`` as complex numbers (a: scale·rotation)."""
    zs = src[:, 0] + 1j * src[:, 1]
    zd = dst[:, 0] + 1j * dst[:, 1]
    ms, md = zs.mean(), zd.mean()
    den = np.sum(np.abs(zs - ms) ** 2)
    a = np.sum(np.conj(zs - ms) * (zd - md)) / den if den > 0 else 1.0 + 0j
    return complex(a), complex(md - a * ms)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(a @ b)
    s = np.linalg.norm(v)
    if s < 1e-12:
        return np.eye(3)
    Kx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * Kx + (1 - np.cos(ang)) * Kx @ Kx


def initial_pose(
    R_view: np.ndarray,
    junctions_canonical_px: np.ndarray,
    junctions_image_px: np.ndarray,
    K: np.ndarray,
    index_params: IndexParams,
) -> np.ndarray:
    """``X_CO`` that makes the indexed view's group land on the image group: rotate in the
    image plane, scale to depth, then tilt the view onto the ray through the group."""
    f = index_params.canonical_f_px
    src = junctions_canonical_px / f
    Kinv = np.linalg.inv(K)
    dst = (np.column_stack([junctions_image_px, np.ones(len(junctions_image_px))]) @ Kinv.T)[:, :2]
    a, t = _similarity(src, dst)
    scale = abs(a)
    alpha = np.angle(a)
    Z = index_params.view_distance_m / max(scale, 1e-9)
    ray = np.array([t.real, t.imag, 1.0])
    Rz = np.array(
        [[np.cos(alpha), -np.sin(alpha), 0], [np.sin(alpha), np.cos(alpha), 0], [0, 0, 1.0]]
    )
    R_tilt = _rotation_between(np.array([0.0, 0.0, 1.0]), ray / np.linalg.norm(ray))
    X = np.eye(4)
    X[:3, :3] = R_tilt @ Rz @ R_view
    X[:3, 3] = Z * ray
    return X


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
    Lm = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    u = d / Lm[:, None]
    n = np.column_stack([-u[:, 1], u[:, 0]])
    p, q = image_segs[:, :2], image_segs[:, 2:]
    di = q - p
    Li = np.maximum(np.linalg.norm(di, axis=1), 1e-9)
    ui = di / Li[:, None]
    # (m, i) arrays
    cos = np.abs(u @ ui.T)
    dp = np.abs(np.einsum("mk,mik->mi", n, p[None, :, :] - a[:, None, :]))
    dq = np.abs(np.einsum("mk,mik->mi", n, q[None, :, :] - a[:, None, :]))
    tp = np.einsum("mk,mik->mi", u, p[None, :, :] - a[:, None, :])
    tq = np.einsum("mk,mik->mi", u, q[None, :, :] - a[:, None, :])
    lo, hi = np.minimum(tp, tq), np.maximum(tp, tq)
    overlap = np.minimum(hi, Lm[:, None]) - np.maximum(lo, 0.0)
    ok = (cos > np.cos(angle_rad)) & (dp < tol_px) & (dq < tol_px) & (overlap >= 0.5 * Li[None, :])
    cost = np.where(ok, dp + dq, np.inf)
    best = np.argmin(cost, axis=0)
    has = np.isfinite(cost[best, np.arange(len(image_segs))])
    return best[has], np.flatnonzero(has)


@dataclass(frozen=True, eq=False)
class _Candidate:
    model: VisionModel
    X_CO: np.ndarray
    X_WO: np.ndarray
    rms_px: float
    verification: Verification
    parts_W: list[tuple[np.ndarray, np.ndarray]]
    grown: bool = False  # made by growing a smaller found object into a bigger model


class Recognizer:
    """Recognises a fixed set of object models in grey images.

    ``models``: the objects to look for (default: the movable objects of ``scene``).
    ``scene`` (default: the puzzle scene): its fixed objects, at their poses ``X_WO``, are the
    environment: their image lines are set aside, they occlude, nothing may interpenetrate
    them; the one named ``table`` gives the table height and the work area. The model index is
    loaded from ``cache_dir`` (default: the user cache) or built there (≈ 3 s for 600 views).
    One instance is meant to serve many frames; it is not thread-safe.
    """

    def __init__(
        self,
        models: Sequence[ObjectModel] | None = None,
        scene: Scene | None = None,
        params: RecognizerParams | None = None,
        index_params: IndexParams | None = None,
        group_params: GroupParams | None = None,
        line_params: LineParams | None = None,
        cache_dir: Path | None = None,
    ) -> None:
        scene = scene if scene is not None else load_scene()
        if models is None:
            models = [o.model for o in scene.movable]
        if not models:
            raise ValueError("no object models to recognise")
        self.params = params or RecognizerParams()
        self.line_params = line_params or LineParams()
        self.group_params = group_params or GroupParams()
        self.object_models = list(models)
        self.models = [vision_model(m) for m in models]
        files = []
        for m in models:
            files.append(m.urdf_path)
            files.extend(sorted((m.urdf_path.parent / "meshes").glob(f"{m.urdf_path.stem}_*.obj")))
        self.index: ModelIndex = load_or_build_index(
            self.models, files, index_params, self.group_params, cache_dir
        )
        self.environment = [
            (o.name, o.X_WO,
             [(transform(o.X_WO, p.vertices_O), p.normals_O @ o.X_WO[:3, :3].T)
              for p in o.model.parts],
             [np.column_stack([p.normals_O, p.offsets_m]) for p in o.model.parts])
            for o in scene.objects if o.fixed
        ]  # fmt: skip
        self._wholes = {
            a.name: [
                (b, np.array([invert_pose(X) for X in containments(a, b)]))
                for b in self.models
                if b is not a and containments(a, b)
            ]
            for a in self.models
        }
        self._facets = {
            m.name: (
                np.array([n for n, _ in hull_facets(m.vertices_O)]),
                np.array([d for _, d in hull_facets(m.vertices_O)]),
            )
            for m in self.models
        }
        self._corners = rest_corners(self.models, [m.com_O for m in self.object_models])
        self._edge_faces = {m.name: edge_faces(m) for m in self.models}
        self._env_models = [(vision_model(o.model), o.X_WO) for o in scene.objects if o.fixed]
        table = [o for o in scene.objects if o.fixed and o.name == "table"]
        if table:
            t = table[0]
            corners = transform(t.X_WO, t.model.bbox_O)
            self.table_z = float(corners[:, 2].max())
            self.work_area_xy = (corners[:, :2].min(0), corners[:, :2].max(0))
        else:
            self.table_z = 0.0
            self.work_area_xy = (np.array([-np.inf, -np.inf]), np.array([np.inf, np.inf]))

    # -- the public entry point ------------------------------------------------------------
    def recognise(self, image: np.ndarray, camera: CameraModel) -> list[Recognition]:
        """Objects found in ``image`` (grey uint8, camera's size), best score first.

        Raises ValueError for an unusable image or camera; an image with nothing recognisable
        gives an empty list.
        """
        img = check_grey_image(image)
        check_camera(camera)
        if img.shape != (camera.height, camera.width):
            raise ValueError(
                f"image is {img.shape[1]}×{img.shape[0]} but the camera is "
                f"{camera.width}×{camera.height}"
            )
        t0 = time.perf_counter()
        K = np.asarray(camera.K, dtype=np.float64)
        dist = np.asarray(camera.dist, dtype=np.float64)
        if np.any(dist != 0):
            # Straight edges are straight only in an undistorted image.
            img = cv2.undistort(img, K, dist)
        segs = detect_lines(img, self.line_params)
        X_CW = invert_pose(camera.X_WC)
        env_C = [
            planes_in(X_CW @ X_WO, P) for _, X_WO, _, planes in self.environment for P in planes
        ]
        segs = self._drop_environment(segs, X_CW, K, env_C)
        if len(segs) < 4:
            return []
        gx = cv2.Scharr(img.astype(np.float32), cv2.CV_32F, 1, 0)
        gy = cv2.Scharr(img.astype(np.float32), cv2.CV_32F, 0, 1)
        hyps = self._hypotheses(segs)
        candidates: list[_Candidate] = []
        claimed = np.zeros(len(segs), dtype=bool)
        tested: list[tuple[VisionModel, np.ndarray]] = []
        confident: set[str] = set()
        p = self.params
        stream = self._table_stream(segs, K, camera.X_WC, gx, gy)
        stream += [
            (self.models[int(self.index.model[e])], g_segs, (e, g_junc))
            for g_segs, g_junc, e in hyps[: p.max_hypotheses]
        ]
        for model, g_segs, how in stream:
            if p.time_budget_s is not None and time.perf_counter() - t0 > p.time_budget_s:
                break
            # A group wholly inside an object already found adds nothing; one that reaches
            # beyond it may be a bigger object that explains more (an L seen as its upright).
            if claimed[g_segs].all():
                continue
            if model.name in confident:
                continue
            if isinstance(how, np.ndarray):
                X0 = how  # a table hypothesis: already a whole pose
            else:
                X0 = self._initial_fit(model, how[0], g_segs, how[1], segs, K, camera.X_WC)
            if X0 is None:
                continue
            # Many groups of one object lead to the same pose: test each pose once.
            if self._seen(model, X0, tested):
                continue
            tested.append((model, X0))
            result = self._test(model, X0, segs, K, gx, gy, env_C, camera.X_WC)
            if result is None:
                continue
            found = [(model, result, False)]
            # The object may be part of a bigger one (an L's bar is a tall block): try those
            # too, and let the selection prefer whichever explains more of the image.
            for whole, X_AB_all in self._wholes[model.name]:
                X_CB_all = result[0] @ X_AB_all  # (k, 4, 4)
                X_WB = camera.X_WC @ X_CB_all
                z_W = X_WB[:, 2, :3] @ whole.vertices_O.T + X_WB[:, 2, 3:]  # (k, v)
                X_CB_all = X_CB_all[np.abs(z_W.min(1) - self.table_z) <= p.early_table_tol_m]
                # Cheap support of all of them at once (no occlusion): most poses of a bigger
                # model around a found part hang over empty table and fail here.
                support = batch_support(
                    whole, self._edge_faces[whole.name], X_CB_all, K, gx, gy,
                    p.gradient_min, p.gradient_angle_rad,
                )  # fmt: skip
                for X_CB, s in zip(X_CB_all, support, strict=True):
                    if self._seen(whole, X_CB, tested):
                        continue
                    tested.append((whole, X_CB))
                    if s < p.grow_support_min:
                        continue
                    r2 = self._test(whole, X_CB, segs, K, gx, gy, env_C, camera.X_WC)
                    if r2 is not None:
                        found.append((whole, r2, True))
            for m, (X_CO, rms, v), grown in found:
                X_WO = camera.X_WC @ X_CO
                parts_W = [
                    (transform(X_WO, q), P[:, :3] @ X_WO[:3, :3].T)
                    for q, P in zip(m.parts_vertices_O, m.planes_O, strict=True)
                ]
                if not self._plausible(parts_W, []):
                    continue
                candidates.append(_Candidate(m, X_CO, X_WO, rms, v, parts_W, grown))
                if v.silhouette_fraction >= p.min_silhouette_fraction:
                    claimed[v.matched] = True  # only confident candidates block others
                    if p.max_per_model == 1 and v.score >= p.confident_score:
                        confident.add(m.name)
            if len(confident) == len(self.models):
                break  # every model found once, and once is all there can be
        return self._select(candidates, segs, K, gx, gy, env_C)

    def _select(self, candidates, segs, K, gx, gy, env_C) -> list[Recognition]:
        """Candidates that explain the most image edge length first; a candidate sharing many
        image lines with, or interpenetrating, one already accepted is dropped. Each is
        verified again with the other candidates as occluders, and its outline must show."""
        p = self.params
        accepted: list[Recognition] = []
        accepted_parts: list[list[np.ndarray]] = []
        used: set[int] = set()
        per_model: dict[str, int] = {}
        order = sorted(candidates, key=lambda c: -c.verification.covered_px)
        for c in order:
            rec = c.verification
            if p.max_per_model is not None and per_model.get(c.model.name, 0) >= p.max_per_model:
                continue
            shared = len(used.intersection(rec.matched))
            if shared > 0.3 * max(len(rec.matched), 1):
                continue
            mine = set(rec.matched)
            others = [
                planes_in(o.X_CO, P)
                for o in order
                if o is not c and len(mine.intersection(o.verification.matched)) == 0
                for P in o.model.planes_O
            ]
            v = self._verify(c.model, c.X_CO, K, segs, gx, gy, env_C + others)
            # A bigger model grown around a smaller object found in the image must show its
            # outline clearly: a phantom part over empty table is the usual false object.
            sil_min = p.grown_min_silhouette_fraction if c.grown else p.min_silhouette_fraction
            if v.silhouette_fraction < sil_min or v.score < p.min_score:
                continue
            if not self._plausible(c.parts_W, accepted_parts, environment=False):
                continue
            accepted.append(
                Recognition(
                    model=c.model.name,
                    X_WO=c.X_WO,
                    score=v.score,
                    rms_px=c.rms_px,
                    length_fraction=v.length_fraction,
                    gradient_fraction=v.gradient_fraction,
                    matched_segments=tuple(rec.matched),
                )
            )
            accepted_parts.append(c.parts_W)
            used.update(rec.matched)
            per_model[c.model.name] = per_model.get(c.model.name, 0) + 1
        return sorted(accepted, key=lambda r: -r.score)

    def _seen(self, model: VisionModel, X_CO: np.ndarray, tested) -> bool:
        """Whether a pose of ``model`` equal to ``X_CO`` up to its symmetries was tested."""
        p = self.params
        cos_min = 1 + 2 * np.cos(p.same_pose_rad)
        for m, Xt in tested:
            if m is not model or np.linalg.norm(X_CO[:3, 3] - Xt[:3, 3]) > p.same_pose_m:
                continue
            R = Xt[:3, :3].T @ X_CO[:3, :3]
            if any(np.trace(R @ S) > cos_min for S in model.symmetries):
                return True
        return False

    # -- steps --------------------------------------------------------------------------------
    def _drop_environment(self, segs, X_CW, K, env_C) -> np.ndarray:
        """Image segments not explained by the fixed environment's projected edges: the frame's
        many corners would otherwise flood the hypotheses."""
        if len(segs) == 0:
            return segs
        explained = np.zeros(len(segs), dtype=bool)
        for env in self._env_models:
            X_CO = X_CW @ env[1]
            _, proj, _ = visible_edges(env[0], X_CO, K, env_C)
            _, mj = match_segments(proj, segs, ENV_MATCH_TOL_PX, np.deg2rad(3.0))
            explained[mj] = True
        return segs[~explained]

    def _table_stream(self, segs, K, X_WC, gx, gy) -> list[tuple]:
        """Table hypotheses ``(model, junction's two segments, X_CO)``, best supported first,
        only those with enough cheap support (see :mod:`work_site.vision.table`)."""
        p = self.params
        if not p.table_hypotheses:
            return []
        junctions = find_junctions(segs, self.group_params)
        mod, X_WO, pairs = table_hypotheses(
            self._corners, junctions, segs, K, X_WC, self.table_z, p.table_angle_tol_rad
        )
        if len(mod) == 0:
            return []
        X_CO = invert_pose(X_WC) @ X_WO
        score = np.zeros(len(mod))
        for mi, m in enumerate(self.models):
            sel = np.flatnonzero(mod == mi)
            score[sel] = batch_support(
                m, self._edge_faces[m.name], X_CO[sel], K, gx, gy,
                p.gradient_min, p.gradient_angle_rad,
            )  # fmt: skip
        order = np.argsort(-score, kind="stable")
        order = order[score[order] >= p.quick_support_min][: p.max_table_hypotheses]
        return [(self.models[int(mod[i])], pairs[i], X_CO[i]) for i in order]

    def _hypotheses(self, segs: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """(image group segments, junctions, index entry), most probable first."""
        groups = group_segments(segs, self.group_params, self.index.params.ratio_weight)
        if len(groups.segs) == 0:
            return []
        ids, d2 = self.index.query(groups.vectors)
        if ids.shape[1] == 0:
            return []
        sigma = self.index.params.kernel_sigma
        # Kernel density of the models at the group's vector: a group that lies where model
        # views put many vectors is likely an object's; accidental groups of clutter fall in
        # sparse places. The neighbour's share of the density says which model it points to.
        w = np.exp(-d2 / (2 * sigma**2))
        prob = w / (w.sum(axis=1, keepdims=True) + self.params.kernel_prior)
        rank = w * prob
        order = np.argsort(-rank, axis=None)
        out = []
        seen: set[tuple] = set()
        for flat in order:
            g, k = divmod(int(flat), ids.shape[1])
            if rank[g, k] < 1e-4:
                break
            e = int(ids[g, k])
            key = (int(self.index.model[e]), tuple(sorted(groups.segs[g].tolist())),
                   tuple(self.index.edges[e].tolist()))  # fmt: skip
            if key in seen:
                continue
            seen.add(key)
            out.append((groups.segs[g], groups.junctions[g], e))
        return out

    def _initial_fit(self, model, entry, g_segs, g_junc, segs, K, X_WC):
        """Pose from the hypothesis' four correspondences, or None if it cannot be right: the
        lines do not fit, or the object would be far from resting on the table."""
        p = self.params
        idx = self.index
        X = initial_pose(idx.R_CO[idx.view[entry]], idx.junctions[entry], g_junc, K, idx.params)
        if p.table_prior:
            # Before any fitting: the view must show the object standing on one of its faces,
            # roughly at table height (most accidental matches fail this at no cost).
            X_WO = X_WC @ X
            n_W = self._facets[model.name][0] @ X_WO[:3, :3].T
            if -n_W[:, 2].min() < np.cos(p.prefilter_tilt_rad):
                return None
            z_min = transform(X_WO, model.vertices_O)[:, 2].min()
            if abs(z_min - self.table_z) > p.prefilter_height_m:
                return None
        edges = model.edges_O[idx.edges[entry]]
        fit = fit_pose(
            X, edges, segs[g_segs], K, iterations=p.fit_iterations, tol=p.fit_tol,
            prior=self._prior(model, X_WC),
        )  # fmt: skip
        if fit.rms_px > p.init_rms_max_px or fit.X_CO[2, 3] <= 0.05:
            return None
        V_W = transform(X_WC @ fit.X_CO, model.vertices_O)
        if abs(V_W[:, 2].min() - self.table_z) > p.early_table_tol_m:
            return None
        return fit.X_CO

    def _prior(self, model: VisionModel, X_WC: np.ndarray):
        """Residuals (px-equivalents) saying the object rests on a face on the table, or None
        when the prior is off. Applied softly, so that the lines still decide."""
        if not self.params.table_prior:
            return None
        p = self.params
        N_O, _ = self._facets[model.name]
        R_WC = X_WC[:3, :3]
        g = R_WC[2]  # world z of a camera-frame vector

        def prior(X_CO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            # The update rotates by ω about O's origin in C and shifts by v in C (pose.py):
            # a vertex moves by ω × Q + v, a normal turns by (R_WC ω) × n_W.
            X_WO = X_WC @ X_CO
            n_W = N_O @ X_WO[:3, :3].T
            down = n_W[np.argmin(n_W[:, 2])]
            Q = model.vertices_O @ X_CO[:3, :3].T
            z = (Q + X_CO[:3, 3]) @ g + X_WC[2, 3]
            k = int(np.argmin(z))
            a, b = p.table_prior_px_per_m, p.table_prior_px_per_rad
            r = np.array([a * (z[k] - self.table_z), b * down[0], b * down[1]])
            J = np.zeros((3, 6))
            q = Q[k]
            J[0, :3] = a * np.array(
                [q[1] * g[2] - q[2] * g[1], q[2] * g[0] - q[0] * g[2], q[0] * g[1] - q[1] * g[0]]
            )
            J[0, 3:] = a * g
            # down × e_x = (0, d_z, −d_y); down × e_y = (−d_z, 0, d_x)
            J[1, :3] = b * (R_WC.T @ np.array([0.0, down[2], -down[1]]))
            J[2, :3] = b * (R_WC.T @ np.array([-down[2], 0.0, down[0]]))
            return r, J

        return prior

    def _test(self, model, X, segs, K, gx, gy, occluders_C, X_WC=None):
        """Predict further correspondences, refit and verify; None if the pose does not hold."""
        p = self.params
        prior = self._prior(model, X_WC) if X_WC is not None else None
        if self._quick_support(model, X, K, gx, gy, occluders_C) < p.quick_support_min:
            return None
        mi = mj = np.zeros(0, int)
        fit = None
        pairs = None
        for r in range(p.refine_rounds):
            tol = p.match_tol_px[min(r, len(p.match_tol_px) - 1)]
            ids, proj, _ = visible_edges(model, X, K, occluders_C)
            mi, mj = match_segments(proj, segs, tol, p.match_angle_rad)
            if len(np.unique(mi)) < 4:
                return None
            now = (ids[mi].tobytes(), mj.tobytes())
            if now == pairs:
                continue  # the same correspondences as the last fit: it would not move
            pairs = now
            fit = fit_pose(
                X, model.edges_O[ids[mi]], segs[mj], K, iterations=p.fit_iterations,
                tol=p.fit_tol, prior=prior,
            )  # fmt: skip
            X = fit.X_CO
        if fit is None:
            return None
        if fit.rms_px > p.final_rms_max_px or len(np.unique(mi)) < p.min_matched_edges:
            return None
        v = self._verify(model, X, K, segs, gx, gy, occluders_C)
        if v.length_fraction < p.min_length_fraction or v.score < p.min_score:
            return None
        return X, fit.rms_px, v

    def _quick_support(self, model: VisionModel, X_CO, K, gx, gy, occluders_C) -> float:
        """Cheap test of a pose before any refinement: the fraction of points along its
        predicted visible edges where the image gradient, within ±1.5 px across the edge, is
        strong and at right angles to it."""
        p = self.params
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
        n = np.column_stack([-u[:, 1], u[:, 0]])
        k = 6  # points per edge
        t = (np.arange(k) + 0.5) / k
        P = proj[:, None, :2] + t[None, :, None] * d[:, None, :]  # (e, k, 2)
        N = np.broadcast_to(n[:, None, :], P.shape)
        best = np.zeros(P.shape[:2], dtype=bool)
        for off in (-1.5, 0.0, 1.5):
            Q = (P + off * N).reshape(-1, 2).astype(np.float32)
            sx = cv2.remap(gx, Q[:, :1], Q[:, 1:], cv2.INTER_LINEAR).reshape(P.shape[:2])
            sy = cv2.remap(gy, Q[:, :1], Q[:, 1:], cv2.INTER_LINEAR).reshape(P.shape[:2])
            mag = np.hypot(sx, sy)
            cos = np.abs(sx * N[..., 0] + sy * N[..., 1]) / np.maximum(mag, 1e-9)
            best |= (mag > p.gradient_min) & (cos > np.cos(p.gradient_angle_rad))
        return float(best.mean())

    def _verify(self, model: VisionModel, X_CO, K, segs, gx, gy, occluders_C):
        """Fractions of the visible projected edge length matched by image lines and with the
        image gradient across them, plus the image segments matched."""
        p = self.params
        _, proj, _ = visible_edges(model, X_CO, K, occluders_C)
        h, w = gx.shape
        # Clip to the image: an edge beyond the border is unseen, not missing.
        proj = _clip_segments(proj, w, h)
        L = np.linalg.norm(proj[:, 2:] - proj[:, :2], axis=1)
        keep = L >= 4.0
        proj, L = proj[keep], L[keep]
        if len(proj) == 0 or L.sum() < 20:
            return Verification(0.0, 0.0, 0.0, [], 0.0)
        mi, mj = match_segments(proj, segs, p.verify_tol_px, p.verify_angle_rad)
        covered = 0.0
        for e in range(len(proj)):
            rows = mj[mi == e]
            if len(rows) == 0:
                continue
            a = proj[e, :2]
            u = (proj[e, 2:] - a) / L[e]
            t = np.sort(np.column_stack([(segs[rows, :2] - a) @ u, (segs[rows, 2:] - a) @ u]), 1)
            t = np.clip(t, 0.0, L[e])
            covered += _union_length(t)
        frac_len = covered / L.sum()
        # Gradient direction agreement sampled every 1.5 px along every visible edge.
        pts, normals = [], []
        for e in range(len(proj)):
            a, b = proj[e, :2], proj[e, 2:]
            u = (b - a) / L[e]
            ts = np.arange(1.0, L[e] - 1.0, 1.5)
            pts.append(a + ts[:, None] * u)
            normals.append(np.repeat([[-u[1], u[0]]], len(ts), axis=0))
        P = np.vstack(pts).astype(np.float32)
        N = np.vstack(normals)
        sx = cv2.remap(gx, P[:, :1], P[:, 1:], cv2.INTER_LINEAR).ravel()
        sy = cv2.remap(gy, P[:, :1], P[:, 1:], cv2.INTER_LINEAR).ravel()
        mag = np.hypot(sx, sy)
        cosang = np.abs(sx * N[:, 0] + sy * N[:, 1]) / np.maximum(mag, 1e-9)
        good = (mag > p.gradient_min) & (cosang > np.cos(p.gradient_angle_rad))
        frac_grad = float(np.mean(good)) if len(good) else 0.0
        # The outline against the background must show in the image almost everywhere: a
        # hypothesis that explains one block and hangs over empty table fails here.
        uv = project(transform(X_CO, model.vertices_O), K).astype(np.float32)
        hull = cv2.convexHull(uv)
        on_hull = np.array(
            [abs(cv2.pointPolygonTest(hull, (float(x), float(y)), True)) < 1.0 for x, y in P]
        )
        frac_sil = float(np.mean(good[on_hull])) if on_hull.any() else 0.0
        return Verification(float(frac_len), frac_grad, frac_sil, mj.tolist(), float(covered))

    def _plausible(
        self, parts_W: list[tuple], accepted: list[list[tuple]], environment: bool = True
    ) -> bool:
        """Rests on the table inside the work area; interpenetrates nothing accepted (nor the
        fixed environment, if ``environment``). Parts are (vertices (n, 3), face normals (k, 3))
        in W."""
        p = self.params
        V = np.vstack([v for v, _ in parts_W])
        if abs(V[:, 2].min() - self.table_z) > p.table_tol_m:
            return False
        c = V[:, :2].mean(0)
        lo, hi = self.work_area_xy
        if np.any(c < lo) or np.any(c > hi):
            return False
        others = [q for parts in accepted for q in parts]
        if environment:
            others += [
                q for name, _, parts, _ in self.environment if name != "table" for q in parts
            ]
        for a, na in parts_W:
            for b, nb in others:
                if np.linalg.norm(a.mean(0) - b.mean(0)) > _radius(a) + _radius(b):
                    continue
                if convex_overlap_depth(a, b, na, nb) > p.max_penetration_m:
                    return False
        return True


def _radius(V: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(V - V.mean(0), axis=1)))


def _union_length(t: np.ndarray) -> float:
    """Total length of the union of intervals (n, 2) with lo ≤ hi."""
    t = t[np.argsort(t[:, 0])]
    total, cur_lo, cur_hi = 0.0, t[0, 0], t[0, 1]
    for lo, hi in t[1:]:
        if lo > cur_hi:
            total += cur_hi - cur_lo
            cur_lo, cur_hi = lo, hi
        else:
            cur_hi = max(cur_hi, hi)
    return float(total + cur_hi - cur_lo)


def _clip_segments(segs: np.ndarray, w: int, h: int) -> np.ndarray:
    """Segments clipped to the image rectangle (Liang–Barsky); fully outside → zero length."""
    out = segs.copy()
    for k, (x0, y0, x1, y1) in enumerate(segs):
        dx, dy = x1 - x0, y1 - y0
        t0, t1 = 0.0, 1.0
        for pp, qq in ((-dx, x0), (dx, w - 1 - x0), (-dy, y0), (dy, h - 1 - y0)):
            if pp == 0:
                if qq < 0:
                    t0, t1 = 1.0, 0.0
                continue
            r = qq / pp
            if pp < 0:
                t0 = max(t0, r)
            else:
                t1 = min(t1, r)
        if t0 >= t1:
            out[k] = [x0, y0, x0, y0]
        else:
            out[k] = [x0 + t0 * dx, y0 + t0 * dy, x0 + t1 * dx, y0 + t1 * dy]
    return out
