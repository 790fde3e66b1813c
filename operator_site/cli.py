"""``operator-site``: the operator's web page, connected to a work site over zenoh.

operator-site serve [--connect ENDPOINT] [--port 8080]   # the page, for a running work site
                    [--single-link]                      # (default: two links, PORT and PORT+1)
operator-site demo                                       # both sites on this machine
operator-site demo --scripted corner --seed 3 --json     # the whole chain, no person
operator-site run examples/tasks/cube-corner.json --seed 3 --json   # a task file, no person
operator-site recover retract                                  # back off after a failure
operator-site recover resume --program program.msgpack         # go on after a stop
"""

from __future__ import annotations

import argparse
import logging
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from models.errors import ModelError
from models.scene import DEFAULT_SCENE, load_scene
from protocol import DEFAULT_SITE_ID, DEFAULT_WORK_SITE_ENDPOINT, ProtocolError, make_config
from protocol.keys import check_site_id
from protocol.messages import NAME_PATTERN
from protocol.session import TlsFiles, link_endpoints
from protocol.signals import dump_stacks_on_sigusr1, install_stop_signals

WORK_SITE_STOP_TIMEOUT_S = 10.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="operator-site",
        description="The operator site: a web page with the work-site model, its live camera "
        "and the robot, connected to a work site over zenoh.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    serve = sub.add_parser(
        "serve",
        help="serve the page for a running work site (default)",
        description="Serve the operator page, connected to a work site.",
    )
    demo = sub.add_parser(
        "demo",
        help="start a work site on this machine and serve the page",
        description="The loopback demo: starts `work-site serve` on "
        "this machine and serves the operator page connected to it. Ctrl-C "
        "stops both.",
    )
    for p in (serve, demo):
        p.add_argument(
            "--scene",
            type=Path,
            default=DEFAULT_SCENE,
            help="scene JSON the page shows (default: the puzzle scene)",
        )
        p.add_argument(
            "--site-id", default=DEFAULT_SITE_ID, help="the work site's id (default: %(default)s)"
        )
        p.add_argument(
            "--host",
            default="127.0.0.1",
            help="address the web page listens on (default: %(default)s; "
            "0.0.0.0 for every interface: then only a browser given the access token may "
            "control the robot)",
        )
        p.add_argument(
            "--token",
            default=None,
            help="the page's access token, at least 16 of A-Z a-z 0-9 _ - . ~ (default: a new "
            "one at each start when --host is not loopback, none on loopback); the printed "
            "address carries it",
        )
        p.add_argument(
            "--no-token",
            action="store_true",
            help="no access token: every browser that reaches the page controls the robot "
            "(only with a loopback --host)",
        )
        p.add_argument(
            "--port", type=int, default=8080, help="port of the web page (default: %(default)s)"
        )
        p.add_argument(
            "--view-dpr",
            type=float,
            default=None,
            metavar="RATIO",
            help="the printed address draws the 3D view at this device-pixel ratio: 0.5 on a "
            "machine without a GPU (the page then says 'Software WebGL rendering detected') "
            "draws a quarter of the pixels and answers the mouse faster (default: the "
            "browser's own)",
        )
        p.add_argument(
            "--connect",
            # serve: several routers of a mesh (it goes on through one when another fails)
            action="append" if p is serve else "store",
            default=None if p is serve else DEFAULT_WORK_SITE_ENDPOINT,
            metavar="ENDPOINT",
            help=f"zenoh endpoint of the work site or a router (default: "
            f"{DEFAULT_WORK_SITE_ENDPOINT}{'; repeatable' if p is serve else ''}). A tcp/ "
            "or tls/ endpoint HOST:PORT becomes two links, as `work-site serve --listen` makes "
            "them: commands and reports (priorities 0-3) on PORT, robot state and camera frames "
            "(4-7) on PORT+1",
        )
        p.add_argument(
            "--single-link",
            action="store_true",
            help="connect to the --connect endpoint alone, all priorities on one link (a router "
            "that listens on one port; with demo, the work site listens so too)",
        )
        p.add_argument(
            "--initial-model",
            choices=["empty", "scene"],
            default="empty",
            help="what the page's model holds at first: empty (the table and the frame: "
            "accept the blocks the work site's vision recognises) or scene (the scene file's "
            "layout) (default: %(default)s)",
        )
        p.add_argument("-v", "--verbose", action="store_true", help="log more")
    serve.add_argument(
        "--client",
        action="store_true",
        help="connect as a zenoh client: everything through the --connect router, never "
        "directly to a work site it introduces (so that the router's access control applies)",
    )
    serve.add_argument(
        "--certs",
        type=Path,
        default=None,
        metavar="DIR",
        help="mutual TLS to a work site's tls/ endpoint with DIR/ca.pem and DIR/NAME.{pem,key} "
        "(made by deploy/make-certs.sh; the work site admits the names in its --operators)",
    )
    serve.add_argument(
        "--cert-name",
        default="operator",
        metavar="NAME",
        help="this site's certificate in --certs (default: %(default)s)",
    )
    demo.add_argument(
        "--scripted",
        choices=["corner", "around-corner"],
        default=None,
        metavar="TASK",
        help="no page: run TASK end to end with a scripted operator (corner: a block into an "
        "inside corner of the frame; around-corner: dragged round an outside corner) against a "
        "work site started on loopback with --seed, or the one at --connect if given",
    )
    demo.add_argument("--seed", type=int, default=0, help="layout, workpiece, corner (default 0)")
    demo.add_argument(
        "--json", action="store_true", help="print the result as one JSON line (last line)"
    )
    demo.add_argument(
        "--oracle-vision",
        action="store_true",
        help="with --scripted: take the blocks' poses from the simulated work site's ground "
        "truth instead of vision (measures the rest of the chain alone)",
    )
    demo.add_argument(
        "--surface-stiffness",
        type=float,
        default=None,
        metavar="N_PER_M",
        help="with --scripted: the started work site's `--surface-stiffness` (contact moves' "
        "impedance stiffness along the surfaces; default: the work site's)",
    )
    demo.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        metavar="X",
        help="with --scripted: the started work site simulates X seconds per wall second "
        "(default: 1, real time; the JSON's time_scale_achieved says how fast it managed)",
    )
    recover = sub.add_parser(
        "recover",
        help="release, back off, go home or resume after a failure or a stop",
        description="A way back without restarting anything, sent to a running work site as "
        "a short program made from the robot's latest state (checked and run like any other; "
        "STOP ends it): release opens the fingers; retract backs the gripper away from what "
        "it presses, along the force it feels, and up; home rises clear of the blocks and "
        "parks the arm; resume goes on with a stopped program from the command it was stopped "
        "in, if no other program ran since. Exit code 0 when done, 1 otherwise, 2 for options "
        "that cannot be used.",
    )
    recover.add_argument(
        "action",
        choices=["release", "retract", "home", "resume"],
        help="what to do (resume: go on with the stopped program --program, from the command it "
        "was stopped in)",
    )
    recover.add_argument(
        "--program",
        type=Path,
        default=None,
        metavar="FILE",
        help="with resume: the stopped program, as saved (the page's program files, or "
        "run --save-program)",
    )
    recover.add_argument(
        "--connect",
        default=DEFAULT_WORK_SITE_ENDPOINT,
        metavar="ENDPOINT",
        help="zenoh endpoint of the work site or a router (default: %(default)s)",
    )
    recover.add_argument(
        "--single-link", action="store_true", help="the --connect endpoint alone, one link"
    )
    recover.add_argument(
        "--site-id", default=DEFAULT_SITE_ID, help="the work site's id (default: %(default)s)"
    )
    recover.add_argument(
        "--scene",
        type=Path,
        default=DEFAULT_SCENE,
        help="the scene JSON (its robot; default: the puzzle scene)",
    )
    recover.add_argument(
        "--certs", type=Path, default=None, metavar="DIR", help="as for serve: mutual TLS"
    )
    recover.add_argument(
        "--cert-name", default="operator", metavar="NAME", help="as for serve (default: operator)"
    )
    recover.add_argument(
        "--operator-id",
        default=None,
        metavar="ID",
        help="act as this operator: the id a page that holds the robot shows on its status "
        "line (default: this process's own, which another operator's lease refuses)",
    )
    recover.add_argument("-v", "--verbose", action="store_true", help="log more")
    run = sub.add_parser(
        "run",
        help="run a task file end to end without a page",
        description="The whole chain driven by a task file (docs/tasks.md): a work site "
        "started on loopback (or the one at --connect), vision, the model editor, the task's "
        "drag in the task simulator, the program generator, the robot; the result is judged "
        "by the work site's ground truth. Exit code 0 on success, 1 when the task was not "
        "done, 2 for a task file or option that cannot be used.",
    )
    run.add_argument("task_file", type=Path, metavar="TASK.json", help="the task file")
    run.add_argument(
        "--scene",
        type=Path,
        default=None,
        metavar="FILE",
        help="the scene JSON; the started work site lays the blocks out as it does "
        "(default: the puzzle scene, blocks laid out at random by --seed)",
    )
    run.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="N",
        help="the camera's offset from its calibration and, without --scene, the random "
        "layout (default: %(default)s)",
    )
    run.add_argument(
        "--connect",
        default=None,
        metavar="ENDPOINT",
        help="a running work site's zenoh endpoint (default: start one on loopback)",
    )
    run.add_argument(
        "--site-id",
        default=None,
        help="with --connect: the work site's id (default: site1)",
    )
    run.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        metavar="X",
        help="the started work site simulates X seconds per wall second (default: 1)",
    )
    run.add_argument(
        "--save-program",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the program sent to the robot to FILE (the page's program files: "
        "load it there to look at it or send it again)",
    )
    run.add_argument(
        "--dry-run",
        action="store_true",
        help="make and check the program (and --save-program it) but send nothing: the "
        "robot does not move; exit code 0 when there is a program",
    )
    run.add_argument(
        "--oracle-vision",
        action="store_true",
        help="take the blocks' poses from the simulated work site's ground truth",
    )
    run.add_argument(
        "--json", action="store_true", help="print the result as one JSON line (last line)"
    )
    run.add_argument("-v", "--verbose", action="store_true", help="log more")
    return parser


def _page_token(args: argparse.Namespace) -> str | None:
    """The page's access token from ``--token``/``--no-token`` and ``--host``; warns on stderr
    when the page is reachable from other machines."""
    from operator_site.ui.access import check_token, is_loopback_host, new_token

    loopback = is_loopback_host(args.host)
    # A command without the token options (one that calls serve() itself) gets the defaults.
    token, no_token = getattr(args, "token", None), getattr(args, "no_token", False)
    if no_token and token is not None:
        raise ValueError("--token and --no-token contradict each other")
    if no_token and not loopback:
        raise ValueError(
            f"--no-token needs a loopback --host (127.0.0.1, localhost, ::1), not {args.host}: "
            "anyone who reaches the page would control the robot"
        )
    if token is not None:
        check_token(token)
    if not loopback:
        # viser serves plain HTTP: the token and the page cross the network in clear.
        print(
            f"operator-site: warning: the page listens on {args.host} over plain HTTP (no TLS): "
            "the access token and everything on the page can be read on the network; put it "
            "behind an HTTPS proxy or an SSH tunnel beyond a trusted network",
            file=sys.stderr,
            flush=True,
        )
    if token is not None:
        return token
    return None if loopback or no_token else new_token()


def _link_config(args: argparse.Namespace):
    """The zenoh config and the endpoints' note for ``args``' --connect, --single-link,
    --client and --certs (ValueError, ProtocolError for what cannot be used)."""
    given = args.connect or [DEFAULT_WORK_SITE_ENDPOINT]  # serve's is a list, the others' one
    connect, links_note = link_endpoints(
        given if isinstance(given, list) else [given], args.single_link
    )
    certs = getattr(args, "certs", None)  # demo's work site is on loopback: no TLS
    tls = None
    if certs is not None:
        tls = TlsFiles.in_dir(certs, args.cert_name)
    mode = "client" if getattr(args, "client", False) else "peer"
    return make_config(mode=mode, connect=connect, tls=tls), connect, links_note


RECOVER_STATE_TIMEOUT_S = 15.0
RECOVER_DONE_TIMEOUT_S = 120.0


def recover(args: argparse.Namespace) -> int:
    """``recover ACTION``: send the recovery and follow it to its end."""
    import time

    from operator_site.link import WorkSiteLink
    from operator_site.session import OperatorSession, load_program

    try:
        check_site_id(args.site_id)
        if args.operator_id is not None and not re.fullmatch(NAME_PATTERN, args.operator_id):
            raise ValueError(
                f"--operator-id must be letters, digits and _.- only, got {args.operator_id!r}"
            )
        scene = load_scene(args.scene)
        config, connect, _ = _link_config(args)
        if (args.action == "resume") != (args.program is not None):
            raise ValueError("--program FILE goes with resume, and resume needs it")
        stopped = load_program(args.program) if args.program is not None else None
    except (ModelError, ProtocolError, ValueError, OSError) as e:
        print(f"operator-site: {e}", file=sys.stderr)
        return 2
    link = WorkSiteLink(config, args.site_id, args.operator_id)
    try:
        deadline = time.monotonic() + RECOVER_STATE_TIMEOUT_S
        while link.robot_state is None and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.05)
        if link.robot_state is None:
            print(
                f"operator-site: no robot state from work site {args.site_id!r} at "
                f"{', '.join(connect)} within {RECOVER_STATE_TIMEOUT_S:.0f} s",
                file=sys.stderr,
            )
            return 1
        op = OperatorSession(scene, link)
        program = op.resume(stopped) if stopped is not None else op.recover(args.action)
        print(f"{args.action}: sent as {program.program_id}", flush=True)
        deadline, shown = time.monotonic() + RECOVER_DONE_TIMEOUT_S, 0
        while time.monotonic() < deadline:
            link.poll()
            mine = [r for r in link.status.reports if r.program_id == program.program_id]
            for r in mine[shown:]:
                print(f"  command {r.command_index}: {r.status} {r.message}", flush=True)
            shown = len(mine)
            end = op.outcome(program.program_id)
            if end is not None:
                return 0 if end.status == "done" else 1
            time.sleep(0.05)
        print(f"operator-site: no end of {program.program_id} within "
              f"{RECOVER_DONE_TIMEOUT_S:.0f} s", file=sys.stderr)  # fmt: skip
        return 1
    finally:
        link.close()


def serve(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Serve the page until SIGINT/SIGTERM (or ``stop``); returns the exit code."""
    from operator_site.link import WorkSiteLink  # heavy imports after parsing
    from operator_site.ui import OperatorPage

    try:
        check_site_id(args.site_id)
        scene = load_scene(args.scene)
        config, connect, links_note = _link_config(args)
        if not 1 <= args.port <= 65535:
            raise ValueError(f"--port must be in 1..65535, got {args.port}")
        if args.view_dpr is not None:
            from operator_site.ui.access import check_view_dpr

            try:
                check_view_dpr(args.view_dpr)
            except ValueError as e:
                raise ValueError(f"--view-dpr: {e}") from None
        token = _page_token(args)
    except (ModelError, ProtocolError, ValueError) as e:
        print(f"operator-site: {e}", file=sys.stderr)
        return 2
    if stop is None:
        stop = threading.Event()
        install_stop_signals(stop, "operator-site")
    link = WorkSiteLink(config, args.site_id)
    try:
        page = OperatorPage(
            scene,
            link,
            host=args.host,
            port=args.port,
            initial_model=args.initial_model,
            token=token,
            browse_host=socket.gethostname() if args.host in ("0.0.0.0", "::") else None,
            view_dpr=args.view_dpr,
        )
        try:
            print(
                f"operator-site: open {page.url} in a web browser (work site "
                f"{args.site_id!r} at {', '.join(connect)}: {links_note}; Ctrl-C to stop)",
                flush=True,
            )
            page.run(stop)
        finally:
            page.close()
    finally:
        link.close()
    return 0


def demo(args: argparse.Namespace) -> int:
    """Start a work site as a child process, serve the page, stop both on Ctrl-C."""
    stop = threading.Event()
    install_stop_signals(stop, "operator-site")
    cmd = [
        sys.executable,
        "-m",
        "work_site",
        "serve",
        "--scene",
        str(args.scene),
        "--site-id",
        args.site_id,
        "--listen",
        args.connect,
        *(["--single-link"] if args.single_link else []),
    ]
    print(f"operator-site: starting the work site: {' '.join(cmd)}", flush=True)
    # Its own process group: Ctrl-C reaches it through us, once, in order.
    work_site = subprocess.Popen(cmd, start_new_session=True)
    try:
        return serve(args, stop)
    finally:
        if work_site.poll() is None:
            work_site.send_signal(signal.SIGINT)
            try:
                work_site.wait(WORK_SITE_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                work_site.kill()
                work_site.wait()
        print(f"operator-site: work site stopped (exit code {work_site.returncode})", flush=True)


def main(argv: list[str]) -> int:
    """Parse ``argv`` (without the program name) and run the chosen command."""
    parser = build_parser()
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help")):
        argv = ["serve", *argv]
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    if args.command == "run":
        return run_task_file(args)
    if args.command == "recover":
        return recover(args)
    if args.command == "demo" and args.scripted:
        return run_scripted_demo(args, connect_given="--connect" in argv)
    return demo(args) if args.command == "demo" else serve(args)


def _work_site_args(args: argparse.Namespace) -> tuple[str, ...]:
    """Options for a work site that a scripted run starts."""
    k = args.surface_stiffness
    return () if k is None else ("--surface-stiffness", str(k))


def run_scripted_demo(args: argparse.Namespace, connect_given: bool) -> int:
    """``demo --scripted``: one end-to-end run; exit code 0 on success, 1 otherwise."""

    from operator_site.scripted import run_scripted

    result = run_scripted(
        args.scripted,
        args.seed,
        connect=args.connect if connect_given else None,
        site_id=args.site_id if connect_given else None,
        scene=load_scene(args.scene),
        oracle=args.oracle_vision,
        time_scale=args.time_scale,
        work_site_args=_work_site_args(args),
    )
    return _print_result(result, args.json)


def _print_result(result: dict, as_json: bool) -> int:
    """Print an end-to-end run's result (one JSON line, or a line a field); its exit code."""
    import json

    if as_json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
    return 0 if result["success"] else 1


def run_task_file(args: argparse.Namespace) -> int:
    """``run TASK.json``: check the file and the options, then one end-to-end run; exit code
    0 on success, 1 otherwise, 2 (one line on stderr) for what cannot be used."""

    from operator_site.taskfile import TaskFileError, load_task

    try:
        task = load_task(args.task_file)
        scene = load_scene(args.scene) if args.scene is not None else load_scene()
        fixed = {o.name for o in scene.objects if o.fixed}
        task.check_names({o.name for o in scene.movable}, fixed, where=str(args.task_file))
        if not args.time_scale > 0:
            raise ValueError(f"--time-scale must be > 0, got {args.time_scale}")
        if args.site_id is not None:
            check_site_id(args.site_id)
    except (TaskFileError, ModelError, ProtocolError, ValueError) as e:
        print(f"operator-site: {e}", file=sys.stderr)
        return 2
    # Heavy imports after the checks.
    from operator_site.runner import run_task
    from operator_site.session import generated_program, save_program

    def make_program(session, program_id: str):
        made = generated_program(session, program_id)
        if args.save_program is not None:
            save_program(args.save_program, made.program)
        return made

    result = run_task(
        task,
        args.seed,
        scene=scene,
        scene_file=args.scene,
        connect=args.connect,
        site_id=args.site_id if args.connect is not None else None,
        oracle=args.oracle_vision,
        time_scale=args.time_scale,
        label=args.task_file.stem,
        make_program=make_program,
        dry_run=args.dry_run,
    )
    result["task_file"] = str(args.task_file)
    return _print_result(result, args.json)


def run() -> None:
    """Console-script entry point."""
    dump_stacks_on_sigusr1()
    sys.exit(main(sys.argv[1:]))
