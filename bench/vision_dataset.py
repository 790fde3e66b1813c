"""Rendered scenes with known answers: random block layouts on the table, seen by the camera.

Each scene is a grey PNG (pybullet's renderer, supersampled and averaged down so that edges have
sub-pixel grey levels), the camera JSON and the ground truth: every movable object's pose
``X_WO`` and the fraction of its projected area that is visible (occlusion by other objects and
the robot, and the image border, count as hidden).

Render one to a directory: ``python -m bench.vision_dataset --n N --seed S --out DIR``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from models.scene import CameraModel, Scene, load_scene
from models.transforms import invert_pose, make_pose
from work_site.camera import render_grey
from work_site.vision.model import convex_overlap_depth, project, transform
from work_site.vision.table import rest_rotations

WORK_AREA_XY_M = ((0.22, 0.68), (-0.25, 0.32))
"""Where blocks are dropped: around the frame, inside and outside it (x range, y range)."""
TOUCH_PROBABILITY = 0.35
"""Chance that a block is pushed against one placed before it (to make touching layouts)."""
CONTACT_GAP_M = 5e-4
"""Gap left between blocks placed 'touching' (the renderer cannot see the difference)."""


@dataclass(frozen=True)
class GroundTruth:
    """One movable object in a rendered scene."""

    model: str
    X_WO: np.ndarray
    visible_fraction: float


class SceneRenderer:
    """Places the scene's movable blocks at random and renders them; owns a pybullet World."""

    def __init__(self, scene: Scene | None = None, supersample: int = 2) -> None:
        from work_site.world import World

        self.scene = scene if scene is not None else load_scene()
        self.world = World(self.scene)
        self.supersample = supersample
        self.movable = [o for o in self.scene.objects if not o.fixed]
        self._rotations = {
            o.name: rest_rotations(
                np.vstack([pt.vertices_O for pt in o.model.parts]), o.model.com_O
            )
            for o in self.movable
        }
        self._fixed_parts_W = [
            transform(o.X_WO, pt.vertices_O)
            for o in self.scene.objects
            if o.fixed and o.name != "table"
            for pt in o.model.parts
        ]

    def close(self) -> None:
        """Release the pybullet client."""
        self.world.close()

    def _parts_W(self, name: str, X_WO: np.ndarray) -> list[np.ndarray]:
        model = self.scene.object(name).model
        return [transform(X_WO, pt.vertices_O) for pt in model.parts]

    def _collides(self, parts: list[np.ndarray], others: list[np.ndarray]) -> bool:
        for a in parts:
            ca, ra = a.mean(0), np.max(np.linalg.norm(a - a.mean(0), axis=1))
            for b in others:
                cb = b.mean(0)
                rb = np.max(np.linalg.norm(b - cb, axis=1))
                if np.linalg.norm(ca - cb) > ra + rb + CONTACT_GAP_M:
                    continue
                if convex_overlap_depth(a, b) > 0:
                    return True
        return False

    def random_layout(self, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """Poses ``X_WO`` for every movable object: resting on a stable face, not colliding with
        the frame or each other, some pushed into contact with another block."""
        placed: dict[str, np.ndarray] = {}
        occupied = list(self._fixed_parts_W)
        (x0, x1), (y0, y1) = WORK_AREA_XY_M
        for obj in self.movable:
            rots = self._rotations[obj.name]
            V_O = np.vstack([pt.vertices_O for pt in obj.model.parts])
            for _ in range(200):
                R0 = rots[rng.integers(len(rots))]
                yaw = rng.uniform(-np.pi, np.pi)
                Rz = np.array(
                    [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]]
                )
                R = Rz @ R0
                z = -np.min(V_O @ R[2])
                if placed and rng.random() < TOUCH_PROBABILITY:
                    anchor = placed[list(placed)[rng.integers(len(placed))]]
                    ang = rng.uniform(-np.pi, np.pi)
                    u = np.array([np.cos(ang), np.sin(ang), 0.0])
                    lo, hi = 0.0, 0.2
                    xy = anchor[:3, 3] + hi * u
                    X = make_pose(R, [xy[0], xy[1], z])
                    if self._collides(self._parts_W(obj.name, X), occupied):
                        continue
                    for _ in range(20):  # bisect to the contact distance
                        mid = 0.5 * (lo + hi)
                        xy = anchor[:3, 3] + mid * u
                        X = make_pose(R, [xy[0], xy[1], z])
                        if self._collides(self._parts_W(obj.name, X), occupied):
                            lo = mid
                        else:
                            hi = mid
                    xy = anchor[:3, 3] + (hi + CONTACT_GAP_M) * u
                else:
                    xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
                X = make_pose(R, [xy[0], xy[1], z])
                parts = self._parts_W(obj.name, X)
                if self._collides(parts, occupied):
                    continue
                placed[obj.name] = X
                occupied.extend(parts)
                break
            else:
                # No room: park it off the table, out of view (it is then 0 % visible).
                placed[obj.name] = make_pose(None, [5.0 + len(placed), 5.0, -1.0])
        return placed

    def render(self, poses: dict[str, np.ndarray]) -> tuple[np.ndarray, list[GroundTruth]]:
        """Set the poses, render the grey image (h, w) uint8 and measure visibility."""
        for name, X_WO in poses.items():
            self.world.set_object_pose(name, X_WO)
        cam = self.scene.camera
        s = self.supersample
        grey, seg = render_grey(self.world.cid, cam, s, segmentation=True)
        truth = []
        for obj in self.movable:
            X_WO = poses[obj.name]
            body = self.world.bodies[obj.name]
            visible = int(np.count_nonzero(seg == body))
            full = _projected_area_px(cam, X_WO, obj.model.parts, s)
            frac = float(min(1.0, visible / full)) if full > 0 else 0.0
            truth.append(GroundTruth(obj.name, X_WO, frac))
        return grey, truth


def _projected_area_px(camera: CameraModel, X_WO: np.ndarray, parts, supersample: int) -> float:
    """Area (in supersampled pixels) of the object's silhouette, inside or outside the image."""
    X_CO = invert_pose(camera.X_WC) @ X_WO
    s = supersample
    K = camera.K.copy()
    K[:2] *= s
    K[:2, 2] += (s - 1) / 2  # pixel centres of the supersampled grid
    w, h = camera.width * s, camera.height * s
    pad_x, pad_y = w, h
    canvas = np.zeros((3 * h, 3 * w), dtype=np.uint8)
    for part in parts:
        p_C = transform(X_CO, part.vertices_O)
        if np.any(p_C[:, 2] <= 1e-3):
            return 0.0
        uv = project(p_C, K) + np.array([pad_x, pad_y])
        if np.any(np.abs(uv) > 1e6):
            return 0.0
        hull = cv2.convexHull(np.round(uv * 16).astype(np.int32))
        cv2.fillConvexPoly(canvas, hull, 1, lineType=cv2.LINE_8, shift=4)
    return float(np.count_nonzero(canvas))


def degrade(
    image: np.ndarray,
    rng: np.random.Generator,
    noise_sigma: float = 0.0,
    blur_sigma_px: float = 0.0,
    gain: float = 1.0,
    offset: float = 0.0,
) -> np.ndarray:
    """A camera's imperfections on a rendered grey image: lighting gain/offset, Gaussian blur,
    additive Gaussian noise (grey levels); 8-bit result."""
    img = image.astype(np.float64) * gain + offset
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def write_dataset(
    out: Path, n: int, seed: int, supersample: int = 2, noise_sigma: float = 1.0
) -> list[Path]:
    """Render ``n`` scenes into ``out``: ``scene_NNNN.png`` + ``scene_NNNN.json`` (ground truth)
    and one ``camera.json``. Returns the scene JSON paths."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    renderer = SceneRenderer(supersample=supersample)
    try:
        (out / "camera.json").write_text(json.dumps(renderer.scene.camera.to_json(), indent=1))
        paths = []
        for i in range(n):
            poses = renderer.random_layout(rng)
            grey, truth = renderer.render(poses)
            grey = degrade(grey, rng, noise_sigma=noise_sigma)
            stem = f"scene_{i:04d}"
            cv2.imwrite(str(out / f"{stem}.png"), grey)
            doc = {
                "image": f"{stem}.png",
                "camera": "camera.json",
                "seed": seed,
                "index": i,
                "objects": [
                    {
                        "model": t.model,
                        "X_WO": t.X_WO.tolist(),
                        "visible_fraction": round(t.visible_fraction, 4),
                    }
                    for t in truth
                ],
            }
            path = out / f"{stem}.json"
            path.write_text(json.dumps(doc, indent=1))
            paths.append(path)
        return paths
    finally:
        renderer.close()


def read_truth(path: Path) -> list[GroundTruth]:
    """The ground truth of one scene JSON written by :func:`write_dataset`."""
    doc = json.loads(Path(path).read_text())
    return [
        GroundTruth(o["model"], np.array(o["X_WO"], dtype=np.float64), o["visible_fraction"])
        for o in doc["objects"]
    ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench.vision_dataset``."""
    parser.add_argument("--n", type=int, required=True, help="number of scenes to render")
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the layouts and the noise (default: %(default)s)",
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="directory for the PNG, scene JSON and camera.json"
    )
    parser.add_argument(
        "--supersample",
        type=int,
        default=4,
        metavar="K",
        help="render K× larger and average down, for sub-pixel edges (default: %(default)s)",
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=1.0,
        metavar="SIGMA",
        help="standard deviation of the Gaussian noise added to each pixel, grey levels "
        "(default: %(default)s)",
    )


def main(args: argparse.Namespace) -> int:
    """Render the dataset; returns the exit code (2 for options out of range)."""
    problem = (
        "--n must be ≥ 1" if args.n < 1
        else "--supersample must be in 1..8" if not 1 <= args.supersample <= 8
        else "--noise must be in [0, 64]" if not 0 <= args.noise <= 64
        else None
    )  # fmt: skip
    if problem:
        print(f"bench.vision_dataset: {problem}", file=sys.stderr)
        return 2
    paths = write_dataset(args.out, args.n, args.seed, args.supersample, args.noise)
    print(f"wrote {len(paths)} scenes to {args.out}")
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(
        prog="python -m bench.vision_dataset",
        description="Write N grey PNG scenes, camera.json and per-scene ground-truth JSON "
        "(poses X_WO and visible fraction of every block).",
    )
    add_arguments(_parser)
    sys.exit(main(_parser.parse_args()))
