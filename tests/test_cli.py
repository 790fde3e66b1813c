"""The command lines: help that helps, clear refusals of bad input, and `make demo` as written."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from operator_site.link import WorkSiteLink
from protocol import DEFAULT_SITE_ID, DEFAULT_WORK_SITE_ENDPOINT, make_config
from tests.conftest import REPO, free_port, stop_like_ctrl_c, wait_until

pytestmark = pytest.mark.integration  # starts the CLIs as processes


def run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.parametrize("module", ["work_site", "operator_site"])
def test_help(module: str) -> None:
    result = run(module, "--help")
    assert result.returncode == 0
    assert "serve" in result.stdout
    result = run(module, "serve", "--help")
    assert result.returncode == 0 and "--site-id" in result.stdout


@pytest.mark.parametrize("module", ["work_site", "operator_site"])
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scene", "/nonexistent/scene.json"], "scene.json: scene file does not exist"),
        (["--site-id", "a/b"], "site_id: must match"),
        (["--certs", "/nonexistent/certs"], "no such file '/nonexistent/certs/ca.pem'"),
    ],
)
def test_bad_arguments_are_refused_clearly(module: str, args: list[str], message: str) -> None:
    result = run(module, "serve", *args)
    assert result.returncode == 2
    assert message in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--vision-scale", "9"], "vision_scale must be in [0.25, 2], got 9.0"),
        (["--vision-index-views", "3"], "vision_index_views must be in [50, 20000], got 3"),
        (["--surface-stiffness", "1"], "surface_stiffness_n_per_m must be in [100, 1e5]"),
        (["--deadman-s", "0.05"], "deadman_s must be in [0.2, 5] s (the dead-man's timeout)"),
        (["--deadman-s", "60"], "deadman_s must be in [0.2, 5] s"),
        (["--physics-rate", "5000"], "physics_rate_hz must be in [500, 2000] Hz (where grasping"),
        (["--physics-rate", "1234"], "whole number of steps per 0.01 s control period"),
        (["--camera-supersample", "64"], "camera_supersample must be in 1..4, got 64"),
    ],
)
def test_work_site_refuses_knobs_out_of_range(args: list[str], message: str) -> None:
    result = run("work_site", "serve", *args)
    assert result.returncode == 2 and message in result.stderr


def test_operator_site_refuses_a_bad_port() -> None:
    result = run("operator_site", "serve", "--port", "70000")
    assert result.returncode == 2 and "--port must be in 1..65535" in result.stderr


def _port_in_use(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_make_demo_serves_the_page_and_ctrl_c_stops_both(tmp_path: Path) -> None:
    """The README's first command, as written (its default ports must be free)."""
    if _port_in_use(8080) or _port_in_use(7447):
        pytest.skip("ports 8080/7447 are in use on this machine; `make demo` needs them")
    log_path = tmp_path / "demo.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            ["make", "-s", "demo"],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    link = None
    try:
        assert wait_until(lambda: "open http://localhost:8080" in log_path.read_text(), 120), (
            log_path.read_text()
        )
        with urllib.request.urlopen("http://localhost:8080/", timeout=10) as response:
            assert response.status == 200
        link = WorkSiteLink(make_config(connect=[DEFAULT_WORK_SITE_ENDPOINT]), DEFAULT_SITE_ID)
        assert wait_until(
            lambda: (
                link.poll(),
                link.status.label == "connected" and link.camera_frame is not None,
            )[1],
            30,
        ), log_path.read_text()
    finally:
        if link is not None:
            link.close()
        stop_like_ctrl_c(proc, log_path=log_path)
    text = log_path.read_text()
    assert "work site stopped (exit code 0)" in text, text
    time.sleep(0.5)
    assert not _port_in_use(8080) and not _port_in_use(7447)
    assert free_port()  # the loopback stack is still usable


@pytest.mark.parametrize(
    ("script", "said"),
    [
        # Ignores Ctrl-C: asked for its stacks, killed, the test failed saying so.
        ("import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); time.sleep(60)",
         "did not end"),
        # Ends, but leaves a child in a session of its own holding its output (for longer than
        # the helper waits: 1 s, its stacks' 1 s, 1 s more; then it ends by itself).
        ("import subprocess, sys; subprocess.Popen(['sleep', '6'], start_new_session=True)",
         "ended, but a child of its held its output open"),
    ],
)  # fmt: skip
def test_a_process_that_lingers_after_ctrl_c_fails_the_test_saying_how(script, said) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    time.sleep(0.5)  # past its start
    with pytest.raises(pytest.fail.Exception, match=said):
        stop_like_ctrl_c(proc, timeout_s=1.0)
    assert proc.returncode is not None
