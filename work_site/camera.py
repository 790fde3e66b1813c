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
from models.transforms import invert_pose
from protocol import CameraFrame, encode
from protocol.images import DEFAULT_JPEG_QUALITY
from work_site.child import stop_child

CAMERA_NEAR_M = 0.05
CAMERA_FAR_M = 5.0
LIGHT_DIRECTION_W = (0.4, -0.6, 1.0)
# OpenCV camera (x right, y down, z forward) to OpenGL camera (x right, y up, z backward).
_X_CV_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_matrices(
    camera: CameraModel, near_m: float = CAMERA_NEAR_M, far_m: float = CAMERA_FAR_M
) -> tuple[list[float], list[float]]:
    """pybullet view and projection matrices (column-major lists) for a pinhole camera.

    The projection reproduces OpenCV's ``u = fx x/z + cx`` with pixel centres at integer
    coordinates, including an off-centre principal point (lens distortion is not rendered).
    """
    w, h = camera.width, camera.height
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
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
    cid: int, camera: CameraModel, supersample: int = 1, *, segmentation: Literal[False] = False
) -> np.ndarray: ...


@overload
def render_grey(
    cid: int, camera: CameraModel, supersample: int = 1, *, segmentation: Literal[True]
) -> tuple[np.ndarray, np.ndarray]: ...


def render_grey(
    cid: int, camera: CameraModel, supersample: int = 1, *, segmentation: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Render physics client ``cid`` through ``camera`` as an 8-bit grey image (h, w).

    ``supersample`` > 1 renders that many times larger and averages down (``INTER_AREA``), for
    sub-pixel edges closer to a real camera's, at about ``supersample²`` times the cost. With
    ``segmentation``, also the segmentation buffer (h·k, w·k) int64 of body ids (−1 for none)
    at the supersampled size k: the ground truth of what each pixel sees.
    """
    if supersample < 1:
        raise ValueError(f"supersample must be ≥ 1, got {supersample}")
    view, proj = opengl_matrices(camera)
    w, h = camera.width * supersample, camera.height * supersample
    _, _, rgba, _, seg = p.getCameraImage(
        w,
        h,
        view,
        proj,
        lightDirection=LIGHT_DIRECTION_W,
        shadow=0,
        renderer=p.ER_TINY_RENDERER,
        physicsClientId=cid,
    )
    rgba = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)
    grey = cv2.cvtColor(rgba, cv2.COLOR_RGBA2GRAY)
    if supersample > 1:
        grey = cv2.resize(grey, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    if not segmentation:
        return grey
    seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
    # Body ids sit in the low 24 bits (pybullet puts link indices above them when asked to).
    return grey, np.where(seg < 0, -1, seg & ((1 << 24) - 1))


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


@dataclass(frozen=True)
class RenderRequest:
    """A snapshot of the world to render: object poses ``X_WO`` and the robot's joints."""

    seq: int
    stamp_s: float
    X_WO: dict[str, np.ndarray]
    q: np.ndarray
    fingers_m: np.ndarray


def _render_worker(
    scene_path: str,
    supersample: int,
    X_WC: np.ndarray | None,
    noise_grey: float,
    wire: FrameEncoding,
    conn: Connection,
) -> None:
    from work_site.world import World  # imported in the child: it owns its own client

    scene = load_scene(Path(scene_path))
    calibrated = wire.calibration or scene.camera  # what frames say, wherever it really is
    if X_WC is not None:  # the real camera, off its calibrated pose
        scene = dataclasses.replace(
            scene, camera=dataclasses.replace(scene.camera, X_WC=np.asarray(X_WC))
        )
    world = World(scene)
    try:
        while True:
            request = conn.recv()
            if request is None:
                return
            for name, X_WO in request.X_WO.items():
                world.set_object_pose(name, X_WO)
            world.set_robot_joint_positions(request.q, request.fingers_m)
            image = render_grey(world.cid, world.scene.camera, supersample)
            if noise_grey > 0:  # a real sensor's noise, seeded by the frame
                rng = np.random.default_rng(request.seq)
                noisy = image + rng.normal(0.0, noise_grey, image.shape)
                image = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
            payload = encode(
                CameraFrame(
                    seq=request.seq,
                    stamp_s=request.stamp_s,
                    X_WC=calibrated.X_WC,
                    K=calibrated.K,
                    dist=calibrated.dist,
                    image=image,
                    encoding=wire.encoding,
                    quality=wire.quality,
                )
            )
            conn.send(RenderedFrame(request.seq, request.stamp_s, image, payload))
    except (EOFError, KeyboardInterrupt):
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
        noise_grey: float = 0.0,
        wire: FrameEncoding = FrameEncoding(),
    ) -> None:
        """``X_WC``: where the camera really is, if not where the scene file says (frames carry
        the scene file's, the calibration); ``noise_grey``: standard deviation of the sensor
        noise added to each pixel (grey levels); ``wire``: how frames are encoded."""
        ctx = mp.get_context("spawn")  # never fork a process that runs zenoh threads
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_render_worker,
            args=(str(scene_path), supersample, X_WC, noise_grey, wire, child),
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
