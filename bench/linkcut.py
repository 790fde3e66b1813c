"""``python -m bench linkcut``: a link cut and restored: how soon the operator site sees the work
site gone, and how soon alive again.

Each trial joins a fresh ``work-site serve`` (``--no-camera``) in one network namespace and an
operator site's link (``deploy/operator_probe.py watch``, a ``WorkSiteLink`` with its heartbeat
process) in another by the emulated link of ``deploy/netns.py`` (``--delay-ms`` each way), both
with a zenoh lease of ``--lease-ms``. Once the operator sees the work site, the link is cut (every
packet dropped: no FIN, no RST); when the operator has seen the work site gone it is restored.
``--busy-loops`` processes spin meanwhile (a loaded machine: the one-sided expiry that splits a
transport, see ``protocol.session.PeerWatch``, showed there).

- ``detect_s``: cut → the operator sees the work site gone;
- ``heal_s``: restore → the operator sees it alive again (none within ``--heal-timeout-s``: the
  trial never healed);
- ``misrouted``: lines where the operator rejected a message that came under another topic's key
  (the sign of the split transport that ``protocol.session.PeerWatch`` exists to avoid).

Needs root (network namespaces). Prints progress on stderr and a JSON summary as the last line of
stdout; writes ``linkcut.json``, ``linkcut.csv`` (one row per trial) and ``linkcut.png`` into
``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from deploy import netns

REPO = Path(__file__).resolve().parents[1]
SITE_ID = "linkcut"
PORT = 7447
SEE_WORK_SITE_S = 60.0
"""A trial gives up when the operator has not seen the work site this long after starting."""


def trial(index: int, args: argparse.Namespace, log_dir: Path) -> dict[str, Any]:
    """One cut and restore against fresh processes; returns its row."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    endpoint = f"tcp/{netns.WORK_ADDR}:{PORT}"
    lease = f"--lease-ms={args.lease_ms}"
    with netns.emulated_link(prefix=f"lc{uuid.uuid4().hex[:6]}", delay_ms=args.delay_ms) as link:
        site_log = (log_dir / f"work_site_{index}.log").open("w")
        watch_log = (log_dir / f"operator_{index}.log").open("w")
        site = subprocess.Popen(
            link.pair.exec_argv(link.pair.work, [
                sys.executable, str(REPO / "deploy" / "serve_work_site.py"), "--listen", endpoint,
                "--site-id", SITE_ID, "--no-camera", "--insecure", lease,
            ]),
            cwd=REPO, stdout=site_log, stderr=subprocess.STDOUT, start_new_session=True, env=env,
        )  # fmt: skip
        watcher = subprocess.Popen(
            link.pair.exec_argv(link.pair.ops, [
                sys.executable, str(REPO / "deploy" / "operator_probe.py"), "watch",
                f"--connect={endpoint}", f"--site-id={SITE_ID}", lease,
            ]),
            cwd=REPO, stdout=subprocess.PIPE, stderr=watch_log, text=True,
            start_new_session=True, env=env,
        )  # fmt: skip
        events: queue.Queue[dict] = queue.Queue()

        def read() -> None:
            for line in watcher.stdout:
                if line.startswith("{"):
                    events.put(json.loads(line))

        reader = threading.Thread(target=read, daemon=True)
        reader.start()

        def until(alive: bool, timeout_s: float) -> float | None:
            deadline = time.monotonic() + timeout_s
            while (left := deadline - time.monotonic()) > 0:
                try:
                    event = events.get(timeout=left)
                except queue.Empty:
                    break
                if event["alive"] is alive:
                    return float(event["t"])
            return None

        row: dict[str, Any] = {"trial": index, "detect_s": None, "heal_s": None}
        try:
            if until(True, SEE_WORK_SITE_S) is None:
                raise RuntimeError(f"trial {index}: the operator never saw the work site")
            time.sleep(args.settle_s)
            cut_s = time.time()
            link.cut()
            gone_s = until(False, 3 * args.lease_ms / 1000.0 + 5.0)
            if gone_s is None:
                raise RuntimeError(f"trial {index}: the cut was never seen")
            row["detect_s"] = gone_s - cut_s
            restore_s = time.time()
            link.restore()
            back_s = until(True, args.heal_timeout_s)
            row["heal_s"] = None if back_s is None else back_s - restore_s
        finally:
            for proc in (watcher, site):
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            reader.join(timeout=5.0)
            watcher.stdout.close()
            site_log.close()
            watch_log.close()
        rejected = (log_dir / f"operator_{index}.log").read_text(errors="replace")
        row["misrouted"] = sum("rejected a" in line and "expected" in line
                               for line in rejected.splitlines())  # fmt: skip
        return row


def summarise(rows: list[dict[str, Any]], args: argparse.Namespace) -> dict[str, Any]:
    detect = np.array([r["detect_s"] for r in rows], dtype=float)
    healed = np.array([r["heal_s"] for r in rows if r["heal_s"] is not None], dtype=float)
    return {
        "cuts": len(rows),
        "healed": int(healed.size),
        "lease_ms": args.lease_ms,
        "delay_ms": args.delay_ms,
        "heal_timeout_s": args.heal_timeout_s,
        "detect_s_median": float(np.median(detect)),
        "detect_s_max": float(detect.max()),
        "heal_s_median": float(np.median(healed)) if healed.size else None,
        "heal_s_max": float(healed.max()) if healed.size else None,
        "misrouted_trials": sum(r["misrouted"] > 0 for r in rows),
        "busy_loops": args.busy_loops,
        "load_average": os.getloadavg(),
    }


def plot(rows: list[dict[str, Any]], summary: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    trials = [r["trial"] for r in rows]
    ax.plot(trials, [r["detect_s"] for r in rows], "o", label="cut → seen gone")
    healed = [(r["trial"], r["heal_s"]) for r in rows if r["heal_s"] is not None]
    if healed:
        ax.plot(*zip(*healed, strict=True), "s", label="restored → seen alive")
    never = [r["trial"] for r in rows if r["heal_s"] is None]
    if never:
        ax.plot(never, [summary["heal_timeout_s"]] * len(never), "x", color="red", ms=10,
                label=f"never alive again (within {summary['heal_timeout_s']:.0f} s)")  # fmt: skip
    ax.axhline(summary["lease_ms"] / 1000.0, color="grey", ls=":", label="lease")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_xlabel("trial (fresh work site and operator each)")
    ax.set_ylabel("s")
    ax.set_title(f"link cut and restored: {summary['healed']} of {summary['cuts']} healed "
                 f"({summary['delay_ms']:g} ms each way, {summary['busy_loops']} busy loops)",
                 fontsize=10)  # fmt: skip
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cuts", type=int, default=20, help="trials (default 20)")
    parser.add_argument("--lease-ms", type=int, default=2000, help="zenoh lease, both sides")
    parser.add_argument("--delay-ms", type=float, default=5.0, help="link delay each way")
    parser.add_argument(
        "--settle-s", type=float, default=1.0,
        help="wait after the operator saw the work site, before the cut",
    )  # fmt: skip
    parser.add_argument(
        "--heal-timeout-s", type=float, default=30.0,
        help="a trial not alive again this long after the restore never healed",
    )  # fmt: skip
    parser.add_argument(
        "--busy-loops", type=int, default=2, help="processes spinning meanwhile (default 2)"
    )
    parser.add_argument("--out", type=Path, default=Path("docs/bench"))


def _trials(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="linkcut-") as tmp:
        for i in range(args.cuts):
            row = trial(i, args, Path(tmp))
            rows.append(row)
            heal = "never" if row["heal_s"] is None else f"{row['heal_s']:.2f} s"
            print(f"cut {i + 1}/{args.cuts}: seen gone after {row['detect_s']:.2f} s, alive "
                  f"again {heal} after the restore", file=sys.stderr, flush=True)  # fmt: skip
    return rows


def main(args: argparse.Namespace) -> int:
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"linkcut: network namespaces unavailable: {reason}", file=sys.stderr)
        return 2
    for name, value, low, high in (("cuts", args.cuts, 1, 1000),
                                   ("busy-loops", args.busy_loops, 0, 64)):  # fmt: skip
        if not low <= value <= high:
            print(f"linkcut: --{name} must be in [{low}, {high}], got {value}", file=sys.stderr)
            return 2
    args.out.mkdir(parents=True, exist_ok=True)
    spin = [sys.executable, "-c", "while True: pass"]
    busy = [subprocess.Popen(spin) for _ in range(args.busy_loops)]
    try:
        rows = _trials(args)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()
    summary = summarise(rows, args)
    with (args.out / "linkcut.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["trial", "detect_s", "heal_s", "misrouted"])
        writer.writeheader()
        writer.writerows(rows)
    (args.out / "linkcut.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(rows, summary, args.out / "linkcut.png")
    print(json.dumps(summary))
    return 0
