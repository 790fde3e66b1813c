"""Ways back without restarting: after a program fails in contact, ``operator-site recover``
backs the gripper off what it presses, releases the block and parks the arm, and the work site
takes the next program. A real work site and real operator processes over zenoh."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from bench.control import corner_program
from models.robot import TCP_LINK, load_robot
from models.scene import load_scene
from operator_site.link import WorkSiteLink
from operator_site.program import park_pose_W
from protocol import ContactState, make_config
from tests.conftest import REPO, wait_until

pytestmark = pytest.mark.integration

PARKED_M = 0.003
"""The arm is parked when its gripper is this close to the park pose (m)."""
FREE_N = 1.0
"""Backed off, the wrist feels less than this sideways force (N): nothing presses the hand."""
PRESSED_N = 2.0
"""Failed in the corner, the hand is pressed sideways at least this hard (N)."""
DEADMAN_S = 2.0
"""The work sites' dead-man time: what is tested here is recovery, and on a loaded machine the
operator's beats have come further apart than the default (the dead-man has tests of its own)."""


def _recover(ws, action: str, operator_id: str) -> subprocess.CompletedProcess:
    """``operator-site recover`` acting as the operator that holds the robot (a page's id)."""
    return subprocess.run(
        [sys.executable, "-m", "operator_site", "recover", action, "--connect", ws.endpoint,
         "--single-link", "--site-id", ws.site_id, "--operator-id", operator_id],
        capture_output=True, text=True, timeout=180, cwd=REPO,
    )  # fmt: skip


def test_after_a_failure_in_contact_the_arm_backs_off_releases_and_parks(work_site) -> None:
    ws = work_site("--no-camera", "--deadman-s", str(DEADMAN_S))
    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    scene = load_scene()
    robot = load_robot(scene.robot.urdf_path)

    def ended(pid: str):
        link.poll()
        return next(
            (r for r in link.status.reports if r.program_id == pid and r.command_index == -1
             and r.status in ("done", "failed", "stopped", "refused")),
            None,
        )  # fmt: skip

    try:
        assert wait_until(lambda: (link.poll(), link.robot_state is not None)[1], 30), ws.log()
        cube = next(o for o in scene.objects if o.name == "cube")
        good, _ = corner_program(cube.X_WO)
        # The same corner, but the last contact also expects the table from below: a contact
        # the robot cannot verify, so the program fails pressing into the corner.
        contact = [c.kind for c in good.commands].index("contact_move")
        cmd = good.commands[contact]
        impossible = ContactState(object="table", normals_W=np.array([[0.0, 0.0, -1.0]]))
        failing = dataclasses.replace(
            good,
            program_id="fails-in-contact",
            commands=(
                *good.commands[:contact],
                dataclasses.replace(cmd, contacts=(*cmd.contacts, impossible)),
                *good.commands[contact + 1 :],
            ),
        )
        link.send_program(failing)
        assert wait_until(lambda: ended("fails-in-contact") is not None, 120), ws.log()
        assert ended("fails-in-contact").status == "failed", ended("fails-in-contact")

        def sideways_n() -> float:
            state = link.robot_state
            assert wait_until(lambda: (link.poll(), link.robot_state.seq > state.seq + 3)[1], 5)
            f_W = link.robot_state.X_WF[:3, :3] @ link.robot_state.wrench_S[:3]
            return float(np.hypot(f_W[0], f_W[1]))

        pressed_n = sideways_n()
        assert pressed_n >= PRESSED_N, pressed_n  # the stuck state: pressing into the corner
        out = _recover(ws, "retract", link.operator_id)
        assert out.returncode == 0, (out.stdout, out.stderr, ws.log()[-3000:])
        assert "retract: sent as retract-" in out.stdout and ": done" in out.stdout
        assert sideways_n() < FREE_N, pressed_n
        out = _recover(ws, "release", link.operator_id)
        assert out.returncode == 0, (out.stdout, out.stderr)
        assert wait_until(lambda: (link.poll(), link.robot_state.gripper_opening_m > 0.06)[1], 5)
        out = _recover(ws, "home", link.operator_id)
        assert out.returncode == 0, (out.stdout, out.stderr)
        state = link.robot_state
        assert wait_until(lambda: (link.poll(), link.robot_state.seq > state.seq + 5)[1], 5)
        X_WG = robot.link_poses_W(link.robot_state.q, 0.0, scene.robot.X_WB)[TCP_LINK]
        park = park_pose_W(scene)
        assert np.linalg.norm(X_WG[:3, 3] - park[:3, 3]) <= PARKED_M, (X_WG, park)

        # And the work site takes the next program.
        again = dataclasses.replace(good, program_id="after-recovery")
        link.send_program(again)
        assert wait_until(lambda: ended("after-recovery") is not None, 120), ws.log()
        reports = [r for r in link.status.reports if r.program_id == "after-recovery"]
        assert reports[0].status == "accepted", reports[0]  # (the cube is elsewhere now)
    finally:
        link.close()


def test_a_program_stopped_while_carrying_resumes_from_the_command_line(work_site, tmp_path):
    """STOP while the cube is carried; ``operator-site recover resume --program FILE`` goes on
    from the command it was stopped in, the cube still held, and puts it in the corner."""
    from operator_site.session import save_program

    ws = work_site("--no-camera", "--publish-truth", "--deadman-s", str(DEADMAN_S))
    link = WorkSiteLink(make_config(connect=[ws.endpoint]), ws.site_id)
    scene = load_scene()
    try:
        assert wait_until(lambda: (link.poll(), link.robot_state is not None)[1], 30), ws.log()
        cube = next(o for o in scene.objects if o.name == "cube")
        program, _ = corner_program(cube.X_WO)
        program = dataclasses.replace(program, program_id="stopped-mid-carry")
        carry = 2  # the grasp, the lift, then this: the block is in the hand

        def reports(pid: str) -> list:
            link.poll()
            return [r for r in link.status.reports if r.program_id == pid]

        link.send_program(program)
        assert wait_until(
            lambda: any(r.command_index == carry and r.status == "started"
                        for r in reports(program.program_id)), 120
        ), ws.log()  # fmt: skip
        link.send_stop("operator pressed stop")
        assert wait_until(
            lambda: any(r.command_index == -1 and r.status == "stopped"
                        for r in reports(program.program_id)), 10
        ), ws.log()  # fmt: skip
        assert link.robot_state.gripper_opening_m < 0.06  # still holding the cube
        path = tmp_path / "program.msgpack"
        save_program(path, program)
        out = subprocess.run(
            [sys.executable, "-m", "operator_site", "recover", "resume", "--program", str(path),
             "--connect", ws.endpoint, "--single-link", "--site-id", ws.site_id,
             "--operator-id", link.operator_id],
            capture_output=True, text=True, timeout=300, cwd=REPO,
        )  # fmt: skip
        assert out.returncode == 0, (out.stdout, out.stderr, ws.log()[-3000:])
        assert "resume: sent as stopped-mid-carry-resumed-" in out.stdout, out.stdout
        started = [
            int(line.split()[1].rstrip(":"))
            for line in out.stdout.splitlines()
            if line.strip().startswith("command") and ": started" in line
        ]
        assert started and min(i for i in started if i >= 0) == carry, out.stdout
    finally:
        link.close()
