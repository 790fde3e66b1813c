"""Sets of poses: those already tested (to test each pose once), and the selection of the
candidates that explain the image into the accepted set of detections, resolving conflicts
between candidates that share image lines or interpenetrate.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import chi2

from models.transforms import invert_pose
from work_site.vision.model import (
    Occluders,
    VisionModel,
    parts_in,
    planes_in,
    project,
    transform,
    visible_edges,
)
from work_site.vision.params import RecognizerParams
from work_site.vision.verification import Surroundings, Verification, verify


@dataclass(frozen=True)
class Detection:
    """One object found in an image: model name, pose ``X_WO``, score in [0, 1] and diagnostics."""

    model: str
    X_WO: np.ndarray
    score: float
    rms_px: float = 0.0
    length_fraction: float = 0.0
    gradient_fraction: float = 0.0
    matched_segments: tuple[int, ...] = field(default=(), repr=False)
    resting: bool = True  # found resting on a face on the table (fitted with the table prior)

    def __iter__(self):
        """Unpacks as ``(model, X_WO, score)``, the triple the work-site server publishes."""
        return iter((self.model, self.X_WO, self.score))


@dataclass(frozen=True, eq=False)
class Candidate:
    """A pose that passed its own test, waiting for the selection."""

    model: VisionModel
    X_CO: np.ndarray
    X_WO: np.ndarray
    rms_px: float
    verification: Verification
    parts_W: list[tuple[np.ndarray, np.ndarray]]
    part_px: np.ndarray | None = None  # grown around a smaller object found in the image:
    # that object's outline (k, 2) px, a convex polygon
    resting: bool = True  # found resting on the table; if not, it must be held up by what
    # else is found (see select)
    verified_on: np.ndarray | None = field(default=None, repr=False)  # the image lines its
    # verification was made against, with the frame's fixed occluders alone (None: not known)
    off_table: bool = False  # found resting on the table, but a pose of it above the table
    # explains its lines significantly better: weighed after the candidates that are not
    settled_from: Candidate | None = field(default=None, repr=False)  # the candidate this
    # is, moved along its line of sight out of an accepted object (see _settled)

    @property
    def grown(self) -> bool:
        """Made by growing a smaller object found in the image into a bigger model."""
        return self.part_px is not None

    @property
    def origin(self) -> Candidate:
        """The candidate as it was found (itself unless settled)."""
        return self.settled_from if self.settled_from is not None else self


class PoseSet:
    """Poses already tested, per model, to skip equal ones: equal means translations within
    ``same_pose_m`` and rotations within ``same_pose_rad`` up to one of the model's
    symmetries. Kept as growing arrays, so a look-up is a few array operations."""

    def __init__(self, same_pose_m: float, same_pose_rad: float) -> None:
        self.same_pose_m = same_pose_m
        self.cos_min = 1 + 2 * np.cos(same_pose_rad)  # trace of a rotation by that angle
        self._X: dict[str, np.ndarray] = {}  # (capacity, 4, 4) per model name
        self._n: dict[str, int] = {}

    def add(self, model: VisionModel, X_CO: np.ndarray) -> None:
        """Record a tested pose ``X_CO`` of ``model``."""
        n = self._n.get(model.name, 0)
        X = self._X.get(model.name)
        if X is None or n == len(X):
            grown = np.empty((max(16, 2 * n), 4, 4))
            if X is not None:
                grown[:n] = X[:n]
            self._X[model.name] = X = grown
        X[n] = X_CO
        self._n[model.name] = n + 1

    def add_new(self, model: VisionModel, X_CO: np.ndarray) -> np.ndarray:
        """Poses (k, 4, 4) in turn: each is recorded unless equal to one recorded before it
        (earlier in ``X_CO`` included), as :meth:`seen` then :meth:`add` one by one would
        do; returns (k,) bool, True for those recorded."""
        k = len(X_CO)
        new = np.zeros(k, dtype=bool)
        if k == 0:
            return new
        n = self._n.get(model.name, 0)
        R = X_CO[:, :3, :3]
        RS = R[:, None] @ model.symmetries[None]  # (k, s, 3, 3)
        old = np.zeros(k, dtype=bool)
        if n:
            X = self._X[model.name][:n]
            d = X_CO[:, None, :3, 3] - X[None, :, :3, 3]
            near = np.einsum("kni,kni->kn", d, d) <= self.same_pose_m**2  # (k, n)
            ki, ni = np.nonzero(near)
            if len(ki):
                tr = np.einsum("mij,msij->ms", X[ni, :3, :3], RS[ki])
                old[ki[np.any(tr > self.cos_min, axis=1)]] = True
        d = X_CO[:, None, :3, 3] - X_CO[None, :, :3, 3]
        close = np.einsum("abi,abi->ab", d, d) <= self.same_pose_m**2  # (k, k)
        ai, bi = np.nonzero(np.tril(close, -1))  # b recorded before a
        if len(ai):
            tr = np.einsum("mij,msij->ms", R[bi], RS[ai])
            eq = np.any(tr > self.cos_min, axis=1)
            ai, bi = ai[eq], bi[eq]
        if len(ai) == 0:
            new = ~old  # no two of them equal (the usual case): no order to follow
        else:
            same = np.zeros((k, k), dtype=bool)
            same[ai, bi] = True
            for a in range(k):
                new[a] = not old[a] and not (same[a, :a] & new[:a]).any()
        self._add_all(model, X_CO[new])
        return new

    def _add_all(self, model: VisionModel, X_CO: np.ndarray) -> None:
        """Record poses (k, 4, 4) of ``model``, as :meth:`add` on each in turn."""
        k = len(X_CO)
        n = self._n.get(model.name, 0)
        X = self._X.get(model.name)
        if X is None or n + k > len(X):
            grown = np.empty((max(16, 2 * (n + k)), 4, 4))
            if X is not None:
                grown[:n] = X[:n]
            self._X[model.name] = X = grown
        X[n : n + k] = X_CO
        self._n[model.name] = n + k

    def seen(self, model: VisionModel, X_CO: np.ndarray) -> bool:
        """Whether a pose of ``model`` equal to ``X_CO`` up to its symmetries was recorded."""
        n = self._n.get(model.name, 0)
        if n == 0:
            return False
        X = self._X[model.name][:n]
        d = X[:, :3, 3] - X_CO[:3, 3]
        near = np.einsum("ki,ki->k", d, d) <= self.same_pose_m**2
        if not near.any():
            return False
        # trace(R_tᵀ·R·S) for every near tested R_t and symmetry S
        RS = X_CO[:3, :3] @ model.symmetries  # (s, 3, 3)
        tr = np.einsum("kij,sij->ks", X[near, :3, :3], RS)
        return bool(np.any(tr > self.cos_min))


def select(
    candidates: list[Candidate],
    segs: np.ndarray,
    K: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    occluders_C,
    params: RecognizerParams,
    surroundings: Surroundings,
    max_height_m: float = 0.0,
) -> list[Detection]:
    """Candidates that explain the most image edge length first; a candidate sharing many
    image lines with, or interpenetrating, one already accepted is dropped; an accepted
    candidate grown around a smaller object stands only if the selection without it explains
    no more of the image's lines. Each is
    verified again with the other candidates as occluders, and its outline must show. A
    candidate not found resting on the table must be held up by the table, the fixed
    environment or another accepted object; one that is not is dropped and the selection made
    again without it (an object floating in the air is not there), unless its score
    reaches ``hidden_support_min_score``: then what holds it up is hidden (a block under a
    block). That is the last explanation: where another pose of the same object rests on the
    table (a candidate of its model that shares its lines), the selection made without the
    floating one stands if it takes that pose."""

    def once(kept: list[Candidate]) -> list[tuple[Candidate, Detection]]:
        return _select_once(kept, segs, K, gx, gy, occluders_C, params, surroundings, max_height_m)

    pool = list(candidates)
    accepted, held = _select_held(pool, once, surroundings, params)
    # A candidate grown around a smaller object (an L around what is a tall block) can take
    # that object's lines and its own model's place first, and leave the true object of that
    # model to be explained as something else: the selection without it stands when it
    # explains more of the image's lines.
    length_px = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    for _ in range(len(candidates)):  # each round takes one candidate out of the pool
        for c, _ in accepted:
            if not c.grown:
                continue
            without = [o for o in pool if o is not c.origin]
            again, held_again = _select_held(without, once, surroundings, params)
            if _explained_px(again, length_px) > _explained_px(accepted, length_px):
                pool, accepted, held = without, again, held_again
                break
        else:
            break
    for _ in range(len(candidates)):  # each round takes one candidate out of the pool
        for (c, _), h in zip(accepted, held, strict=True):
            if h or not any(_other_pose_resting(o, c, params) for o in pool):
                continue
            without = [o for o in pool if o is not c.origin]
            again, held_again = _select_held(without, once, surroundings, params)
            if any(
                h2 and _other_pose_resting(o, c, params)
                for (o, _), h2 in zip(again, held_again, strict=True)
            ):
                pool, accepted, held = without, again, held_again
                break
        else:
            break
    return sorted((d for _, d in accepted), key=lambda r: -r.score)


def _explained_px(accepted: list[tuple[Candidate, Detection]], length_px: np.ndarray) -> float:
    """The image lines' length (px) that the accepted objects explain together."""
    matched = set().union(*(d.matched_segments for _, d in accepted)) if accepted else set()
    return float(length_px[list(matched)].sum()) if matched else 0.0


def _other_pose_resting(o: Candidate, c: Candidate, params: RecognizerParams) -> bool:
    """Whether ``o`` is another pose of ``c``'s object, found resting on the table (and not
    rejected there by its lines): the same model, sharing more of ``c``'s image lines than two
    objects side by side do."""
    if o.origin is c.origin or o.model is not c.model or not o.resting or o.off_table:
        return False
    return shares_lines(c, set(o.verification.matched), params)


def shares_lines(c: Candidate, lines: set[int], params: RecognizerParams) -> bool:
    """Whether ``c`` shares more of its image lines with ``lines`` than two objects side by
    side do (so the two are poses of one object)."""
    shared = len(lines.intersection(c.verification.matched))
    return shared > params.max_shared_fraction * max(len(c.verification.matched), 1)


def _select_held(
    candidates: list[Candidate],
    once: Callable[[list[Candidate]], list[tuple[Candidate, Detection]]],
    surroundings: Surroundings,
    params: RecognizerParams,
) -> tuple[list[tuple[Candidate, Detection]], list[bool]]:
    """:func:`select` but for its last resort, each round made by ``once`` (a
    :func:`_select_once` on the image): the accepted candidates with their detections, and
    for each whether what is found holds it up (if not, its score kept it)."""
    banned: set[int] = set()
    for _ in range(len(candidates) + 1):
        kept = [c for k, c in enumerate(candidates) if k not in banned]
        accepted = once(kept)
        parts = [c.parts_W for c, _ in accepted]
        held = [c.resting for c, _ in accepted]
        for _ in range(len(accepted)):  # held up by what is held up, level by level
            more = [
                k
                for k, (c, _) in enumerate(accepted)
                if not held[k]
                and surroundings.supported_by(
                    c.parts_W, [parts[j] for j in range(len(accepted)) if held[j]], params
                )
            ]
            if not more:
                break
            for k in more:
                held[k] = True
        floating = [
            c.origin
            for (c, d), h in zip(accepted, held, strict=True)
            if not h and d.score < params.hidden_support_min_score
        ]
        if not floating:
            return accepted, held
        banned.update(k for k, c in enumerate(candidates) if any(c is f for f in floating))
    raise AssertionError("unreachable: every round bans a candidate")


def _verified_among(
    c: Candidate,
    segs: np.ndarray,
    K: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    occluders_C: Occluders,
    others: Occluders,
    params: RecognizerParams,
) -> Verification:
    """``c`` verified against ``segs`` with ``others`` (other candidates' parts) hiding it too.
    Its own verification is that result when it was made against the same lines (and with no
    grown part's test) and ``others`` hide none of the edges it weighed: it is not redone."""
    own = c.verification
    same_lines = (
        c.verified_on is not None
        and c.part_px is None
        and own.edges_px is not None
        and (c.verified_on is segs or np.array_equal(c.verified_on, segs))
    )
    if same_lines and not others.relevant(transform(c.X_CO, c.model.edges_O).reshape(-1, 3), K):
        return own
    occluders = occluders_C + others
    _, proj, _ = visible_edges(c.model, c.X_CO, K, occluders)
    if same_lines and np.array_equal(proj, own.edges_px):
        return own
    return verify(c.model, c.X_CO, K, segs, gx, gy, occluders, params, proj, part_px=c.part_px)


def _shows(c: Candidate, v: Verification, p: RecognizerParams) -> bool:
    """Whether the image shows ``c`` as verified in ``v`` well enough to accept it. A bigger
    model grown around a smaller object found in the image must show its outline clearly: a
    phantom part over empty table is the usual false object."""
    sil_min = p.grown_min_silhouette_fraction if c.grown else p.min_silhouette_fraction
    return (
        v.silhouette_fraction >= sil_min
        and v.score >= p.min_score
        and v.length_fraction >= p.min_length_fraction
        and v.extra_fraction >= p.grown_min_extra_fraction
    )


SETTLE_STEPS = 8
"""Places tried on each side of a candidate along its line of sight when settling it."""


def _settled(
    c: Candidate,
    accepted_parts: list[list[tuple]],
    surroundings: Surroundings,
    p: RecognizerParams,
    K: np.ndarray,
    height_m: float,
) -> Candidate | None:
    """``c`` (found above the table) moved along its line of sight, the direction one view
    tells least (its pose's translation scaled), to the nearest place where it interpenetrates
    nothing accepted (and lies at most ``height_m`` above the table); None if there is none
    that its lines accept. Two blocks one on the other, each fitted a millimetre or so off
    along its own ray, then touch instead of overlapping.

    The lines accept a move if the squared distances its visible edges' ends move across them,
    in units of the fit's rms residual, sum to no more than χ² with one degree of freedom (the
    depth) exceeds with probability ``table_rejection_p``, the significance at which the
    lines also reject the table (:func:`~.pose.constraint_p_value`)."""
    if not c.rms_px > 0.0 or p.table_rejection_p <= 0.0:
        return None
    ids, _, _ = visible_edges(c.model, c.X_CO, K)
    ends_O = c.model.edges_O[ids].reshape(-1, 3)
    uv0 = project(transform(c.X_CO, ends_O), K).reshape(-1, 2, 2)
    along = uv0[:, 1] - uv0[:, 0]
    normal = np.column_stack([-along[:, 1], along[:, 0]])
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-12)[:, None]
    limit = float(chi2.isf(p.table_rejection_p, 1)) * c.rms_px**2

    def moved(scale: float) -> tuple[np.ndarray, float]:
        X = c.X_CO.copy()
        X[:3, 3] *= scale
        d = project(transform(X, ends_O), K).reshape(-1, 2, 2) - uv0
        return X, float(np.sum(np.einsum("eki,ei->ek", d, normal) ** 2))

    # The sum grows with the square of the scale's change: the change that reaches the limit,
    # from a small one.
    probe = 1e-4
    per_change2 = moved(1.0 + probe)[1] / probe**2
    if not per_change2 > 0.0:
        return None
    reach = np.sqrt(limit / per_change2)
    X_WC = c.X_WO @ invert_pose(c.X_CO)
    for k in range(1, SETTLE_STEPS + 1):
        for sign in (-1.0, 1.0):  # towards the camera first: up, off what it sits on
            X_CO, moved_px2 = moved(1.0 + sign * reach * k / SETTLE_STEPS)
            if moved_px2 > limit or np.any(transform(X_CO, c.model.vertices_O)[:, 2] <= 0.0):
                continue
            X_WO = X_WC @ X_CO
            parts_W = parts_in(X_WO, c.model)
            if surroundings.plausible(parts_W, accepted_parts, p, False, height_m):
                return replace(
                    c, X_CO=X_CO, X_WO=X_WO, parts_W=parts_W, verified_on=None, settled_from=c
                )
    return None


def _select_once(
    candidates: list[Candidate],
    segs: np.ndarray,
    K: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    occluders_C,
    params: RecognizerParams,
    surroundings: Surroundings,
    max_height_m: float,
) -> list[tuple[Candidate, Detection]]:
    """One round of :func:`select`, without the support test: the accepted candidates and
    their detections."""
    p = params
    accepted: list[tuple[Candidate, Detection]] = []
    accepted_parts: list[list[np.ndarray]] = []
    used: set[int] = set()
    taken: set[int] = set()  # indices in order of the accepted
    per_model: dict[str, int] = {}
    order = sorted(candidates, key=lambda c: (c.off_table, -c.verification.covered_px))
    # Each candidate's parts as occluders (with their images' boxes, so that each other
    # candidate tests only those that can hide it) and its matched lines, once for all
    parts = [
        Occluders.of_parts(
            [transform(o.X_CO, V) for V in o.model.parts_vertices_O],
            [planes_in(o.X_CO, P) for P in o.model.planes_O],
            K,
        )
        for o in order
    ]
    lines = [set(o.verification.matched) for o in order]
    for i, c in enumerate(order):
        rec = c.verification
        if p.max_per_model is not None and per_model.get(c.model.name, 0) >= p.max_per_model:
            continue
        shared = len(used.intersection(rec.matched))
        if shared > p.max_shared_fraction * max(len(rec.matched), 1):
            continue
        mine = lines[i]
        # Objects accepted already hide what is behind them; another candidate does so only
        # if it explains other lines (one that shares mine may be another guess at my object).
        others = Occluders.joined(
            [
                parts[j]
                for j in range(len(order))
                if j != i and (j in taken or mine.isdisjoint(lines[j]))
            ]
        )
        v = _verified_among(c, segs, K, gx, gy, occluders_C, others, p)
        if not _shows(c, v, p):
            continue
        height = 0.0 if c.resting else max_height_m
        if not surroundings.plausible(c.parts_W, accepted_parts, p, False, height):
            settled = None if c.resting else _settled(c, accepted_parts, surroundings, p, K, height)
            if settled is None:
                continue
            v = _verified_among(settled, segs, K, gx, gy, occluders_C, others, p)
            if not _shows(settled, v, p):
                continue
            c = replace(settled, verification=v)
            rec = v
        accepted.append(
            (
                c,
                Detection(
                    model=c.model.name,
                    X_WO=c.X_WO,
                    score=v.score,
                    rms_px=c.rms_px,
                    length_fraction=v.length_fraction,
                    gradient_fraction=v.gradient_fraction,
                    matched_segments=tuple(rec.matched),
                    resting=c.resting,
                ),
            )
        )
        accepted_parts.append(c.parts_W)
        taken.add(i)
        used.update(rec.matched)
        per_model[c.model.name] = per_model.get(c.model.name, 0) + 1
    return accepted
