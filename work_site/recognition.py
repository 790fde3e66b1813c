"""Recognition of the camera's frames in a child process (§IV), so that vision never stalls the
control loop: the server hands it the newest frame whenever it is idle, for a full search at
most at the rate it is given and to track the objects found in the frames between, and
publishes what comes back with the frame's sequence number."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from work_site.child import BLAS_THREAD_VARIABLES, stop_child, yield_to_control

if TYPE_CHECKING:
    from work_site.camera import RenderedFrame

log = logging.getLogger("work-site")


@dataclass(frozen=True)
class VisionResult:
    """What vision found in frame ``seq`` (objects as (model, X_WO, score)), or why it failed."""

    seq: int
    stamp_s: float
    elapsed_s: float
    objects: tuple[tuple[str, np.ndarray, float], ...]
    error: str = ""
    note: str = ""
    """Something to log once, such as the camera pose calibrated from the first frame."""
    tracked: bool = False
    """The objects were followed from the frame before, not searched for anew."""


CALIBRATION_MAX_RMS_PX = 1.0
"""A camera pose fitted to the frame's edges with a larger line residual is not trusted (the
calibrated model is kept)."""


def _calibrated(image: np.ndarray, scene):
    """The scene's camera with its pose fitted to the frame's edges in ``image``, and a note
    saying how well it fitted (or why the calibrated pose is kept)."""
    from models.transforms import so3_log
    from work_site.vision.calibration import (
        calibrate_extrinsics,
        calibrated_camera,
        frame_object,
    )

    try:
        ext = calibrate_extrinsics(image, scene.camera, frame_object(scene))
    except ValueError as e:
        return scene.camera, f"camera pose not calibrated from the frame ({e}): file pose kept"
    if not ext.rms_px <= CALIBRATION_MAX_RMS_PX:
        return scene.camera, (
            f"camera pose fit to the frame rejected (line RMS {ext.rms_px:.2f} px > "
            f"{CALIBRATION_MAX_RMS_PX} px): file pose kept"
        )
    shift_mm = float(np.linalg.norm(ext.X_WC[:3, 3] - scene.camera.X_WC[:3, 3])) * 1e3
    turn = float(np.linalg.norm(so3_log(scene.camera.X_WC[:3, :3].T @ ext.X_WC[:3, :3])))
    return calibrated_camera(scene.camera, None, ext.X_WC), (
        f"camera pose calibrated from the frame's {ext.edges} edges: {shift_mm:.1f} mm and "
        f"{np.degrees(turn):.2f}° from the file's, line RMS {ext.rms_px:.2f} px, corner RMS "
        f"{ext.corner_rms_px:.2f} px"
    )


def _vision_worker(scene_path: str, scale: float, index_views: int | None, conn) -> None:
    yield_to_control()
    import cv2

    from models.scene import load_scene
    from work_site.vision import IndexParams, Recognizer

    scene = load_scene(scene_path)
    try:
        index = IndexParams(n_views=index_views) if index_views is not None else None
        recognizer = Recognizer(scene=scene, index_params=index)
    except Exception as e:  # reported to the server, which keeps serving
        conn.send(VisionResult(-1, 0.0, 0.0, (), f"vision could not start: {e}"))
        return
    conn.send(VisionResult(-1, 0.0, 0.0, ()))  # ready
    camera, note = scene.camera, None
    previous: list = []  # the last frame's detections, to track
    try:
        while True:
            request = conn.recv()
            if request is None:
                return
            seq, stamp_s, image, robot, track = request
            if note is None:  # §IV-B: the camera's pose from the frame, on the first image
                t0 = time.perf_counter()
                camera, note = _calibrated(image, scene)
                note += f" ({time.perf_counter() - t0:.2f} s, once)"
            t0 = time.perf_counter()  # elapsed_s is the recognition's alone
            try:
                seen, img = camera, image
                if scale != 1.0:
                    seen = camera.scaled(scale)
                    size = (seen.width, seen.height)
                    img = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
                if track:  # nothing found before: nothing to follow, until the next search
                    found = recognizer.track(img, seen, previous, *robot) if previous else []
                else:
                    found = recognizer.recognize(img, seen, *robot)
                objects = tuple((r.model, r.X_WO, float(r.score)) for r in found)
                error = ""
            except Exception as e:  # one bad frame must not end vision
                found, objects, error = [], (), f"{type(e).__name__}: {e}"
            previous = found
            elapsed_s = time.perf_counter() - t0
            conn.send(VisionResult(seq, stamp_s, elapsed_s, objects, error, note, bool(track)))
            note = ""
    except (EOFError, BrokenPipeError, KeyboardInterrupt):  # the parent is gone
        return


class VisionProcess:
    """Recognises frames in a child process; at most one frame in flight."""

    def __init__(
        self, scene_path: Path, scale: float = 1.0, index_views: int | None = None
    ) -> None:
        """``scale``: recognise the frame resized by this factor; ``index_views``: viewing
        directions of the model index (None: vision's default)."""
        ctx = mp.get_context("spawn")  # never fork a process that runs zenoh threads
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_vision_worker,
            args=(str(scene_path), scale, index_views, child),
            name="vision",
            daemon=True,
        )
        # Vision is one core's work: BLAS threads on its small products only add CPU time
        # (twice the CPU for the same wall time, measured); the child reads this at start.
        saved = {k: os.environ.get(k) for k in BLAS_THREAD_VARIABLES}
        os.environ.update(dict.fromkeys(BLAS_THREAD_VARIABLES, "1"))
        try:
            self._proc.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        child.close()
        self.ready = False
        self.busy = True  # until the worker says it is ready
        self.failed = ""

    def request(self, frame: RenderedFrame, track: bool = False) -> bool:
        """Start recognising a frame (the arm's joints in it known) unless busy (or not
        ready); True if started. ``track``: only follow the objects of the last frame
        (:meth:`~work_site.vision.recognizer.Recognizer.track`) instead of a full search."""
        if self.busy or not self.ready:
            return False
        robot = (frame.q, frame.finger_opening_m)
        self._conn.send((frame.seq, frame.stamp_s, frame.image, robot, track))
        self.busy = True
        return True

    def poll(self) -> VisionResult | None:
        """A finished result if one is ready, without waiting."""
        if self.failed:
            return None
        if self.busy and self._conn.poll():
            self.busy = False
            result: VisionResult = self._conn.recv()
            if result.seq < 0:  # the worker's start-up message
                if result.error:
                    self.failed = result.error
                    log.error("%s; serving without vision", result.error)
                else:
                    self.ready = True
                    log.info("vision ready")
                return None
            return result
        if not self._proc.is_alive():
            self.failed = f"vision process died (exit code {self._proc.exitcode})"
            log.error("%s; serving without vision", self.failed)
        return None

    def close(self) -> None:
        """Stop the vision process (at once: nothing it computes needs saving; a busy child
        would not read the sign to exit)."""
        stop_child(self._proc, self._conn, ask=self.ready and not self.busy, grace_s=1.0)
