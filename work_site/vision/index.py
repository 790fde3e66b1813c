"""Grouping of image lines and indexing of the groups into the models (§IV-A; Beis & Lowe).

A *group* is a chain of four segments ``s0 – s1 – s2 – s3`` joined end to end at three junctions
``J1, J2, J3`` (an end of one segment and an end of the next meet, up to a tolerance). Its index
vector holds the three turning angles at the junctions (as cos/sin pairs, so no wrap-around) and
the log ratio of the two inner lengths ``|J2J3| / |J1J2|``: invariant to 2-D translation,
rotation and scale, varying with the 3-D viewing direction. The free ends of ``s0`` and ``s3``
give only directions, because occlusion shortens outer segments more than inner ones.

The index is built by projecting each model from ``n_views`` directions spread evenly over the
sphere (a Fibonacci lattice), removing hidden edges, grouping the visible edges with the same
code as the image and storing every group's vector with its model edges and view. It is looked
up by exact nearest neighbour (a k-d tree, ``scipy.spatial.cKDTree``) out to the distance where
the kernel weight becomes negligible, and each neighbour becomes a hypothesis ranked by a kernel
estimate of its probability.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from work_site.vision.model import VisionModel, visible_edges

INDEX_FORMAT_VERSION = 3
"""Bumped whenever the stored index's meaning changes; part of the cache key."""


@dataclass(frozen=True)
class GroupParams:
    """How segments are joined into groups (pixels, radians)."""

    junction_tol_px: float = 4.0
    junction_tol_frac: float = 0.2
    min_junction_angle_rad: float = np.deg2rad(12.0)
    min_inner_length_px: float = 6.0
    max_groups: int = 4000


@dataclass(frozen=True)
class IndexParams:
    """How the model index is built and searched."""

    n_views: int = 1200
    view_distance_m: float = 0.85
    canonical_f_px: float = 580.0
    ratio_weight: float = 0.6
    neighbours: int = 6
    kernel_sigma: float = 0.03
    max_distance: float = 0.13  # neighbours are looked for out to this distance only: farther
    # ones weigh exp(−d²/2σ²) < 1e-4 with σ = kernel_sigma, below what the recogniser ranks.
    # The search is exact: FLANN's approximate randomised kd-trees were slower here.


@dataclass(frozen=True)
class Groups:
    """Chains of four segments: ``segs`` (g, 4) indices, ``junctions`` (g, 3, 2) px,
    ``vectors`` (g, 7) index vectors."""

    segs: np.ndarray
    junctions: np.ndarray
    vectors: np.ndarray


def find_junctions(
    segs: np.ndarray, params: GroupParams
) -> list[tuple[int, int, int, int, np.ndarray]]:
    """Pairs of segments whose lines meet near an end of each: ``(i, end_i, j, end_j, X)``."""
    n = len(segs)
    if n < 2:
        return []
    P0, P1 = segs[:, :2], segs[:, 2:]
    D = P1 - P0
    L = np.linalg.norm(D, axis=1)
    i, j = np.triu_indices(n, 1)
    cross = D[i, 0] * D[j, 1] - D[i, 1] * D[j, 0]
    sin = np.abs(cross) / np.maximum(L[i] * L[j], 1e-12)
    ok = sin > np.sin(params.min_junction_angle_rad)
    i, j, cross = i[ok], j[ok], cross[ok]
    W = P0[j] - P0[i]
    s = (W[:, 0] * D[j, 1] - W[:, 1] * D[j, 0]) / cross
    t = (W[:, 0] * D[i, 1] - W[:, 1] * D[i, 0]) / cross
    end_i = (np.abs(1 - s) < np.abs(s)).astype(int)
    end_j = (np.abs(1 - t) < np.abs(t)).astype(int)
    dist_i = np.where(end_i == 1, np.abs(1 - s), np.abs(s)) * L[i]
    dist_j = np.where(end_j == 1, np.abs(1 - t), np.abs(t)) * L[j]
    tol_i = params.junction_tol_px + params.junction_tol_frac * L[i]
    tol_j = params.junction_tol_px + params.junction_tol_frac * L[j]
    # The meeting point must not be deep inside either segment (that is a T, not a corner).
    hit = (dist_i <= tol_i) & (dist_j <= tol_j)
    X = P0[i] + s[:, None] * D[i]
    return [
        (int(a), int(ea), int(b), int(eb), x)
        for a, ea, b, eb, x in zip(i[hit], end_i[hit], j[hit], end_j[hit], X[hit], strict=True)
    ]


def group_segments(
    segs: np.ndarray,
    params: GroupParams | None = None,
    ratio_weight: float = 0.6,
    junctions: list[tuple[int, int, int, int, np.ndarray]] | None = None,
) -> Groups:
    """All chains of four segments joined at three junctions (both directions of each);
    ``ratio_weight`` scales the length-ratio entry of the index vectors. ``junctions``:
    :func:`find_junctions` of ``segs`` with ``params``, if already known."""
    params = params or GroupParams()
    if junctions is None:
        junctions = find_junctions(segs, params)
    adj: dict[tuple[int, int], list[tuple[int, int, np.ndarray]]] = {}
    for a, ea, b, eb, X in junctions:
        adj.setdefault((a, ea), []).append((b, eb, X))
        adj.setdefault((b, eb), []).append((a, ea, X))
    chains, junctions = [], []
    for s1 in range(len(segs)):
        for a in (0, 1):
            left = adj.get((s1, a), [])
            mid = adj.get((s1, 1 - a), [])
            if not left or not mid:
                continue
            for s2, e2, J2 in mid:
                for s3, _e3, J3 in adj.get((s2, 1 - e2), []):
                    if s3 == s1:
                        continue
                    for s0, _e0, J1 in left:
                        if s0 in (s2, s3):
                            continue
                        chains.append((s0, s1, s2, s3))
                        junctions.append((J1, J2, J3))
                        if len(chains) >= params.max_groups:
                            break
    if not chains:
        return Groups(np.zeros((0, 4), int), np.zeros((0, 3, 2)), np.zeros((0, 7)))
    C = np.array(chains, dtype=np.int64)
    J = np.array(junctions, dtype=np.float64)
    inner1 = np.linalg.norm(J[:, 1] - J[:, 0], axis=1)
    inner2 = np.linalg.norm(J[:, 2] - J[:, 1], axis=1)
    ok = (inner1 >= params.min_inner_length_px) & (inner2 >= params.min_inner_length_px)
    C, J = C[ok], J[ok]
    return Groups(C, J, _vectors(segs, C, J, ratio_weight))


def _far_end(segs: np.ndarray, idx: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The end point of each segment ``idx`` farther from the point ``near`` (g, 2)."""
    P0, P1 = segs[idx, :2], segs[idx, 2:]
    d0 = np.linalg.norm(P0 - near, axis=1)
    d1 = np.linalg.norm(P1 - near, axis=1)
    return np.where((d0 > d1)[:, None], P0, P1)


def _turn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.arctan2(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0], np.sum(u * v, axis=1))


def _vectors(segs: np.ndarray, C: np.ndarray, J: np.ndarray, ratio_weight: float = 0.6):
    if len(C) == 0:
        return np.zeros((0, 7))
    d0 = J[:, 0] - _far_end(segs, C[:, 0], J[:, 0])
    d1 = J[:, 1] - J[:, 0]
    d2 = J[:, 2] - J[:, 1]
    d3 = _far_end(segs, C[:, 3], J[:, 2]) - J[:, 2]
    th = np.column_stack([_turn(d0, d1), _turn(d1, d2), _turn(d2, d3)])
    ratio = np.log(np.linalg.norm(d2, axis=1) / np.linalg.norm(d1, axis=1))
    return np.column_stack(
        [np.cos(th[:, 0]), np.sin(th[:, 0]), np.cos(th[:, 1]), np.sin(th[:, 1]),
         np.cos(th[:, 2]), np.sin(th[:, 2]), ratio_weight * ratio]
    )  # fmt: skip


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere, (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def view_rotation(v_O: np.ndarray) -> np.ndarray:
    """``R_CO`` of a camera on the ray ``v_O`` (unit, from O's origin) looking back at O."""
    z = -v_O
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.array([x, y, z])


def canonical_K(params: IndexParams) -> np.ndarray:
    """Intrinsics of the camera the model views are projected with (principal point 0)."""
    f = params.canonical_f_px
    return np.array([[f, 0.0, 0.0], [0.0, f, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class ModelIndex:
    """Index vectors of all model views and what each one stands for.

    ``vectors`` (e, 7) float32; ``model`` (e,) index into ``names``; ``view`` (e,);
    ``edges`` (e, 4) model edge ids; ``junctions`` (e, 3, 2) canonical px;
    ``R_CO`` (n_views, 3, 3) view rotations (shared by all models).
    """

    names: tuple[str, ...]
    vectors: np.ndarray
    model: np.ndarray
    view: np.ndarray
    edges: np.ndarray
    junctions: np.ndarray
    R_CO: np.ndarray
    params: IndexParams
    group_params: GroupParams

    def __post_init__(self) -> None:
        tree = cKDTree(np.asarray(self.vectors, dtype=np.float64)) if len(self.vectors) else None
        object.__setattr__(self, "_tree", tree)

    def query(self, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ``neighbours`` nearest entries of each vector within ``max_distance``: (q, k) ids
        and squared distances, nearest first; where fewer are that near, the rest are id 0 at
        distance ``inf`` (kernel weight 0)."""
        k = min(self.params.neighbours, len(self.vectors))
        if self._tree is None or len(vectors) == 0 or k == 0:  # type: ignore[attr-defined]
            return np.zeros((len(vectors), 0), int), np.zeros((len(vectors), 0))
        d, ids = self._tree.query(  # type: ignore[attr-defined]
            np.asarray(vectors, dtype=np.float64).reshape(len(vectors), -1),
            k=k,
            distance_upper_bound=self.params.max_distance,
        )
        d, ids = d.reshape(len(vectors), k), ids.reshape(len(vectors), k)
        found = np.isfinite(d)
        return np.where(found, ids, 0).astype(np.int64), d * d


def build_index(
    models: Sequence[VisionModel],
    params: IndexParams | None = None,
    group_params: GroupParams | None = None,
) -> ModelIndex:
    """Project every model from every sampled direction and index its edge groups."""
    params = params or IndexParams()
    gp = group_params or GroupParams()
    # Exact projections: junctions meet to rounding, so a tight tolerance suffices.
    model_gp = GroupParams(
        junction_tol_px=0.5,
        junction_tol_frac=0.0,
        min_junction_angle_rad=gp.min_junction_angle_rad,
        min_inner_length_px=gp.min_inner_length_px,
        max_groups=100000,
    )
    K = canonical_K(params)
    dirs = fibonacci_directions(params.n_views)
    R_CO = np.array([view_rotation(v) for v in dirs])
    vec, mod, view, edg, jun = [], [], [], [], []
    for mi, m in enumerate(models):
        for vi in range(len(dirs)):
            X_CO = np.eye(4)
            X_CO[:3, :3] = R_CO[vi]
            X_CO[2, 3] = params.view_distance_m
            ids, segs, _ = visible_edges(m, X_CO, K, min_fraction=0.3)
            if len(ids) < 4:
                continue
            g = group_segments(segs, model_gp, params.ratio_weight)
            if len(g.segs) == 0:
                continue
            v = g.vectors
            vec.append(v)
            mod.append(np.full(len(v), mi))
            view.append(np.full(len(v), vi))
            edg.append(ids[g.segs])
            jun.append(g.junctions)
    if not vec:
        raise ValueError("no model produced any edge group: nothing to index")
    return ModelIndex(
        names=tuple(m.name for m in models),
        vectors=np.vstack(vec).astype(np.float32),
        model=np.concatenate(mod),
        view=np.concatenate(view),
        edges=np.vstack(edg),
        junctions=np.vstack(jun),
        R_CO=R_CO,
        params=params,
        group_params=gp,
    )


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/telerobot/vision`` (``~/.cache/telerobot/vision`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "telerobot" / "vision"


def index_key(
    models: Sequence[VisionModel],
    model_files: Sequence[Path],
    params: IndexParams,
    group_params: GroupParams,
) -> str:
    """A digest of the model files' contents, the derived geometry and the parameters."""
    h = hashlib.sha256()
    h.update(f"v{INDEX_FORMAT_VERSION}".encode())
    h.update(json.dumps([asdict(params), asdict(group_params)], sort_keys=True).encode())
    for path in sorted(Path(p) for p in model_files):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    for m in models:
        h.update(m.name.encode())
        h.update(np.ascontiguousarray(m.edges_O).tobytes())
        for P in m.planes_O:
            h.update(np.ascontiguousarray(P).tobytes())
    return h.hexdigest()[:32]


def load_or_build_index(
    models: Sequence[VisionModel],
    model_files: Sequence[Path],
    params: IndexParams | None = None,
    group_params: GroupParams | None = None,
    cache_dir: Path | None = None,
) -> ModelIndex:
    """The index from the on-disk cache if its key matches, else built and stored there.

    The cache lives in ``cache_dir`` (default :func:`default_cache_dir`), never in the source
    tree; a file that cannot be read is rebuilt, one that cannot be written is skipped.
    """
    params = params or IndexParams()
    gp = group_params or GroupParams()
    key = index_key(models, model_files, params, gp)
    path = (cache_dir or default_cache_dir()) / f"index-{key}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                names = tuple(str(s) for s in z["names"])
                if names == tuple(m.name for m in models):
                    return ModelIndex(
                        names, z["vectors"], z["model"], z["view"], z["edges"],
                        z["junctions"], z["R_CO"], params, gp,
                    )  # fmt: skip
        except (OSError, ValueError, KeyError):
            pass
    index = build_index(models, params, gp)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
        np.savez(
            tmp,
            names=np.array(index.names),
            vectors=index.vectors,
            model=index.model,
            view=index.view,
            edges=index.edges,
            junctions=index.junctions,
            R_CO=index.R_CO,
        )
        os.replace(tmp, path)
    except OSError:
        pass
    return index
