"""``python -m bench trade``: each user knob's effect on the scripted task end to end.

For every knob, the scripted task (:func:`operator_site.scripted.run_scripted`) runs over the
same seeds at each of the knob's values, all other knobs at their defaults; the defaults' runs
are shared by all knobs. Writes ``trade.csv`` (one row a run), ``trade.json`` (per knob and
value: successes, final error, computation and execution time; and every run's row) and
``trade.png`` (per knob: success and final error against the value, the default marked) into
the output directory.
The component benchmarks plot each knob's cost against its own accuracy (sim_sweeps.png,
vision_sweeps.png, deform_trade.png, control.png); this one says what that does to the task.

Knobs may be run a few at a time into the same directory: an earlier run's other knobs (same
task and seeds) are kept and its defaults' runs reused. Knobs of the operator site's program
generator apply to the program made from the scripted demonstration (the demonstration itself
is dragged with the default simulator); the work site's apply to the work site the run starts.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.e2e import add_time_scale_argument
from operator_site.chain import ProgramMaker
from operator_site.program import CommandParams, DeformParams
from operator_site.scripted import TASKS, run_scripted
from operator_site.session import generated_program
from operator_site.simulator import SimParams
from work_site.control.controller import DEFAULT_SURFACE_STIFFNESS_N_PER_M
from work_site.vision import IndexParams


@dataclass(frozen=True)
class Knob:
    """A setting users may turn: its values to try (the default among them) and where it goes:
    ``target`` is ``sim`` (SimParams), ``deform`` (DeformParams), ``command`` (CommandParams)
    or ``work_site`` (a ``work-site serve`` option named ``field``)."""

    label: str
    target: str
    field: str
    values: tuple[float, ...]
    default: float


KNOBS: dict[str, Knob] = {
    "contact_speed": Knob(
        "speed in contact (m/s)", "command", "contact_speed_mps",
        (0.005, CommandParams().contact_speed_mps, 0.02), CommandParams().contact_speed_mps,
    ),
    "surface_stiffness": Knob(
        "stiffness along surfaces (N/m)", "work_site", "--surface-stiffness",
        (1000.0, 5000.0), DEFAULT_SURFACE_STIFFNESS_N_PER_M,
    ),
    "vision_scale": Knob(
        "vision's image scale (0.5: 320×240)", "work_site", "--vision-scale", (0.5, 1.0), 1.0,
    ),
    "vision_index_views": Knob(
        "vision index: viewing directions", "work_site", "--vision-index-views",
        (300, IndexParams().n_views), IndexParams().n_views,
    ),
    "deform_sweeps": Knob(
        "deformation sweeps (max)", "deform", "max_sweeps",
        (10, DeformParams().max_sweeps, 300), DeformParams().max_sweeps,
    ),
    "sim_dt": Knob(
        "generator's simulator Δt (s)", "sim", "dt_s",
        (0.025, SimParams().dt_s, 0.1), SimParams().dt_s,
    ),
    "eps_barrier": Knob(
        "barrier ε_b (m)", "sim", "eps_barrier_m",
        (0.05e-3, SimParams().eps_barrier_m, 0.25e-3), SimParams().eps_barrier_m,
    ),
    "golden_tol": Knob(
        "golden tolerance (× Δt)", "sim", "golden_rel_tol",
        (1e-3, SimParams().golden_rel_tol, 1e-8), SimParams().golden_rel_tol,
    ),
}  # fmt: skip


def _program_maker(knob: Knob, value: float) -> ProgramMaker:
    """The scripted run's program generator with ``knob`` at ``value`` (ValueError, from the
    parameters' own checks, if the value is not allowed)."""
    field = {knob.field: type(knob.default)(value)}
    params = {
        "sim_params": dataclasses.replace(SimParams(), **field) if knob.target == "sim" else None,
        "deform_params": DeformParams(**field) if knob.target == "deform" else None,
        "command_params": CommandParams(**field) if knob.target == "command" else None,
    }
    return functools.partial(generated_program, **params)


def _append(path: Path, row: dict) -> None:
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def _previous(
    out_dir: Path, task: str, seeds: int, knobs: tuple[str, ...], time_scale: float
) -> dict[str, Any]:
    """What an earlier run into ``out_dir`` of the same task, seeds and time scale measured for
    other knobs (kept, so that knobs can be run a few at a time), and its defaults' rows
    (reused)."""
    kept: dict[str, Any] = {"rows": [], "default": [], "summary": {}}
    try:
        before = json.loads((out_dir / "trade.json").read_text())
    except (OSError, ValueError):
        return kept
    same = (before.get("task"), before.get("seeds"), before.get("time_scale", 1.0))
    if same != (task, seeds, time_scale):
        return kept
    kept["rows"] = [r for r in before.get("runs", []) if r["knob"] not in knobs]
    kept["default"] = [r for r in kept["rows"] if r["knob"] == "default"]
    kept["summary"] = {k: v for k, v in before.get("knobs", {}).items() if k not in knobs}
    if len(kept["default"]) != seeds:  # the defaults must be rerun with the knobs asked for
        kept["default"] = []
        kept["rows"] = [r for r in kept["rows"] if r["knob"] != "default"]
    return kept


def _summary(rows: list[dict]) -> dict[str, Any]:
    def median(key: str, only_ok: bool = False) -> float | None:
        values = [r[key] for r in rows if r.get(key) is not None and (r["success"] or not only_ok)]
        return float(np.median(values)) if values else None

    return {
        "runs": len(rows),
        "success": sum(bool(r["success"]) for r in rows),
        "final_error_mm_median": median("final_error_mm", only_ok=True),
        "computation_s_median": median("computation_s"),
        "execute_s_median": median("execute_s"),
        "failures": {str(r["seed"]): r["outcome"] for r in rows if not r["success"]},
    }


def _plot(out_dir: Path, task: str, summary: dict[str, dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(summary), figsize=(3.2 * len(summary), 6), squeeze=False)
    for col, (name, by_value) in enumerate(summary.items()):
        knob = KNOBS[name]
        xs = [float(v) for v in by_value]
        rate = [s["success"] / s["runs"] for s in by_value.values()]
        err = [s["final_error_mm_median"] or np.nan for s in by_value.values()]
        comp = [s["computation_s_median"] or np.nan for s in by_value.values()]
        top, bottom = axes[0][col], axes[1][col]
        top.plot(xs, rate, "o-")
        top.set(title=knob.label, ylim=(-0.05, 1.05), ylabel="success" if col == 0 else None)
        bottom.plot(xs, err, "o-", label="final error (mm, successes)")
        bottom.plot(xs, comp, "s--", label="computation (s)")
        bottom.set(xlabel=knob.field)
        for ax in (top, bottom):
            ax.axvline(knob.default, color="grey", ls=":", label="default")
            if min(xs) > 0 and max(xs) / min(xs) > 20:
                ax.set_xscale("log")
        if col == 0:
            bottom.legend(fontsize=7)
    fig.suptitle(f"{task}: each knob's effect end to end (other knobs at their defaults)")
    fig.tight_layout()
    fig.savefig(out_dir / "trade.png", dpi=90)
    plt.close(fig)


def run(
    out_dir: Path,
    seeds: int,
    task: str = "corner",
    knobs: tuple[str, ...] = tuple(KNOBS),
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    time_scale: float = 1.0,
) -> dict:
    """Run ``seeds`` seeds of ``task`` per knob value (work sites started at ``time_scale``);
    write the files; the summary."""
    unknown = [k for k in knobs if k not in KNOBS]
    if unknown:
        raise ValueError(f"unknown knob(s) {unknown} (known: {', '.join(KNOBS)})")
    for name in knobs:  # every value checked before the first run, not after an hour
        knob = KNOBS[name]
        if knob.target != "work_site":
            for value in knob.values:
                _program_maker(knob, value)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    runs: dict[tuple[str, float], list[dict]] = {}
    csv_path = out_dir / "trade.csv"
    kept = _previous(out_dir, task, seeds, knobs, time_scale)
    if kept["default"]:
        runs[("default", 0.0)] = kept["default"]
    csv_path.unlink(missing_ok=True)
    for row in kept["rows"]:
        _append(csv_path, row)

    def run(name: str, value: float) -> list[dict]:
        knob = KNOBS[name]
        shared = value == knob.default
        cache_key = ("default", 0.0) if shared else (name, value)
        if cache_key in runs:
            return runs[cache_key]
        work_site_args: tuple[str, ...] = ()
        make = _program_maker(knob, value) if knob.target != "work_site" and not shared else None
        if knob.target == "work_site" and not shared:
            work_site_args = (knob.field, str(type(knob.default)(value)))
        done = []
        for seed in range(seeds):
            r = run_scripted(
                task, seed, log=lambda _: None, work_site_args=work_site_args,
                time_scale=time_scale,
                **({"make_program": make} if make is not None else {}),
            )  # fmt: skip
            row = {
                "knob": "default" if shared else name,
                "value": value,
                "seed": seed,
                "success": bool(r.get("success")),
                "final_error_mm": r.get("final_error_mm"),
                "final_error_deg": r.get("final_error_deg"),
                "computation_s": r["stage_s"].get("computation"),
                "execute_s": r["stage_s"].get("execute"),
                "commands": r.get("commands"),
                "outcome": r.get("error") or r.get("execution") or "",
            }
            done.append(row)
            rows.append(row)
            _append(csv_path, row)  # each run kept as it ends
            log(f"trade {row['knob']}={value:g} seed {seed}: "
                f"{'ok' if row['success'] else 'FAILED ' + row['outcome']}")  # fmt: skip
        runs[cache_key] = done
        return done

    summary: dict[str, dict] = dict(kept["summary"])
    for name in knobs:
        summary[name] = {str(v): _summary(run(name, v)) for v in KNOBS[name].values}
    summary = {n: summary[n] for n in KNOBS if n in summary}
    result = {
        "task": task,
        "seeds": seeds,
        "time_scale": time_scale,
        "defaults": {n: KNOBS[n].default for n in summary},
        "knobs": summary,
        "runs": kept["rows"] + rows,
    }
    (out_dir / "trade.json").write_text(json.dumps(result, indent=1))
    _plot(out_dir, task, summary)
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench trade``."""
    parser.add_argument(
        "--seeds", type=int, default=100, help="seeds per knob value (default: %(default)s)"
    )
    add_time_scale_argument(parser)
    parser.add_argument(
        "--tasks",
        nargs="+",
        choices=TASKS,
        default=list(TASKS),
        help="the scripted task to run is the first of these (default: %(default)s)",
    )
    parser.add_argument(
        "--knobs",
        nargs="+",
        default=None,
        metavar="KNOB",
        help=f"which knobs to turn, one at a time (default: all: {', '.join(KNOBS)})",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for trade.csv, trade.json and trade.png (default: %(default)s)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last; 2 for an unknown knob."""
    knobs = tuple(args.knobs) if args.knobs else tuple(KNOBS)
    if unknown := [k for k in knobs if k not in KNOBS]:
        print(f"python -m bench trade: unknown knob(s) {unknown} (known: {', '.join(KNOBS)})",
              file=sys.stderr)  # fmt: skip
        return 2
    result = run(args.out, args.seeds, args.tasks[0], knobs, time_scale=args.time_scale)
    print(json.dumps(result))
    return 0
