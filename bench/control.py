"""``python -m bench control``: how well the arm executes moves and contact programs.

- tracking: a 10 cm TCP line at several speeds, commanded against measured;
- guarded: closed fingertips lowered onto the table until 10 N, at several speeds: the force's
  overshoot past the threshold (the speed/accuracy trade of execution);
- corner: a scripted program puts the ``cube`` into the frame's inside corner with contact
  moves; the block's final pose against the goal and the three contacts verified by force;
- slide: the cube pressed on a wall of the frame and slid 6 cm along it under impedance: the
  force along the wall's normal during the slide.

Prints a JSON object; writes ``control.csv``, ``control_guarded.csv`` and ``control.png``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np

from models.robot import load_robot
from models.scene import Scene, load_scene
from models.transforms import invert_pose, make_pose, rpy_to_R, so3_log
from protocol import ContactState, MotionCommand, MotionProgram
from work_site.control.controller import (
    DEFAULT_SURFACE_STIFFNESS_N_PER_M,
    TCP_ACCEL_MPS2,
    Guard,
    Impedance,
    TaskController,
)
from work_site.control.executor import (
    CONTACT_VERIFY_N,
    Execution,
    default_impedance,
    program_refusal,
)
from work_site.world import World

DOWN = rpy_to_R(np.array([math.pi, 0.0, math.pi]))
SPEEDS_MPS = (0.025, 0.05, 0.1, 0.2)
GUARD_SPEEDS_MPS = (0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.25)
GUARD_THRESHOLD_N = 10.0
TOUCH_PHASES = 5
"""Each guarded speed is run this many times, the touch falling at evenly spread points of the
10 ms control period (the overshoot depends on where it falls)."""
CUBE_HALF_M = 0.025
FINGERTIPS_BELOW_TCP_M = 0.015
CORNER_GRIP_DEPTH_M = 0.018
"""The fingertips reach this far down the cube: 2 mm above the frame's 30 mm bars."""
CONTACT_FORCE_LIMIT_N = 20.0
PLACE_GUARD_N = 4.0
"""Setting the block down stops at this force (N)."""


def frame_inner_W(scene: Scene) -> tuple[tuple[float, float], tuple[float, float]]:
    """The frame's inner walls in W (x from, to; y from, to; m): where rays from the middle of
    the frame's bounding box, along −x, +x, −y and +y, first enter one of its convex parts."""
    frame = scene.object("frame")
    R_WO, p_WO = frame.X_WO[:3, :3], frame.X_WO[:3, 3]
    V_W = np.vstack([pt.vertices_O for pt in frame.model.parts]) @ R_WO.T + p_WO
    c_W = 0.5 * (V_W.min(axis=0) + V_W.max(axis=0))
    c_O = R_WO.T @ (c_W - p_WO)

    def entry_m(u_W: np.ndarray) -> float:
        u_O = R_WO.T @ u_W
        nearest = math.inf
        for part in frame.model.parts:  # the ray against each face plane: n·(c + t u) ≤ d
            along, room = part.normals_O @ u_O, part.offsets_m - part.normals_O @ c_O
            if np.any((np.abs(along) < 1e-12) & (room < 0)):
                continue  # parallel to a face and outside it
            t_in = max((room[along < -1e-12] / along[along < -1e-12]).max(initial=0.0), 0.0)
            t_out = (room[along > 1e-12] / along[along > 1e-12]).min(initial=math.inf)
            if t_in <= t_out:
                nearest = min(nearest, t_in)
        if not math.isfinite(nearest):
            raise ValueError(f"no wall of the frame along {u_W.tolist()} from its middle")
        return nearest

    x_axis, y_axis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    return (
        (float(c_W[0] - entry_m(-x_axis)), float(c_W[0] + entry_m(x_axis))),
        (float(c_W[1] - entry_m(-y_axis)), float(c_W[1] + entry_m(y_axis))),
    )


def _site(time_step_s: float = 1e-3) -> tuple[World, TaskController]:
    scene = load_scene()
    world = World(scene, time_step_s=time_step_s)
    return world, TaskController(world, load_robot(scene.robot.urdf_path))


def tracking(speed_mps: float) -> dict:
    """A 10 cm line along x at ``speed_mps``: worst commanded-to-measured TCP distance (mm) and
    worst distance of the measured TCP from the line itself (mm)."""
    world, controller = _site()
    try:
        start, goal = make_pose(DOWN, (0.35, -0.1, 0.15)), make_pose(DOWN, (0.45, -0.1, 0.15))
        for target, speed in ((start, 0.2), (goal, speed_mps)):
            controller.start_move(target, speed)
            worst = off_line = 0.0
            while controller.tick().status == "moving":
                p = controller.measured_tcp_W()[:3, 3]
                X_cmd = controller.move.pose_at(controller.t_s) if controller.move else goal
                worst = max(worst, float(np.linalg.norm(p - X_cmd[:3, 3])))
                a, b = start[:3, 3], goal[:3, 3]
                t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
                off_line = max(off_line, float(np.linalg.norm(p - (a + t * (b - a)))))
            for _ in range(30):
                controller.tick()
        final = float(np.linalg.norm(controller.measured_tcp_W()[:3, 3] - goal[:3, 3]))
    finally:
        world.close()
    return {
        "speed_mps": speed_mps,
        "tracking_mm_max": worst * 1e3,
        "off_line_mm_max": off_line * 1e3,
        "final_error_mm": final * 1e3,
    }


def guarded_touch(speed_mps: float, threshold_n: float = GUARD_THRESHOLD_N) -> dict:
    """:func:`touch` at :data:`TOUCH_PHASES` points of the control period: the worst and the
    mean overshoot (N), and the status and held force of the worst."""
    runs = [
        touch(speed_mps, threshold_n, speed_mps * 0.01 * k / TOUCH_PHASES)
        for k in range(TOUCH_PHASES)
    ]
    worst = max(runs, key=lambda r: r["overshoot_n"])
    return {
        **worst,
        "overshoot_n_mean": float(np.mean([r["overshoot_n"] for r in runs])),
        "statuses": sorted({r["status"] for r in runs}),
    }


def touch(speed_mps: float, threshold_n: float, shift_m: float = 0.0) -> dict:
    """Closed fingertips lowered onto the bare table at ``speed_mps`` with a guard at
    ``threshold_n``, starting ``shift_m`` higher (which moves the touch within the control
    period): the largest force along the guard afterwards, less the threshold (N)."""
    world, c = _site()
    try:
        world.finger_target_m = 0.0
        x, y = 0.30, 0.20
        # Far enough to reach full speed before the touch, and to keep it through the touch.
        run_m = speed_mps**2 / (2 * TCP_ACCEL_MPS2) + 0.01
        c.start_move(make_pose(DOWN, (x, y, FINGERTIPS_BELOW_TCP_M + run_m + shift_m)), 0.1)
        while c.tick().status == "moving":
            pass
        for _ in range(30):
            c.tick()
        up = np.array([0.0, 0.0, 1.0])
        # Aim into the table: the guard, not the target, must end the move.
        c.start_move(
            make_pose(DOWN, (x, y, FINGERTIPS_BELOW_TCP_M - run_m)),
            speed_mps,
            guard=Guard(up, threshold_n),
        )
        result = c.tick()
        while result.status == "moving":
            result = c.tick()
        peak = c.force_peak_n
        for _ in range(30):  # the force the stop leaves, and any ringing
            c.tick()
            peak = max(peak, float(c.force_W @ up))
        held = float(c.force_W @ up)
    finally:
        world.close()
    return {
        "speed_mps": speed_mps,
        "status": result.status,
        "threshold_n": threshold_n,
        "peak_n": peak,
        "overshoot_n": peak - threshold_n,
        "held_n": held,
    }


def _cmd(
    kind: str, X_WP: np.ndarray, speed: float, contacts=(), force_n=CONTACT_FORCE_LIMIT_N
) -> MotionCommand:
    return MotionCommand(
        kind=kind, X_WP=X_WP, speed_mps=speed, force_limit_n=force_n, contacts=tuple(contacts)
    )


def _run(execution: Execution, controller: TaskController, max_s: float = 60.0) -> list:
    for _ in range(round(max_s / 0.01)):
        execution.tick()
        if execution.finished:
            return []
    raise RuntimeError("program did not finish in time")


def corner_grasp_GP() -> np.ndarray:
    """``X_GP`` holding the cube from above by its ±y faces, fingertips CORNER_GRIP_DEPTH_M down."""
    X_OG = make_pose(DOWN, (0.0, 0.0, CUBE_HALF_M - CORNER_GRIP_DEPTH_M + FINGERTIPS_BELOW_TCP_M))
    return invert_pose(X_OG)


def _set_down(
    X_WP_start: np.ndarray, X_WP_goal: np.ndarray, out_m: tuple, table: ContactState
) -> tuple[MotionCommand, ...]:
    """Grasp at the start, lift 6 cm, carry over to ``out_m`` away from the goal and 6 cm up,
    and set the block down there with a guarded move (the table verified)."""
    lifted = X_WP_start.copy()
    lifted[2, 3] += 0.06
    near = X_WP_goal.copy()
    near[:3, 3] += out_m
    above = near.copy()
    above[2, 3] += 0.06
    return (
        _cmd("guarded_grasp", X_WP_start, 0.1),
        _cmd("move", lifted, 0.1),
        _cmd("move", above, 0.1),
        _cmd("guarded_move", near, 0.02, (table,), PLACE_GUARD_N),
    )


def corner_program(
    X_WP_start: np.ndarray, scene: Scene | None = None
) -> tuple[MotionProgram, np.ndarray]:
    """The cube from ``X_WP_start`` into the frame's (−x, −y) inside corner of ``scene`` (default:
    the puzzle scene), and the goal pose.

    Like a deformed operator path (Fig. 12): over the bars, down onto the table 1 cm out from
    both walls, then a contact move into the corner with table and both walls required."""
    (x0, _), (y0, _) = frame_inner_W(scene or load_scene())
    goal = make_pose(np.eye(3), (x0 + CUBE_HALF_M, y0 + CUBE_HALF_M, CUBE_HALF_M))
    table = ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]]))
    walls = ContactState(object="frame", normals_W=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    commands = (
        *_set_down(X_WP_start, goal, (0.01, 0.01, 0.0), table),
        _cmd("contact_move", goal, 0.01, (table, walls)),
        _cmd("release", goal, 0.01),
        _cmd("move", goal @ make_pose(np.eye(3), (0.0, 0.0, 0.06)), 0.05),
    )
    return MotionProgram(program_id="corner", X_GP=corner_grasp_GP(), commands=commands), goal


def corner() -> dict:
    """Run :func:`corner_program` on the puzzle scene's cube; the cube's final pose against
    the goal and the contact reports."""
    world, c = _site()
    reports: list[tuple] = []
    try:
        program, goal = corner_program(world.object_pose("cube"), world.scene)
        problem = program_refusal(program, c)
        if problem:
            raise RuntimeError(f"corner program refused: {problem}")
        _run(Execution(program, c, lambda *r: reports.append(r)), c)
        for _ in range(50):
            c.tick()
        X = world.object_pose("cube")
    finally:
        world.close()
    verified = [r for r in reports if r[2] == "contact_verified"]
    angle = float(np.linalg.norm(so3_log(goal[:3, :3].T @ X[:3, :3])))
    return {
        "corner_status": reports[-1][2],
        "corner_message": reports[-1][3],
        "corner_error_mm": float(np.linalg.norm(X[:3, 3] - goal[:3, 3])) * 1e3,
        "corner_error_xyz_mm": ((X[:3, 3] - goal[:3, 3]) * 1e3).round(3).tolist(),
        "corner_error_deg": math.degrees(angle),
        "corner_contacts_verified": bool(verified) and reports[-1][2] == "done",
        "corner_contact_report": verified[-1][3] if verified else "",
    }


def slide(impedance: Impedance | None = None, time_step_s: float = 1e-3) -> dict:
    """The cube put against the frame's x = 0.35 wall, then slid 6 cm along it (+y) by a
    contact move: the force along the wall's normal at each period of the slide, and how far
    short of its goal along the wall the cube ends (friction against the impedance);
    ``time_step_s``: the physics step."""
    world, c = _site(time_step_s)
    (x0, _), _ = frame_inner_W(world.scene)
    start_y, end_y = -0.03, 0.03
    table = ContactState(object="table", normals_W=np.array([[0.0, 0.0, 1.0]]))
    wall = ContactState(object="frame", normals_W=np.array([[1.0, 0.0, 0.0]]))
    on_wall = make_pose(np.eye(3), (x0 + CUBE_HALF_M, start_y, CUBE_HALF_M))
    slid = make_pose(np.eye(3), (x0 + CUBE_HALF_M, end_y, CUBE_HALF_M))
    program = MotionProgram(
        program_id="slide",
        X_GP=corner_grasp_GP(),
        commands=(
            *_set_down(world.object_pose("cube"), on_wall, (0.01, 0.0, 0.0), table),
            _cmd("contact_move", on_wall, 0.01, (table, wall)),
            _cmd("contact_move", slid, 0.01, (table, wall)),
        ),
    )
    reports: list[tuple] = []
    normal_n: list[float] = []
    try:
        execution = Execution(
            program, c, lambda *r: reports.append(r), impedance=impedance or default_impedance()
        )
        for _ in range(6000):
            execution.tick()
            if execution.index == len(program.commands) - 1 and c.move is not None:
                normal_n.append(float(c.force_W[0]))
            if execution.finished:
                break
        end_error_m = float(world.object_pose("cube")[1, 3] - end_y)
    finally:
        world.close()
    f = np.array(normal_n)
    return {
        "slide_end_along_wall_mm": end_error_m * 1e3,
        "slide_status": reports[-1][2] if reports else "none",
        "slide_message": reports[-1][3] if reports else "",
        "slide_normal_n_mean": float(f.mean()) if f.size else math.nan,
        "slide_normal_n_min": float(f.min()) if f.size else math.nan,
        "slide_normal_n_max": float(f.max()) if f.size else math.nan,
        "slide_band_n": [CONTACT_VERIFY_N, CONTACT_FORCE_LIMIT_N],
        "slide_samples": int(f.size),
    }


def _write_csv(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _plot(out_dir: Path, tracking_rows: list[dict], guarded_rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    v = [r["speed_mps"] * 1e3 for r in tracking_rows]
    a.plot(v, [r["tracking_mm_max"] for r in tracking_rows], "o-")
    a.axhline(0.5, color="grey", ls="--", label="goal 0.5 mm")
    a.set(xlabel="TCP speed (mm/s)", ylabel="max tracking error (mm)", title="Linear moves")
    a.legend()
    v = [r["speed_mps"] * 1e3 for r in guarded_rows]
    b.plot(v, [r["overshoot_n"] for r in guarded_rows], "o-", label=f"worst of {TOUCH_PHASES}")
    b.plot(v, [r["overshoot_n_mean"] for r in guarded_rows], "s--", label="mean")
    b.axhline(5.0, color="grey", ls="--", label="goal 5 N at 20 mm/s")
    b.axvline(20.0, color="grey", ls=":")
    b.set_xscale("log")
    b.set(
        xlabel="approach speed (mm/s)",
        ylabel=f"force overshoot past {GUARD_THRESHOLD_N:.0f} N (N)",
        title="Guarded move onto the table",
    )
    b.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "control.png", dpi=100)
    plt.close(fig)


TANGENTIAL_STIFFNESSES_N_PER_M = (1000.0, 2000.0, 5000.0, 10000.0, 20000.0)
"""The slide's sweep of the impedance's stiffness along the surfaces (1000: isotropic)."""


def slide_sweep() -> list[dict]:
    """The slide at each of :data:`TANGENTIAL_STIFFNESSES_N_PER_M`: how far short along the wall
    it ends against the normal force's range (the knob's accuracy/force trade)."""
    rows = []
    for k in TANGENTIAL_STIFFNESSES_N_PER_M:
        r = slide(Impedance(tangential_stiffness_n_per_m=k))
        rows.append(
            {
                "tangential_stiffness_n_per_m": k,
                "end_along_wall_mm": r["slide_end_along_wall_mm"],
                "normal_n_min": r["slide_normal_n_min"],
                "normal_n_max": r["slide_normal_n_max"],
                "status": r["slide_status"],
            }
        )
    return rows


GRID_STIFFNESSES_N_PER_M = (100.0, 1000.0, 5000.0, 20000.0, 100000.0)
"""The grid's surface stiffnesses: the accepted range's ends, the default and between."""
GRID_RATES_HZ = (500.0, 1000.0, 2000.0)
"""The grid's physics rates: the work site's accepted range's ends and its default."""


def impedance_grid() -> list[dict]:
    """The slide at each surface stiffness × physics rate of the grid (every cell within the
    accepted ranges, so K·Δt/B ≤ 1): how far short along the wall it ends and the normal
    force's range against the verification band."""
    rows = []
    for rate_hz in GRID_RATES_HZ:
        for k in GRID_STIFFNESSES_N_PER_M:
            impedance = Impedance(tangential_stiffness_n_per_m=k)
            gain = impedance.step_gain(1.0 / rate_hz)
            r = slide(impedance, 1.0 / rate_hz)
            lo, hi = r["slide_band_n"]
            f_min, f_max = r["slide_normal_n_min"], r["slide_normal_n_max"]
            rows.append(
                {
                    "physics_rate_hz": rate_hz,
                    "tangential_stiffness_n_per_m": k,
                    "step_gain": gain,
                    "status": r["slide_status"],
                    "end_along_wall_mm": r["slide_end_along_wall_mm"],
                    "normal_n_min": f_min,
                    "normal_n_max": f_max,
                    "in_band": bool(lo <= f_min and f_max <= hi),
                }
            )
    return rows


def _plot_grid(out_dir: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for rate in GRID_RATES_HZ:
        sub = [r for r in rows if r["physics_rate_hz"] == rate]
        k = [r["tangential_stiffness_n_per_m"] for r in sub]
        a.loglog(k, [abs(r["end_along_wall_mm"]) for r in sub], "o-", label=f"{rate:g} Hz")
        b.fill_between(
            k,
            [r["normal_n_min"] for r in sub],
            [r["normal_n_max"] for r in sub],
            alpha=0.25,
            label=f"{rate:g} Hz",
        )
    b.set_xscale("log")
    b.axhline(CONTACT_VERIFY_N, color="grey", ls="--", label="verification band")
    b.axhline(CONTACT_FORCE_LIMIT_N, color="grey", ls="--")
    a.set(
        xlabel="surface stiffness (N/m)",
        ylabel="|end along the wall − goal| (mm)",
        title="Slide: accuracy along the wall",
    )
    b.set(
        xlabel="surface stiffness (N/m)",
        ylabel="force along the wall's normal (N)",
        title="Slide: normal force, min to max",
    )
    a.axvline(DEFAULT_SURFACE_STIFFNESS_N_PER_M, color="grey", ls=":")
    b.axvline(DEFAULT_SURFACE_STIFFNESS_N_PER_M, color="grey", ls=":")
    a.legend(fontsize=8)
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "control_grid.png", dpi=100)
    plt.close(fig)


def run(out_dir: Path, grid_only: bool = False) -> dict:
    """Run every case; write control.json, the CSVs and the plot under ``out_dir``; return the
    JSON summary (with ``grid_only``, only the impedance grid's rows and files)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    grid = impedance_grid()
    _write_csv(out_dir / "control_grid.csv", grid)
    _plot_grid(out_dir, grid)
    if grid_only:
        return {"impedance_grid": grid}
    rows = [tracking(v) for v in SPEEDS_MPS]
    _write_csv(out_dir / "control.csv", rows)
    guarded = [guarded_touch(v) for v in GUARD_SPEEDS_MPS]
    _write_csv(out_dir / "control_guarded.csv", guarded)
    _plot(out_dir, rows, guarded)
    sweep = slide_sweep()
    _write_csv(out_dir / "control_slide.csv", sweep)
    at_tenth = next(r for r in rows if r["speed_mps"] == 0.1)
    at_20 = next(r for r in guarded if r["speed_mps"] == 0.02)
    summary = {
        "tracking_mm_max": at_tenth["tracking_mm_max"],
        "guarded_overshoot_n": at_20["overshoot_n"],
        **corner(),
        **slide(),
        "slide_by_tangential_stiffness": sweep,
        "impedance_grid": grid,
        "tracking_by_speed": rows,
        "guarded_by_speed": guarded,
    }
    (out_dir / "control.json").write_text(json.dumps(summary, indent=1))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench control``."""
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for control.json, control.csv, control_guarded.csv, control_slide.csv "
        "and control.png (default: %(default)s)",
    )
    parser.add_argument(
        "--grid-only",
        action="store_true",
        help="only the slide over surface stiffness × physics rate (control_grid.csv, .png)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    print(json.dumps(run(args.out, grid_only=args.grid_only)))
    return 0
