"""The work site's grey camera: renders the pybullet world as the camera model sees it.

pybullet's software renderer takes tens of milliseconds a frame, many 1 ms physics steps, so
:class:`CameraProcess` renders in a separate process holding a mirror of the world; the physics
loop only sends poses and collects finished images, and never waits. The child also encodes the
:class:`~protocol.messages.CameraFrame` for the wire (PNG takes milliseconds too): the physics
loop only publishes bytes.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Literal, overload

import cv2
import numpy as np
import pybullet as p

from models.scene import CameraModel, load_scene
from models.transforms import invert_pose, so3_log
from protocol import CameraFrame, encode
from protocol.images import DEFAULT_JPEG_QUALITY
from work_site.child import stop_child, yield_to_control
from work_site.sensor import Lighting, Sensor

CAMERA_NEAR_M = 0.05
CAMERA_FAR_M = 5.0
TINY_RENDERER_SAMPLE_PX = (0.5, -0.5)
"""Where pybullet's TinyRenderer puts a scene point, in pixels, relative to OpenCV's pinhole
with pixel centres at integer coordinates: it samples pixels at a corner (measured on a
block's silhouette: +0.50, −0.48 px at 1×, half that at 2×; the test holds it)."""
# OpenCV camera (x right, y down, z forward) to OpenGL camera (x right, y up, z backward).
_X_CV_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_matrices(
    camera: CameraModel, near_m: float = CAMERA_NEAR_M, far_m: float = CAMERA_FAR_M
) -> tuple[list[float], list[float]]:
    """pybullet view and projection matrices (column-major lists) for a pinhole camera.

    The rendering reproduces OpenCV's ``u = fx x/z + cx`` with pixel centres at integer
    coordinates, including an off-centre principal point (no lens distortion: see
    :func:`render_grey`). TinyRenderer samples each pixel at a corner, not at its centre:
    the principal point is moved by :data:`TINY_RENDERER_SAMPLE_PX` to make up for it.
    """
    w, h = camera.width, camera.height
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    cx = camera.K[0, 2] - TINY_RENDERER_SAMPLE_PX[0]
    cy = camera.K[1, 2] - TINY_RENDERER_SAMPLE_PX[1]
    view = invert_pose(camera.X_WC @ _X_CV_GL)
    proj = np.array(
        [
            [2 * fx / w, 0.0, 1.0 - 2 * (cx + 0.5) / w, 0.0],
            [0.0, 2 * fy / h, 2 * (cy + 0.5) / h - 1.0, 0.0],
            [
                0.0,
                0.0,
                -(far_m + near_m) / (far_m - near_m),
                -2 * far_m * near_m / (far_m - near_m),
            ],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )
    return view.T.flatten().tolist(), proj.T.flatten().tolist()


@overload
def render_grey(
    cid: int,
    camera: CameraModel,
    supersample: int = 1,
    *,
    segmentation: Literal[False] = False,
    lighting: Lighting | None = None,
) -> np.ndarray: ...


@overload
def render_grey(
    cid: int,
    camera: CameraModel,
    supersample: int = 1,
    *,
    segmentation: Literal[True],
    lighting: Lighting | None = None,
) -> tuple[np.ndarray, np.ndarray]: ...


def render_grey(
    cid: int,
    camera: CameraModel,
    supersample: int = 1,
    *,
    segmentation: bool = False,
    lighting: Lighting | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Render physics client ``cid`` through ``camera`` as an 8-bit grey image (h, w).

    ``supersample`` > 1 renders that many times larger and averages down (``INTER_AREA``), for
    sub-pixel edges closer to a real camera's, at about ``supersample²`` times the cost. The
    camera's lens distortion (``dist``) is rendered: straight edges come out curved as a real
    lens shows them. ``lighting``: the light (default: :class:`~work_site.sensor.Lighting`'s).
    With ``segmentation``, also the segmentation buffer (h·k, w·k) int64 of body ids (−1 for
    none) at the supersampled size k: the ground truth of what each pixel sees.
    """
    if supersample < 1:
        raise ValueError(f"supersample must be ≥ 1, got {supersample}")
    light = lighting or Lighting()
    k = supersample
    w, h = camera.width * k, camera.height * k
    lens = _lens_map(camera, k) if np.any(np.asarray(camera.dist) != 0) else None
    canvas = camera.scaled(k) if lens is None else lens.canvas
    view, proj = opengl_matrices(canvas)
    _, _, rgba, _, seg = p.getCameraImage(
        canvas.width,
        canvas.height,
        view,
        proj,
        lightDirection=list(light.direction_W),
        lightAmbientCoeff=light.ambient,
        lightDiffuseCoeff=light.diffuse,
        lightSpecularCoeff=light.specular,
        shadow=0,
        renderer=p.ER_TINY_RENDERER,
        physicsClientId=cid,
    )
    rgba = np.asarray(rgba, dtype=np.uint8).reshape(canvas.height, canvas.width, 4)
    grey = cv2.cvtColor(rgba, cv2.COLOR_RGBA2GRAY)
    seg = np.asarray(seg, dtype=np.int64).reshape(canvas.height, canvas.width)
    if lens is not None:
        grey = cv2.remap(grey, lens.map_x, lens.map_y, cv2.INTER_LINEAR, borderValue=0)
        if segmentation:
            seg = cv2.remap(
                seg.astype(np.float32), lens.map_x, lens.map_y, cv2.INTER_NEAREST, borderValue=-1
            ).astype(np.int64)
    if k > 1:
        grey = cv2.resize(grey, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    if not segmentation:
        return grey
    assert seg.shape == (h, w)
    # Body ids sit in the low 24 bits (pybullet puts link indices above them when asked to).
    return grey, np.where(seg < 0, -1, seg & ((1 << 24) - 1))


@dataclass(frozen=True, eq=False)
class _LensMap:
    """Where each pixel of a distorted image (supersampled) looks in an undistorted render."""

    canvas: CameraModel  # the undistorted render: same focal lengths, wide enough to cover
    map_x: np.ndarray  # (h, w) float32: the canvas's column of each distorted pixel
    map_y: np.ndarray


LENS_MAP_TOL_PX = 1e-3
"""The inverted distortion must land within this of the distorted pixel it was drawn from."""


def _lens_map(camera: CameraModel, supersample: int) -> _LensMap:
    key = (
        camera.width, camera.height, supersample,
        tuple(np.asarray(camera.K, dtype=np.float64).ravel()),
        tuple(np.asarray(camera.dist, dtype=np.float64).ravel()),
    )  # fmt: skip
    if key not in _LENS_MAPS:
        if len(_LENS_MAPS) >= 8:  # a few cameras per process; keep the memory bounded
            _LENS_MAPS.pop(next(iter(_LENS_MAPS)))
        _LENS_MAPS[key] = _build_lens_map(camera, supersample)
    return _LENS_MAPS[key]


_LENS_MAPS: dict[tuple, _LensMap] = {}


def distort_px(rays: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of normalised rays (n, 2) through OpenCV's 5-coefficient lens model
    ``(k1, k2, p1, p2, k3)``: what ``cv2.projectPoints`` computes, vectorised for whole images."""
    if dist.shape != (5,):
        raise ValueError(f"camera dist must be the 5 coefficients (k1, k2, p1, p2, k3), got {dist}")
    k1, k2, p1, p2, k3 = dist
    x, y = rays[:, 0], rays[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def _build_lens_map(camera: CameraModel, supersample: int) -> _LensMap:
    """The undistorted canvas and the remap tables of ``camera``'s distortion at ``supersample``:
    each distorted pixel's normalised ray by OpenCV's iterative inversion, checked by
    distorting it again."""
    big = camera.scaled(supersample)
    K = np.asarray(big.K, dtype=np.float64)
    dist = np.asarray(camera.dist, dtype=np.float64)
    u, v = np.meshgrid(np.arange(big.width, dtype=np.float64), np.arange(big.height))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    rays = cv2.undistortPoints(pts, K, dist, None, None, None, criteria).reshape(-1, 2)
    miss_px = float(np.max(np.abs(distort_px(rays, K, dist) - pts.reshape(-1, 2))))
    if not miss_px <= LENS_MAP_TOL_PX:
        raise ValueError(
            f"camera distortion {dist.tolist()} cannot be inverted over the image "
            f"(off by {miss_px:.3g} px): too strong for the lens model"
        )
    uu = K[0, 0] * rays[:, 0] + K[0, 1] * rays[:, 1] + K[0, 2]
    vv = K[1, 1] * rays[:, 1] + K[1, 2]
    margin = 2.0  # pixels of canvas beyond the farthest sample, for the interpolation
    u0, v0 = np.floor(uu.min()) - margin, np.floor(vv.min()) - margin
    width = int(np.ceil(uu.max() - u0 + margin)) + 1
    height = int(np.ceil(vv.max() - v0 + margin)) + 1
    Kc = K.copy()
    Kc[0, 2] -= u0
    Kc[1, 2] -= v0
    canvas = dataclasses.replace(big, width=width, height=height, K=Kc, dist=np.zeros(5))
    shape = (big.height, big.width)
    return _LensMap(
        canvas,
        (uu - u0).reshape(shape).astype(np.float32),
        (vv - v0).reshape(shape).astype(np.float32),
    )


@dataclass(frozen=True)
class FrameEncoding:
    """How the child encodes frames for the wire: ``encoding`` (protocol/images.py), JPEG
    ``quality``, and the calibration each frame carries (``None``: the scene file's camera)."""

    encoding: str = "raw"
    quality: int = DEFAULT_JPEG_QUALITY
    calibration: CameraModel | None = None


@dataclass(frozen=True)
class RenderedFrame:
    """A finished render: the pixels (for vision) and the encoded ``CameraFrame`` (for the wire)."""

    seq: int
    stamp_s: float
    image: np.ndarray
    payload: bytes
    q: np.ndarray  # the arm's joint angles (6,) and the finger opening (m) in the image:
    finger_opening_m: float  # vision sets the arm's lines aside
    rendered: bool = True
    """Whether the world was rendered for this frame (False: the last render was reused,
    nothing having moved; its noise is this frame's own)."""


@dataclass(frozen=True)
class RenderRequest:
    """A snapshot of the world to render: object poses ``X_WO`` and the robot's joints."""

    seq: int
    stamp_s: float
    X_WO: dict[str, np.ndarray]
    q: np.ndarray
    fingers_m: np.ndarray
    quality: int | None = None
    """This frame's JPEG quality (None: the wire's :class:`FrameEncoding`)."""


RENDER_REUSE_M = 1e-6
"""A render is reused while no object and no finger has moved more than this (m) since it
was made: a hundredth of a pixel and less at the camera's range (its focal length is under a
thousand pixels a metre away), far below the sensor's noise, which every frame draws anew.
A scene at rest (the operator dragging in the model, vision looking) then costs the renderer
the sensor's stages alone, not a render of the supersampled world."""
RENDER_REUSE_RAD = 1e-6
"""The same for rotations: an object's, and each joint's (rad; a link a metre long moves its
far end 1 µm)."""


def same_view(a: RenderRequest, b: RenderRequest) -> bool:
    """Whether ``a`` and ``b`` show the world alike, within :data:`RENDER_REUSE_M` and
    :data:`RENDER_REUSE_RAD`: the same objects at the same poses, the arm at the same joint
    angles and finger openings."""
    if a.X_WO.keys() != b.X_WO.keys():
        return False
    if np.max(np.abs(np.asarray(a.q) - np.asarray(b.q)), initial=0.0) > RENDER_REUSE_RAD:
        return False
    fingers_m = np.abs(np.asarray(a.fingers_m) - np.asarray(b.fingers_m))
    if np.max(fingers_m, initial=0.0) > RENDER_REUSE_M:
        return False
    for name, X_a in a.X_WO.items():
        X_b = b.X_WO[name]
        if np.linalg.norm(X_a[:3, 3] - X_b[:3, 3]) > RENDER_REUSE_M:
            return False
        if np.linalg.norm(so3_log(X_a[:3, :3].T @ X_b[:3, :3])) > RENDER_REUSE_RAD:
            return False
    return True


def _render_worker(
    scene_path: str,
    supersample: int,
    X_WC: np.ndarray | None,
    sensor: Sensor,
    wire: FrameEncoding,
    conn: Connection,
) -> None:
    yield_to_control()
    from work_site.world import World  # imported in the child: it owns its own client

    scene = load_scene(Path(scene_path))
    calibrated = wire.calibration or scene.camera  # what frames say, wherever it really is
    if X_WC is not None:  # the real camera, off its calibrated pose
        scene = dataclasses.replace(
            scene, camera=dataclasses.replace(scene.camera, X_WC=np.asarray(X_WC))
        )
    world = World(scene)
    last: tuple[RenderRequest, np.ndarray] | None = None  # the last render, and of what
    try:
        while True:
            request = conn.recv()
            if request is None:
                return
            fresh = last is None or not same_view(last[0], request)
            if fresh:
                for name, X_WO in request.X_WO.items():
                    world.set_object_pose(name, X_WO)
                world.set_robot_joint_positions(request.q, request.fingers_m)
                last = (request, render_grey(world.cid, world.scene.camera, supersample))
            # The sensor's noise, seeded by the frame: a frame renders the same every time.
            image = sensor.apply(last[1], np.random.default_rng(request.seq))
            payload = encode(
                CameraFrame(
                    seq=request.seq,
                    stamp_s=request.stamp_s,
                    X_WC=calibrated.X_WC,
                    K=calibrated.K,
                    dist=calibrated.dist,
                    image=image,
                    encoding=wire.encoding,
                    quality=wire.quality if request.quality is None else request.quality,
                )
            )
            opening = float(np.sum(request.fingers_m))
            conn.send(
                RenderedFrame(
                    request.seq, request.stamp_s, image, payload, request.q, opening, fresh
                )
            )
    except (EOFError, BrokenPipeError, KeyboardInterrupt):  # the parent is gone
        return
    finally:
        world.close()


class CameraProcess:
    """Renders in a child process; at most one request is in flight at a time."""

    def __init__(
        self,
        scene_path: Path,
        supersample: int = 1,
        X_WC: np.ndarray | None = None,
        sensor: Sensor | None = None,
        wire: FrameEncoding = FrameEncoding(),
    ) -> None:
        """``X_WC``: where the camera really is, if not where the scene file says (frames carry
        the scene file's, the calibration); ``sensor``: the camera's blur, exposure and noise
        (default: ideal); ``wire``: how frames are encoded."""
        ctx = mp.get_context("spawn")  # never fork a process that runs zenoh threads
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_render_worker,
            args=(str(scene_path), supersample, X_WC, sensor or Sensor(), wire, child),
            name="camera-renderer",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self.busy = False

    def request(self, req: RenderRequest) -> bool:
        """Start rendering ``req`` unless a render is already running; True if started."""
        if self.busy:
            return False
        self._conn.send(req)
        self.busy = True
        return True

    def poll(self) -> RenderedFrame | None:
        """A finished frame if one is ready, without waiting."""
        if self.busy and self._conn.poll():
            self.busy = False
            return self._conn.recv()
        if not self._proc.is_alive():
            raise RuntimeError(f"camera renderer died (exit code {self._proc.exitcode})")
        return None

    def close(self) -> None:
        """Stop the renderer process."""
        stop_child(self._proc, self._conn, ask=True, grace_s=5.0)
