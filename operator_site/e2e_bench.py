"""``operator-site bench e2e``: the scripted tasks over many seeds (issue 9).

Each seed runs :func:`operator_site.scripted.run_scripted` against its own freshly started,
seeded work site. Writes ``e2e.csv`` (one row per run), ``e2e.json`` (the summary) and
``e2e.png`` (final errors and stage times) into the output directory.
"""

from __future__ import annotations

import csv
import json
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


def main(
    out_dir: Path,
    seeds: int,
    tasks: tuple[str, ...] = TASKS,
    oracle: bool = False,
    time_scale: float = 1.0,
    work_site_args: tuple[str, ...] = (),
) -> dict:
    """Run ``seeds`` seeds of each task (work sites started at ``time_scale`` with
    ``work_site_args``); write the files; the summary by task."""
    out_dir.mkdir(parents=True, exist_ok=True)
    by_task: dict[str, list[dict]] = {}
    for task in tasks:
        rows = by_task.setdefault(task, [])
        for seed in range(seeds):
            r = run_scripted(
                task,
                seed,
                oracle=oracle,
                log=lambda _: None,
                time_scale=time_scale,
                work_site_args=work_site_args,
            )
            rows.append(r)
            print(
                f"{task} seed {seed}: {'ok' if r.get('success') else 'FAILED'} "
                f"{r.get('final_error_mm', float('nan')):.3f} mm "
                f"{r.get('error') or r.get('execution', '')}",
                file=sys.stderr,
                flush=True,
            )
    fields = ["task", "seed", "success", "workpiece", "corner", "final_error_mm",
              "final_error_deg", "contacts_required", "contacts_verified", "commands",
              "time_scale_achieved",
              *[f"{s}_s" for s in STAGES], "execution", "error"]  # fmt: skip
    with (out_dir / "e2e.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for rows in by_task.values():
            for r in rows:
                writer.writerow(r | {f"{s}_s": r["stage_s"].get(s) for s in STAGES})
    summary = {task: summarise(rows) for task, rows in by_task.items()}
    summary["oracle_vision"] = oracle
    summary["time_scale"] = time_scale
    summary["work_site_args"] = list(work_site_args)
    (out_dir / "e2e.json").write_text(json.dumps(summary, indent=1))
    _plot(out_dir, by_task)
    return summary
