"""Camera calibration (§IV-B): intrinsics from images of a chessboard target rendered in front of
the camera (OpenCV's ``calibrateCamera``), and the camera pose from the puzzle frame's edges and
corners, fitted by the same line-based least squares as the objects.

The paper calibrated intrinsics off line and had the operator click known features for the
pose; here both are automatic, and both report a residual a person can judge.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import pybullet as p

from models.scene import CameraModel, Scene, SceneObject
from models.transforms import invert_pose, make_pose, rpy_to_R
from work_site.camera import render_grey
from work_site.vision.lines import LineParams, detect_lines
from work_site.vision.model import VisionModel, transform, visible_edges, vision_model
from work_site.vision.pose import fit_pose
from work_site.vision.recognizer import match_segments

BOARD_INNER = (8, 6)
"""Inner corners of the chessboard (columns, rows)."""
BOARD_SQUARE_M = 0.02


@dataclass(frozen=True)
class IntrinsicsResult:
    """``K`` (3, 3), ``dist`` (5,), RMS reprojection error (px), views used, and the standard
    deviations of ``fx, fy, cx, cy`` (px) OpenCV estimates from the residuals: how sure the
    calibration is (a dozen views leave the principal point a pixel or two uncertain)."""

    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    views: int
    std_f_c_px: np.ndarray


@dataclass(frozen=True)
class ExtrinsicsResult:
    """Camera pose ``X_WC``, line-fit RMS residual (px), RMS corner residual (px), the number
    of frame edges matched."""

    X_WC: np.ndarray
    rms_px: float
    corner_rms_px: float
    edges: int


def board_points_B() -> np.ndarray:
    """The chessboard's inner corners in its frame B (z = 0 on the top face), (n, 3) m."""
    cols, rows = BOARD_INNER
    s = BOARD_SQUARE_M
    xs = (np.arange(cols) - (cols - 1) / 2) * s
    ys = (np.arange(rows) - (rows - 1) / 2) * s
    return np.array([[x, y, 0.0] for y in ys for x in xs])


def _make_board(cid: int) -> list[int]:
    """A white plate and its black squares, one body each (pybullet's visual shape arrays
    drop shapes, and a body has one colour)."""
    cols, rows = BOARD_INNER[0] + 1, BOARD_INNER[1] + 1
    s = BOARD_SQUARE_M
    plate = p.createVisualShape(
        p.GEOM_BOX,
        halfExtents=[(cols + 1) * s / 2, (rows + 1) * s / 2, 0.001],
        visualFramePosition=[0, 0, -0.001],
        rgbaColor=[1, 1, 1, 1],
        physicsClientId=cid,
    )
    bodies = [p.createMultiBody(baseVisualShapeIndex=plate, physicsClientId=cid)]
    square = p.createVisualShape(
        p.GEOM_BOX, halfExtents=[s / 2, s / 2, 0.0002], rgbaColor=[0.05, 0.05, 0.05, 1],
        physicsClientId=cid,
    )  # fmt: skip
    for j in range(rows):
        for i in range(cols):
            if (i + j) % 2 == 0:
                b = p.createMultiBody(baseVisualShapeIndex=square, physicsClientId=cid)
                offset = [(i - (cols - 1) / 2) * s, (j - (rows - 1) / 2) * s, 0.0]
                bodies.append((b, offset))  # type: ignore[arg-type]
    return bodies


def render_board_views(
    camera: CameraModel, n_views: int, seed: int = 0, supersample: int = 3
) -> list[np.ndarray]:
    """Grey images of the chessboard at random poses 0.45–0.8 m in front of ``camera``."""
    from work_site.world import pose_to_pybullet

    cid = p.connect(p.DIRECT)
    try:
        bodies = _make_board(cid)
        rng = np.random.default_rng(seed)
        images = []
        for _ in range(n_views):
            d = rng.uniform(0.45, 0.8)
            # Off-centre positions so that the corners cover the image (distortion, centre).
            x = rng.uniform(-0.25, 0.25) * d
            y = rng.uniform(-0.18, 0.18) * d
            tilt = rng.uniform(-0.6, 0.6, 2)
            R_CB = rpy_to_R(np.array([np.pi + tilt[0], tilt[1], rng.uniform(-0.4, 0.4)]))
            X_WB = camera.X_WC @ make_pose(R_CB, [x, y, d])
            for b in bodies:
                body, offset = (b, [0.0, 0.0, 0.0]) if isinstance(b, int) else b
                pos, quat = pose_to_pybullet(X_WB @ make_pose(None, offset))
                p.resetBasePositionAndOrientation(body, pos, quat, physicsClientId=cid)
            images.append(render_grey(cid, camera, supersample))
        return images
    finally:
        p.disconnect(cid)


def calibrate_intrinsics(images: list[np.ndarray]) -> IntrinsicsResult:
    """OpenCV's chessboard calibration over ``images``; ValueError if too few boards are seen."""
    obj, img_pts = [], []
    shape = None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    for im in images:
        ok, corners = cv2.findChessboardCorners(im, BOARD_INNER)
        if not ok:
            continue
        corners = cv2.cornerSubPix(im, corners, (5, 5), (-1, -1), crit)
        obj.append(board_points_B().astype(np.float32))
        img_pts.append(corners.reshape(-1, 2).astype(np.float32))
        shape = im.shape[::-1]
    if len(obj) < 4:
        raise ValueError(f"the chessboard was found in only {len(obj)} images; need ≥ 4")
    # k3 is left out: with a few dozen views it mostly fits noise.
    rms, K, dist, _, _, std_intrinsics, _, _ = cv2.calibrateCameraExtended(
        obj, img_pts, shape, None, None, flags=cv2.CALIB_FIX_K3
    )
    return IntrinsicsResult(
        np.asarray(K, np.float64),
        np.ravel(dist)[:5],
        float(rms),
        len(obj),
        np.ravel(std_intrinsics)[:4].astype(np.float64),
    )


def calibrate_extrinsics(
    image: np.ndarray, camera: CameraModel, frame: SceneObject, rounds: int = 4
) -> ExtrinsicsResult:
    """The camera pose from the fixed frame's edges, starting from ``camera.X_WC`` (a rough
    guess, within about 1 cm and 2° is enough): match projected frame edges to image lines, fit
    the frame's pose in the camera by least squares, repeat with tighter matching."""
    model: VisionModel = vision_model(frame.model)
    segs = detect_lines(image, LineParams())
    X_CF0 = invert_pose(camera.X_WC) @ frame.X_WO
    # The frame's inner and outer edges are parallel and about 15 px apart, so a guess a
    # centimetre off can lock onto the wrong ones: start from a small grid of shifted guesses
    # and keep the fit that explains the most edges, then the smallest residual.
    best = None
    grid = (-0.012, 0.0, 0.012)
    for dx, dy, dz in itertools.product(grid, grid, (-0.02, 0.0, 0.02)):
        X_CF = X_CF0.copy()
        X_CF[:3, 3] += [dx, dy, dz]
        try:
            fit, n_edges = _fit_frame(model, X_CF, camera.K, segs, rounds)
        except ValueError:
            continue
        key = (n_edges, -fit.rms_px)
        if best is None or key > best[0]:
            best = (key, fit, n_edges)
    if best is None:
        raise ValueError("too few frame edges found in the image to fit the camera pose")
    _, fit, n_edges = best
    X_CF = fit.X_CO
    X_WC = frame.X_WO @ invert_pose(X_CF)
    # Corner residual: the frame's top corners against the meets of the fitted image lines.
    corner_err = _corner_residuals(model, X_CF, camera.K, segs)
    corner_rms = float(np.sqrt(np.mean(np.square(corner_err)))) if len(corner_err) else np.nan
    return ExtrinsicsResult(X_WC, fit.rms_px, corner_rms, n_edges)


def _fit_frame(model: VisionModel, X_CF: np.ndarray, K: np.ndarray, segs: np.ndarray, rounds):
    """Match-and-fit rounds with shrinking tolerance; the last fit and its matched edges."""
    fit = None
    mi = np.zeros(0, int)
    for tol in (12.0, 6.0, 3.0, 1.5)[-rounds:]:
        ids, proj, _ = visible_edges(model, X_CF, K)
        mi, mj = match_segments(proj, segs, tol, np.deg2rad(6.0))
        if len(np.unique(mi)) < 4:
            raise ValueError("too few frame edges matched")
        fit = fit_pose(X_CF, model.edges_O[ids[mi]], segs[mj], K, iterations=30)
        X_CF = fit.X_CO
    assert fit is not None
    return fit, len(np.unique(mi))


def _corner_residuals(model: VisionModel, X_CF, K, segs) -> np.ndarray:
    """Distances (px) between projected model corners and intersections of the image lines
    matched to two edges meeting there."""
    ids, proj, _ = visible_edges(model, X_CF, K, min_fraction=0.9)
    mi, mj = match_segments(proj, segs, 1.5, np.deg2rad(3.0))
    line_of = {int(ids[a]): segs[b] for a, b in zip(mi, mj, strict=True)}
    E = model.edges_O
    out = []
    for a, b in ((a, b) for a in line_of for b in line_of if a < b):
        shared = [pa for pa in E[a] for pb in E[b] if np.linalg.norm(pa - pb) < 1e-9]
        if not shared:
            continue
        corner = transform(X_CF, shared[0])
        uv = (K @ corner)[:2] / corner[2]
        s1, s2 = line_of[a], line_of[b]
        l1 = np.cross([*s1[:2], 1.0], [*s1[2:], 1.0])
        l2 = np.cross([*s2[:2], 1.0], [*s2[2:], 1.0])
        x = np.cross(l1, l2)
        if abs(x[2]) < 1e-9:
            continue
        out.append(np.linalg.norm(x[:2] / x[2] - uv))
    return np.array(out)


def calibrated_camera(
    camera: CameraModel, intrinsics: IntrinsicsResult | None, X_WC: np.ndarray | None
) -> CameraModel:
    """``camera`` with the calibrated parts replaced."""
    out = camera
    if intrinsics is not None:
        out = dataclasses.replace(out, K=intrinsics.K, dist=intrinsics.dist)
    if X_WC is not None:
        out = dataclasses.replace(out, X_WC=X_WC)
    return out


def frame_object(scene: Scene) -> SceneObject:
    """The scene's fixed puzzle frame (the feature the camera pose is calibrated from)."""
    return scene.object("frame")
