"""``python -m bench e2e``: the scripted tasks over many seeds.

Each seed runs :func:`operator_site.scripted.run_scripted` against its own freshly started,
seeded work site. Writes ``e2e.jsonl`` (one JSON row per run, appended as each run ends, so a
long run that is stopped loses nothing), ``e2e.csv`` (the same rows), ``e2e.json`` (the summary)
and ``e2e.png`` (final errors and stage times) into the output directory. With ``keep``, the
rows already in ``e2e.jsonl`` for other tasks or seeds stay and are summarised too: a 100-seed
run can be made in parts (``--first-seed``), one task at a time.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from operator_site.scripted import SUCCESS_DEG, SUCCESS_MM, TASKS, run_scripted

STAGES = ("vision", "model", "operator", "program", "execute")


def _nanmedian(values: list[float]) -> float:
    """Median over the runs that reached a stage (NaN when none did)."""
    kept = [v for v in values if not np.isnan(v)]
    return float(np.median(kept)) if kept else float("nan")


def summarise(rows: list[dict]) -> dict:
    """Success count, error percentiles and median stage times of one task's runs."""
    ok = [r for r in rows if r.get("success")]
    err = np.array([r["final_error_mm"] for r in rows if "final_error_mm" in r])
    deg = np.array([r["final_error_deg"] for r in rows if "final_error_deg" in r])
    comp = np.array([r["stage_s"].get("computation", np.nan) for r in rows])
    return {
        "runs": len(rows),
        "success": len(ok),
        "success_rate": len(ok) / len(rows) if rows else 0.0,
        "final_error_mm_median": float(np.median(err)) if err.size else None,
        "final_error_mm_p95": float(np.percentile(err, 95)) if err.size else None,
        "final_error_deg_median": float(np.median(deg)) if deg.size else None,
        "computation_s_median": float(np.nanmedian(comp)) if comp.size else None,
        "computation_s_max": float(np.nanmax(comp)) if comp.size else None,
        "time_scale_achieved_min": min(
            (r["time_scale_achieved"] for r in rows if "time_scale_achieved" in r), default=None
        ),
        "stage_s_median": {
            s: _nanmedian([r["stage_s"].get(s, np.nan) for r in rows]) for s in STAGES
        },
        "failures": {
            r["seed"]: r.get("error") or r.get("execution") for r in rows if not r.get("success")
        },
    }


def _plot(out_dir: Path, by_task: dict[str, list[dict]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for task, rows in by_task.items():
        err = [r["final_error_mm"] for r in rows if "final_error_mm" in r]
        deg = [r["final_error_deg"] for r in rows if "final_error_deg" in r]
        a.scatter(err, deg, s=12, label=task)
    a.axvline(SUCCESS_MM, color="grey", ls="--")
    a.axhline(SUCCESS_DEG, color="grey", ls="--")
    a.set(
        xscale="log",
        yscale="log",
        xlabel="final position error (mm)",
        ylabel="final rotation error (°)",
        title="Block at the work site vs the simulator's goal",
    )
    a.legend()
    width = 0.8 / max(1, len(by_task))
    for k, (task, rows) in enumerate(by_task.items()):
        med = [_nanmedian([r["stage_s"].get(s, np.nan) for r in rows]) for s in STAGES]
        b.bar(np.arange(len(STAGES)) + k * width, med, width, label=task)
    b.set_xticks(np.arange(len(STAGES)) + 0.4 - width / 2, STAGES)
    b.set(yscale="log", ylabel="median wall time (s)", title="Stages")
    b.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "e2e.png", dpi=100)
    plt.close(fig)


def _tree() -> str:
    """The source tree the rows come from: ``git describe`` of this checkout ("unknown" outside
    git), ``-dirty`` when it has uncommitted changes."""
    try:
        return subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _read_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    rows = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as e:  # a line cut by a killed run: say so, keep the rest
            print(f"{path}:{k}: skipped, not a JSON row ({e})", file=sys.stderr)
    return rows


def run(
    out_dir: Path,
    seeds: int,
    tasks: tuple[str, ...] = TASKS,
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
    first_seed: int = 0,
    keep: bool = False,
) -> dict:
    """Run seeds ``first_seed`` … ``first_seed + seeds − 1`` of each task (work sites started at
    ``time_scale`` with ``work_site_args``); write the files; the summary by task (over the
    kept rows too with ``keep``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows_path = out_dir / "e2e.jsonl"
    todo = {(task, seed) for task in tasks for seed in range(first_seed, first_seed + seeds)}
    kept = [r for r in _read_rows(rows_path) if (r["task"], r["seed"]) not in todo] if keep else []
    with rows_path.open("w") as f:
        f.writelines(json.dumps(r) + "\n" for r in kept)
    tree = _tree()
    for task in tasks:
        for seed in range(first_seed, first_seed + seeds):
            r = run_scripted(
                task,
                seed,
                oracle=oracle,
                log=lambda _: None,
                time_scale=time_scale,
                work_site_args=work_site_args,
            )
            r["tree"] = tree
            with rows_path.open("a") as f:
                f.write(json.dumps(r) + "\n")
            print(
                f"{task} seed {seed}: {'ok' if r.get('success') else 'FAILED'} "
                f"{r.get('final_error_mm', float('nan')):.3f} mm "
                f"{r.get('error') or r.get('execution', '')}",
                file=sys.stderr,
                flush=True,
            )
    by_task: dict[str, list[dict]] = {}
    for r in sorted(_read_rows(rows_path), key=lambda r: (TASKS.index(r["task"]), r["seed"])):
        by_task.setdefault(r["task"], []).append(r)
    fields = ["task", "seed", "success", "workpiece", "corner", "final_error_mm",
              "final_error_deg", "contacts_required", "contacts_verified", "commands",
              "time_scale_achieved",
              *[f"{s}_s" for s in STAGES], "execution", "error", "tree"]  # fmt: skip
    with (out_dir / "e2e.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for rows in by_task.values():
            for r in rows:
                writer.writerow(r | {f"{s}_s": r["stage_s"].get(s) for s in STAGES})
    summary = {task: summarise(rows) for task, rows in by_task.items()}
    for task, rows in by_task.items():
        summary[task]["trees"] = sorted({r.get("tree", "unknown") for r in rows})
    summary["oracle_vision"] = oracle
    summary["time_scale"] = time_scale
    summary["work_site_args"] = list(work_site_args)
    (out_dir / "e2e.json").write_text(json.dumps(summary, indent=1))
    _plot(out_dir, by_task)
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench e2e``."""
    parser.add_argument(
        "--seeds", type=int, default=100, help="seeds per task (default: %(default)s)"
    )
    parser.add_argument(
        "--first-seed",
        type=int,
        default=0,
        metavar="N",
        help="the first seed (default: %(default)s); seeds N … N + --seeds − 1 are run",
    )
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep the rows of other tasks and seeds already in --out's e2e.jsonl and "
        "summarise them with this run's (a long run in parts)",
    )
    parser.add_argument(
        "--oracle-vision",
        action="store_true",
        help="blocks' poses from the work site's ground truth instead of vision",
    )
    parser.add_argument(
        "--surface-stiffness",
        type=float,
        default=None,
        metavar="N_PER_M",
        help="the started work sites' `--surface-stiffness` (default: theirs)",
    )
    add_time_scale_argument(parser)
    parser.add_argument(
        "--tasks",
        nargs="+",
        choices=TASKS,
        default=list(TASKS),
        help="which scripted tasks (default: all)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for e2e.jsonl, e2e.csv, e2e.json and e2e.png (default: %(default)s)",
    )


def add_time_scale_argument(parser: argparse.ArgumentParser) -> None:
    """``--time-scale``, shared with ``python -m bench trade``."""
    parser.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        metavar="X",
        help="the started work sites simulate X seconds per wall second (default: 1); the "
        "physics is stepped alike at any scale, only the wall time differs (the JSON's "
        "time_scale_achieved_min says how fast the machine managed)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    stiffness = args.surface_stiffness
    summary = run(
        args.out,
        args.seeds,
        tuple(args.tasks),
        oracle=args.oracle_vision,
        time_scale=args.time_scale,
        work_site_args=() if stiffness is None else ("--surface-stiffness", str(stiffness)),
        first_seed=args.first_seed,
        keep=args.keep,
    )
    print(json.dumps(summary))
    return 0
