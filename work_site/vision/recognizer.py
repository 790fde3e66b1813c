"""Recognition and location of known objects in one grey image (§IV-A), with verification
better than the paper's "50 % of visible edge length" (§VII-A).

Pipeline: lines → groups → index look-up → probability-ranked hypotheses (:mod:`.hypotheses`);
for each hypothesis in turn, an initial pose from the group's junctions and the indexed view,
Lowe's least-squares fit, prediction of further edge correspondences and refitting; then
verification (:mod:`.verification`): matched visible edge length, agreement of the image
gradient's direction along every predicted edge, a final residual bound, no interpenetration
with accepted objects or the fixed environment, and the object inside the work area, resting
on the table or held up by what else is found. The table's hypotheses and prior come first, as
a fast first guess; then the same junction hypotheses on the found blocks' upward faces, as on
tables at their heights (blocks on blocks); then the hypotheses they set aside are fitted
without the prior (leaning, any way up). The arm, at the joint angles given with the image, is
part of the environment (:mod:`.robot_parts`). The selection of the candidates that explain the
image best is in :mod:`.pose_sets`, the tuning in :mod:`.params`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from models.robot import load_robot
from models.scene import CameraModel, ObjectModel, Scene, load_scene
from models.transforms import invert_pose
from work_site.vision.hypotheses import (
    grown_poses,
    index_hypotheses,
    index_stream,
    initial_fit,
    resting_prior,
    table_stream,
    turned_poses,
)
from work_site.vision.index import (
    GroupParams,
    IndexParams,
    ModelIndex,
    find_junctions,
    load_or_build_index,
)
from work_site.vision.lines import (
    FAINT_LINE_PARAMS,
    LineParams,
    check_grey_image,
    detect_lines,
    image_gradients,
)
from work_site.vision.model import (
    Occluders,
    VisionModel,
    containments,
    hull_facets,
    parts_in,
    planes_in,
    project,
    transform,
    visible_edges,
    vision_model,
)
from work_site.vision.params import ENV_MATCH_TOL_PX, RecognizerParams
from work_site.vision.pose import constraint_p_value
from work_site.vision.pose_sets import Candidate, Detection, PoseSet, select, shares_lines
from work_site.vision.robot_parts import RobotParts
from work_site.vision.table import rest_corners
from work_site.vision.verification import (
    Surroundings,
    Verification,
    fit_and_verify,
    match_segments,
    verify,
)

FACE_TOL_M = 1e-9
"""A model vertex this close to a hull face's plane is on the face."""
FAINT_SAME_LINE_PX = 1.5
FAINT_SAME_LINE_RAD = np.deg2rad(3.0)
"""A faint-pass line within these of a first-pass one, at both ends and in direction, is that
line found again."""
TEST_FIT_ITERATIONS = 30
"""Levenberg–Marquardt iterations of each fit a statistical test compares: both fits converge
(the fits of the search need not; their later rounds refit)."""
SUPPORT_HEIGHT_MERGE_M = 1e-3
"""Found faces this close in height (blocks of one size side by side) share one set of stacked
hypotheses: the fit without the prior settles the height."""


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


@dataclass(frozen=True, eq=False)
class _Frame:
    """One image as every hypothesis test sees it."""

    segs: np.ndarray  # (n, 4) image lines (px), those of the fixed environment set aside
    K: np.ndarray  # (3, 3)
    X_WC: np.ndarray  # (4, 4)
    gx: np.ndarray  # (h, w) image gradient
    gy: np.ndarray
    env: _EnvView  # the fixed environment and the robot, as this camera sees them
    t0: float  # time.perf_counter() at the start, for the time budget
    n_strong: int  # segs[:n_strong] are the first pass's lines, from which hypotheses come
    # and are fitted and verified; the faint pass's after them only weigh in the selection
    img: np.ndarray  # the image undistorted, for a later line pass
    first_px: np.ndarray  # the first pass's lines before the environment's were set aside
    rects: list[tuple[int, int, int, int]] | None  # where lines were looked for (None: all);
    # the image and its gradients are zero outside

    @property
    def strong(self) -> np.ndarray:
        return self.segs[: self.n_strong]

    @property
    def occluders_C(self) -> Occluders:
        """The fixed environment and the robot's parts, in C."""
        return self.env.occluders_C


@dataclass(eq=False)
class _Search:
    """The state of one image's search: the candidates found so far and what they claim."""

    claimed: np.ndarray  # (n,) bool: image lines explained by a confident candidate
    tested: PoseSet
    candidates: list[Candidate] = field(default_factory=list)
    confident: set[str] = field(default_factory=set)  # models found with a confident score


class _EnvView:
    """The fixed environment and the robot seen from one camera pose: their parts as occluders
    in C and, worked out when first needed, each model's visible edges in the image."""

    def __init__(
        self, occluders_C: Occluders, K: np.ndarray, models_C: list[tuple[VisionModel, np.ndarray]]
    ) -> None:
        self.occluders_C, self._K, self._models_C = occluders_C, K, models_C
        self._boxes_px: list[np.ndarray | None] = []
        for model, X_CO in models_C:
            V_C = transform(X_CO, model.vertices_O)
            if np.all(V_C[:, 2] > 1e-9):
                uv = project(V_C, K)
                self._boxes_px.append(np.concatenate([uv.min(0), uv.max(0)]))
            else:  # reaches behind the camera: no image box to cull by
                self._boxes_px.append(None)
        self._edges_px: dict[int, np.ndarray] = {}

    def explained(self, segs: np.ndarray) -> np.ndarray:
        """Which image segments (bool, one per row of ``segs``) the models' projected edges
        explain: set aside, since the frame's many corners would otherwise flood the
        hypotheses, and the robot's fingers look like a plank."""
        explained = np.zeros(len(segs), dtype=bool)
        if len(segs) == 0:
            return explained
        lo = np.minimum(segs[:, :2], segs[:, 2:]) + ENV_MATCH_TOL_PX
        hi = np.maximum(segs[:, :2], segs[:, 2:]) - ENV_MATCH_TOL_PX
        for k, (model, X_CO) in enumerate(self._models_C):
            box = self._boxes_px[k]
            # A line a model explains lies within its image's box (within the tolerance):
            # models far from every line need no edges projected.
            if box is not None and not np.any(
                np.all(lo >= box[:2], axis=1) & np.all(hi <= box[2:], axis=1)
            ):
                continue
            if k not in self._edges_px:
                self._edges_px[k] = visible_edges(model, X_CO, self._K, self.occluders_C)[1]
            _, mj = match_segments(self._edges_px[k], segs, ENV_MATCH_TOL_PX, np.deg2rad(3.0))
            explained[mj] = True
        return explained


class Recognizer:
    """Recognises a fixed set of object models in grey images.

    ``models``: the objects to look for (default: the movable objects of ``scene``).
    ``scene`` (default: the puzzle scene): its fixed objects, at their poses ``X_WO``, are the
    environment: their image lines are set aside, they occlude, nothing may interpenetrate
    them; the one named ``table`` gives the table height and the work area. The model index is
    loaded from ``cache_dir`` (default: the user cache) or built there (a few seconds).
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
        self._by_name = {m.name: m for m in self.models}
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
        self._turned = {m.name: turned_poses(m) for m in self.models}
        self._facets = {
            m.name: (
                np.array([n for n, _ in hull_facets(m.vertices_O)]),
                np.array([d for _, d in hull_facets(m.vertices_O)]),
            )
            for m in self.models
        }
        self._corners = rest_corners(self.models, [m.com_O for m in self.object_models])
        self._max_height_m = float(
            sum(np.max(np.linalg.norm(m.vertices_O - m.vertices_O.mean(0), axis=1)) * 2
                for m in self.models)
        )  # fmt: skip
        self._robot = RobotParts(load_robot(scene.robot.urdf_path), scene.robot.X_WB)
        self._env_models = [(vision_model(o.model), o.X_WO) for o in scene.objects if o.fixed]
        self._maps_key: tuple | None = None
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        self._env_key: tuple | None = None
        self._env: _EnvView | None = None
        table = [o for o in scene.objects if o.fixed and o.name == "table"]
        if table:
            t = table[0]
            corners = transform(t.X_WO, t.model.bbox_O)
            table_z = float(corners[:, 2].max())
            work_area_xy = (corners[:, :2].min(0), corners[:, :2].max(0))
        else:
            table_z = 0.0
            work_area_xy = (np.array([-np.inf, -np.inf]), np.array([np.inf, np.inf]))
        # The fixed parts that objects may not interpenetrate: all but the table's.
        self.surroundings = Surroundings(
            table_z,
            work_area_xy,
            [q for name, _, parts, _ in self.environment if name != "table" for q in parts],
        )

    def with_params(self, params: RecognizerParams) -> Recognizer:
        """A recogniser like this one (sharing its index and models) with other parameters."""
        clone = object.__new__(Recognizer)
        clone.__dict__.update(self.__dict__)
        clone.params = params
        return clone

    @property
    def robot(self) -> RobotParts:
        """The arm as vision sees it: its links' models, placed by joint angles."""
        return self._robot

    @property
    def max_height_m(self) -> float:
        """How high above the table an object's lowest point may be: on all the others piled
        up (the sum of their sizes), the most a stack of them can lift it."""
        return self._max_height_m

    @property
    def table_z(self) -> float:
        """Height of the table top in W (m)."""
        return self.surroundings.table_z

    @property
    def work_area_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """The work area: lowest and highest (x, y) in W (m)."""
        return self.surroundings.work_area_xy

    # -- the public entry point ------------------------------------------------------------
    def recognize(
        self,
        image: np.ndarray,
        camera: CameraModel,
        robot_q_rad: np.ndarray | None = None,
        finger_opening_m: float = 0.0,
    ) -> list[Detection]:
        """Objects found in ``image`` (grey uint8, camera's size), best score first.

        ``robot_q_rad`` (6,): the arm's joint angles when the image was taken (and the
        gripper's opening, m): the robot's lines are then set aside and it hides what is behind
        it. Raises ValueError for an unusable image, camera or joint state; an image with
        nothing recognisable gives an empty list.
        """
        f = self._frame(image, camera, self._robot_at(robot_q_rad, finger_opening_m))
        if len(f.strong) < 4:
            return []
        p = self.params
        junctions = find_junctions(f.strong, self.group_params)  # for both kinds of hypotheses
        hyps = (
            index_hypotheses(
                self.index, self.group_params, f.strong, p, p.max_hypotheses, junctions
            )
            if p.max_hypotheses > 0
            else []
        )
        s = _Search(np.zeros(len(f.segs), dtype=bool), PoseSet(p.same_pose_m, p.same_pose_rad))
        stream = table_stream(
            self._corners, self.models, self.group_params, self.table_z,
            f.strong, f.K, f.X_WC, f.gx, f.gy, p, junctions,
        )  # fmt: skip
        resting, free = index_stream(
            hyps, self.index, self.models, self._facets, self.table_z, f.K, f.X_WC, p,
            self.max_height_m,
        )  # fmt: skip
        passed = self._search(stream + resting, f, s)
        accepted = self._select(s, f)
        # A confident candidate that the selection drops (a phantom, such as a wedge fitted
        # into a neighbour's corner) has kept its model's and its lines' other hypotheses from
        # being tested: test those now, with only the accepted objects claiming, for models
        # not accepted yet (retrying those too let phantoms displace true objects).
        self._claimed_by(accepted, s)
        n_before = len(s.candidates)
        self._search(
            [h for h in passed if not s.claimed[h[1]].all() and h[0].name not in s.confident],
            f,
            s,
        )
        if len(s.candidates) > n_before:
            accepted = self._select(s, f)
        if p.stacked_search and p.table_hypotheses and accepted:
            self._claimed_by(accepted, s)
            n_before = len(s.candidates)
            self._stacked(accepted, f, s, junctions)
            if len(s.candidates) > n_before:
                accepted = self._select(s, f)
        if not p.free_search or not free:
            return accepted
        # What is left may not rest on the table: on other blocks, leaning, any way up. Fit
        # those hypotheses without the table prior; the selection then keeps only objects
        # held up by what else is found.
        self._claimed_by(accepted, s)
        n_before = len(s.candidates)
        self._unpriored(accepted, f, s)
        self._search(free, f, s, resting=False)
        return self._select(s, f) if len(s.candidates) > n_before else accepted

    def track(
        self,
        image: np.ndarray,
        camera: CameraModel,
        previous: Sequence[Detection],
        robot_q_rad: np.ndarray | None = None,
        finger_opening_m: float = 0.0,
    ) -> list[Detection]:
        """The objects ``previous`` (an earlier frame's detections) found again in ``image``,
        best score first; those not found are left out (lost).

        Each object's lines are looked for only near its outline predicted from its earlier
        pose (:attr:`RecognizerParams.track_margin_px`), its pose refitted from there as it
        was found (Lowe's fit, the same prediction of further edges, with the table prior if
        it was found resting on the table) and the results selected as :meth:`recognize`
        selects its candidates: the same verification, support and interpenetration tests, so
        a tracked object is one that full recognition would accept at that pose. Nothing new
        is searched for: new objects, and what tracking loses, are for :meth:`recognize`.
        Raises ValueError as :meth:`recognize` does, and for a model it does not know."""
        check_camera(camera)
        X_CW = invert_pose(np.asarray(camera.X_WC, dtype=np.float64))
        K = np.asarray(camera.K, dtype=np.float64)
        starts: list[tuple[VisionModel, np.ndarray, Detection]] = []
        boxes: list[np.ndarray] = []
        for d in previous:
            model = self._by_name.get(d.model)
            if model is None:
                raise ValueError(f"no model {d.model!r} to track (known: {sorted(self._by_name)})")
            X_CO = X_CW @ np.asarray(d.X_WO, dtype=np.float64)
            V_C = transform(X_CO, model.vertices_O)
            if not np.all(np.isfinite(V_C)) or np.any(V_C[:, 2] <= 0.0):
                continue  # not wholly in front of the camera: nothing to refit
            uv = project(V_C, K)
            m = self.params.track_margin_px
            boxes.append(np.concatenate([uv.min(0) - m, uv.max(0) + m]))
            starts.append((model, X_CO, d))
        # The faint line pass only weighs in the selection (poses are fitted to the first
        # pass's lines): it is needed only where an object is not found without it.
        f = self._frame(
            image, camera, self._robot_at(robot_q_rad, finger_opening_m), boxes, faint=False
        )
        if not starts or len(f.strong) < 4:
            return []
        p = self.params
        s = _Search(np.zeros(len(f.segs), dtype=bool), PoseSet(p.same_pose_m, p.same_pose_rad))
        for model, X_CO, d in starts:
            result = fit_and_verify(
                model, X_CO, f.strong, f.K, f.gx, f.gy, f.occluders_C, p,
                self._prior(model, f.X_WC, d.resting),
            )  # fmt: skip
            if result is not None:
                self._add_candidate(model, *result[:3], None, f, s, d.resting)
        accepted = self._select(s, f) if s.candidates else []
        if len(accepted) == len(starts):
            return accepted
        if self.params.faint_lines:
            f = self._with_faint(f)
            s.claimed = np.concatenate([s.claimed, np.zeros(len(f.segs) - len(s.claimed), bool)])
            accepted = self._select(s, f) if s.candidates else []
            if len(accepted) == len(starts):
                return accepted
        # Refitting need not return a pose the search accepted (lines matched anew can pull
        # it off), while a still object is where it was: for each object not found again,
        # that pose is a candidate too, next to the refitted poses accepted.
        kept = {id(d.X_WO) for d in accepted}
        s.candidates = [c for c in s.candidates if id(c.X_WO) in kept]
        n_before = len(s.candidates)
        need = (
            min(p.min_length_fraction, p.candidate_min_length_fraction),
            min(p.min_score, p.candidate_min_score),
            0.0,
        )  # what fit_and_verify asks of a candidate
        found = {d.model for d in accepted}
        for model, X_CO, d in starts:
            if model.name in found and p.max_per_model == 1:
                continue
            v = verify(model, X_CO, f.K, f.strong, f.gx, f.gy, f.occluders_C, p, None, need)
            if v.length_fraction >= need[0] and v.score >= need[1]:
                self._add_candidate(model, X_CO, d.rms_px, v, None, f, s, d.resting)
        return self._select(s, f) if len(s.candidates) > n_before else accepted

    def _robot_at(self, robot_q_rad: np.ndarray | None, finger_opening_m: float) -> list:
        """The arm's links (model, ``X_WL``) at these joint angles; none if not given."""
        if robot_q_rad is None:
            return []
        q = np.asarray(robot_q_rad, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)) or not np.isfinite(finger_opening_m):
            raise ValueError(f"robot joint state must be 6 finite angles, got {q.tolist()}")
        return self._robot.at(q, float(finger_opening_m))

    def _stacked(self, accepted: list[Detection], f: _Frame, s: _Search, junctions: list) -> None:
        """Blocks resting on the objects found: each found object's upward, near horizontal
        hull face is a table at its height, where the junction hypotheses of :mod:`.table` are
        made as on the table, then fitted without the table prior. The selection keeps those
        that something found holds up."""
        p = self.params
        heights: set[float] = set()
        for r in accepted:
            model = self._by_name[r.model]
            normals_O, offsets = self._facets[model.name]
            up = (normals_O @ r.X_WO[:3, :3].T)[:, 2] >= np.cos(p.stacked_face_tilt_rad)
            for n_O, d in zip(normals_O[up], offsets[up], strict=True):
                on_face = np.abs(model.vertices_O @ n_O - d) < FACE_TOL_M
                z = float(transform(r.X_WO, model.vertices_O[on_face])[:, 2].mean())
                heights.add(round(z / SUPPORT_HEIGHT_MERGE_M) * SUPPORT_HEIGHT_MERGE_M)
        for z in sorted(heights):
            items = table_stream(
                self._corners, self.models, self.group_params, z, f.strong, f.K, f.X_WC,
                f.gx, f.gy, p, junctions,
            )  # fmt: skip
            self._search(items, f, s, resting=False)

    def _unpriored(self, accepted: list[Detection], f: _Frame, s: _Search) -> None:
        """Each accepted object fitted again without the table prior: one view hardly tells
        depth, and the prior may have put a block that sits on a block onto the table further
        along its ray. Where the image alone holds it above the table, that pose becomes a
        candidate too, for the selection to weigh; if the lines reject the table outright
        (:attr:`RecognizerParams.table_rejection_p`), it is weighed before the object's
        poses on the table (which stand if it is not held up)."""
        p = self.params
        X_CW = invert_pose(f.X_WC)
        for r in accepted:
            model = self._by_name[r.model]
            X_CO = X_CW @ r.X_WO
            result = fit_and_verify(model, X_CO, f.strong, f.K, f.gx, f.gy, f.occluders_C, p, None)
            if result is None:
                continue
            X_WO = f.X_WC @ result[0]
            if transform(X_WO, model.vertices_O)[:, 2].min() - self.table_z <= p.table_tol_m:
                continue  # on the table after all: the prior's pose stands
            if r.resting and self._table_rejected(model, result[0], X_CO, f):
                matched = set(result[2].matched)
                s.candidates = [
                    replace(c, off_table=True)
                    if c.resting and c.model is model and shares_lines(c, matched, p)
                    else c
                    for c in s.candidates
                ]
            self._add_candidate(model, *result[:3], None, f, s, resting=False)

    def _table_rejected(
        self, model: VisionModel, X_free_CO: np.ndarray, X_table_CO: np.ndarray, f: _Frame
    ) -> bool:
        """Whether the lines matched at ``X_table_CO`` reject the hypothesis that ``model``
        rests on the table (:func:`~.pose.constraint_p_value`, the free fit started from
        ``X_free_CO``): the hypothesis's own correspondences, which are right if it is. Never
        with the table prior off: there is then no table hypothesis to test."""
        p = self.params
        prior = self._prior(model, f.X_WC)
        if p.table_rejection_p <= 0.0 or prior is None:
            return False
        ids, proj, _ = visible_edges(model, X_table_CO, f.K, f.occluders_C)
        mi, mj = match_segments(proj, f.strong, p.match_tol_px[-1], p.match_angle_rad)
        p_table = constraint_p_value(
            X_free_CO, X_table_CO, model.edges_O[ids[mi]], f.strong[mj], f.K, prior,
            TEST_FIT_ITERATIONS, p.fit_tol,
        )  # fmt: skip
        return p_table < p.table_rejection_p

    # -- steps --------------------------------------------------------------------------------
    def _claimed_by(self, accepted: list[Detection], s: _Search) -> None:
        """Only ``accepted``'s image lines claimed, and its models when each is there once."""
        s.claimed[:] = False
        for r in accepted:
            s.claimed[list(r.matched_segments)] = True
        s.confident.clear()
        if self.params.max_per_model == 1:
            s.confident.update(r.model for r in accepted)

    def _frame(
        self,
        image: np.ndarray,
        camera: CameraModel,
        robot: list | None = None,
        rois_px: list[np.ndarray] | None = None,
        faint: bool = True,
    ) -> _Frame:
        """The image checked, undistorted, its gradients and its lines not explained by the
        fixed environment or the robot (its links' models and poses ``X_WL``). ``rois_px``:
        boxes ``(u_min, v_min, u_max, v_max)`` to look for lines in (both passes), instead of
        the whole image; ``faint``: the faint pass too (if :attr:`RecognizerParams.faint_lines`),
        else only the first (:meth:`_with_faint` adds it)."""
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
        rects = None if rois_px is None else _merged_rects(rois_px, img.shape)
        img, (gx, gy) = self._undistorted(img, K, dist, rects)
        if rects is None:
            first = detect_lines(img, self.line_params, (gx, gy))
        else:
            first = _lines_in(img, (gx, gy), rects, self.line_params)
        env = self._env_view(K, np.asarray(camera.X_WC, dtype=np.float64), robot or [])
        segs = first
        if faint and self.params.faint_lines and len(first):
            segs = np.vstack([first, _faint_lines(img, (gx, gy), rects, first)])
        # Both passes' lines at once: each environment edge is projected once a view.
        kept = ~env.explained(segs)
        n_strong = int(np.count_nonzero(kept[: len(first)]))
        return _Frame(segs[kept], K, camera.X_WC, gx, gy, env, t0, n_strong, img, first, rects)

    @staticmethod
    def _with_faint(f: _Frame) -> _Frame:
        """``f`` with the faint pass's lines added after its own, as :meth:`_frame` would
        have found them."""
        faint = _faint_lines(f.img, (f.gx, f.gy), f.rects, f.first_px)
        faint = faint[~f.env.explained(faint)]
        return replace(f, segs=np.vstack([f.segs, faint]))

    def _env_view(self, K: np.ndarray, X_WC: np.ndarray, robot: list) -> _EnvView:
        """The fixed environment and the robot as this camera sees them, kept for the next
        frame seen from the same place with the robot in the same pose (a still scene's
        frames all are)."""
        key = (K.tobytes(), X_WC.tobytes(), tuple((id(m), X.tobytes()) for m, X in robot))
        if self._env_key != key:
            X_CW = invert_pose(X_WC)
            env_C = Occluders.of_parts(
                [transform(X_CW, V) for _, _, parts, _ in self.environment for V, _ in parts]
                + [transform(X_CW @ X, V) for m, X in robot for V in m.parts_vertices_O],
                [planes_in(X_CW @ X_WO, P)
                 for _, X_WO, _, planes in self.environment for P in planes]
                + [planes_in(X_CW @ X, P) for m, X in robot for P in m.planes_O],
                K,
            )  # fmt: skip
            self._env = _EnvView(
                env_C, K, [(m, X_CW @ X_WO) for m, X_WO in [*self._env_models, *robot]]
            )
            self._env_key = key
        return self._env

    def _undistorted(
        self,
        img: np.ndarray,
        K: np.ndarray,
        dist: np.ndarray,
        rects: list[tuple[int, int, int, int]] | None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The image undistorted (straight edges are straight only then) and its gradients
        (for the lines' refinement and every verification): in the whole image, or only in
        ``rects`` ``(x0, y0, x1, y1)`` with zeros elsewhere (the same values there as the
        whole image's: each rectangle is worked on with a pixel's border for the gradient)."""
        maps = self._undistort_maps(K, dist, img.shape) if np.any(dist != 0) else None
        if rects is None:
            if maps is not None:
                img = cv2.remap(img, *maps, cv2.INTER_LINEAR)
            return img, image_gradients(img)
        h, w = img.shape
        out = np.zeros_like(img)
        gx, gy = np.zeros(img.shape, np.float32), np.zeros(img.shape, np.float32)
        for x0, y0, x1, y1 in rects:
            X0, Y0, X1, Y1 = max(x0 - 1, 0), max(y0 - 1, 0), min(x1 + 1, w), min(y1 + 1, h)
            crop = (slice(Y0, Y1), slice(X0, X1))
            part = (
                img[crop]
                if maps is None
                else cv2.remap(img, maps[0][crop], maps[1][crop], cv2.INTER_LINEAR)
            )
            px, py = image_gradients(part)
            inner = (slice(y0 - Y0, y1 - Y0), slice(x0 - X0, x1 - X0))
            keep = (slice(y0, y1), slice(x0, x1))
            out[keep], gx[keep], gy[keep] = part[inner], px[inner], py[inner]
        return out, (gx, gy)

    def _undistort_maps(
        self, K: np.ndarray, dist: np.ndarray, shape: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pixel maps that undistort images of this camera (what ``cv2.undistort``
        computes on every call), kept for the next frame of the same camera."""
        key = (K.tobytes(), dist.tobytes(), shape)
        if self._maps_key != key:
            self._maps = cv2.initUndistortRectifyMap(
                K, dist, None, K, (shape[1], shape[0]), cv2.CV_16SC2
            )
            self._maps_key = key
        return self._maps

    def _search(
        self, items: list[tuple], f: _Frame, s: _Search, resting: bool = True
    ) -> list[tuple]:
        """Test the hypotheses ``items`` ``(model, group's segments, how)`` in turn, adding to
        ``s.candidates``; returns those passed over because a confident candidate had claimed
        their model or lines. ``resting``: objects resting on the table, fitted with the
        table prior; otherwise anywhere up to :attr:`max_height_m` above it, without."""
        p = self.params
        height = 0.0 if resting else self.max_height_m
        passed: list[tuple] = []
        for k, (model, g_segs, how) in enumerate(items):
            if p.time_budget_s is not None and time.perf_counter() - f.t0 > p.time_budget_s:
                break
            # A group wholly inside an object already found adds nothing; one that reaches
            # beyond it may be a bigger object that explains more (an L seen as its upright).
            if s.claimed[g_segs].all() or model.name in s.confident:
                passed.append(items[k])
                continue
            if isinstance(how, np.ndarray):
                X0 = how  # a table hypothesis: already a whole pose
            else:
                entry, X = how
                X0 = initial_fit(
                    model, self.index, entry, X, g_segs, f.strong, f.K, f.X_WC, self.table_z, p,
                    self._prior(model, f.X_WC, resting), height,
                )  # fmt: skip
            if X0 is None:
                continue
            # Many groups of one object lead to the same pose: test each pose once.
            if s.tested.seen(model, X0):
                continue
            s.tested.add(model, X0)
            result = fit_and_verify(
                model, X0, f.strong, f.K, f.gx, f.gy, f.occluders_C, p,
                self._prior(model, f.X_WC, resting),
            )  # fmt: skip
            if result is None:
                continue
            found = [(model, result[:3], None), *self._grown(model, result, f, s.tested, resting)]
            for m, (X_CO, rms, v), part_px in found:
                self._add_candidate(m, X_CO, rms, v, part_px, f, s, resting)
            if len(s.confident) == len(self.models):
                # every model found once, and once is all there can be
                passed.extend(items[k + 1 :])
                break
        return passed

    def _grown(
        self, model: VisionModel, result: tuple, f: _Frame, tested: PoseSet, resting: bool = True
    ) -> list:
        """Bigger models around the object ``model`` just fitted (``result`` of
        :func:`fit_and_verify`) that pass their test: ``(model, (X_CO, rms_px, Verification),
        the part's outline (k, 2) px)`` each.

        The object may be part of a bigger one (an L's bar is a tall block): try those too, and
        let the selection prefer whichever explains more of the image. A pose fitted to few
        edges may be the object turned about its centre (a wedge turned by 90° shows nearly
        the same outline): try those turns too."""
        p = self.params
        X_CO, n_edges = result[0], result[3]
        others = self._wholes[model.name]
        if n_edges < p.min_matched_edges:
            others = [*others, (model, self._turned[model.name])]
        if not others:
            return []
        uv = project(transform(X_CO, model.vertices_O), f.K).astype(np.float32)
        part_px = cv2.convexHull(uv).reshape(-1, 2).astype(np.float64)
        found = []
        for whole, X_AB_all in others:
            X_CB_all = X_CO @ X_AB_all  # (k, 4, 4)
            for X_CB in grown_poses(
                whole, X_CB_all, f.X_WC, f.K, f.gx, f.gy, self.table_z, tested, p,
                0.0 if resting else self.max_height_m,
            ):  # fmt: skip
                r2 = fit_and_verify(
                    whole, X_CB, f.strong, f.K, f.gx, f.gy, f.occluders_C, p,
                    self._prior(whole, f.X_WC, resting), grown=True,
                )  # fmt: skip
                if r2 is not None:
                    found.append((whole, r2[:3], part_px))
        return found

    def _add_candidate(
        self,
        model: VisionModel,
        X_CO: np.ndarray,
        rms_px: float,
        v: Verification,
        part_px: np.ndarray | None,
        f: _Frame,
        s: _Search,
        resting: bool = True,
    ) -> None:
        """Keep a tested pose as a candidate if it rests plausibly (on the table if
        ``resting``); a confident one claims its image lines (and its model, when each model
        is there once)."""
        p = self.params
        X_WO = f.X_WC @ X_CO
        parts_W = parts_in(X_WO, model)
        height = 0.0 if resting else self.max_height_m
        if not self.surroundings.plausible(parts_W, [], p, max_height_m=height):
            return
        s.candidates.append(
            Candidate(model, X_CO, X_WO, rms_px, v, parts_W, part_px, resting, f.strong)
        )
        if v.silhouette_fraction >= p.min_silhouette_fraction:
            s.claimed[v.matched] = True  # only confident candidates block others
            if p.max_per_model == 1 and v.score >= p.confident_score:
                s.confident.add(model.name)

    def _select(self, s: _Search, f: _Frame) -> list[Detection]:
        """The candidates found so far, conflicts resolved (see :func:`.pose_sets.select`),
        weighed against every line, the faint pass's too: a block whose own faint edges the
        first pass missed is not dropped for want of them, while what becomes a candidate is
        decided on the first pass's lines alone."""
        return select(
            s.candidates, f.segs, f.K, f.gx, f.gy, f.occluders_C, self.params, self.surroundings,
            self.max_height_m,
        )  # fmt: skip

    def _prior(self, model: VisionModel, X_WC: np.ndarray, resting: bool = True):
        """The fits' soft prior that ``model`` rests on a face on the table (None if off, or
        not ``resting``)."""
        if not resting:
            return None
        return resting_prior(model, self._facets[model.name][0], X_WC, self.table_z, self.params)


def _merged_rects(
    boxes_px: list[np.ndarray], shape: tuple[int, int]
) -> list[tuple[int, int, int, int]]:
    """The boxes ``(u_min, v_min, u_max, v_max)`` (px) as whole-pixel rectangles ``(x0, y0,
    x1, y1)`` (ends excluded) inside an image of ``shape``, those that overlap merged."""
    h, w = shape
    rects = []
    for b in boxes_px:
        x0, y0 = max(int(np.floor(b[0])), 0), max(int(np.floor(b[1])), 0)
        x1, y1 = min(int(np.ceil(b[2])) + 1, w), min(int(np.ceil(b[3])) + 1, h)
        if x1 > x0 and y1 > y0:
            rects.append([x0, y0, x1, y1])
    # Merge overlapping boxes until none overlap; each merge removes one, so this ends.
    for _ in range(len(rects)):
        merged = False
        for i in range(len(rects)):
            for j in range(i + 1, len(rects)):
                a, b = rects[i], rects[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    rects[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del rects[j]
                    merged = True
                    break
            if merged:
                break
        if not merged:
            break
    return [(x0, y0, x1, y1) for x0, y0, x1, y1 in rects]


def _lines_in(
    img: np.ndarray,
    gradients: tuple[np.ndarray, np.ndarray],
    rects: list[tuple[int, int, int, int]],
    params: LineParams,
) -> np.ndarray:
    """The lines of ``img`` in the rectangles ``(x0, y0, x1, y1)`` (:func:`_merged_rects`),
    each searched on its own and its lines shifted back to image coordinates."""
    gx, gy = gradients
    found = [np.zeros((0, 4))]
    for x0, y0, x1, y1 in rects:
        crop = (slice(y0, y1), slice(x0, x1))
        segs = detect_lines(img[crop], params, (gx[crop], gy[crop]))
        found.append(segs + np.array([x0, y0, x0, y0], dtype=np.float64))
    segs = np.vstack(found)
    lengths = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    return segs[np.argsort(-lengths)]


def _faint_lines(
    img: np.ndarray,
    gradients: tuple[np.ndarray, np.ndarray],
    rects: list[tuple[int, int, int, int]] | None,
    first_px: np.ndarray,
) -> np.ndarray:
    """The faint pass's lines (:data:`FAINT_LINE_PARAMS`) in ``rects`` (else the whole
    image), less those the first pass found too (``first_px``)."""
    faint = (
        detect_lines(img, FAINT_LINE_PARAMS, gradients)
        if rects is None
        else _lines_in(img, gradients, rects, FAINT_LINE_PARAMS)
    )
    _, again = match_segments(first_px, faint, FAINT_SAME_LINE_PX, FAINT_SAME_LINE_RAD)
    return np.delete(faint, again, axis=0)
