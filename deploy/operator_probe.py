"""A scripted operator site for deployment checks: run a pick-and-place, or watch the link.

    python deploy/operator_probe.py program --connect tcp/10.77.0.2:7447 --block cube --dx -0.08
    python deploy/operator_probe.py watch --connect tcp/10.77.0.2:7447 --lease-ms 2000

``program`` connects (``operator_site.link.WorkSiteLink``), sends the pick-and-place program of
``operator_site.program.pick_and_place`` for one block of the scene moved by (dx, dy), re-sends
it with the same id until the work site acknowledges it (the work site refuses a second copy of
an id, so it runs at most once), waits for the end and prints one JSON line: the reports in
arrival order, the acknowledgement's round trip, and where the gripper ended.
``streams`` watches the camera and the arm's states for ``--seconds`` and prints one JSON line:
how old the frames were on arrival after ``--settle`` seconds (median, 90th percentile), the
rates received at the end and the share of the frames taken that arrived; with ``--series``
every frame's time since the start and age.
``watch`` prints one JSON line per change of the work site's liveliness (``{"alive": bool,
"t": unix time}``) until killed. ``--certs DIR`` uses mutual TLS with DIR/operator.{pem,key}.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from models.robot import load_robot  # noqa: E402
from models.scene import load_scene  # noqa: E402
from operator_site.grasp import top_grasp  # noqa: E402
from operator_site.link import WorkSiteLink  # noqa: E402
from operator_site.program import choose_grasp_yaw, pick_and_place  # noqa: E402
from protocol.session import TlsFiles, link_endpoints, make_config  # noqa: E402

FINAL = ("done", "failed", "stopped")
"""How a program ends (after "accepted"); a re-sent copy's "refused" is not its end."""


def _link(args: argparse.Namespace) -> WorkSiteLink:
    tls = None
    if args.certs is not None:
        tls = TlsFiles.in_dir(args.certs, "operator")
    connect, _ = link_endpoints([args.connect], args.single_link)
    return WorkSiteLink(make_config(connect=connect, tls=tls, lease_ms=args.lease_ms), args.site_id)


def _wait(link: WorkSiteLink, predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.poll()
        if predicate():
            return True
        time.sleep(0.01)
    return False


def run_program(args: argparse.Namespace) -> dict:
    """Send the pick-and-place; returns what happened (see the module docstring)."""
    scene = load_scene()
    robot = load_robot(scene.robot.urdf_path)
    block = scene.object(args.block)
    X_GP, _ = top_grasp(robot, block.model.bbox_O)
    start = block.X_WO.copy()
    goal = start.copy()
    goal[:2, 3] += (args.dx, args.dy)
    program_id = args.program_id or f"{args.block}-{int(time.time() * 1000)}"
    program = pick_and_place(program_id, start, goal, choose_grasp_yaw(start, X_GP))
    link = _link(args)
    try:
        if not _wait(link, lambda: link.status.label == "connected", args.connect_timeout):
            return {"error": "work site not connected", "label": link.status.label}
        mine = lambda: [r for r in link.status.reports if r.program_id == program_id]  # noqa: E731
        sends, t_sent = 0, time.perf_counter()
        ack_ms = None
        while ack_ms is None:
            if sends >= args.max_sends:
                return {"error": f"no acknowledgement after {sends} sends"}
            link.send_program(program)
            sends += 1
            t_sent = time.perf_counter() if sends == 1 else t_sent
            if _wait(link, lambda: bool(mine()), args.ack_timeout):
                ack_ms = (time.perf_counter() - t_sent) * 1000.0
        _wait(
            link,
            lambda: (
                any(r.command_index == -1 and r.status in FINAL for r in mine()[1:])
                or mine()[0].status == "refused"
            ),
            args.timeout,
        )
        time.sleep(0.2)
        link.poll()
        q = link.robot_state.q
        return {
            "program_id": program_id,
            "sends": sends,
            "ack_ms": ack_ms,
            "reports": [(r.command_index, r.status) for r in mine()],
            "messages": [r.message for r in mine()],
            "p_WG": robot.tcp_pose_W(q, scene.robot.X_WB)[:3, 3].tolist(),
            "goal_p_WP": goal[:3, 3].tolist(),
            "commands": len(program.commands),
        }
    finally:
        link.close()


def streams(args: argparse.Namespace) -> dict:
    """Watch the streams; returns what they were like (see the module docstring)."""
    link = _link(args)
    ages_s: list[float] = []
    series: list[tuple[float, float]] = []
    try:
        if not _wait(link, lambda: link.status.label == "connected", args.connect_timeout):
            return {"error": "work site not connected", "label": link.status.label}
        t0 = time.monotonic()
        while (elapsed_s := time.monotonic() - t0) < args.seconds:
            _, new_frame = link.poll()
            if new_frame:
                # Until the work site has echoed its beats the link does not know the work
                # site's clock: the age is then read on this machine's.
                age_s = link.status.frame_age_s
                age_s = time.time() - link.camera_frame.stamp_s if age_s is None else age_s
                series.append((round(elapsed_s, 3), round(age_s, 4)))
                if elapsed_s >= args.settle:
                    ages_s.append(age_s)
            time.sleep(0.05)  # a page's poll
        if not ages_s:
            return {"error": "no camera frame after the settling time"}
        ages_s.sort()
        return {
            "frames": len(ages_s),
            "frame_age_s_median": ages_s[len(ages_s) // 2],
            "frame_age_s_p90": ages_s[int(0.9 * (len(ages_s) - 1))],
            "frame_rate_hz": link.status.frame_rate_hz,
            "state_rate_hz": link.status.state_rate_hz,
            "frame_share": link.status.frame_share,
            **({"series": series} if args.series else {}),
        }
    finally:
        link.close()


def watch(args: argparse.Namespace) -> None:
    """Print liveliness changes of the work site until killed."""
    link = _link(args)
    alive = None
    try:
        while True:
            link.poll()
            if link.status.work_site_alive != alive:
                alive = link.status.work_site_alive
                print(json.dumps({"alive": alive, "t": time.time()}), flush=True)
            time.sleep(0.005)
    finally:
        link.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="operator_probe", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_prog = sub.add_parser("program", help="run a pick-and-place and print its reports")
    p_streams = sub.add_parser("streams", help="measure how old camera frames arrive")
    p_watch = sub.add_parser("watch", help="print the work site's liveliness changes")
    for p in (p_prog, p_streams, p_watch):
        p.add_argument("--connect", required=True, metavar="ENDPOINT")
        p.add_argument("--site-id", default="site1")
        p.add_argument("--certs", type=Path, help="mutual TLS with DIR/operator.{pem,key}")
        p.add_argument("--lease-ms", type=int, help="zenoh link lease (ms)")
        p.add_argument(
            "--single-link",
            action="store_true",
            help="one link for all priorities (default: two, PORT and PORT+1, as the sites do)",
        )
    p_prog.add_argument("--block", default="cube")
    p_prog.add_argument("--dx", type=float, default=-0.08, help="goal offset along x (m)")
    p_prog.add_argument("--dy", type=float, default=0.0, help="goal offset along y (m)")
    p_prog.add_argument("--program-id")
    p_prog.add_argument("--connect-timeout", type=float, default=30.0)
    p_prog.add_argument("--ack-timeout", type=float, default=5.0, help="re-send after (s)")
    p_prog.add_argument("--max-sends", type=int, default=5)
    p_prog.add_argument("--timeout", type=float, default=120.0, help="for the whole program (s)")
    p_streams.add_argument("--connect-timeout", type=float, default=30.0)
    p_streams.add_argument("--seconds", type=float, default=30.0, help="watch this long (s)")
    p_streams.add_argument(
        "--settle", type=float, default=10.0, help="count frames from this long on (s)"
    )
    p_streams.add_argument(
        "--series", action="store_true", help="also print every frame's [time, age] (s)"
    )
    args = parser.parse_args(argv)
    if args.command == "watch":
        watch(args)
        return 0
    result = run_program(args) if args.command == "program" else streams(args)
    print(json.dumps(result), flush=True)
    return 0 if "error" not in result else 1


if __name__ == "__main__":
    sys.exit(main())
