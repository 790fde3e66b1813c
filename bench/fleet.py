"""``python -m bench fleet``: many cells through one zenoh router: each operator's command round
trip and camera rate against the number of cells, and the round trip the router itself adds.

**Cells.** For each N of ``--cells``, ``deploy/fleet.py`` starts a router and N real
``work-site serve`` processes on loopback (camera on at its default rate, vision off) and N
operator probes, one process per cell, each a zenoh client of the router (so everything it sends
and receives is routed), with the cell's own certificate under ``--tls``. Over the same
``--seconds`` window each probe counts the camera frames it receives (rate, and age: receipt
minus the frame's stamp) and every ``--command-period-s`` sends a program that its work site
refuses (it would take the gripper into the robot's base; nothing moves), timing send → the
"refused" report: a command's full round trip through the router and the work site's intake.
It also counts its cell's robot states (100 Hz while the work site keeps real time). The CPU used
over the window by the whole machine, by the router and by the work sites is recorded too: on a
small machine the simulated cells themselves (physics and camera rendering) fill it first.

**The router's hop.** A bare-zenoh echo process (a peer listening on loopback and connected to
the router) is timed ``--hop-samples`` times through the router (a client session) and directly
(a peer session connected to the echo's listener only), taking turns: the router's added round
trip is the difference of the two at the median and at p99. Once beside one cell without camera
(``router_hop_quiet``), once beside the one-cell point's cell, its camera on (``router_hop``; not
under ``--tls``), each over plain TCP: the echo is no cell's member.

Prints progress on stderr and a JSON summary as the last line of stdout; writes ``fleet.json``,
``fleet.csv`` (one row per operator and N) and ``fleet.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import queue
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bench.net import refused_program
from deploy.fleet import Fleet, FleetSpec
from protocol import (
    CameraFrame,
    ExecutionReport,
    ProtocolError,
    decode,
    encode,
    key,
)
from protocol.session import free_port_pair, make_config

REPO = Path(__file__).resolve().parents[1]
START_MARGIN_S = 1.0
"""The probes' common window opens this long after the last of them is ready (s)."""
PROBE_READY_TIMEOUT_S = 120.0
"""A probe not ready (session open, subscribers declared) this long after its start failed (s)."""
REPLY_TIMEOUT_S = 10.0
"""A command not answered within this long counts as lost (s)."""
HOP_KEY = "telerobot/fleet-echo"


# ----------------------------------------------------------------------------- the probes


def probe_operator(
    config: zenoh.Config, site: str, wait_start: Callable[[], float], args: argparse.Namespace
) -> dict:
    """One operator of cell ``site``: once its session is up, ``wait_start()`` gives the window's
    start (time.time()); over ``args.seconds`` from it, the camera frames it receives, its cell's
    robot states and the round trips of refused programs."""
    frames: list[tuple[float, float]] = []  # (receipt, age) per frame

    def on_frame(sample: zenoh.Sample) -> None:
        now = time.time()
        try:
            frame = decode(sample.payload.to_bytes(), CameraFrame)
        except ProtocolError:
            return
        frames.append((now, now - frame.stamp_s))

    states: list[float] = []  # receipt per robot state

    with zenoh.open(config) as session:
        camera = session.declare_subscriber(key(site, "camera"), on_frame)
        state = session.declare_subscriber(
            key(site, "robot_state"), lambda _s: states.append(time.time())
        )
        replies: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        reports = session.declare_subscriber(
            key(site, "report"), lambda s: replies.put(s.payload.to_bytes())
        )
        publisher = session.declare_publisher(
            key(site, "program"), priority=zenoh.Priority.INTERACTIVE_HIGH
        )
        start_s = wait_start()
        time.sleep(max(0.0, start_s - time.time()))
        round_trips_ms: list[float] = []
        lost = 0
        k = 0
        end_s = start_s + args.seconds
        while time.time() < end_s:
            program_id = f"fleet-{os.getpid()}-{k}"
            k += 1
            sent = time.perf_counter()
            publisher.put(encode(refused_program(program_id)))
            answered = False
            while (waited := time.perf_counter() - sent) < REPLY_TIMEOUT_S:
                try:
                    payload = replies.get(timeout=REPLY_TIMEOUT_S - waited)
                except queue.Empty:
                    break
                report = decode(payload, ExecutionReport)
                if report.program_id == program_id and report.command_index == -1:
                    round_trips_ms.append((time.perf_counter() - sent) * 1e3)
                    answered = True
                    break
            lost += not answered
            time.sleep(max(0.0, args.command_period_s - (time.perf_counter() - sent)))
        for sub in (camera, state, reports):
            sub.undeclare()
    window = [age for t, age in frames if start_s <= t < end_s]
    return {
        "site": site,
        "commands": len(round_trips_ms),
        "lost": lost,
        "round_trips_ms": round_trips_ms,
        "frame_hz": len(window) / args.seconds,
        "frame_age_ms_median": float(np.median(window) * 1e3) if window else None,
        "state_hz": sum(start_s <= t < end_s for t in states) / args.seconds,
    }


def serve_hop_echo(listen: str, router: str) -> int:
    """The echo of the router's hop: answers each ping on its own key."""
    with zenoh.open(make_config(listen=[listen], connect=[router])) as session:
        pubs: dict[str, zenoh.Publisher] = {
            way: session.declare_publisher(
                f"{HOP_KEY}/{way}/pong", priority=zenoh.Priority.REAL_TIME
            )
            for way in ("direct", "routed")
        }
        subs = [
            session.declare_subscriber(
                f"{HOP_KEY}/{way}/ping", lambda s, p=pubs[way]: p.put(s.payload)
            )
            for way in pubs
        ]
        print("fleet-echo: ready", flush=True)
        sys.stdin.read()  # until the bench closes our stdin
        for sub in subs:
            sub.undeclare()
    return 0


def measure_hop(router: str, samples: int) -> dict[str, Any]:
    """The echo's round trip through the router and directly, ``samples`` each, in turns."""
    listen = f"tcp/127.0.0.1:{free_port_pair()}"
    echo = subprocess.Popen(
        [sys.executable, "-m", "bench.fleet", "echo", listen, router],
        cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        if "ready" not in (echo.stdout.readline() if echo.stdout else ""):
            raise RuntimeError("the hop's echo process did not start")
        sessions = {
            "routed": zenoh.open(make_config(mode="client", connect=[router])),
            "direct": zenoh.open(make_config(connect=[listen])),
        }
        try:
            pubs, subs, pongs = {}, {}, {}
            for way, session in sessions.items():
                pubs[way] = session.declare_publisher(
                    f"{HOP_KEY}/{way}/ping", priority=zenoh.Priority.REAL_TIME
                )
                pongs[way] = queue.SimpleQueue()
                subs[way] = session.declare_subscriber(
                    f"{HOP_KEY}/{way}/pong", lambda _s, q=pongs[way]: q.put(True)
                )
            deadline = time.monotonic() + 30.0
            while not all(p.matching_status.matching for p in pubs.values()):
                if time.monotonic() > deadline:
                    raise TimeoutError("the hop's echo never matched")
                time.sleep(0.05)
            time.sleep(0.5)  # the echo's publishers have our subscribers too
            # The direct session must not have found the router (it would then be one more
            # path), nor the routed one the echo.
            assert not list(sessions["direct"].info.routers_zid())
            assert not list(sessions["routed"].info.peers_zid())
            out: dict[str, list[float]] = {"routed": [], "direct": []}
            ways = list(out)
            for i in range(samples + 20):  # the first 20 warm up
                for j in range(2):
                    way = ways[(i + j) % 2]  # which goes first takes turns
                    t = time.perf_counter()
                    pubs[way].put(b"ping")
                    try:
                        pongs[way].get(timeout=REPLY_TIMEOUT_S)
                    except queue.Empty:
                        raise TimeoutError(f"no pong ({way})") from None
                    if i >= 20:
                        out[way].append((time.perf_counter() - t) * 1e3)
        finally:
            for session in sessions.values():
                session.close()
    finally:
        if echo.stdin:
            echo.stdin.close()
        try:
            echo.wait(timeout=15)
        except subprocess.TimeoutExpired:
            echo.kill()
            echo.wait()
        if echo.stdout:
            echo.stdout.close()
    stats = {}
    for way, values in out.items():
        stats[f"{way}_ms_median"] = float(np.median(values))
        stats[f"{way}_ms_p99"] = float(np.percentile(values, 99))
    stats["added_ms_median"] = stats["routed_ms_median"] - stats["direct_ms_median"]
    stats["added_ms_p99"] = stats["routed_ms_p99"] - stats["direct_ms_p99"]
    stats["samples"] = samples
    return stats


# ------------------------------------------------------------------------- the orchestrator


def _cpu_times() -> tuple[float, float]:
    """(busy, total) jiffies of the whole machine, from /proc/stat."""
    fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    return sum(fields) - idle, sum(fields)


def _group_cpu_s(pgid: int) -> float:
    """User + system CPU seconds of the processes now in process group ``pgid`` (a process and
    the children it started, e.g. a work site's checker and vision processes)."""
    ticks = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[2]) == pgid:
            ticks += int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def _wait_ready(probes: list[subprocess.Popen]) -> None:
    """Until every probe has said ``ready`` (RuntimeError: one ended or took too long)."""
    deadline = time.monotonic() + PROBE_READY_TIMEOUT_S
    for proc in probes:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
        if not ready or "ready" not in proc.stdout.readline():
            for each in probes:
                each.kill()
            raise RuntimeError(f"an operator probe was not ready in {PROBE_READY_TIMEOUT_S:.0f} s")


def measure_cells(n: int, args: argparse.Namespace, log_dir: Path) -> list[dict[str, Any]]:
    """One fleet of ``n`` cells and its ``n`` operators; one row per operator."""
    spec = FleetSpec(sites=n, tls=args.tls, camera=not args.no_camera)
    with Fleet(spec, log_dir / f"cells-{n}") as fleet:
        probes = []
        for site in spec.site_ids:
            argv = [sys.executable, "-m", "bench.fleet", "operator", site,
                    json.dumps(str(fleet.operator_config(site))), str(args.seconds),
                    str(args.command_period_s)]  # fmt: skip
            probes.append(subprocess.Popen(
                argv, cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                start_new_session=True,
            ))  # fmt: skip
        _wait_ready(probes)
        start_s = time.time() + START_MARGIN_S
        for proc in probes:
            proc.stdin.write(f"{start_s!r}\n")
            proc.stdin.flush()
        time.sleep(max(0.0, start_s - time.time()))
        busy0, total0 = _cpu_times()
        groups = {
            "router_cpu": [fleet.procs["router"].pid],
            "sites_cpu": [fleet.procs[site].pid for site in spec.site_ids],
            "operators_cpu": [proc.pid for proc in probes],
        }
        cpu0 = {name: sum(map(_group_cpu_s, pids)) for name, pids in groups.items()}
        time.sleep(args.seconds)
        busy1, total1 = _cpu_times()
        cpu = {
            name: (sum(map(_group_cpu_s, pids)) - cpu0[name]) / args.seconds
            for name, pids in groups.items()
        }
        rows = []
        for proc in probes:
            out, _ = proc.communicate(timeout=args.seconds + 60)
            if proc.returncode != 0:
                raise RuntimeError(f"an operator probe failed (exit {proc.returncode})")
            rows.append(json.loads(out.strip().splitlines()[-1]))
        # The router's hop beside the running cell (its camera on), its operator done; the
        # echo is no cell's member, so not under --tls.
        hop = None
        if n == 1 and args.tls is None:
            hop = measure_hop(fleet.router_endpoint, args.hop_samples)
    machine_busy = (busy1 - busy0) / (total1 - total0)
    for row in rows:
        row.update(cells=n, machine_cpu=machine_busy, hop=hop, **cpu)
    return rows


def measure_quiet_hop(args: argparse.Namespace, log_dir: Path) -> dict[str, Any]:
    """The router's hop beside one cell without a camera (a machine otherwise idle), plain TCP
    also under ``--tls``: the echo is no cell's member."""
    with Fleet(FleetSpec(sites=1, camera=False), log_dir / "quiet") as fleet:
        return measure_hop(fleet.router_endpoint, args.hop_samples)


def summarise(
    rows: list[dict[str, Any]], quiet_hop: dict[str, Any], args: argparse.Namespace
) -> dict[str, Any]:
    points = []
    for n in sorted({r["cells"] for r in rows}):
        at = [r for r in rows if r["cells"] == n]
        rtts = np.concatenate([r["round_trips_ms"] for r in at])
        hz = np.array([r["frame_hz"] for r in at])
        ages = [r["frame_age_ms_median"] for r in at if r["frame_age_ms_median"] is not None]
        points.append({
            "cells": n,
            "operators": len(at),
            "commands": int(rtts.size),
            "lost": sum(r["lost"] for r in at),
            "command_ms_median": float(np.median(rtts)) if rtts.size else None,
            "command_ms_p99": float(np.percentile(rtts, 99)) if rtts.size else None,
            "frame_hz_min": float(hz.min()),
            "frame_hz_median": float(np.median(hz)),
            "frame_age_ms_median": float(np.median(ages)) if ages else None,
            "state_hz_min": float(min(r["state_hz"] for r in at)),
            "machine_cpu": at[0]["machine_cpu"],
            "router_cpu": at[0]["router_cpu"],
            "sites_cpu": at[0]["sites_cpu"],
            "operators_cpu": at[0]["operators_cpu"],
        })  # fmt: skip
    hop = next((r["hop"] for r in rows if r["hop"] is not None), None)
    return {
        "points": points,
        "router_hop": hop,
        "router_hop_quiet": quiet_hop,
        "camera": not args.no_camera,
        "seconds": args.seconds,
        "command_period_s": args.command_period_s,
        "tls": args.tls is not None,
        "cpus": os.cpu_count(),
    }


def plot(summary: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = summary["points"]
    n = np.array([p["cells"] for p in points])
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(12, 3.6))
    ax1.plot(n, [p["command_ms_median"] for p in points], "o-", label="median")
    ax1.plot(n, [p["command_ms_p99"] for p in points], "s-", label="p99")
    ax1.set_yscale("log")
    ax1.set_xlabel("cells (work sites, each with its operator)")
    ax1.set_ylabel("ms")
    ax1.set_title("command round trip through the router", fontsize=9)
    ax1.legend(fontsize=8)
    ax2.plot(n, [p["frame_hz_median"] for p in points], "o-", label="camera, median operator")
    ax2.plot(n, [p["frame_hz_min"] for p in points], "s-", label="camera, slowest operator")
    ax2.set_xlabel("cells")
    ax2.set_ylabel("camera frames per second")
    ax2.set_ylim(bottom=0)
    ax2b = ax2.twinx()
    ax2b.plot(n, [p["state_hz_min"] for p in points], "k:", marker="^",
              label="robot states, slowest cell")  # fmt: skip
    ax2b.set_ylabel("robot states per second (100: real time)")
    ax2b.set_ylim(0, 105)
    lines = ax2.get_legend_handles_labels()
    more = ax2b.get_legend_handles_labels()
    ax2.legend(lines[0] + more[0], lines[1] + more[1], fontsize=7)
    ax2.set_title("what each operator receives", fontsize=9)
    bottom = np.zeros(len(points))
    for key_, label in (("sites_cpu", "work sites (simulation, camera)"), ("router_cpu", "router"),
                        ("operators_cpu", "operators")):  # fmt: skip
        cores = np.array([p[key_] for p in points])
        ax3.bar(n, cores, bottom=bottom, label=label, width=0.6)
        bottom += cores
    ax3.axhline(
        summary["cpus"], color="grey", ls=":", label=f"the machine ({summary['cpus']} cores)"
    )
    ax3.set_xlabel("cells")
    ax3.set_ylabel("cores busy")
    ax3.set_title("where the CPU goes", fontsize=9)
    ax3.legend(fontsize=7, loc="lower right")
    for ax in (ax1, ax2, ax3):
        ax.set_xticks(n)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _cells(text: str) -> list[int]:
    try:
        cells = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers like 1,2,5,10, got {text!r}") from None
    if not cells or any(not 1 <= n <= 40 for n in cells):
        raise argparse.ArgumentTypeError(f"each number of cells must be 1..40, got {text!r}")
    return list(dict.fromkeys(cells))  # each point once


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cells", type=_cells, default=[1, 2, 5, 10],
        help="numbers of cells, comma-separated (default: 1,2,5,10)",
    )  # fmt: skip
    parser.add_argument("--seconds", type=float, default=30.0, help="window per point (s)")
    parser.add_argument(
        "--command-period-s", type=float, default=0.5,
        help="each operator sends a command this often (s; default 0.5)",
    )  # fmt: skip
    # The p99 of 10,000 round trips rests on 100 tail samples spread over some 25 camera
    # renders of the cell beside; fewer, over a handful of renders, depend on how many of
    # them the samples happened to meet.
    parser.add_argument(
        "--hop-samples", type=int, default=10_000,
        help="round trips each way for the router's hop (default 10000)",
    )  # fmt: skip
    parser.add_argument(
        "--no-camera", action="store_true",
        help="work sites without cameras (the router and the sites' intake without rendering)",
    )  # fmt: skip
    parser.add_argument(
        "--tls", type=Path, metavar="DIR",
        help="mutual TLS and per-cell access control with certificates in DIR (made if missing)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("docs/bench"))


def main(args: argparse.Namespace) -> int:
    for name, value, low, high in (("seconds", args.seconds, 5.0, 3600.0),
                                   ("command-period-s", args.command_period_s, 0.05, 10.0),
                                   ("hop-samples", args.hop_samples, 100, 100_000)):  # fmt: skip
        if not low <= value <= high:
            print(f"fleet: --{name} must be in [{low}, {high}], got {value}", file=sys.stderr)
            return 2
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="fleet-") as tmp:
        print("fleet: the router's hop beside a cell without camera ...", file=sys.stderr)
        quiet_hop = measure_quiet_hop(args, Path(tmp))
        median_ms, p99_ms = quiet_hop["added_ms_median"], quiet_hop["added_ms_p99"]
        print(f"fleet: the router adds {median_ms:.2f} ms at the median, {p99_ms:.2f} ms at p99",
              file=sys.stderr, flush=True)  # fmt: skip
        for n in args.cells:
            print(f"fleet: {n} cells ...", file=sys.stderr, flush=True)
            rows += measure_cells(n, args, Path(tmp))
            points = summarise(rows, quiet_hop, args)["points"]
            point = next(p for p in points if p["cells"] == n)
            p99 = point["command_ms_p99"]
            said = "no command answered" if p99 is None else f"command p99 {p99:.1f} ms"
            print(f"fleet: {n} cells: {said}, camera {point['frame_hz_min']:.1f} Hz at the "
                  f"slowest operator, machine CPU {100 * point['machine_cpu']:.0f} %",
                  file=sys.stderr, flush=True)  # fmt: skip
    summary = summarise(rows, quiet_hop, args)
    with (args.out / "fleet.csv").open("w", newline="") as f:
        fields = ["cells", "site", "commands", "lost", "command_ms_median", "command_ms_p99",
                  "frame_hz", "frame_age_ms_median", "state_hz", "machine_cpu", "router_cpu",
                  "sites_cpu", "operators_cpu"]  # fmt: skip
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for r in rows:
            rtts = r["round_trips_ms"]
            writer.writerow({
                **{k: r[k] for k in fields if k in r},
                "command_ms_median": float(np.median(rtts)) if rtts else None,
                "command_ms_p99": float(np.percentile(rtts, 99)) if rtts else None,
            })  # fmt: skip
    (args.out / "fleet.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(summary, args.out / "fleet.png")
    print(json.dumps(summary))
    return 0


def _role(argv: list[str]) -> int:
    """The processes the bench starts: ``operator SITE CONFIG SECONDS PERIOD_S`` (says ``ready``,
    then reads the window's start on stdin) and ``echo LISTEN ROUTER``."""
    if argv[:1] == ["echo"]:
        return serve_hop_echo(argv[1], argv[2])
    site, config, seconds, period_s = argv[1:5]
    probe_args = argparse.Namespace(seconds=float(seconds), command_period_s=float(period_s))

    def wait_start() -> float:
        print("ready", flush=True)
        return float(sys.stdin.readline())

    row = probe_operator(zenoh.Config.from_json5(json.loads(config)), site, wait_start, probe_args)
    print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_role(sys.argv[1:]))
