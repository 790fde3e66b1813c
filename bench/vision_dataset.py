"""Rendered scenes with known answers: random block layouts on the table, seen by the camera.

Each scene is a grey PNG (pybullet's renderer, supersampled and averaged down so that edges have
sub-pixel grey levels), the camera JSON and the ground truth: every movable object's pose
``X_WO`` and the fraction of its projected area that is visible (occlusion by other objects and
the robot, and the image border, count as hidden).

Render one to a directory: ``python -m bench.vision_dataset --n N --seed S --out DIR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pybullet as p

from models.scene import CameraModel, Scene, load_scene
from models.transforms import invert_pose, make_pose
from work_site.camera import distort_px, render_grey
from work_site.sensor import CameraConditions, Lighting
from work_site.vision.model import convex_overlap_depth, transform
from work_site.vision.table import rest_rotations

DATASET_VERSION = 2
"""Written into every scene; a cached set of another version is rendered again. Raise it when
the rendering or the ground truth changes (2: the renderer's half-pixel offset made up for,
the arm's joints recorded)."""
WORK_AREA_XY_M = ((0.22, 0.68), (-0.25, 0.32))
"""Where blocks are dropped: around the frame, inside and outside it (x range, y range)."""
TOUCH_PROBABILITY = 0.35
"""Chance that a block is pushed against one placed before it (to make touching layouts)."""
CONTACT_GAP_M = 5e-4
"""Gap left between blocks placed 'touching' (the renderer cannot see the difference)."""


SUPPORTS = ("table", "leaning", "stacked")
"""How a block rests: flat on the table; an edge or corner on the table, leaning on something;
or not touching the table at all (on other blocks or the frame)."""
ON_TABLE_TOL_M = 2e-3
"""A vertex this close to the table top touches it (the physics lets contacts sink a little)."""
DROP_CLEARANCE_M = 0.01
"""A dropped block starts this far above the top of the block it is dropped on."""
DROP_SCATTER_M = 0.02
"""Standard deviation of a dropped block's start across the block it is dropped on."""
SETTLE_MAX_S = 4.0
"""Simulated time a drop may take to come to rest, at most."""
REST_SPEED_M_PER_S = 2e-3
REST_TURN_RAD_PER_S = 0.02
"""A block moving slower than these has come to rest."""


@dataclass(frozen=True)
class GroundTruth:
    """One movable object in a rendered scene: its model, pose, the fraction of its projected
    area that is visible and how it rests (one of :data:`SUPPORTS`; "" if not known)."""

    model: str
    X_WO: np.ndarray
    visible_fraction: float
    support: str = ""


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
        table = self.scene.object("table")
        corners = transform(table.X_WO, table.model.bbox_O)
        self.table_z = float(corners[:, 2].max())
        self._table_xy = tuple(zip(corners[:, :2].min(0), corners[:, :2].max(0), strict=True))
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

    def dropped_layout(
        self, rng: np.random.Generator, drop_probability: float
    ) -> dict[str, np.ndarray]:
        """:meth:`random_layout`, then each block with ``drop_probability`` lifted, turned at
        random (any orientation) and dropped onto another block, the physics letting it come to
        rest: on the block, leaning against it or the frame, or fallen to the table (the first,
        with nothing standing, is dropped onto the table). A block that falls off the table is
        parked out of view."""
        from scipy.spatial.transform import Rotation

        placed = self.random_layout(rng)
        on_table = [n for n, X in placed.items() if X[2, 3] > -0.5]
        dropped = [n for n in on_table if rng.random() < drop_probability]
        for name in dropped:  # off the table until its turn
            self.world.set_object_pose(name, make_pose(None, [5.0, 5.0 + len(name), -1.0]))
        for name, X in placed.items():
            if name not in dropped:
                self.world.set_object_pose(name, X)
        standing = [n for n in on_table if n not in dropped]
        V_O = {o.name: np.vstack([pt.vertices_O for pt in o.model.parts]) for o in self.movable}
        for name in dropped:
            if standing:
                target = standing[rng.integers(len(standing))]
                X_t = self.world.object_pose(target)
                top_z = float(transform(X_t, V_O[target])[:, 2].max())
                centre_xy = X_t[:2, 3]
            else:  # nothing to drop it on yet: onto the table where it was
                top_z, centre_xy = self.table_z, placed[name][:2, 3]
            R = Rotation.random(random_state=rng).as_matrix()
            xy = centre_xy + rng.normal(0.0, DROP_SCATTER_M, 2)
            lift = -float((V_O[name] @ R.T)[:, 2].min())
            X = make_pose(R, [xy[0], xy[1], top_z + DROP_CLEARANCE_M + lift])
            self.world.set_object_pose(name, X)
            standing.append(name)
            self._settle(standing)
        out = {}
        for name in placed:
            X = self.world.object_pose(name)
            low = float(transform(X, V_O[name])[:, 2].min())
            (x0, x1), (y0, y1) = self._table_xy
            inside = x0 <= X[0, 3] <= x1 and y0 <= X[1, 3] <= y1
            out[name] = (
                X
                if name not in standing or (low > self.table_z - ON_TABLE_TOL_M and inside)
                else make_pose(None, [5.0 + len(out), 5.0, -1.0])
            )
        return out

    def _settle(self, names: list[str]) -> None:
        """Step the physics until the blocks ``names`` have come to rest (bounded time)."""
        chunk = 50
        for _ in range(int(SETTLE_MAX_S / (chunk * self.world.time_step_s))):
            self.world.step(chunk)
            moving = False
            for name in names:
                v, w = p.getBaseVelocity(self.world.bodies[name], physicsClientId=self.world.cid)
                if np.linalg.norm(v) > REST_SPEED_M_PER_S or np.linalg.norm(w) > (
                    REST_TURN_RAD_PER_S
                ):
                    moving = True
                    break
            if not moving:
                return

    def support(self, name: str, X_WO: np.ndarray) -> str:
        """How block ``name`` at ``X_WO`` rests (one of :data:`SUPPORTS`)."""
        model = self.scene.object(name).model
        z = transform(X_WO, np.vstack([pt.vertices_O for pt in model.parts]))[:, 2]
        low = np.abs(z - self.table_z) < ON_TABLE_TOL_M
        if not low.any():
            return "stacked"
        V = transform(X_WO, np.vstack([pt.vertices_O for pt in model.parts]))[low]
        # Flat on the table: the touching vertices span an area, not a line or a point.
        spread = np.linalg.svd(V[:, :2] - V[:, :2].mean(0), compute_uv=False) if len(V) > 2 else 0
        return "table" if len(V) > 2 and spread[1] > 1e-3 else "leaning"

    def render(
        self,
        poses: dict[str, np.ndarray],
        camera: CameraModel | None = None,
        lighting: Lighting | None = None,
    ) -> tuple[np.ndarray, list[GroundTruth]]:
        """Set the poses, render the ideal grey image (h, w) uint8 through ``camera`` (default:
        the scene's) and measure visibility and support."""
        for name, X_WO in poses.items():
            self.world.set_object_pose(name, X_WO)
        cam = camera or self.scene.camera
        s = self.supersample
        grey, seg = render_grey(self.world.cid, cam, s, segmentation=True, lighting=lighting)
        truth = []
        for obj in self.movable:
            X_WO = poses[obj.name]
            body = self.world.bodies[obj.name]
            visible = int(np.count_nonzero(seg == body))
            full = _projected_area_px(cam, X_WO, obj.model.parts, s)
            frac = float(min(1.0, visible / full)) if full > 0 else 0.0
            support = self.support(obj.name, X_WO) if X_WO[2, 3] > -0.5 else ""
            truth.append(GroundTruth(obj.name, X_WO, frac, support))
        return grey, truth


def _projected_area_px(camera: CameraModel, X_WO: np.ndarray, parts, supersample: int) -> float:
    """Area (in supersampled pixels) of the object's silhouette, inside or outside the image."""
    X_CO = invert_pose(camera.X_WC) @ X_WO
    s = supersample
    big = camera.scaled(s)
    K = big.K
    dist = np.asarray(camera.dist, dtype=np.float64)
    w, h = big.width, big.height
    pad_x, pad_y = w, h
    canvas = np.zeros((3 * h, 3 * w), dtype=np.uint8)
    for part in parts:
        p_C = transform(X_CO, part.vertices_O)
        if np.any(p_C[:, 2] <= 1e-3):
            return 0.0
        uv = distort_px(p_C[:, :2] / p_C[:, 2:], K, dist) + np.array([pad_x, pad_y])
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
    out: Path,
    n: int,
    seed: int,
    supersample: int = 2,
    noise_sigma: float = 1.0,
    conditions: CameraConditions | None = None,
    drop_probability: float = 0.0,
) -> list[Path]:
    """Render ``n`` scenes into ``out``: ``scene_NNNN.png`` + ``scene_NNNN.json`` (ground truth)
    and the camera JSON. Returns the scene JSON paths.

    Without ``conditions`` every scene is seen by the scene's camera with Gaussian noise
    ``noise_sigma``; with them, each scene draws its own sensor, light, camera place and lens
    (``camera_NNNN.json``, the camera as calibrated: where it really is). With
    ``drop_probability`` > 0 blocks are also dropped onto others (:meth:`dropped_layout`)."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    renderer = SceneRenderer(supersample=supersample)
    nominal = renderer.scene.camera
    try:
        if conditions is None:
            (out / "camera.json").write_text(json.dumps(nominal.to_json(), indent=1))
        paths = []
        for i in range(n):
            if n >= 20 and i % (n // 10) == 0:
                print(f"rendering scene {i + 1} of {n}", file=sys.stderr, flush=True)
            stem = f"scene_{i:04d}"
            poses = (
                renderer.dropped_layout(rng, drop_probability)
                if drop_probability > 0
                else renderer.random_layout(rng)
            )
            doc: dict = {
                "version": DATASET_VERSION,
                "image": f"{stem}.png",
                "camera": "camera.json",
                "seed": seed,
                "index": i,
            }
            if conditions is None:
                grey, truth = renderer.render(poses)
                grey = degrade(grey, rng, noise_sigma=noise_sigma)
            else:
                c = conditions.draw(rng)
                camera = dataclasses.replace(nominal, X_WC=nominal.X_WC @ c.X_offset, dist=c.dist)
                grey, truth = renderer.render(poses, camera, c.lighting)
                grey = c.sensor.apply(grey, rng)
                doc["camera"] = f"camera_{i:04d}.json"
                (out / doc["camera"]).write_text(json.dumps(camera.to_json(), indent=1))
                doc["conditions"] = {
                    "sensor": dataclasses.asdict(c.sensor),
                    "lighting": dataclasses.asdict(c.lighting),
                    "camera_offset_m": float(np.linalg.norm(c.X_offset[:3, 3])),
                    "camera_turn_deg": float(
                        np.rad2deg(
                            np.arccos(np.clip((np.trace(c.X_offset[:3, :3]) - 1) / 2, -1, 1))
                        )
                    ),
                    "dist": c.dist.tolist(),
                }
            cv2.imwrite(str(out / f"{stem}.png"), grey)
            q, fingers = renderer.world.robot_joint_positions()
            doc["robot_q_rad"] = q.tolist()  # the arm in view hides blocks; vision knows it
            doc["finger_opening_m"] = float(np.sum(fingers))
            doc["objects"] = [
                {
                    "model": t.model,
                    "X_WO": t.X_WO.tolist(),
                    "visible_fraction": round(t.visible_fraction, 4),
                    "support": t.support,
                }
                for t in truth
            ]
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
        GroundTruth(
            o["model"],
            np.array(o["X_WO"], dtype=np.float64),
            o["visible_fraction"],
            o.get("support", ""),
        )
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
