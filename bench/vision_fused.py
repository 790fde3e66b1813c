"""Vision's poses fused over frames (:mod:`work_site.vision.fusion`), measured on a dataset's
scenes: each scene rendered again as it was (its blocks, its camera where it really is, its
light) and seen through its own sensor ``frames`` times, each time with fresh noise, as the
work site's camera sees a still scene; each frame recognised and fused with those before.
Scored: the last frame's recognitions alone, fused, and fused with the frames after the first
tracked from it (as the work site does between its full searches).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.vision_dataset import SceneRenderer, read_truth
from models.scene import load_camera
from work_site.sensor import Lighting, Sensor
from work_site.vision.fusion import FUSED_FRAMES, PoseFusion
from work_site.vision.recognizer import Recognizer


class _Found:
    """A fused recognition as :func:`bench.vision.score` reads one: model and pose."""

    def __init__(self, model: str, X_WO: np.ndarray) -> None:
        self.model, self.X_WO = model, X_WO


def fused_scenes(paths: list[Path], supersample: int, frames: int = FUSED_FRAMES) -> list[tuple]:
    """Each scene as :func:`bench.vision.score` takes it, its image a tuple of ``frames``
    images: the scene's clean render (at the dataset's ``supersample``) through its sensor
    with frame-seeded noise."""
    renderer = SceneRenderer(supersample=supersample)
    out = []
    try:
        for k, path in enumerate(paths):
            if len(paths) >= 20 and k % (len(paths) // 10) == 0:
                print(f"rendering scene {k + 1} of {len(paths)} again", file=sys.stderr)
            doc = json.loads(path.read_text())
            c = doc["conditions"]
            camera = load_camera(path.parent / doc["camera"])
            lighting = Lighting(
                **{**c["lighting"], "direction_W": tuple(c["lighting"]["direction_W"])}
            )
            poses = {o["model"]: np.array(o["X_WO"]) for o in doc["objects"]}
            clean, _ = renderer.render(poses, camera, lighting)
            sensor = Sensor(**c["sensor"])
            images = tuple(
                sensor.apply(clean, np.random.default_rng([doc["seed"], doc["index"], j]))
                for j in range(frames)
            )
            robot = (np.array(doc["robot_q_rad"]), doc["finger_opening_m"])
            out.append((images, camera, read_truth(path), robot))
    finally:
        renderer.close()
    return out


class FusedRun:
    """Recognise functions for :func:`bench.vision.score` over :func:`fused_scenes`: every
    frame of a scene recognised once and fused in turn (:meth:`fused`: the last frame's fused
    recognitions); :meth:`last_frame`: that frame's own, from the same run; :meth:`tracked`:
    the first frame recognised and the others tracked from it, as the work site does between
    full searches, fused (each tracking call's wall and CPU time in :attr:`track_s`,
    :attr:`track_cpu_s`)."""

    def __init__(self, recognizer: Recognizer, symmetries: dict[str, np.ndarray]) -> None:
        self.recognizer, self.symmetries = recognizer, symmetries
        self._last: dict[int, list] = {}
        self.track_s: list[float] = []
        self.track_cpu_s: list[float] = []

    def tracked(self, images, camera, *robot) -> list:
        fusion = PoseFusion(self.symmetries)
        found = self.recognizer.recognize(images[0], camera, *robot)
        result = fusion.add([(d.model, d.X_WO, d.score) for d in found], searched=True)
        for image in images[1:]:
            t0, c0 = time.perf_counter(), time.process_time()
            found = self.recognizer.track(image, camera, found, *robot)
            self.track_s.append(time.perf_counter() - t0)
            self.track_cpu_s.append(time.process_time() - c0)
            result = fusion.add([(d.model, d.X_WO, d.score) for d in found], searched=False)
        return [_Found(f.model, f.X_WO) for f in result]

    def fused(self, images, camera, *robot) -> list:
        fusion = PoseFusion(self.symmetries)
        result: list = []
        for image in images:
            found = self.recognizer.recognize(image, camera, *robot)
            result = fusion.add([(d.model, d.X_WO, d.score) for d in found])
        self._last[id(images)] = found
        return [_Found(f.model, f.X_WO) for f in result]

    def last_frame(self, images, camera, *robot) -> list:
        return self._last.pop(id(images))
