"""Vision commands of ``work-site``: ``recognize`` and ``calibrate``.

work-site recognize IMAGE.png --camera CAMERA.json [--models DIR] [--scene FILE] [--json]
work-site calibrate --out CAMERA.json [--camera FILE] [--scene FILE] [--image FILE]

Also runnable alone: ``python -m work_site.vision.cli recognize …`` / ``calibrate …``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from models.errors import ModelError
from models.layout import random_layout
from models.scene import DEFAULT_SCENE, Scene, load_camera, load_object, load_scene


def add_recognize_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", type=Path, help="8-bit grey (or colour) image file, e.g. PNG")
    parser.add_argument(
        "--camera", type=Path, required=True, help="camera JSON (docs/design.md format)"
    )
    parser.add_argument(
        "--models",
        type=Path,
        default=None,
        metavar="DIR",
        help="directory of object URDFs to look for (default: the scene's movable objects)",
    )
    parser.add_argument(
        "--scene",
        type=Path,
        default=DEFAULT_SCENE,
        help="scene JSON for the fixed environment and work area (default: %(default)s)",
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="where the model index is cached (default: ~/.cache/telerobot/vision)",
    )
    parser.add_argument("--json", action="store_true", help="print the recognitions JSON")


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="camera JSON to write")
    parser.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera JSON with the rough pose to start from (default: the scene's camera)",
    )
    parser.add_argument(
        "--scene",
        type=Path,
        default=DEFAULT_SCENE,
        help="scene JSON: its frame is the calibration feature (default: %(default)s)",
    )
    parser.add_argument(
        "--image",
        type=Path,
        default=None,
        help="camera image of the work site for the pose (default: render the simulated work "
        "site, its blocks laid out by --seed)",
    )
    parser.add_argument(
        "--views", type=int, default=15, help="chessboard views for the intrinsics (default: 15)"
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the chessboard views and of the rendered image's block layout (default: 0)",
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``recognize`` and ``calibrate`` to a ``work-site`` sub-command set."""
    rec = subparsers.add_parser(
        "recognize",
        help="recognise and locate the blocks in one camera image",
        description="Print the objects recognised in IMAGE with their poses X_WO and scores.",
    )
    add_recognize_arguments(rec)
    rec.set_defaults(func=recognize_main)
    cal = subparsers.add_parser(
        "calibrate",
        help="calibrate the camera: intrinsics from a chessboard, pose from the frame",
        description="Render chessboard views for the intrinsics (OpenCV), fit the camera pose "
        "to the puzzle frame's edges starting from --camera, print the residuals and write "
        "the camera JSON.",
    )
    add_calibrate_arguments(cal)
    cal.set_defaults(func=calibrate_main)


def _read_image(path: Path) -> np.ndarray:
    """An 8-bit grey image from a file; ValueError naming the problem."""
    import cv2

    if not path.is_file():
        raise ValueError(f"{path}: image file does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not an image file OpenCV can read")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"{path}: expected an 8-bit grey image, got {img.dtype} {img.shape}")
    return img


def recognize_main(args: argparse.Namespace) -> int:
    """Run recognition on one image file; prints JSON or a table; returns the exit code."""
    from work_site.vision.recognizer import Recognizer

    try:
        image = _read_image(args.image)
        camera = load_camera(args.camera)
        if image.shape != (camera.height, camera.width):
            raise ValueError(
                f"{args.image}: image is {image.shape[1]}×{image.shape[0]} but camera "
                f"{args.camera} is {camera.width}×{camera.height}"
            )
        scene = load_scene(args.scene)
        models = None
        if args.models is not None:
            if not args.models.is_dir():
                raise ValueError(f"{args.models}: models directory does not exist")
            urdfs = sorted(args.models.glob("*.urdf"))
            if not urdfs:
                raise ValueError(f"{args.models}: no .urdf object models in it")
            fixed = {o.model.urdf_path for o in scene.objects if o.fixed}
            models = [load_object(u) for u in urdfs if u.resolve() not in fixed]
        recognizer = Recognizer(models, scene=scene, cache_dir=args.cache_dir)
        t0 = time.perf_counter()
        found = recognizer.recognize(image, camera)
        elapsed = time.perf_counter() - t0
    except (ModelError, ValueError) as e:
        print(f"work-site recognize: {e}", file=sys.stderr)
        return 2
    doc = {
        "objects": [
            {"model": r.model, "X_WO": r.X_WO.tolist(), "score": round(r.score, 4)} for r in found
        ],
        "elapsed_s": round(elapsed, 4),
    }
    if args.json:
        print(json.dumps(doc))
    else:
        for r in found:
            x, y, z = r.X_WO[:3, 3]
            print(f"{r.model:12s} score {r.score:.2f}  at x {x:.4f} y {y:.4f} z {z:.4f} m")
        print(f"{len(found)} object(s) in {elapsed * 1000:.0f} ms")
    return 0


def _render(scene: Scene, seed: int) -> np.ndarray:
    """The simulated work site's camera image, the blocks laid out by ``seed`` around the frame
    (as ``work-site serve --seed`` lays them), supersampled 3× for sub-pixel edges."""
    from work_site.camera import render_grey
    from work_site.world import World

    world = World(scene)
    try:
        for name, X_WO in random_layout(scene, seed).items():
            world.set_object_pose(name, X_WO)
        return render_grey(world.cid, scene.camera, supersample=3)
    finally:
        world.close()


def calibrate_main(args: argparse.Namespace) -> int:
    """Calibrate intrinsics and pose in simulation; write the camera JSON; exit code."""
    from work_site.vision.calibration import (
        calibrate_extrinsics,
        calibrate_intrinsics,
        calibrated_camera,
        frame_object,
        render_board_views,
    )

    try:
        if not 4 <= args.views <= 200:
            raise ValueError("--views must be in 4..200")
        scene = load_scene(args.scene)
        guess = load_camera(args.camera) if args.camera is not None else scene.camera
        # The simulated camera is the scene's: render through it, estimate from the images.
        intr = calibrate_intrinsics(render_board_views(scene.camera, args.views, args.seed))
        image = _read_image(args.image) if args.image is not None else _render(scene, args.seed)
        with_k = calibrated_camera(guess, intr, None)
        extr = calibrate_extrinsics(image, with_k, frame_object(scene))
    except (ModelError, ValueError) as e:
        print(f"work-site calibrate: {e}", file=sys.stderr)
        return 2
    camera = calibrated_camera(guess, intr, extr.X_WC)
    args.out.write_text(json.dumps(camera.to_json(), indent=1))
    print(
        f"intrinsics: {intr.views} chessboard views, RMS reprojection {intr.rms_px:.3f} px; "
        + " ".join(
            f"{name} {value:.2f} ± {sd:.2f}"
            for name, value, sd in zip(
                ("fx", "fy", "cx", "cy"),
                (intr.K[0, 0], intr.K[1, 1], intr.K[0, 2], intr.K[1, 2]),
                intr.std_f_c_px,
                strict=True,
            )
        )
        + " px (± one standard deviation)"
    )
    print(
        f"pose: {extr.edges} frame edges, line RMS {extr.rms_px:.3f} px, corner RMS "
        f"{extr.corner_rms_px:.3f} px; camera at {np.round(extr.X_WC[:3, 3], 4).tolist()} m"
    )
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str]) -> int:
    """``python -m work_site.vision.cli COMMAND …``: the vision commands without the server's."""
    parser = argparse.ArgumentParser(prog="work-site", description="Vision commands.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    register(sub)
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
