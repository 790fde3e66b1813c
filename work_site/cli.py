"""``work-site``: the work-site server and its tools.

work-site serve [--scene FILE] [--site-id ID] [--listen ENDPOINT] [--connect ENDPOINT]
                [--single-link] [--certs DIR [--operators CN ...]] [--insecure]
                [--camera-encoding raw|png|jpeg[:QUALITY]]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import threading
from pathlib import Path

import zenoh

from models.errors import ModelError
from models.layout import laid_out, perturbed_camera_pose, random_layout
from models.scene import DEFAULT_SCENE, load_scene
from protocol import DEFAULT_SITE_ID, DEFAULT_WORK_SITE_ENDPOINT, ProtocolError, make_config
from protocol.images import DEFAULT_JPEG_QUALITY, parse_image_encoding
from protocol.keys import check_site_id
from protocol.session import (
    TlsFiles,
    check_listeners,
    link_endpoints,
    operator_only_access_control,
)
from protocol.signals import dump_stacks_on_sigusr1, install_stop_signals
from work_site.control.controller import DEFAULT_SURFACE_STIFFNESS_N_PER_M
from work_site.options import DEFAULT_CAMERA_SENSOR
from work_site.vision import cli as vision_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="work-site",
        description="The work site: a simulated Puma-type arm, gripper, wrist force sensor, camera "
        "and wooden blocks (pybullet), served to operator sites over zenoh.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    serve = sub.add_parser(
        "serve",
        help="run the work-site server (the default command)",
        description="Run the work-site server until Ctrl-C or SIGTERM.",
    )
    add_serve_arguments(serve)
    vision_cli.register(sub)  # recognize, calibrate
    return parser


def default_journal(site_id: str) -> Path:
    """``$XDG_STATE_HOME/telerobot/<site_id>-programs.jsonl`` (``~/.local/state/…``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "telerobot" / f"{site_id}-programs.jsonl"


DEFAULT_VISION_RATE_HZ = 1.0
"""Vision's default rate: what it sustains here next to the camera renderer and the 1 kHz
control loop on two cores (see docs/benchmarks.md)."""


def add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scene",
        type=Path,
        default=DEFAULT_SCENE,
        help="scene JSON (default: the puzzle scene, %(default)s)",
    )
    parser.add_argument(
        "--site-id",
        default=DEFAULT_SITE_ID,
        help="this work site's id in key expressions (default: %(default)s)",
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on; repeatable (default: "
        f"{DEFAULT_WORK_SITE_ENDPOINT}). One tcp/ or tls/ endpoint HOST:PORT becomes two links: "
        "commands, programs, reports, heartbeats, recognitions (priorities 0-3) on PORT, robot "
        "state and camera frames (4-7) on PORT+1, so that neither images nor a lost state's "
        "resend delay a command or a report; several are each split so",
    )
    parser.add_argument(
        "--single-link",
        action="store_true",
        help="listen on (and connect to) the one endpoint given, all priorities on one link (no "
        "PORT+1)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint (router or peer) to connect to; repeatable. One tcp/ or tls/ "
        "HOST:PORT is split like --listen's (a router from deploy/router.py listens on both "
        "ports); several (e.g. two meshed routers) are each split so",
    )
    security = parser.add_argument_group(
        "security",
        "A listener on a non-loopback address must be a tls/ endpoint with --certs (mutual TLS); "
        "loopback listeners stay unauthenticated.",
    )
    security.add_argument(
        "--certs",
        type=Path,
        default=None,
        metavar="DIR",
        help="mutual TLS for tls/ endpoints with DIR/ca.pem and DIR/NAME.{pem,key} (made by "
        "deploy/make-certs.sh)",
    )
    security.add_argument(
        "--cert-name",
        default="work-site",
        metavar="NAME",
        help="this site's certificate in --certs (default: %(default)s)",
    )
    security.add_argument(
        "--operators",
        nargs="+",
        default=None,
        metavar="CN",
        help="only peers whose certificate common name is listed may send programs and stops "
        "(zenoh access control; needs --certs)",
    )
    security.add_argument(
        "--lease-ms",
        type=int,
        default=None,
        metavar="MS",
        help="zenoh link lease: a silent peer (a cut link) is declared gone after this long "
        "(default: zenoh's 10000)",
    )
    security.add_argument(
        "--insecure",
        action="store_true",
        help="allow a plain (unauthenticated, unencrypted) listener on a non-loopback address: "
        "for an isolated lab network only",
    )
    parser.add_argument(
        "--no-camera", action="store_true", help="do not render or publish camera frames"
    )
    parser.add_argument(
        "--no-stream-pacing",
        action="store_true",
        help="send robot states and camera frames at their full rates even when the operator's "
        "link queues them (default: fewer, until the queue is gone)",
    )
    parser.add_argument(
        "--camera-supersample",
        type=int,
        default=2,
        metavar="N",
        help="render N× larger and average down, for realistic anti-aliased edges (cost ≈ N²; "
        "default: %(default)s)",
    )
    parser.add_argument(
        "--camera-encoding",
        default="jpeg",
        metavar="raw|png|jpeg[:QUALITY]",
        help="how camera frames travel to operators (vision here always uses the uncompressed "
        "frame): raw (308 kB a 640×480 frame), png (lossless, 133 kB), jpeg at QUALITY 1..100 "
        f"(default {DEFAULT_JPEG_QUALITY}: 12 kB, within the sensor noise; docs/benchmarks.md) "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--camera-noise",
        type=float,
        default=DEFAULT_CAMERA_SENSOR.read_noise_grey,
        metavar="GREY",
        help="the sensor's read noise, standard deviation in grey levels, on top of its shot "
        "noise, blur and gain (docs/design.md, 'The camera as a real one sees') "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="lay the blocks out at random (seeded), outside the frame, and put the real "
        "camera a little off its calibration (2 mm, 0.2°); default: the scene file as it is",
    )
    parser.add_argument(
        "--camera-seed",
        type=int,
        default=None,
        metavar="N",
        help="put the real camera a little off its calibration (2 mm, 0.2°), seeded, the "
        "blocks where the scene file has them (--seed does both); default: --seed's",
    )
    parser.add_argument(
        "--publish-truth",
        action="store_true",
        help="publish the simulation's ground truth (every object's true pose) with each "
        "camera frame, for end-to-end evaluation: operator-site run and the benchmarks need "
        "it; a real cell has none",
    )
    parser.add_argument(
        "--vision-rate",
        type=float,
        default=None,
        metavar="HZ",
        help="recognise at most this many camera frames per second, in a separate process; "
        "0 turns vision off (default: 1 with the camera, 0 without)",
    )
    parser.add_argument(
        "--no-vision-tracking",
        action="store_true",
        help="recognise frames only at --vision-rate, in full; by default the objects found are "
        "also followed in every camera frame between (a fraction of the time, poses fused "
        "over more frames)",
    )
    parser.add_argument(
        "--vision-scale",
        type=float,
        default=1.0,
        metavar="F",
        help="recognise the frame resized by F, 0.25..2 (0.5: 320×240; faster, less accurate; "
        "default: %(default)s)",
    )
    parser.add_argument(
        "--vision-index-views",
        type=int,
        default=None,
        metavar="N",
        help="viewing directions sampled for vision's model index, 50..20000 (default: "
        "vision's own; a new value builds and caches its index at start-up)",
    )
    parser.add_argument(
        "--physics-rate",
        type=float,
        default=1000.0,
        metavar="HZ",
        help="physics steps per second of real time, 500..2000 and a multiple of 100 "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--journal",
        type=Path,
        default=None,
        metavar="FILE",
        help="append every program id and report here, so that a program re-sent after a "
        "restart is never run twice (default: $XDG_STATE_HOME/telerobot/SITE_ID-programs.jsonl)",
    )
    parser.add_argument(
        "--surface-stiffness",
        type=float,
        default=DEFAULT_SURFACE_STIFFNESS_N_PER_M,
        metavar="N_PER_M",
        help="contact moves' impedance stiffness along the contact surfaces; along the normals "
        "it is 1000 N/m (default: %(default)s; 1000 is the paper's isotropic impedance, under "
        "which friction holds the block 2-5 mm behind its path: docs/benchmarks.md, end to end)",
    )
    parser.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        metavar="X",
        help="simulate X seconds per second of wall time (default: 1, real time; more for "
        "benchmarks, as far as the machine keeps up)",
    )
    parser.add_argument(
        "--state-rate",
        type=float,
        default=100.0,
        metavar="HZ",
        help="robot-state messages per second (default: %(default)s)",
    )
    parser.add_argument(
        "--deadman-s",
        type=float,
        default=0.5,
        metavar="S",
        help="stop a running program when its operator's heartbeats have not come for S "
        "seconds, 0.2..5 (default: %(default)s), and 3 of its round trips more as its "
        "heartbeats measure them (at most 5 s in all)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")


def serve(args: argparse.Namespace) -> int:
    """Run the server with parsed ``args`` until SIGINT/SIGTERM; returns the exit code."""
    from work_site.options import ServerOptions
    from work_site.server import WorkSiteServer  # heavy imports after parsing
    from work_site.world import check_scene

    try:
        check_site_id(args.site_id)
        scene = load_scene(args.scene)
        check_scene(scene)
        camera_X_WC = None
        if args.seed is not None:
            scene = laid_out(scene, random_layout(scene, args.seed))
        camera_seed = args.camera_seed if args.camera_seed is not None else args.seed
        if camera_seed is not None:
            X_WC = perturbed_camera_pose(scene.camera.X_WC, camera_seed)
            camera_X_WC = tuple(map(tuple, X_WC))
        camera_encoding, camera_quality = parse_image_encoding(args.camera_encoding)
        if not 0.0 <= args.camera_noise <= 64.0:
            raise ValueError(f"--camera-noise must be in [0, 64] grey levels: {args.camera_noise}")
        options = ServerOptions(
            camera_encoding=camera_encoding,
            camera_quality=camera_quality,
            camera_X_WC=camera_X_WC,
            time_scale=args.time_scale,
            surface_stiffness_n_per_m=args.surface_stiffness,
            journal=args.journal or default_journal(args.site_id),
            site_id=args.site_id,
            physics_rate_hz=args.physics_rate,
            state_rate_hz=args.state_rate,
            deadman_s=args.deadman_s,
            publish_truth=args.publish_truth,
            camera=not args.no_camera,
            stream_pacing=not args.no_stream_pacing,
            camera_supersample=args.camera_supersample,
            camera_sensor=dataclasses.replace(
                DEFAULT_CAMERA_SENSOR, read_noise_grey=args.camera_noise
            ),
            vision_scale=args.vision_scale,
            vision_tracking=not args.no_vision_tracking,
            vision_index_views=args.vision_index_views,
            vision_rate_hz=(
                args.vision_rate
                if args.vision_rate is not None
                else (0.0 if args.no_camera else DEFAULT_VISION_RATE_HZ)
            ),
        )
        given = args.listen if args.listen is not None else [DEFAULT_WORK_SITE_ENDPOINT]
        listen, links_note = link_endpoints(given, args.single_link)
        tls = None
        if args.certs is not None:
            tls = TlsFiles.in_dir(args.certs, args.cert_name)
        if args.operators and tls is None:
            raise ValueError("--operators needs --certs (identities come from TLS certificates)")
        check_listeners(given, tls, args.insecure)  # the derived ones share host and protocol
        acl = operator_only_access_control(args.site_id, args.operators) if args.operators else None
        connect = link_endpoints(args.connect, args.single_link)[0] if args.connect else []
        config = make_config(
            listen=listen, connect=connect, tls=tls, access_control=acl, lease_ms=args.lease_ms
        )
    except (ModelError, ProtocolError, ValueError) as e:
        print(f"work-site: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    install_stop_signals(stop, "work-site")
    print(
        f"work-site: serving site {args.site_id!r} on {', '.join(listen) or 'no listener'}"
        + (f", connecting to {', '.join(connect)}" if connect else "")
        + f" ({links_note})"
        + ("; mutual TLS" if tls else "")
        + ("; commands only from " + ", ".join(args.operators) if args.operators else "")
        + ("; --insecure" if args.insecure else ""),
        flush=True,
    )
    try:
        WorkSiteServer(scene, config, options).run(stop)
    except zenoh.ZError as e:  # zenoh.open: e.g. a port in use
        hint = " (the state and camera link takes PORT+1: choose another port, or --single-link)"
        print(f"work-site: zenoh: {e}".strip() + (hint if len(listen) > 1 else ""), file=sys.stderr)
        return 1
    return 0


def main(argv: list[str]) -> int:
    """Parse ``argv`` (without the program name) and run the chosen command."""
    parser = build_parser()
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help")):
        argv = ["serve", *argv]
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    if args.command == "serve":
        return serve(args)
    if hasattr(args, "func"):  # recognize, calibrate
        return args.func(args)
    parser.print_help()
    return 2


def run() -> None:
    """Console-script entry point."""
    dump_stacks_on_sigusr1()
    sys.exit(main(sys.argv[1:]))
