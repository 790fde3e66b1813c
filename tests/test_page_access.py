"""Who may control the robot from the page: beyond loopback, only a client that showed the
access token; the command line makes, prints and checks the token."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from urllib.parse import parse_qs, urlsplit

import msgspec
import pytest
import viser

from models.scene import load_scene
from operator_site.cli import _page_token, build_parser
from operator_site.link import WorkSiteLink
from operator_site.ui import OperatorPage
from operator_site.ui.access import PageAccess, is_loopback_host, new_token, page_url
from protocol import Stop, decode, key, make_config
from tests.conftest import REPO, free_port, stop_like_ctrl_c, wait_until

TOKEN = "correct-horse-battery"
MINE = "mine-0123456789ab"


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.0.1.1", True),
        ("localhost", True),
        ("LOCALHOST", True),
        ("::1", True),
        ("[::1]", True),
        ("0.0.0.0", False),
        ("::", False),
        ("192.168.1.20", False),
        ("robot.example", False),
    ],
)
def test_loopback_hosts(host: str, loopback: bool) -> None:
    assert is_loopback_host(host) is loopback


def test_the_url_makes_the_browser_websocket_carry_the_token() -> None:
    assert page_url("127.0.0.1", 8080, None, "localhost") == "http://localhost:8080/"
    url = page_url("0.0.0.0", 8080, "a-b_c.d~0123456789", "ops")
    assert url == "http://ops:8080/?websocket=ws://ops:8080/?token=a-b_c.d~0123456789"
    # As viser's page reads it: the websocket parameter, query included.
    ws = parse_qs(urlsplit(url).query)["websocket"][0]
    assert parse_qs(urlsplit(ws).query) == {"token": ["a-b_c.d~0123456789"]}
    assert page_url("::", 8080, None, "::1") == "http://[::1]:8080/"


def test_the_url_may_fix_the_3d_views_pixel_ratio_and_refuses_one_out_of_range() -> None:
    url = page_url("127.0.0.1", 8080, "a-b_c.d~0123456789", view_dpr=0.5)
    query = parse_qs(urlsplit(url).query)
    assert query["fixedDpr"] == ["0.5"]
    assert query["websocket"] == ["ws://127.0.0.1:8080/?token=a-b_c.d~0123456789"]
    assert page_url("127.0.0.1", 8080, None, view_dpr=2) == "http://127.0.0.1:8080/?fixedDpr=2"
    for ratio in (0.1, 5.0, float("nan")):
        with pytest.raises(ValueError, match=r"0\.25\.\.4"):
            page_url("127.0.0.1", 8080, None, view_dpr=ratio)


def test_only_the_token_admits_a_client() -> None:
    access = PageAccess(TOKEN)
    assert not access.open and not access.allows(1)
    assert not access.admit(1, None) and not access.admit(1, "wrong") and not access.admit(1, "")
    assert access.admit(1, TOKEN) and access.allows(1) and not access.allows(2)
    access.forget(1)
    assert not access.allows(1)
    assert PageAccess(None).allows(7)
    for bad in ("", "short", "sixteen&chars+++", "sixteen chars ok"):
        with pytest.raises(ValueError, match="at least 16 characters"):
            PageAccess(bad)
    assert len(new_token()) >= 32 and new_token() != new_token()


def args_for(*argv: str):
    return build_parser().parse_args(["serve", *argv])


def test_the_command_line_token(capsys: pytest.CaptureFixture[str]) -> None:
    assert _page_token(args_for()) is None  # loopback: no token, no warning
    assert _page_token(args_for("--token", MINE)) == MINE
    assert capsys.readouterr().err == ""
    made = _page_token(args_for("--host", "0.0.0.0"))
    assert made is not None and len(made) >= 32
    assert "warning" in capsys.readouterr().err  # plain HTTP beyond loopback
    assert _page_token(args_for("--host", "0.0.0.0", "--token", MINE)) == MINE
    with pytest.raises(ValueError, match="--no-token needs a loopback --host"):
        _page_token(args_for("--host", "0.0.0.0", "--no-token"))
    with pytest.raises(ValueError, match="contradict"):
        _page_token(args_for("--token", "x", "--no-token"))
    with pytest.raises(ValueError, match="at least 16 characters"):
        _page_token(args_for("--token", "guessable"))


def test_a_page_beyond_loopback_needs_a_token() -> None:
    with pytest.raises(ValueError, match="needs an access token"):
        OperatorPage(load_scene(), None, host="0.0.0.0", port=free_port())  # type: ignore[arg-type]


# ------------------------------------------------------------------------- processes, sockets


CAMERA = {
    "type": "ViewerCameraMessage",
    "wxyz": [1.0, 0.0, 0.0, 0.0],
    "position": [1.0, 1.0, 1.0],
    "fov": 1.0,
    "near": 0.01,
    "far": 100.0,
    "image_height": 480,
    "image_width": 640,
    "look_at": [0.0, 0.0, 0.0],
    "up_direction": [0.0, 0.0, 1.0],
}
"""A camera report: viser counts a client as connected from its first one."""


def press(port: int, uuid: str, query: str = "") -> None:
    """Press the button ``uuid`` from a raw websocket client, as a script could."""
    from websockets.sync.client import connect

    url = f"ws://127.0.0.1:{port}/{query}"
    with connect(url, subprotocols=[f"viser-v{viser.__version__}"]) as ws:
        ws.send(msgspec.msgpack.encode(CAMERA))
        ws.send(
            msgspec.msgpack.encode(
                {"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": True}}
            )
        )
        time.sleep(0.5)  # the page handles it before the connection closes


@pytest.mark.integration
def test_a_client_without_the_token_cannot_stop_or_send() -> None:
    link = WorkSiteLink(make_config(connect=[f"tcp/127.0.0.1:{free_port()}"]), "access_test")
    page = OperatorPage(load_scene(), link, port=free_port(), token=TOKEN)
    stops: list[Stop] = []
    sub = link.session.declare_subscriber(
        key(link.site_id, "stop"), lambda s: stops.append(decode(s.payload.to_bytes(), Stop))
    )
    try:
        port = page.server.get_port()
        stop_uuid = page.stop_button._impl.uuid
        press(port, stop_uuid)
        press(port, stop_uuid, "?token=wrong")
        press(port, page.program_button._impl.uuid)
        time.sleep(1.0)
        assert stops == [] and page.program_md.content == ""
        press(port, stop_uuid, f"?token={TOKEN}")
        assert wait_until(lambda: len(stops) == 1, 5.0)
        assert stops[0].reason == "operator pressed stop"
    finally:
        sub.undeclare()
        page.close()
        link.close()


@pytest.mark.integration
def test_serve_beyond_loopback_prints_a_url_with_a_new_token() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "operator_site", "serve", "--host", "0.0.0.0", "--no-token"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "--no-token needs a loopback --host" in result.stderr
    help_text = subprocess.run(
        [sys.executable, "-m", "operator_site", "serve", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    assert "--token" in help_text and "--no-token" in help_text
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "operator_site",
            "serve",
            "--host",
            "0.0.0.0",
            "--port",
            str(port),
            "--connect",
            f"tcp/127.0.0.1:{free_port()}",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        line = ""
        deadline = time.monotonic() + 60
        while "open http://" not in line and time.monotonic() < deadline:
            line = proc.stdout.readline()
        m = re.search(rf":{port}/\?websocket=ws://\S+:{port}/\?token=([\w-]+) ", line)
        assert m is not None and len(m.group(1)) >= 32, line
    finally:
        _, err = stop_like_ctrl_c(proc)
    assert "warning" in err and "plain HTTP" in err


@pytest.mark.integration
@pytest.mark.browser
def test_in_chromium_the_printed_url_or_the_typed_token_gives_control() -> None:
    from bench.ui import CHROMIUM, chromium_flags

    if not os.access(CHROMIUM, os.X_OK):
        print(f"skipping: {CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
        pytest.skip(f"{CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
    playwright = pytest.importorskip("playwright.sync_api")
    link = WorkSiteLink(make_config(connect=[f"tcp/127.0.0.1:{free_port()}"]), "access_test")
    page = OperatorPage(load_scene(), link, port=free_port(), token=TOKEN)
    stops: list[Stop] = []
    sub = link.session.declare_subscriber(
        key(link.site_id, "stop"), lambda s: stops.append(decode(s.payload.to_bytes(), Stop))
    )
    port = page.server.get_port()
    try:
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=chromium_flags())
            try:
                # The bare address: read only, and says how to get control.
                tab = browser.new_page(viewport={"width": 1400, "height": 900})
                tab.goto(f"http://127.0.0.1:{port}/")
                tab.get_by_text("Read only.").wait_for(timeout=60_000)
                tab.get_by_role("button", name="STOP the robot").click()
                tab.wait_for_timeout(1_000)
                assert stops == []
                # viser's text input has no id for its label: the first input after it.
                field = tab.locator(
                    "xpath=//label[normalize-space()='access token']/following::input[1]"
                )
                field.fill("wrong")
                tab.get_by_role("button", name="get control").click()
                tab.get_by_text("That is not the token").wait_for(timeout=10_000)
                field.fill(TOKEN)
                tab.get_by_role("button", name="get control").click()
                tab.get_by_text("Read only.").wait_for(state="detached", timeout=10_000)
                tab.get_by_role("button", name="STOP the robot").click()
                assert wait_until(lambda: len(stops) == 1, 10.0)
                tab.close()
                # The printed address: control at once (here with the 3D view drawn at half
                # the pixel ratio: a canvas half as wide in pixels as on the page).
                tab = browser.new_page(viewport={"width": 1400, "height": 900})
                tab.goto(page_url("127.0.0.1", port, TOKEN, view_dpr=0.5))
                tab.get_by_role("button", name="STOP the robot").wait_for(timeout=60_000)
                ratio = tab.wait_for_function(
                    "() => { const c = [...document.querySelectorAll('canvas')]"
                    ".find(c => c.clientWidth > 100 && c.width > 0);"
                    " return c && c.width / c.clientWidth; }",
                    timeout=60_000,
                ).json_value()
                assert ratio == pytest.approx(0.5, abs=0.01), ratio
                tab.wait_for_timeout(1_000)  # a notice would have come with the first panel
                assert tab.get_by_text("Read only.").count() == 0
                tab.get_by_role("button", name="STOP the robot").click()
                assert wait_until(lambda: len(stops) == 2, 10.0)
            finally:
                browser.close()
    finally:
        sub.undeclare()
        page.close()
        link.close()
