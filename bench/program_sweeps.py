"""The deformation's sweep cap on the scripted tasks: program generator CPU time against how far
the program moves from the uncapped one (the end-to-end computation figure, the ``deform_sweeps``
knob).

Run: ``.venv/bin/python -m bench program_sweeps --out docs/bench``. For each
seed, the scripted operator's demonstration of each task on the seed's layout (the work site's
``--seed`` layout, taken as recognised: no vision, no work site), then :func:`generate_program`
at each sweep cap, CPU time best of ``--repeats``. "Targets away": the largest distance of a
program's targets from the polyline of the reference cap's targets (m; the reference is the
largest cap). Writes ``program_sweeps.csv``, ``program_sweeps.json`` (medians per task and cap)
and ``program_sweeps.png``; prints the JSON.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

from models.scene import load_scene
from operator_site.program import DeformParams
from operator_site.scripted import TASKS, layout_demonstration
from operator_site.session import generated_program

CAPS = (10, 20, 30, 45, 100, 300)


def _polyline_distance_m(p: np.ndarray, line: np.ndarray) -> float:
    """Distance from point ``p`` (3,) to the polyline through ``line`` (n, 3) (m)."""
    if len(line) == 1:
        return float(np.linalg.norm(p - line[0]))
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum((ab * ab).sum(1), 1e-30), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def targets_away_m(program, reference) -> float:
    """Largest distance of ``program``'s target positions from ``reference``'s target polyline."""
    ref = np.array([c.X_WP[:3, 3] for c in reference.commands])
    return max(_polyline_distance_m(c.X_WP[:3, 3], ref) for c in program.commands)


def run(seeds: range, caps: tuple[int, ...], repeats: int) -> list[dict]:
    scene = load_scene()
    rows = []
    for task in TASKS:
        for seed in seeds:
            demo = layout_demonstration(task, seed, scene)
            programs = {}
            for cap in caps:
                params = DeformParams(max_sweeps=cap)
                best = float("inf")
                for _ in range(repeats):
                    t0 = time.process_time()
                    made = generated_program(demo.session, "p", deform_params=params)
                    programs[cap] = made.program
                    best = min(best, time.process_time() - t0)
                rows.append({"task": task, "seed": seed, "max_sweeps": cap, "cpu_s": best,
                             "commands": len(programs[cap].commands)})  # fmt: skip
            for r in rows[-len(caps) :]:
                r["targets_away_mm"] = 1e3 * targets_away_m(programs[r["max_sweeps"]],
                                                             programs[max(caps)])  # fmt: skip
            print(json.dumps(rows[-len(caps) :]), flush=True)
    return rows


def summarise(rows: list[dict], caps: tuple[int, ...]) -> dict:
    out: dict = {"default_max_sweeps": DeformParams().max_sweeps}
    for task in TASKS:
        out[task] = {}
        for cap in caps:
            sel = [r for r in rows if r["task"] == task and r["max_sweeps"] == cap]
            out[task][str(cap)] = {
                "cpu_s_median": float(np.median([r["cpu_s"] for r in sel])),
                "cpu_s_max": float(np.max([r["cpu_s"] for r in sel])),
                "targets_away_mm_max": float(np.max([r["targets_away_mm"] for r in sel])),
                "targets_away_mm_median": float(np.median([r["targets_away_mm"] for r in sel])),
                "seeds": len(sel),
            }
    return out


def plot(summary: dict, caps: tuple[int, ...], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    default = summary["default_max_sweeps"]
    for task in TASKS:
        cpu = [summary[task][str(c)]["cpu_s_median"] for c in caps]
        away = [summary[task][str(c)]["targets_away_mm_max"] for c in caps]
        ax.plot(cpu, away, "o-", label=task)
        # Caps giving the same program (the deformation stopped before them) share one label.
        points: dict[tuple[float, float], tuple[float, float, list[int]]] = {}
        for c, x, y in zip(caps, cpu, away, strict=True):
            points.setdefault((round(x, 2), round(y, 1)), (x, y, []))[2].append(c)
        for x, y, same in points.values():
            label = ", ".join(map(str, same)) + (f" (default {default})" if default in same else "")
            weight = "bold" if default in same else "normal"
            ax.annotate(label, (x, y), fontsize=8, fontweight=weight, xytext=(4, 4),
                        textcoords="offset points")  # fmt: skip
    ax.axvline(1.0, color="grey", ls="--", lw=0.8, label="goal: ≤ 1 s computation a task")
    ax.set(
        xscale="log",
        xlabel="program generator CPU time, median over seeds (s)",
        ylabel=f"targets away from the {max(caps)}-sweep program, max (mm)",
        title="Deformation sweep cap: cost against change",
    )
    ax.legend(loc="center", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench program_sweeps``."""
    parser.add_argument(
        "--seeds", type=int, default=10, help="run seeds 0 … N − 1 (default: %(default)s)"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=2,
        help="CPU time is the best of this many runs (default: %(default)s)",
    )
    parser.add_argument(
        "--caps",
        type=int,
        nargs="+",
        default=list(CAPS),
        help="deformation sweep caps to compare; the largest is the reference (default: "
        "%(default)s)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for program_sweeps.csv, .json and .png (default: %(default)s)",
    )
    parser.add_argument(
        "--plot-only",
        action="store_true",
        help="redraw program_sweeps.png from --out's program_sweeps.json, measuring nothing",
    )


def main(args: argparse.Namespace) -> int:
    """Run the sweep (or only redraw the plot); print its JSON (one line) last."""
    caps = tuple(sorted(args.caps))
    if args.plot_only:
        summary = json.loads((args.out / "program_sweeps.json").read_text())
        caps = tuple(sorted(int(c) for c in summary[TASKS[0]]))
        plot(summary, caps, args.out / "program_sweeps.png")
        return 0
    rows = run(range(args.seeds), caps, args.repeats)
    args.out.mkdir(parents=True, exist_ok=True)
    with (args.out / "program_sweeps.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows, caps)
    summary["date_utc"] = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    (args.out / "program_sweeps.json").write_text(json.dumps(summary, indent=1))
    plot(summary, caps, args.out / "program_sweeps.png")
    print(json.dumps(summary))
    return 0
