"""Several sites through one zenoh router (deploy/router.py, deploy/zenoh/router.json5): two
work sites under their own site ids and one operator, all connected only to the router. Also
keeps the example configs in deploy/zenoh/ loadable by zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zenoh

from models.transforms import make_pose, rpy_to_R
from operator_site.link import WorkSiteLink
from protocol import MotionCommand, MotionProgram, make_config
from tests.conftest import free_port, wait_until

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "deploy" / "zenoh").glob("*.json5"))
DOWN = rpy_to_R(np.array([np.pi, 0.0, np.pi]))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_example_configs_are_valid_zenoh_configs(path: Path) -> None:
    conf = zenoh.Config.from_file(str(path))
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("transport/shared_memory/enabled") == "false"


def test_two_work_sites_and_an_operator_through_a_router(tmp_path: Path) -> None:
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    procs: list[subprocess.Popen] = []
    logs: list[Path] = []

    def spawn(name: str, argv: list[str]) -> None:
        log_path = tmp_path / f"{name}.log"
        logs.append(log_path)
        with log_path.open("w") as log:
            procs.append(
                subprocess.Popen(
                    argv,
                    cwd=REPO,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                    env={**os.environ, "PYTHONUNBUFFERED": "1"},
                )
            )

    links: list[WorkSiteLink] = []
    try:
        spawn(
            "router",
            [sys.executable, str(REPO / "deploy" / "router.py"),
             str(REPO / "deploy" / "zenoh" / "router.json5"), "--listen", router_ep],
        )  # fmt: skip
        for site in ("cell-a", "cell-b"):
            spawn(
                site,
                [sys.executable, "-m", "work_site", "serve", "--site-id", site, "--no-camera",
                 "--listen", "tcp/127.0.0.1:0", "--connect", router_ep,
                 "--journal", str(tmp_path / f"{site}.jsonl")],
            )  # fmt: skip
        # The operator knows only the router.
        links = [WorkSiteLink(make_config(connect=[router_ep]), s) for s in ("cell-a", "cell-b")]
        a, b = links

        def both_connected() -> bool:
            a.poll(), b.poll()
            return a.status.label == "connected" and b.status.label == "connected"

        assert wait_until(both_connected, 30.0), [p.read_text() for p in logs]
        q_b = b.robot_state.q.copy()
        command = MotionCommand(
            kind="move",
            X_WP=make_pose(DOWN, (0.40, -0.1, 0.15)),
            speed_mps=0.1,
            force_limit_n=10.0,
            contacts=(),
        )
        a.send_program(MotionProgram(program_id="to-a", X_GP=np.eye(4), commands=(command,)))

        def a_done() -> bool:
            a.poll(), b.poll()
            return any(r.program_id == "to-a" and r.status == "done" for r in a.status.reports)

        assert wait_until(a_done, 30.0), (a.status.reports, [p.read_text() for p in logs])
        # Site b heard nothing of it and did not move; site a did.
        assert b.status.reports == []
        np.testing.assert_allclose(b.robot_state.q, q_b, atol=1e-4)
        assert np.linalg.norm(a.robot_state.q - q_b) > 0.05
    finally:
        for link in links:
            link.close()
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
