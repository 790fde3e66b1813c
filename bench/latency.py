"""``python -m bench latency``: a shipped task end to end across an emulated long link: success and
task time against the round trip and the loss.

Each run is a fresh ``work-site serve`` in one network namespace (its blocks laid out by the
run's seed, vision on, ground truth published to judge the result) and ``operator-site run
TASK --connect`` in the other, joined by ``deploy/netns.py``'s link: half the round trip each
way, ``--jitter`` of it as jitter, the point's loss each way. The operator does everything as
on loopback: waits for recognitions, builds its model, demonstrates, generates and sends the
program, and waits for its end.

Per run: success (the work site's ground truth, as ``operator-site run`` judges it), the failure
if any, ``task_s`` (from the work site seen to the program's end: vision, the operator's
demonstration, the program, its execution), ``execute_s`` (program sent to its last report),
and the operator's waits while it runs: ``first_report_s`` (program sent to its first report
heard), ``frame_age_s`` (median age of a camera frame as it arrives, from the moment the work
site took it) and ``frame_rate_hz`` (median camera rate at the operator).
Per point: ``runs``, ``successes``, ``task_s_median`` and ``overhead_s_median``: the median over
seeds of a run's task time less the same seed's at the 0 ms point of the same loss (or of loss
0), both successful; each seed lays the blocks out alike at every point; and the median of each
wait over the point's runs (``first_report_s_median``, ...).

Needs root (network namespaces). Prints progress on stderr and, as the last line of stdout, a
JSON list of the points; writes ``latency.json``, ``latency.csv`` (one row per run) and
``latency.png`` into ``--out``; ``--logs DIR`` keeps each run's work-site log and journal.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from deploy import netns

REPO = Path(__file__).resolve().parents[1]
SITE_ID = "latency"
PORT = 7447
DEFAULT_TASK = REPO / "examples" / "tasks" / "cube-corner.json"
RUN_TIMEOUT_S = 900.0
"""One run (work site start, vision, the task, its execution) is given up after this long."""
TASK_STAGES = ("vision_wait", "operator", "program", "execute")
"""``operator-site run``'s stages that make the task's time (not "connect": the start-up)."""
WAITS = ("first_report_s", "frame_age_s", "frame_rate_hz")
"""What the operator waits for while the program runs, as ``operator-site run`` reports it."""
MEASURES = ("task_s", "execute_s", *WAITS)
"""A run's figures (None: not measured), each summarised by its median at a point."""


def _floats(text: str, low: float, high: float, name: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: expected numbers separated by commas") from None
    if not values or any(not low <= v <= high for v in values):
        raise argparse.ArgumentTypeError(f"{name}: each value must be in [{low:g}, {high:g}]")
    return values


def run_once(task: Path, rtt_ms: float, loss: float, seed: int, args: argparse.Namespace,
             log_dir: Path) -> dict[str, Any]:  # fmt: skip
    """One end-to-end run at one link point; returns its row."""
    endpoint = f"tcp/{netns.WORK_ADDR}:{PORT}"
    one_way_ms = rtt_ms / 2.0
    params = {"delay_ms": one_way_ms, "jitter_ms": args.jitter * one_way_ms, "loss": loss,
              "seed": seed + 1}  # fmt: skip
    row: dict[str, Any] = {"rtt_ms": rtt_ms, "loss": loss, "seed": seed, "success": False,
                           "failure": None, **dict.fromkeys(MEASURES)}  # fmt: skip
    site_log = log_dir / f"work_site_{rtt_ms:g}_{loss:g}_{seed}.log"
    with netns.emulated_link(prefix=f"lt{uuid.uuid4().hex[:6]}", **params) as link:
        with site_log.open("w") as out:
            site = subprocess.Popen(
                link.pair.exec_argv(link.pair.work, [
                    sys.executable, "-m", "work_site", "serve", "--listen", endpoint,
                    "--site-id", SITE_ID, "--insecure", "--vision-rate", "2",
                    "--time-scale", str(args.time_scale), "--publish-truth", "--seed", str(seed),
                    "--journal", str(log_dir / f"journal_{rtt_ms:g}_{loss:g}_{seed}.jsonl"),
                ]),
                cwd=REPO, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )  # fmt: skip
        try:
            done = subprocess.run(
                link.pair.exec_argv(link.pair.ops, [
                    sys.executable, "-m", "operator_site", "run", str(task), "--connect",
                    endpoint, "--site-id", SITE_ID, "--seed", str(seed), "--json",
                ]),
                cwd=REPO, capture_output=True, text=True, timeout=RUN_TIMEOUT_S,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            row["failure"] = {"kind": "timeout", "message": f"no result in {RUN_TIMEOUT_S:.0f} s"}
            return row
        finally:
            os.killpg(site.pid, signal.SIGKILL)
            site.wait()
    try:
        result = json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        row["failure"] = {"kind": "no_result", "message": done.stderr[-500:]}
        return row
    stages = result.get("stage_s", {})
    row["success"] = bool(result.get("success"))
    row["failure"] = result.get("failure")
    if all(k in stages for k in TASK_STAGES):
        row["task_s"] = sum(stages[k] for k in TASK_STAGES)
    row["execute_s"] = stages.get("execute")
    for name in WAITS:
        row[name] = result.get(name)
    return row


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The points, each with its runs' counts and medians (see the module docstring)."""
    points: list[dict[str, Any]] = []
    for rtt_ms, loss in dict.fromkeys((r["rtt_ms"], r["loss"]) for r in rows):
        mine = [r for r in rows if (r["rtt_ms"], r["loss"]) == (rtt_ms, loss)]
        times = [r["task_s"] for r in mine if r["success"] and r["task_s"] is not None]
        points.append({
            "rtt_ms": rtt_ms, "loss": loss, "runs": len(mine),
            "successes": sum(r["success"] for r in mine),
            "task_s_median": statistics.median(times) if times else None,
            "failures": sorted({r["failure"]["kind"] for r in mine if r["failure"]}),
        })  # fmt: skip
        for name in WAITS:  # every run's, successful or not: the waits are the link's
            measured = [r[name] for r in mine if r.get(name) is not None]
            points[-1][f"{name}_median"] = statistics.median(measured) if measured else None
    timed = {
        (r["rtt_ms"], r["loss"], r["seed"]): r["task_s"]
        for r in rows
        if r["success"] and r["task_s"] is not None
    }
    measured = {(q["rtt_ms"], q["loss"]) for q in points}
    for p in points:
        base_loss = p["loss"] if (0.0, p["loss"]) in measured else 0.0
        extra = [
            t - timed[(0.0, base_loss, seed)]
            for (rtt_ms, loss, seed), t in timed.items()
            if (rtt_ms, loss) == (p["rtt_ms"], p["loss"]) and (0.0, base_loss, seed) in timed
        ]
        p["overhead_s_median"] = statistics.median(extra) if extra else None
    return points


def plot(points: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_ok, ax_t) = plt.subplots(1, 2, figsize=(10, 3.8))
    for loss in sorted({p["loss"] for p in points}):
        mine = sorted((p for p in points if p["loss"] == loss), key=lambda p: p["rtt_ms"])
        rtt = [p["rtt_ms"] for p in mine]
        ax_ok.plot(rtt, [p["successes"] / p["runs"] for p in mine], "o-",
                   label=f"loss {loss:.0%}")  # fmt: skip
        timed = [p for p in mine if p["overhead_s_median"] is not None]
        ax_t.plot([p["rtt_ms"] for p in timed], [p["overhead_s_median"] for p in timed], "o-",
                  label=f"loss {loss:.0%}")  # fmt: skip
    top = max(p["rtt_ms"] for p in points)
    ax_t.plot([0, top], [0, 3 * top / 1000.0], "k:", label="3 round trips")
    ax_ok.set_ylim(-0.05, 1.05)
    ax_ok.set_xlabel("round trip (ms)")
    ax_ok.set_ylabel("success rate")
    ax_t.set_xlabel("round trip (ms)")
    ax_t.set_ylabel("task time over the 0 ms link (s, median)")
    for ax in (ax_ok, ax_t):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--task", type=Path, default=DEFAULT_TASK,
        help="the task file (default: examples/tasks/cube-corner.json)",
    )  # fmt: skip
    parser.add_argument(
        "--rtt-ms", type=lambda t: _floats(t, 0.0, 5000.0, "--rtt-ms"),
        default=[0.0, 50.0, 100.0, 250.0, 500.0, 1000.0],
        help="round trips, comma-separated (default 0,50,100,250,500,1000)",
    )  # fmt: skip
    parser.add_argument(
        "--loss", type=lambda t: _floats(t, 0.0, 0.5, "--loss"), default=[0.0, 0.01, 0.05],
        help="loss each way, fractions, comma-separated (default 0,0.01,0.05)",
    )  # fmt: skip
    parser.add_argument("--jitter", type=float, default=0.1,
                        help="jitter as a fraction of the one-way delay (default 0.1)")  # fmt: skip
    parser.add_argument("--runs", type=int, default=3, help="seeds per point (default 3)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument(
        "--time-scale", type=float, default=1.0,
        help="the work site's simulated seconds per wall second (default 1: a faster "
        "simulation would shrink the motion against the delay)",
    )  # fmt: skip
    parser.add_argument(
        "--from-csv", type=Path, nargs="+", metavar="CSV",
        help="run nothing: rebuild the outputs from runs recorded in these latency.csv files "
        "(a later file's run of a round trip, loss and seed replaces an earlier one's)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("docs/bench"))
    parser.add_argument(
        "--logs", type=Path,
        help="keep each run's work-site log and program journal in this directory (default: "
        "a temporary one, removed at the end)",
    )  # fmt: skip


CSV_FIELDS = ["rtt_ms", "loss", "seed", "success", *MEASURES, "failure"]


def read_rows(paths: list[Path]) -> list[dict[str, Any]]:
    """The runs recorded in ``paths`` (``latency.csv`` files), a later file's run of the same
    round trip, loss and seed replacing an earlier one's; ValueError naming a malformed row."""
    runs: dict[tuple[float, float, int], dict[str, Any]] = {}
    for path in paths:
        with path.open(newline="") as f:
            for line, raw in enumerate(csv.DictReader(f), start=2):
                try:
                    row = {
                        "rtt_ms": float(raw["rtt_ms"]), "loss": float(raw["loss"]),
                        "seed": int(raw["seed"]), "success": raw["success"] == "True",
                        "failure": json.loads(raw["failure"]) if raw["failure"] else None,
                    }  # fmt: skip
                    # A file recorded before a figure was measured lacks its column.
                    for name in MEASURES:
                        row[name] = float(raw[name]) if raw.get(name) else None
                except (KeyError, TypeError, ValueError) as e:
                    raise ValueError(f"{path}:{line}: not a latency run ({e})") from None
                runs[(row["rtt_ms"], row["loss"], row["seed"])] = row
    return sorted(runs.values(), key=lambda r: (r["loss"], r["rtt_ms"], r["seed"]))


def write_outputs(rows: list[dict[str, Any]], args: argparse.Namespace) -> list[dict[str, Any]]:
    """``latency.csv``, ``.json`` and ``.png`` in ``args.out`` for ``rows``; the points."""
    points = summarise(rows)
    with (args.out / "latency.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for r in rows:
            writer.writerow({**r, "failure": json.dumps(r["failure"]) if r["failure"] else ""})
    summary = {"task": args.task.name, "jitter": args.jitter, "time_scale": args.time_scale,
               "load_average": os.getloadavg(), "points": points}  # fmt: skip
    (args.out / "latency.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(points, args.out / "latency.png")
    return points


def main(args: argparse.Namespace) -> int:
    if args.from_csv:
        args.out.mkdir(parents=True, exist_ok=True)
        try:
            points = write_outputs(read_rows(args.from_csv), args)
        except (OSError, ValueError) as e:
            print(f"latency: {e}", file=sys.stderr)
            return 2
        print(json.dumps(points))
        return 0
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"latency: network namespaces unavailable: {reason}", file=sys.stderr)
        return 2
    if not args.task.is_file():
        print(f"latency: --task {args.task}: no such file", file=sys.stderr)
        return 2
    for name, value, low, high in (("runs", args.runs, 1, 1000), ("jitter", args.jitter, 0, 1),
                                   ("time-scale", args.time_scale, 0.1, 10)):  # fmt: skip
        if not low <= value <= high:
            print(f"latency: --{name} must be in [{low}, {high}], got {value}", file=sys.stderr)
            return 2
    args.out.mkdir(parents=True, exist_ok=True)
    grid = [(rtt, loss) for loss in args.loss for rtt in args.rtt_ms]
    rows: list[dict[str, Any]] = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="latency-") as tmp:
        log_dir = args.logs or Path(tmp)
        log_dir.mkdir(parents=True, exist_ok=True)
        for n, (rtt_ms, loss) in enumerate(grid):
            for seed in range(args.first_seed, args.first_seed + args.runs):
                row = run_once(args.task, rtt_ms, loss, seed, args, log_dir)
                rows.append(row)
                how = "success" if row["success"] else (row["failure"] or {}).get("kind", "?")
                took = "" if row["task_s"] is None else f", task {row['task_s']:.1f} s"
                print(f"point {n + 1}/{len(grid)} ({rtt_ms:g} ms, loss {loss:g}) seed {seed}: "
                      f"{how}{took} [{time.monotonic() - t0:.0f} s]", file=sys.stderr,
                      flush=True)  # fmt: skip
    points = write_outputs(rows, args)
    print(json.dumps(points))
    return 0
