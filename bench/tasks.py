"""``python -m bench tasks``: every shipped task file end to end over seeded layouts.

Each (task, seed) runs :func:`operator_site.runner.run_task` against its own freshly started
work site, blocks laid out by the seed. A task runs on the first seeds whose layouts leave it
room (:func:`operator_site.runner.room_for_task`); the seeds passed over are in ``tasks.json``
with the reason. Writes ``tasks.jsonl`` (one JSON row per run, appended
as each run ends), ``tasks.csv`` (the same rows), ``tasks.json`` (a list, one summary object per
task) and ``tasks.png`` (successes and failure kinds per task, final errors) into the output
directory.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from bench.e2e import _read_rows, _tree, add_time_scale_argument
from models.layout import random_layout
from models.scene import Scene, load_scene
from operator_site.runner import room_for_task, run_task
from operator_site.taskfile import Task, TaskFileError, load_task

TASKS_DIR = Path(__file__).resolve().parents[1] / "examples" / "tasks"
PASSED_OVER_FILE = "tasks_passed_over.json"
"""Per task file, the seeds passed over for want of room, with why."""
MAX_SEEDS_PASSED_OVER = 10
"""A task may pass over at most this many layouts per layout it runs on."""


def seeds_with_room(
    task: Task, scene: Scene, first_seed: int, count: int
) -> tuple[list[int], dict[int, str]]:
    """The first ``count`` seeds from ``first_seed`` on whose layouts leave ``task`` room, and
    the seeds passed over with why; ValueError when too few do."""
    seeds: list[int] = []
    passed_over: dict[int, str] = {}
    for seed in range(first_seed, first_seed + count * (1 + MAX_SEEDS_PASSED_OVER)):
        if len(seeds) == count:
            break
        reason = room_for_task(task, scene, random_layout(scene, seed))
        if reason is None:
            seeds.append(seed)
        else:
            passed_over[seed] = reason
    if len(seeds) < count:
        raise ValueError(
            f"{task.name}: only {len(seeds)} of {len(seeds) + len(passed_over)} layouts from "
            f"seed {first_seed} leave it room"
        )
    return seeds, passed_over


def _stat(values: list[float], how) -> float | None:
    kept = [v for v in values if v is not None and np.isfinite(v)]
    return float(how(kept)) if kept else None


def summarise(file: str, workpiece: str, rows: list[dict]) -> dict:
    """One task's runs: successes, failure kinds counted, final error and computation time."""
    err_mm = [r.get("final_error_mm") for r in rows if r.get("success")]
    err_deg = [r.get("final_error_deg") for r in rows if r.get("success")]
    comp = [r.get("stage_s", {}).get("computation") for r in rows]
    return {
        "task": rows[0]["task"] if rows else file,
        "file": file,
        "workpiece": workpiece,
        "runs": len(rows),
        "successes": sum(bool(r.get("success")) for r in rows),
        "failures": dict(
            Counter(
                (r.get("failure") or {}).get("kind", "error") for r in rows if not r.get("success")
            )
        ),
        "failed_seeds": {
            r["seed"]: (r.get("failure") or {}).get("message") or r.get("error", "")
            for r in rows
            if not r.get("success")
        },
        # Vision's check of where the block ended, after each run the work site called done.
        "vision_checks": dict(
            Counter(r["vision_check"]["verdict"] for r in rows if r.get("vision_check"))
        ),
        "final_error_mm_median": _stat(err_mm, np.median),
        "final_error_mm_max": _stat(err_mm, np.max),
        "final_error_deg_median": _stat(err_deg, np.median),
        "final_error_deg_max": _stat(err_deg, np.max),
        "computation_s_median": _stat(comp, np.median),
        "computation_s_max": _stat(comp, np.max),
        "trees": sorted({r.get("tree", "unknown") for r in rows}),
    }


def _plot(out_dir: Path, summaries: list[dict], rows_by_file: dict[str, list[dict]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    names = [s["file"] for s in summaries]
    y = np.arange(len(names))
    a.barh(y, [s["successes"] for s in summaries], color="tab:green", label="success")
    left = np.array([s["successes"] for s in summaries], dtype=float)
    kinds = sorted({k for s in summaries for k in s["failures"]})
    for kind in kinds:
        n = np.array([s["failures"].get(kind, 0) for s in summaries], dtype=float)
        a.barh(y, n, left=left, label=kind)
        left += n
    a.set_yticks(y, names)
    a.invert_yaxis()
    a.set(xlabel="runs", title="Shipped tasks on seeded layouts")
    a.legend(fontsize=8)
    for file, rows in rows_by_file.items():
        ok = [r for r in rows if r.get("success")]
        b.scatter(
            [r["final_error_mm"] for r in ok], [r["final_error_deg"] for r in ok], s=14, label=file
        )
    b.set(
        xlabel="final position error (mm)",
        ylabel="final rotation error (°)",
        title="Successful runs against their goal",
    )
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "tasks.png", dpi=100)
    plt.close(fig)


def run(
    out_dir: Path,
    seeds: int,
    files: list[Path],
    first_seed: int = 0,
    time_scale: float = 1.0,
    keep: bool = False,
) -> list[dict]:
    """Run seeds ``first_seed`` … ``first_seed + seeds − 1`` of each task file; write the
    files; the summaries (over rows already in ``tasks.jsonl`` for other runs too with
    ``keep``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tasks = {f.name: load_task(f) for f in files}  # refused here, before any run, if malformed
    scene = load_scene()
    chosen = {name: seeds_with_room(task, scene, first_seed, seeds) for name, task in tasks.items()}
    passed_path = out_dir / PASSED_OVER_FILE
    passed = json.loads(passed_path.read_text()) if keep and passed_path.exists() else {}
    for name, (_, passed_over) in chosen.items():  # JSON's keys are strings
        passed[name] = passed.get(name, {}) | {str(seed): why for seed, why in passed_over.items()}
    passed_path.write_text(json.dumps(passed, indent=1))
    rows_path = out_dir / "tasks.jsonl"
    todo = {(name, seed) for name, (task_seeds, _) in chosen.items() for seed in task_seeds}
    kept = [r for r in _read_rows(rows_path) if (r["file"], r["seed"]) not in todo] if keep else []
    with rows_path.open("w") as f:
        f.writelines(json.dumps(r) + "\n" for r in kept)
    tree = _tree()
    summaries: list[dict] = []
    # Layout by layout, every task at each: a run stopped early has as many layouts of each task.
    for i in range(seeds):
        for k, (name, task) in enumerate(tasks.items(), 1):
            seed = chosen[name][0][i]
            r = run_task(task, seed, log=lambda _: None, time_scale=time_scale)
            r |= {"file": name, "workpiece": task.workpiece, "tree": tree}
            with rows_path.open("a") as f:
                f.write(json.dumps(r) + "\n")
            failure = r.get("failure") or {}
            print(
                f"[{k}/{len(tasks)}] {name} seed {seed}: "
                f"{'ok' if r.get('success') else failure.get('kind', 'FAILED')} "
                f"{r.get('final_error_mm', float('nan')):.3f} mm {failure.get('message', '')}",
                file=sys.stderr,
                flush=True,
            )
        summaries = write_summaries(out_dir, rows_path)  # after each seed: usable if stopped
    return summaries


def write_summaries(out_dir: Path, rows_path: Path) -> list[dict]:
    """``tasks.csv``, ``tasks.json`` and ``tasks.png`` from the rows in ``rows_path``; the
    summaries."""
    rows_by_file: dict[str, list[dict]] = {}
    for r in sorted(_read_rows(rows_path), key=lambda r: (r["file"], r["seed"])):
        rows_by_file.setdefault(r["file"], []).append(r)
    fields = [
        "file",
        "task",
        "workpiece",
        "seed",
        "success",
        "final_error_mm",
        "final_error_deg",
        "contacts_required",
        "contacts_verified",
        "commands",
        "time_scale_achieved",
        "computation_s",
        "failure_kind",
        "failure_message",
        "vision_verdict",
        "vision_error_mm",
        "vision_error_deg",
        "tree",
    ]
    with (out_dir / "tasks.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for rows in rows_by_file.values():
            for r in rows:
                failure = r.get("failure") or {}
                check = r.get("vision_check") or {}
                writer.writerow(
                    r
                    | {
                        "computation_s": r.get("stage_s", {}).get("computation"),
                        "failure_kind": failure.get("kind"),
                        "failure_message": failure.get("message"),
                        "vision_verdict": check.get("verdict"),
                        "vision_error_mm": check.get("error_mm"),
                        "vision_error_deg": check.get("error_deg"),
                    }
                )
    passed_path = out_dir / PASSED_OVER_FILE
    passed = json.loads(passed_path.read_text()) if passed_path.exists() else {}
    summaries = [
        summarise(f, rows[0]["workpiece"], rows) | {"passed_over_seeds": passed.get(f, {})}
        for f, rows in rows_by_file.items()
    ]
    (out_dir / "tasks.json").write_text(json.dumps(summaries, indent=1))
    _plot(out_dir, summaries, rows_by_file)
    return summaries


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench tasks``."""
    parser.add_argument("--seeds", type=int, default=20, help="layouts per task (default: 20)")
    parser.add_argument(
        "--first-seed", type=int, default=0, metavar="N", help="the first seed (default: 0)"
    )
    add_time_scale_argument(parser)
    parser.add_argument(
        "--tasks",
        type=Path,
        nargs="+",
        default=None,
        metavar="FILE",
        help=f"task files (default: every file in {TASKS_DIR})",
    )
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep rows of other tasks and seeds already in --out's tasks.jsonl",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for tasks.json, .jsonl, .csv and .png (default: docs/bench)",
    )


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        print(f"--seeds must be at least 1, got {args.seeds}", file=sys.stderr)
        return 2
    files = args.tasks or sorted(TASKS_DIR.glob("*.json"))
    try:
        summaries = run(args.out, args.seeds, files, args.first_seed, args.time_scale, args.keep)
    except (TaskFileError, ValueError) as e:
        print(e, file=sys.stderr)
        return 2
    print(json.dumps(summaries))
    return 0
