"""``python -m bench step_gain``: steps a free pull takes to settle against the spring's step
gain x = Δt·d_t·k_t, for each of the six blocks, with the simulator's exact step and with the
explicit step of equation (1) as written.

A block 0.24 m above anything is pulled 50 mm and turned 0.5 rad to its dragger, with no speed
limit in reach (10 m/s). It has settled when every later step is within ``SETTLED_M`` of the
target (its centre, and its rotation times its largest radius); a pull that has not settled
after ``MAX_STEPS`` steps, or that swings, is reported as such. Writes ``step_gain.csv`` and
``step_gain.png``; prints the JSON summary last.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
from pathlib import Path

import numpy as np

from models.scene import Scene, load_scene
from models.transforms import make_pose, rpy_to_R, so3_log
from operator_site.simulator.params import SimParams
from operator_site.simulator.stepper import Simulator

BLOCKS = ("cube", "tall_block", "plank", "wedge", "l_block", "hex_prism")
SETTLED_M = 1e-6
MAX_STEPS = 200_000
"""Above the ≈ 1.1e5 steps x = 1e-4 needs; an explicit step that swings stops long before."""
SETTLED_STEPS = 50
"""Steps a pull stays settled before the run stops (the error never grows again: it shrinks
by e^(−x), or by |1 − x| < 1 for an explicit step that settles)."""
SWING_STEPS = 500
"""An explicit step still not settled after this many steps at x ≥ 2 swings for ever (its
error shrinks by |1 − x| a step, which is ≥ 1 there): stopped early."""


@functools.cache
def _scene(block: str) -> Scene:
    scene = load_scene()
    keep = {"table", "frame", block}
    return dataclasses.replace(scene, objects=tuple(o for o in scene.objects if o.name in keep))


def pull(block: str, x: float, explicit: bool) -> dict:
    """One pull at step gain ``x``; ``explicit``: the spring unscaled, as equation (1) steps."""
    base = SimParams(max_speed_mps=10.0)
    params = dataclasses.replace(base, d_t=x / (base.dt_s * base.k_t))
    X0 = make_pose(np.eye(3), (0.45, 0.3, 0.5))
    sim = Simulator(_scene(block), block, params, X_WO={block: X0})
    if explicit:
        sim._spring_factor = 1.0  # the paper's step, for comparison only
    X_D = make_pose(rpy_to_R(np.array([0.0, 0.0, 0.5])), (0.49, 0.33, 0.5))
    sim.set_target(X_D)
    c_D = X_D[:3, :3] @ sim.c_O + X_D[:3, 3]
    u = c_D - (X0[:3, :3] @ sim.c_O + X0[:3, 3])
    u /= np.linalg.norm(u)
    settled_at, overshoot_m, worst_m = 0, 0.0, 0.0
    limit = SWING_STEPS if explicit and x >= 2.0 else MAX_STEPS
    for k in range(1, limit + 1):
        X = sim.step().X_WO
        c = X[:3, :3] @ sim.c_O + X[:3, 3]
        err = float(np.linalg.norm(c_D - c))
        err += float(np.linalg.norm(so3_log(X_D[:3, :3] @ X[:3, :3].T))) * sim.r_max_m
        overshoot_m = max(overshoot_m, -float((c_D - c) @ u))
        if err >= SETTLED_M:
            settled_at = 0
        elif not settled_at:
            settled_at = k
        worst_m = err
        if settled_at and (sim.state.resting or k - settled_at >= SETTLED_STEPS):
            break
    return {
        "block": block,
        "step": "explicit" if explicit else "exact",
        "step_gain": x,
        "steps_to_settle": settled_at or None,
        "steps_run": k,
        "overshoot_m": overshoot_m,
        "error_at_end_m": worst_m,
    }


def run(out: Path, points_per_decade: int) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    gains = np.logspace(-4, 4, 8 * points_per_decade + 1)
    rows = []
    for explicit in (False, True):
        for block in BLOCKS:
            for x in gains:
                rows.append(pull(block, float(x), explicit))
                r = rows[-1]
                print(
                    f"{r['step']:8s} {block:10s} x={x:9.3g}: {r['steps_to_settle']} steps, "
                    f"overshoot {r['overshoot_m']:.3g} m",
                    flush=True,
                )
    with (out / "step_gain.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, out / "step_gain.png")
    exact = [r for r in rows if r["step"] == "exact"]
    explicit_rows = [r for r in rows if r["step"] == "explicit"]
    return {
        "blocks": len(BLOCKS),
        "step_gains": [float(gains[0]), float(gains[-1]), len(gains)],
        "exact_all_settled": all(r["steps_to_settle"] for r in exact),
        "exact_overshoot_max_m": max(r["overshoot_m"] for r in exact),
        "exact_steps_at_default_gain": pull("cube", SimParams().step_gain, False)[
            "steps_to_settle"
        ],
        "explicit_unsettled_from_gain": min(
            (r["step_gain"] for r in explicit_rows if not r["steps_to_settle"]), default=None
        ),
        "explicit_overshoot_max_m": max(r["overshoot_m"] for r in explicit_rows),
    }


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for step, style in (("exact", "-"), ("explicit", "--")):
        for block in BLOCKS:
            sel = [r for r in rows if r["step"] == step and r["block"] == block]
            xs = [r["step_gain"] for r in sel if r["steps_to_settle"]]
            ys = [r["steps_to_settle"] for r in sel if r["steps_to_settle"]]
            label = f"{step} step" if block == BLOCKS[0] else None
            ax.loglog(
                xs,
                ys,
                style,
                color="C0" if step == "exact" else "C3",
                alpha=0.6,
                label=label,
                marker="." if step == "exact" else "x",
            )
    swing = sorted(
        {r["step_gain"] for r in rows if r["step"] == "explicit" and not r["steps_to_settle"]}
    )
    if swing:
        ax.axvspan(
            swing[0],
            max(r["step_gain"] for r in rows),
            color="C3",
            alpha=0.08,
            label=f"explicit step never settles (x ≥ {swing[0]:.2g})",
        )
    ax.axvline(SimParams().step_gain, color="k", lw=0.8, ls=":", label="default x = 0.25")
    ax.set_xlabel("step gain x = Δt·d_t·k_t")
    ax.set_ylabel(f"steps until within {SETTLED_M * 1e6:g} µm for good")
    ax.set_title("Free pull of each block (50 mm, 0.5 rad): steps to settle")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench step_gain``."""
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for step_gain.csv and .png (default: %(default)s)",
    )
    parser.add_argument(
        "--points-per-decade",
        type=int,
        default=2,
        help="step gains per decade from 1e-4 to 1e4 (default: %(default)s)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    if not 1 <= args.points_per_decade <= 20:
        raise SystemExit("--points-per-decade must be in [1, 20]")
    print(json.dumps(run(args.out, args.points_per_decade)))
    return 0
