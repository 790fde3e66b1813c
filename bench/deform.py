"""``python -m bench deform``: the program generator on the paper's figures.

Prints a JSON list (one object per case) and writes ``deform.csv``, ``deform_trade.csv`` and
the PNG plots ``deform_scaling.png`` and ``deform_trade.png`` into the output directory. Times
are of the deformation alone (``ms`` wall, ``cpu_ms`` this process's CPU: the wall time
wanders when other processes share the machine) and of commands + check (``commands_ms``), one
core, median of the repeats; the simulated operator that makes each raw path is not timed.
``nodes`` counts the history's distinct poses; ``working_nodes`` the deformed path's nodes
(the history is first thinned to the node spacing, so the work follows the path's length
rather than the history's length).

Cases: ``fig12`` (the operator wanders, aligns on the frame's bar, drags over it and slides into
the inner corner), ``fig13_bottom`` (round the frame's outer corner with frame and table
captured), ``straight`` (a straight carry in free space), and the scaling runs: the Fig. 12 task
dragged at operator speeds that give about 100, 300, 1,000 and 3,000 history nodes.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

from bench import scenarios
from models.transforms import make_pose
from operator_site.program.check import Sweeper
from operator_site.program.commands import CommandParams, build_program
from operator_site.program.deform import Deformer, DeformParams
from operator_site.program.path import (
    WorkpiecePath,
    lost_contact_nodes,
    path_from_history,
    unwanted_contact_nodes,
)
from operator_site.simulator import Simulator

SCALING_NODES = (100, 300, 1000, 3000)
SWEEP_CAPS = (5, 10, 20, 40, 80, 160)
SPACINGS_M = (0.0025, 0.005, 0.01, 0.02, 0.04)
COMMAND_TOLS_M = (0.0005, 0.001, 0.002, 0.004, 0.008, 0.016)
FORCE_SWEEPS: dict[str, tuple[float, ...]] = {
    "tension_n": (0.1, 0.3, 1.0, 3.0, 10.0),
    "repulsion_n": (0.3, 1.0, 3.0, 10.0, 30.0),
    "hold_n": (0.05, 0.15, 0.5, 1.5, 5.0),
    "step_fraction": (0.05, 0.1, 0.25, 0.4, 0.5),
}
"""The deformation's forces and its step, each over two decades (one for the step, whose range
ends at a half) around its default, the rest at theirs. Only the forces' ratios shape a path:
tension and repulsion mirror each other."""
FORCE_SWEEP_CASE = {"hold_n": "fig13_bottom"}
"""The case each force is swept on where not Fig. 12: the holding force acts only on nodes that
must keep a contact, and Fig. 12's one such node is its fixed end."""
REPEATS = 3
"""Timed runs per case; the median is reported (this VM's timings wander between runs)."""


def _raw(
    case: str, speed_mps: float = scenarios.OPERATOR_SPEED_MPS
) -> tuple[Simulator, WorkpiecePath]:
    if case == "straight":
        scene = scenarios.figure_scene()
        sim = scenarios.drive(
            scene,
            make_pose(p_AB=np.array([0.20, 0.25, 0.20])),
            [scenarios.Waypoint((0.45, 0.35, 0.20))],
            speed_mps=speed_mps,
        )
    else:
        sim = getattr(scenarios, case)(speed_mps=speed_mps)
    return sim, path_from_history(sim.history, "cube", sim.c_O)


def clearance_m(deformer: Deformer, path: WorkpiecePath) -> float:
    """Smallest distance from a node without required contacts (ends excluded) to anything,
    capped at the deformer's reach (nothing nearer than that counts as clear)."""
    d = deformer.stepper.reach_m
    for node in path.nodes[1:-1]:
        if not node.required:
            probe = deformer.stepper.probe(node.X_WO)
            d = min(d, min((p.distance_m for p in probe.nearest.values()), default=d))
    return d


def run_case(
    case: str,
    raw: WorkpiecePath,
    sim: Simulator,
    deform_params: DeformParams | None = None,
    command_params: CommandParams | None = None,
    repeats: int = 1,
) -> dict:
    """Deform ``raw``, build and check its program; the path, contact, timing and program
    metrics of one case."""
    times, cpu = [], []
    for _ in range(repeats):
        deformer = Deformer(sim.scene, "cube", deform_params, sim.params)
        c0 = time.process_time()
        result = deformer.deform(raw)
        cpu.append(time.process_time() - c0)
        times.append(result.elapsed_s)
    path = result.path
    t0 = time.perf_counter()
    sweeper = Sweeper(sim.scene, "cube", sim.params)
    program = build_program(case, path, np.eye(4), command_params, sweeper)
    check = sweeper.program(program)
    commands_ms = (time.perf_counter() - t0) * 1e3
    C = path.centres_W
    final = C[-1]
    near_end = [i for i in range(len(C) - 1) if np.linalg.norm(C[i] - final) < 0.03]
    approach = (C[near_end[0]] - final).tolist() if near_end else [0.0, 0.0, 0.0]
    return {
        "case": case,
        "nodes": len(raw),
        "working_nodes": len(path),
        "ms": float(np.median(times)) * 1e3,
        "cpu_ms": float(np.median(cpu)) * 1e3,
        "sweeps": result.sweeps,
        "settled": result.settled,
        "stopped": result.stopped,
        "probes": result.probes,
        "length_raw_m": raw.length_m(),
        "length_m": path.length_m(),
        "length_reduction": 1.0 - path.length_m() / raw.length_m(),
        "unwanted_contacts": len(unwanted_contact_nodes(path)),
        "unwanted_contacts_raw": len(unwanted_contact_nodes(raw)),
        "required_contacts_kept": not lost_contact_nodes(path),
        "required_nodes": sum(bool(n.required) for n in path.nodes),
        "clearance_m": clearance_m(deformer, path),
        "commands": len(program.commands),
        "commands_ms": commands_ms,
        "check_ok": check.ok,
        "check_reason": check.reason,
        "final_contacts": sorted(c.object for c in path.nodes[-1].contacts),
        "approach_from_final_m": approach,
    }


def scaling(repeats: int) -> list[dict]:
    """The Fig. 12 task at operator speeds giving about each of :data:`SCALING_NODES` nodes
    (the speed is corrected once by the ratio of nodes obtained to nodes wanted)."""
    _, base = _raw("fig12")
    rows = []
    for n in SCALING_NODES:
        speed = scenarios.OPERATOR_SPEED_MPS * len(base) / n
        sim, raw = _raw("fig12", speed)
        if abs(len(raw) - n) > 0.1 * n:
            speed *= len(raw) / n
            sim, raw = _raw("fig12", speed)
        row = run_case(f"fig12_n{n}", raw, sim, repeats=repeats)
        row["operator_speed_mps"] = speed
        rows.append(row)
    return rows


def trade() -> list[dict]:
    """Fig. 12 (Fig. 13's bottom path for the holding force): sweep cap, node spacing, the
    forces and the step, and command tolerance against path length, clearance, commands and
    time."""
    sim, raw = _raw("fig12")
    rows = []
    for cap in SWEEP_CAPS:
        row = run_case("fig12", raw, sim, DeformParams(max_sweeps=cap))
        rows.append({"knob": "max_sweeps", "value": cap, **row})
    for spacing in SPACINGS_M:
        row = run_case("fig12", raw, sim, DeformParams(spacing_m=spacing))
        rows.append({"knob": "spacing_m", "value": spacing, **row})
    for knob, values in FORCE_SWEEPS.items():
        case = FORCE_SWEEP_CASE.get(knob, "fig12")
        case_sim, case_raw = (sim, raw) if case == "fig12" else _raw(case)
        for value in values:
            row = run_case(case, case_raw, case_sim, DeformParams(**{knob: value}))
            rows.append({"knob": knob, "value": value, **row})
    for tol in COMMAND_TOLS_M:
        params = CommandParams(position_tol_m=tol, angle_tol_rad=10 * tol)
        row = run_case("fig12", raw, sim, command_params=params)
        rows.append({"knob": "position_tol_m", "value": tol, **row})
    return rows


def _write_csv(rows: list[dict], path: Path) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: json.dumps(v) if isinstance(v, list) else v for k, v in r.items()})


def _plot(
    scaling_rows: list[dict], trade_rows: list[dict], out_dir: Path, default_sweeps: int
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    n = [r["nodes"] for r in scaling_rows]
    ax.loglog(n, [r["ms"] for r in scaling_rows], "o-", label="deformation")
    ax.loglog(n, [r["commands_ms"] for r in scaling_rows], "s--", label="commands + check")
    ax.axhline(200, color="grey", lw=0.8, ls=":", label="200 ms target")
    for r in scaling_rows:
        ax.annotate(f"{r['working_nodes']} working", (r["nodes"], r["ms"]), fontsize=7)
    ax.set_xlabel("history nodes (Fig. 12 task at different operator speeds)")
    ax.set_ylabel("ms")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    spacing = [r for r in trade_rows if r["knob"] == "spacing_m"]
    ax2.loglog([r["working_nodes"] for r in spacing], [r["ms"] for r in spacing], "o-")
    for r in spacing:
        label = f"{r['value'] * 1e3:g} mm, {r['sweeps']} sweeps"
        ax2.annotate(label, (r["working_nodes"], r["ms"]), fontsize=7)
    ax2.set_xlabel("working nodes (node spacing varied; Fig. 12, 315 history nodes)")
    ax2.set_ylabel("deformation ms")
    ax2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "deform_scaling.png", dpi=110)
    plt.close(fig)

    metrics = [("length_m", "path length (m)"), ("clearance_m", "clearance (m)")]
    metrics += [("commands", "motion commands"), ("ms", "deformation ms")]
    defaults = {
        # The default settles by itself after ``default_sweeps``; its cap is only a guard.
        "max_sweeps": default_sweeps,
        "position_tol_m": CommandParams().position_tol_m,
        "spacing_m": DeformParams().spacing_m,
    } | {knob: getattr(DeformParams(), knob) for knob in FORCE_SWEEPS}
    # One row per knob, one column per figure of merit.
    fig, axes = plt.subplots(
        len(defaults), len(metrics), figsize=(3.6 * len(metrics), 2.6 * len(defaults))
    )
    for row, (knob, default) in enumerate(defaults.items()):
        sub = [r for r in trade_rows if r["knob"] == knob]
        for col, (key, label) in enumerate(metrics):
            ax = axes[row, col]
            ax.semilogx([r["value"] for r in sub], [r[key] for r in sub], "o-")
            ax.axvline(default, color="grey", lw=0.8, ls=":")
            ax.set_xlabel(f"{knob} ({sub[0]['case']}; dotted: the default)")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("Each knob varied alone, on the case its x label names (dotted: its default)")
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(out_dir / "deform_trade.png", dpi=80)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench deform``."""
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for deform.json, deform.csv, deform_trade.csv and the PNG plots "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="one timed run per case, no trade sweep"
    )


def run(out_dir: Path, quick: bool = False) -> list[dict]:
    """Run every case; write deform.json, CSV and PNG files into ``out_dir``; return the rows."""
    out_dir.mkdir(parents=True, exist_ok=True)
    repeats = 1 if quick else REPEATS
    results = []
    for case in ("fig12", "fig13_bottom", "straight"):
        sim, raw = _raw(case)
        results.append(run_case(case, raw, sim, repeats=repeats))
    scaling_rows = scaling(repeats)
    results += scaling_rows
    _write_csv(results, out_dir / "deform.csv")
    if not quick:
        trade_rows = trade()
        _write_csv(trade_rows, out_dir / "deform_trade.csv")
        _plot(scaling_rows, trade_rows, out_dir, results[0]["sweeps"])
    (out_dir / "deform.json").write_text(json.dumps(results, indent=1))
    return results


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    print(json.dumps(run(args.out, args.quick)))
    return 0
