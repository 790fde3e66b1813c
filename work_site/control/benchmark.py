"""``work-site bench control``: how well the arm executes moves (issue 5).

Today: linear-move tracking at several TCP speeds. Guarded moves, corner placement and sliding
under impedance come with the rest of issue 5. Prints a JSON object; writes ``control.csv``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from models.robot import load_robot
from models.scene import load_scene
from models.transforms import make_pose, rpy_to_R
from work_site.control.controller import TaskController
from work_site.world import World

DOWN = rpy_to_R(np.array([math.pi, 0.0, math.pi]))
SPEEDS_MPS = (0.025, 0.05, 0.1, 0.2)


def tracking(speed_mps: float) -> dict:
    """A 10 cm line along x at ``speed_mps``: worst commanded-to-measured TCP distance (mm) and
    worst distance of the measured TCP from the line itself (mm)."""
    scene = load_scene()
    world = World(scene)
    try:
        controller = TaskController(world, load_robot(scene.robot.urdf_path))
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


def main(out_dir: Path) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [tracking(v) for v in SPEEDS_MPS]
    with (out_dir / "control.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    at_tenth = next(r for r in rows if r["speed_mps"] == 0.1)
    return {"tracking_mm_max": at_tenth["tracking_mm_max"], "tracking_by_speed": rows}
