"""``python -m bench sim``: the task simulator's speed and accuracy on the benchmark scenes.

Prints a JSON list (one object per scene) and writes ``sim.csv``, ``sim_sweeps.csv`` and PNG
plots into the output directory. Wall times are per step, on this machine, one core.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from models.scene import Scene, SceneObject, load_scene
from models.transforms import make_pose, rpy_to_R, so3_log
from operator_site.simulator.params import REST_GAP_FRACTION, SimParams
from operator_site.simulator.stepper import Simulator

CUBE_HALF_M = 0.025
CORNER_W = np.array([0.35, -0.10])  # the frame's inside corner at its smallest x and y
OUTER_CORNER_W = np.array([0.57, 0.12])  # the frame's outside corner at its largest x and y
FAR_BLOCKS = 1000


def _pose(x: float, y: float, z: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_pose(rpy_to_R(np.array([0.0, 0.0, np.deg2rad(yaw_deg)])), (x, y, z))


def _far_blocks(scene: Scene, n: int) -> Scene:
    """``scene`` plus n fixed 5 cm cubes in a grid far (≥ 2 m) from the work area."""
    cube = scene.object("cube").model
    side = math.ceil(math.sqrt(n))
    extra = [
        SceneObject(
            f"far_{i}", cube, _pose(3.0 + 0.1 * (i % side), 0.1 * (i // side), CUBE_HALF_M), True
        )
        for i in range(n)
    ]
    return dataclasses.replace(scene, objects=(*scene.objects, *extra))


def _run(sim: Simulator, targets: Callable[[int], np.ndarray | None], steps: int) -> dict:
    times, queries, moving = [], [], []
    min_sep = math.inf
    for k in range(steps):
        target = targets(k)
        if target is not None:
            sim.set_target(target)
        t0 = time.perf_counter()
        r = sim.step()
        times.append(time.perf_counter() - t0)
        queries.append(r.queries)
        moving.append(r.s_fraction > 0)
        min_sep = min(min_sep, r.min_distance_m)
    t = np.array(times) * 1e3
    t_moving = t[np.array(moving)] if any(moving) else t
    return {
        "steps": steps,
        "step_ms_median": float(np.median(t)),
        "step_ms_p99": float(np.percentile(t, 99)),
        "moving_step_ms_median": float(np.median(t_moving)),
        "moving_step_ms_p99": float(np.percentile(t_moving, 99)),
        "queries_per_step": float(np.mean(queries)),
        "min_separation_m": min_sep,
    }


SETTLED_MM_DEG = 1e-3
"""The corner scene has settled when every later pose is within 1 µm and 0.001° of its last."""


CORNER_TARGET_OFFSET_M = np.array([-0.005, -0.005, -0.005])
"""The corner scene's dragger, from the cube touching both walls of the inside corner and the
table: 5 mm into each."""
REST_POSE_ITERATIONS = 50
"""Fixed-point iterations for the analytic resting pose (each gains many digits: the gaps are
ε_b-sized against centimetre-sized stretches)."""


def corner_rest_pose(params: SimParams) -> np.ndarray:
    """The analytic resting pose of the cube pressed into the inside corner: square with the
    frame, each wall and the table as far away as the barrier holds the force the spring
    presses against it with (``rest_gap_fraction`` for the largest; further out for less)."""
    contact_c = np.array([*(CORNER_W + CUBE_HALF_M), CUBE_HALF_M])
    target_c = contact_c + CORNER_TARGET_OFFSET_M
    kappa = 1.0 / (1.0 / REST_GAP_FRACTION - 1.0)
    gaps = np.full(3, params.eps_barrier_m)
    for _ in range(REST_POSE_ITERATIONS):
        # Per axis: the barrier's force K/ε_b·(1/δ − 1) with K = gain·κ·pull·ε_b against the
        # spring's press there (its scale φ cancels: it scales both).
        press = np.abs(target_c - (contact_c + gaps * np.sign(-CORNER_TARGET_OFFSET_M)))
        ratio = press / (params.barrier_gain * kappa * np.linalg.norm(press))
        gaps = params.eps_barrier_m / (1.0 + ratio)
    return _pose(*(contact_c + gaps * np.sign(-CORNER_TARGET_OFFSET_M)))


def pose_error(X: np.ndarray, X_ref: np.ndarray) -> tuple[float, float]:
    """Position error (mm) and rotation error (deg) of ``X`` against ``X_ref``."""
    return (
        float(np.linalg.norm(X[:3, 3] - X_ref[:3, 3]) * 1e3),
        float(np.rad2deg(np.linalg.norm(so3_log(X_ref[:3, :3].T @ X[:3, :3])))),
    )


def corner_scene(scene: Scene, params: SimParams, steps: int = 200) -> dict:
    sim = Simulator(scene, "cube", params, X_WO={"cube": _pose(0.45, 0.0, CUBE_HALF_M + 2e-4, 5)})
    target = _pose(*(np.array([*(CORNER_W + CUBE_HALF_M), CUBE_HALF_M]) + CORNER_TARGET_OFFSET_M))
    out = _run(sim, lambda k: target if k == 0 else None, steps)
    err_mm, err_deg = pose_error(sim.X_WO, corner_rest_pose(params))
    moving = [r.time_s for r in sim.history if r.s_fraction > 0]
    out["last_move_s"] = max(moving, default=0.0)
    # The contact step approaches the barrier's zero geometrically: the last moves are of
    # nanometres and less, so "settled" is measured as in the step-gain benchmark.
    far = [r.time_s for r in sim.history if max(pose_error(r.X_WO, sim.X_WO)) > SETTLED_MM_DEG]
    out["settle_s"] = max(far) + params.dt_s if far else 0.0
    contact = _pose(*(CORNER_W + CUBE_HALF_M), CUBE_HALF_M)
    return out | {
        "final_error_mm": err_mm,
        "final_error_deg": err_deg,
        "final_gap_to_contact_mm": pose_error(sim.X_WO, contact)[0],
        "final_contacts": sorted(c.object for c in sim.state.contacts),
    }


def scenes(params: SimParams) -> list[dict]:
    """The benchmark scenes (free, slide, corner, around the corner), the far-objects
    comparison and the MuJoCo peer."""
    scene = load_scene()
    results = []
    sim = Simulator(scene, "cube", params, X_WO={"cube": _pose(0.3, 0.3, 0.2)})
    results.append(
        {"scene": "free"}
        | _run(sim, lambda k: _pose(0.3 + 0.1 * (k // 50 % 2), 0.3, 0.2, 30 * (k // 50 % 2)), 200)
    )
    sim = Simulator(scene, "cube", params, X_WO={"cube": _pose(0.2, 0.3, CUBE_HALF_M + 2e-4)})
    results.append(
        {"scene": "slide"}
        | _run(sim, lambda k: _pose(0.2 - 0.1 * (k // 50 % 2), 0.3, CUBE_HALF_M - 0.005), 200)
    )
    results.append({"scene": "corner"} | corner_scene(scene, params))
    far = corner_scene(_far_blocks(scene, FAR_BLOCKS), params)
    results.append(
        {"scene": f"corner+{FAR_BLOCKS}_far"}
        | far
        | {
            "far_objects_cost_ratio": far["moving_step_ms_median"]
            / results[-1]["moving_step_ms_median"]
        }
    )
    results.append({"scene": "around_corner"} | around_corner(scene, params))
    try:
        results.append(mujoco_corner(params))
    except ImportError:
        results.append(
            {
                "scene": "corner_mujoco_mocap_weld",
                "skipped": "mujoco is not installed (pip install mujoco)",
            }
        )
    return results


def around_corner(scene: Scene, params: SimParams) -> dict:
    """Drag the cube along the frame's outside, around its outer corner, frame and table
    captured (Fig. 2): the target runs along a square path a little inside the frame."""
    cx, cy = OUTER_CORNER_W
    start = _pose(cx - 0.08, cy + CUBE_HALF_M + 2e-4, CUBE_HALF_M + 2e-4)
    sim = Simulator(scene, "cube", params, X_WO={"cube": start})
    sim.capture("frame")
    sim.capture("table")
    # Along the top face 1 cm inside it, past the corner, then down the side face 1 cm inside.
    waypoints = [(cx - 0.08, cy + 0.015), (cx + 0.035, cy + 0.015), (cx + 0.015, cy - 0.08)]
    steps_per_leg = 100

    def target(k: int) -> np.ndarray:
        leg = min(k // steps_per_leg, len(waypoints) - 2)
        f = min(1.0, (k - leg * steps_per_leg) / (0.8 * steps_per_leg))
        (x0, y0), (x1, y1) = waypoints[leg], waypoints[leg + 1]
        return _pose(x0 + f * (x1 - x0), y0 + f * (y1 - y0), CUBE_HALF_M - 0.003)

    out = _run(sim, target, 2 * steps_per_leg)
    X = sim.X_WO
    frame_d = [
        min((c.distance_m for c in r.contacts if c.object == "frame"), default=math.inf)
        for r in sim.history
    ]
    return out | {
        "final_xy_m": X[:2, 3].tolist(),
        "max_frame_distance_m": max(frame_d),
        "went_around": bool(X[1, 3] < cy - 0.03 and X[0, 3] > cx),
    }


def distance_accuracy(n_poses: int = 300, seed: int = 0) -> dict:
    """python-fcl's GJK against the simulator's exact distances, on ``n_poses`` pairs of the
    scene's parts (a block's part against any other object's) at random rotations, near face-
    aligned or anywhere, moved to gaps drawn log-uniformly over 1e-7–1e-3 m; both against the
    Qhull reference (:func:`~operator_site.simulator.polytope.reference_distance_m`), and the
    time per query of each (one pair; the simulator queries all near obstacles at once)."""
    import fcl

    from models.geometry import ConvexPart
    from models.transforms import so3_exp
    from operator_site.simulator.polytope import (
        Polytope,
        PolytopeGroup,
        polytope_distance,
        posed_distances,
        reference_distance_m,
    )
    from operator_site.simulator.world import fcl_convex

    rng = np.random.default_rng(seed)
    scene = load_scene()
    parts = [(o.name, p) for o in scene.objects for p in o.model.parts]
    pairs = [
        (a, b) for na, a in parts for nb, b in parts if na != nb and na not in {"frame", "table"}
    ]
    request = fcl.DistanceRequest(enable_nearest_points=True)
    rows = []
    fcl_s = exact_s = 0.0
    while len(rows) < n_poses:
        a, b = pairs[rng.integers(len(pairs))]
        posed = []
        for part in (a, b):
            spread = rng.choice([0.0, 1e-6, 1e-3, 0.3, 3.0])
            R = so3_exp(rng.normal(size=3) * spread)
            posed.append(
                Polytope.of(part).moved(R, rng.normal(size=3) * 0.02 - R @ part.vertices_O.mean(0))
            )
        A, B = posed
        d0, p_A, p_B = polytope_distance(A, B)
        if d0 <= 0.0:
            continue
        gap_m = 10 ** rng.uniform(-7, -3)
        B = B.moved(np.eye(3), -(d0 - gap_m) * (p_B - p_A) / d0)
        oa = fcl.CollisionObject(fcl_convex(ConvexPart(A.vertices, a.faces, A.normals, A.offsets)))
        ob = fcl.CollisionObject(fcl_convex(ConvexPart(B.vertices, b.faces, B.normals, B.offsets)))
        fcl.distance(oa, ob, request, fcl.DistanceResult())  # fcl sets a pair up on its first query
        t0 = time.perf_counter()
        d_fcl = fcl.distance(oa, ob, request, fcl.DistanceResult())
        group = PolytopeGroup.of((B,))  # as the simulator keeps its near obstacles
        t1 = time.perf_counter()
        d_exact = posed_distances(A, np.eye(3), np.zeros(3), group)[0][0]
        t2 = time.perf_counter()
        fcl_s, exact_s = fcl_s + t1 - t0, exact_s + t2 - t1
        rows.append((reference_distance_m(A.vertices, B.vertices), d_fcl, d_exact))
    ref, d_fcl, d_exact = np.array(rows).T
    rel = (d_fcl - ref) / ref
    return {
        "scene": "distance_accuracy",
        "poses": n_poses,
        "python_fcl_over_1pct": int(np.sum(rel > 0.01)),
        "python_fcl_under_1pct": int(np.sum(rel < -0.01)),
        "python_fcl_max_over_ratio": float(np.max(d_fcl / ref)),
        "exact_max_abs_error_m": float(np.max(np.abs(d_exact - ref))),
        "python_fcl_us_per_query": fcl_s / n_poses * 1e6,
        "exact_us_per_query": exact_s / n_poses * 1e6,
    }


def rotation_drift(steps: int = 1_000_000) -> dict:
    """The pose update's rotation, applied ``steps`` times: how far RᵀR drifts from I."""
    from models.transforms import orthonormalize, so3_exp

    rng = np.random.default_rng(0)
    turns = [so3_exp(w) for w in rng.normal(scale=0.02, size=(97, 3))]
    R = np.eye(3)
    t0 = time.perf_counter()
    for k in range(steps):
        R = orthonormalize(turns[k % len(turns)] @ R)
    return {
        "scene": "rotation_drift",
        "steps": steps,
        "max_abs_RtR_minus_I": float(np.max(np.abs(R.T @ R - np.eye(3)))),
        "us_per_update": (time.perf_counter() - t0) / steps * 1e6,
    }


MUJOCO_CORNER_XML = """
<mujoco>
  <option timestep="{timestep}"/>
  <worldbody>
    <geom type="box" size="0.7 0.7 0.02" pos="0.35 0 -0.02"/>
    <geom type="box" size="0.12 0.01 0.015" pos="0.45 -0.11 0.015"/>
    <geom type="box" size="0.12 0.01 0.015" pos="0.45 0.11 0.015"/>
    <geom type="box" size="0.01 0.10 0.015" pos="0.34 0 0.015"/>
    <geom type="box" size="0.01 0.10 0.015" pos="0.56 0 0.015"/>
    <body name="cube" pos="0.45 0 0.0252" euler="0 0 5" >
      <freejoint/>
      <geom type="box" size="0.025 0.025 0.025" mass="0.075"/>
    </body>
    <body name="target" mocap="true" pos="{tx} {ty} {tz}"/>
  </worldbody>
  <equality>
    <weld body1="target" body2="cube" relpose="0 0 0 1 0 0 0" solref="0.05 1"/>
  </equality>
</mujoco>"""


def mujoco_corner(params: SimParams, seconds: float = 10.0, timestep_s: float = 0.002) -> dict:
    """The corner scene as people drive it in MuJoCo today: a mocap body pulling the block
    through a soft weld. Costs are per Δt of simulated time, to compare with our steps."""
    import mujoco

    tx, ty = CORNER_W + 0.02
    model = mujoco.MjModel.from_xml_string(
        MUJOCO_CORNER_XML.format(timestep=timestep_s, tx=tx, ty=ty, tz=CUBE_HALF_M - 0.005)
    )
    data = mujoco.MjData(model)
    per_dt = round(params.dt_s / timestep_s)
    times, pen = [], 0.0
    for _ in range(round(seconds / params.dt_s)):
        t0 = time.perf_counter()
        for _ in range(per_dt):
            mujoco.mj_step(model, data)
        times.append(time.perf_counter() - t0)
        pen = max(pen, max((-c.dist for c in data.contact[: data.ncon]), default=0.0))
    X = make_pose(data.xmat[1].reshape(3, 3), data.xpos[1])
    contact = _pose(*(CORNER_W + CUBE_HALF_M), CUBE_HALF_M)
    err_mm, err_deg = pose_error(X, contact)
    t = np.array(times) * 1e3
    return {
        "scene": "corner_mujoco_mocap_weld",
        "mujoco_version": mujoco.__version__,
        "timestep_s": timestep_s,
        "step_ms_median": float(np.median(t)),
        "step_ms_p99": float(np.percentile(t, 99)),
        "final_error_contact_mm": err_mm,
        "final_error_deg": err_deg,
        "max_penetration_m": float(pen),
    }


SWEEPS: dict[str, list] = {
    "dt_s": [0.005, 0.01, 0.02, 0.05, 0.1],
    "golden_rel_tol": [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8],
    "eps_barrier_m": [1e-5, 3e-5, 1e-4, 2e-4, 4e-4],
    "tunnel_fraction": [0.125, 0.25, 0.5, 1.0],
    "char_length_m": [0.005, 0.0125, 0.025, 0.05, 0.1],
    "max_speed_mps": [0.05, 0.1, 0.2, 0.4, 1.0, 2.0],
    "barrier_gain": [0.4, 1.0, 10.0, 100.0, 1e4],
    "eps_contact_m": [0.2e-3, 0.3e-3, 0.5e-3, 1e-3, 1.9e-3],
    "eps_capture_m": [0.6e-3, 1e-3, 2e-3, 5e-3, 1e-2],
    "max_points_per_pair": [3, 4, 8, 16, 32],
}
"""Each knob's values in the sweeps: around the default, inside the accepted range and keeping
ε_b < ε_c < ε_o with the other two at their defaults."""


def sweeps(base: SimParams) -> list[dict]:
    """The corner scene with one knob varied at a time (the speed/accuracy trade)."""
    scene = load_scene()
    rows = []
    for knob, values in SWEEPS.items():
        for value in values:
            params = dataclasses.replace(base, **{knob: value})
            steps = round(10.0 / params.dt_s)  # ten seconds of simulated time
            r = corner_scene(scene, params, steps)
            a = around_corner(scene, params)
            rows.append(
                {"knob": knob, "value": value, "default": value == getattr(SimParams(), knob)}
                | {
                    k: r[k]
                    for k in (
                        "moving_step_ms_median",
                        "step_ms_p99",
                        "queries_per_step",
                        "settle_s",
                        "last_move_s",
                        "final_error_mm",
                        "final_error_deg",
                        "min_separation_m",
                        "final_gap_to_contact_mm",
                    )
                }
                | {
                    f"around_{k}": a[k]
                    for k in (
                        "moving_step_ms_median",
                        "queries_per_step",
                        "min_separation_m",
                        "max_frame_distance_m",
                        "went_around",
                    )
                }
            )
    return rows


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # x: the distance queries per step of the scene that row measures (the cost, without the
    # wall time's noise; sim_sweeps.csv has the times and the final errors too).
    metrics = [
        ("", "settle_s", "corner: simulated s to within 1 µm"),
        ("", "min_separation_m", "corner: min separation (m)"),
        ("around_", "min_separation_m", "around corner: min separation (m)"),
        ("around_", "max_frame_distance_m", "around corner: max distance to frame (m)"),
    ]
    # One row per knob, one column per figure of merit.
    fig, axes = plt.subplots(
        len(SWEEPS), len(metrics), figsize=(4.2 * len(metrics), 3.0 * len(SWEEPS))
    )
    for row, knob in enumerate(SWEEPS):
        sub = [r for r in rows if r["knob"] == knob]
        for col, (scene, key, label) in enumerate(metrics):
            ax = axes[row, col]
            x = [r[f"{scene}queries_per_step"] for r in sub]
            y = [r[f"{scene}{key}"] for r in sub]
            ax.semilogy(x, y, "o")
            for r, xi, yi in zip(sub, x, y, strict=True):
                ax.annotate(
                    f"{r['value']:g}" + (" (default)" if r["default"] else ""),
                    (xi, yi),
                    fontsize=7,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
            ax.set_title(knob, fontsize=9)
            ax.set_xlabel("distance queries per step")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _write_csv(rows: list[dict], path: Path) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: json.dumps(v) if isinstance(v, list) else v for k, v in r.items()})


REPEATS = 3
"""Each scene runs this many times; the run with the median timing is reported (this VM's
timings wander by ±50 % between runs)."""


def run(out_dir: Path, quick: bool = False, sweeps_only: bool = False) -> list[dict]:
    """Run the scenes (and, unless ``quick``, the sweeps); write sim.json, CSV and PNG; return
    the JSON (with ``sweeps_only``, only the sweeps' rows and files)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    params = SimParams()
    if sweeps_only:
        rows = sweeps(params)
        _write_csv(rows, out_dir / "sim_sweeps.csv")
        _plot(rows, out_dir / "sim_sweeps.png")
        return rows
    runs = [scenes(params) for _ in range(1 if quick else REPEATS)]
    results = []
    for same in zip(*runs, strict=True):
        key = "moving_step_ms_median" if "moving_step_ms_median" in same[0] else "step_ms_median"
        ordered = sorted(same, key=lambda r: r.get(key, 0.0))
        results.append(ordered[len(ordered) // 2])
    results.append(rotation_drift(100_000 if quick else 1_000_000))
    results.append(distance_accuracy(100 if quick else 1000))
    _write_csv(results, out_dir / "sim.csv")
    (out_dir / "sim.json").write_text(json.dumps(results, indent=1))
    if not quick:
        rows = sweeps(params)
        _write_csv(rows, out_dir / "sim_sweeps.csv")
        _plot(rows, out_dir / "sim_sweeps.png")
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench sim``."""
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for sim.json, sim.csv, sim_sweeps.csv and sim_sweeps.png "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="each scene once, a shorter drift run, no sweeps"
    )
    parser.add_argument(
        "--sweeps-only",
        action="store_true",
        help="only the knob sweeps (sim_sweeps.csv and .png), not the scenes",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    print(json.dumps(run(args.out, quick=args.quick, sweeps_only=args.sweeps_only)))
    return 0
