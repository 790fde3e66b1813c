"""Markup in text from the wire or from files never runs in the page: a real work site echoes a
crafted program's field name in its refusal, a crafted report arrives on its key, and task files
carry markup in their contents and their paths; headless Chromium then shows all of it as text,
runs none of it and fetches nothing from outside."""

from __future__ import annotations

import json
import os
import threading
import time
from ipaddress import ip_address
from pathlib import Path
from urllib.parse import urlsplit

import msgpack
import numpy as np
import pytest

from bench.ui import CHROMIUM, chromium_flags
from models.scene import load_scene
from operator_site.link import WorkSiteLink
from operator_site.ui import OperatorPage
from protocol import ExecutionReport, encode, key, make_config
from tests.conftest import free_port, one_move_program, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.integration]

OUTSIDE = "203.0.113.7"
"""An outside address (TEST-NET-3): any request to it is a payload that came alive."""

FIELD_PAYLOADS = ("<img src=x onerror=window.__pwned=1>", f"<img src=http://{OUTSIDE}/f>")
"""Field names short enough for the work site's refusal to echo them whole."""
REPORT_PAYLOAD = (
    '<iframe srcdoc="<script>parent.__pwned=2</script>"></iframe> '
    f"[a link](http://{OUTSIDE}/link) ![an image](http://{OUTSIDE}/md.png) www.example.com"
)
SCENE_PAYLOAD = f'<img src=x onerror="window.__pwned=3"><img src="http://{OUTSIDE}/scene.png">'
PATH_PAYLOAD = "<script>window.__pwned=4<"  # a directory name: the path goes on with "/script>"

SHOWN = {
    "the work site's refusal": "onerror=window.__pwned=1>",
    "a report's message": "parent.__pwned=2",
    "a task file's names": 'onerror="window.__pwned=3"',
    "a task file's path": "<script>window.__pwned=4</script>",
}
"""What each payload shows as text on the page."""


def crafted_program() -> bytes:
    """A valid program with more fields, named with markup: the work site refuses it and its
    refusal names the fields."""
    envelope = msgpack.unpackb(encode(one_move_program("crafted")), raw=False)
    for name in FIELD_PAYLOADS:
        envelope["b"][name] = 1
    return msgpack.packb(envelope)


def crafted_report() -> bytes:
    """A valid report whose message is markup, as a compromised work site could send it."""
    return encode(
        ExecutionReport(
            program_id="crafted-report",
            command_index=-1,
            status="failed",
            wrench_S=np.zeros(6),
            message=REPORT_PAYLOAD,
            stamp_s=time.time(),
        )
    )


def is_loopback(url: str) -> bool:
    parts = urlsplit(url)
    if parts.scheme in ("data", "blob"):
        return True
    host = parts.hostname or ""
    if host == "localhost":
        return True
    try:
        return ip_address(host).is_loopback
    except ValueError:
        return False


def test_markup_from_the_wire_and_files_is_shown_as_text(work_site, tmp_path: Path) -> None:
    if not os.access(CHROMIUM, os.X_OK):
        print(f"skipping: {CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
        pytest.skip(f"{CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
    playwright = pytest.importorskip("playwright.sync_api")
    import zenoh

    ws = work_site()
    # The crafted report comes from a peer of the page's own (peers do not forward between
    # peers); the crafted program goes to the work site.
    sender_endpoint = f"tcp/127.0.0.1:{free_port()}"
    sender = zenoh.open(make_config(listen=[sender_endpoint], connect=[ws.endpoint]))
    link = WorkSiteLink(make_config(connect=[ws.endpoint, sender_endpoint]), ws.site_id)
    page = OperatorPage(load_scene(), link, port=free_port())
    stop = threading.Event()
    runner = threading.Thread(target=page.run, args=(stop,), daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: page.link.status.work_site_alive, 60), ws.log()

        # From the wire: until both are in the page's execution log (the link comes up first).
        def sent_and_logged() -> bool:
            sender.put(key(ws.site_id, "program"), crafted_program())
            sender.put(key(ws.site_id, "report"), crafted_report())
            messages = [r.message for r in page.link.status.reports]
            echoed = any(all(name in m for name in FIELD_PAYLOADS) for m in messages)
            return echoed and REPORT_PAYLOAD in messages

        assert wait_until(sent_and_logged, 60, poll_s=1.0), (page.link.status.reports, ws.log())
        # From files: a task file whose names are markup, and a path with markup.
        task_file = tmp_path / "task.json"
        pose = {"xyz_m": [0, 0, 0], "rpy_deg": [0, 0, 0]}
        task_file.write_text(
            json.dumps(
                {"task": 1, "name": SCENE_PAYLOAD, "workpiece": SCENE_PAYLOAD,
                 "reference": "frame", "steps": [pose],
                 "goal": {**pose, "contacts": []}}
            )
        )  # fmt: skip
        page.on_load(str(task_file))
        assert "window.__pwned=3" not in page.task_md.content  # escaped at the source
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=chromium_flags())
            try:
                tab = browser.new_page(viewport={"width": 1400, "height": 1400})
                requests: list[str] = []
                tab.on("request", lambda r: requests.append(r.url))
                tab.goto(f"http://127.0.0.1:{page.server.get_port()}/")
                tab.get_by_text("work site: connected").wait_for(timeout=60_000)
                for what, text in list(SHOWN.items())[:3]:
                    # Shown in its panel (visible: laid out and not hidden, in view or not).
                    shown = tab.get_by_text(text).first
                    shown.wait_for(timeout=30_000)
                    assert shown.is_visible(), what
                # The path's payload: typed into the page as the task file, loaded by a click.
                bad_path = tmp_path / PATH_PAYLOAD / "script>.json"
                field = tab.locator('input[value="task.json"]').first
                field.fill(str(bad_path))
                tab.keyboard.press("Enter")
                tab.get_by_role("button", name="load a task").click()
                tab.get_by_text(SHOWN["a task file's path"]).first.wait_for(timeout=30_000)
                assert "no such file" in tab.inner_text("body")
                tab.wait_for_timeout(1_000)  # time for anything that did come alive to run
                tab.screenshot(path=str(tmp_path / "injection.png"))
                assert tab.evaluate("typeof window.__pwned") == "undefined"
                assert len(tab.frames) == 1, [f.url for f in tab.frames]  # no iframe was made
                made = tab.evaluate(
                    """() => ({
                        iframes: document.querySelectorAll('iframe').length,
                        images: [...document.querySelectorAll('img')]
                            .filter(i => !/^(blob|data):/.test(i.src)).map(i => i.outerHTML),
                        scripts: [...document.querySelectorAll('script')]
                            .filter(s => s.textContent.includes('__pwned')).length,
                        links: [...document.querySelectorAll('a[href]')].map(a => a.href)
                            .filter(h => h.includes('203.0.113') || h.includes('example.com')),
                    })"""
                )
                assert made == {"iframes": 0, "images": [], "scripts": 0, "links": []}, made
                outside = [u for u in requests if not is_loopback(u)]
                assert not outside, outside
            finally:
                browser.close()
    finally:
        stop.set()
        runner.join(timeout=10)
        sender.close()
        page.close()
        link.close()
