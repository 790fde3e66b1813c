"""The page's list of reachable work sites and its switch between them: the link lists the
sites whose liveliness tokens it sees (through a router, only those its certificate may see:
``tests/test_net_fleet.py``), and the page switches to a chosen one unless a program of its own
is still running where it is. Real zenoh sessions on loopback; stand-in work sites that only
declare their tokens (and never answer a program)."""

from __future__ import annotations

import html
import os

import pytest
import zenoh

from bench.ui import CHROMIUM, chromium_tab, run_page
from models.scene import load_scene
from operator_site.link import WorkSiteLink, site_of_token
from operator_site.ui import OperatorPage
from protocol import make_config
from tests.conftest import free_port, one_move_program, wait_until


def test_a_token_key_names_its_site() -> None:
    assert site_of_token("telerobot/cell-01/alive/work_site") == "cell-01"
    for key in ("telerobot/cell-01/alive/operator_site", "other/cell-01/alive/work_site",
                "telerobot/cell 01/alive/work_site", "telerobot/a/b/alive/work_site"):  # fmt: skip
        assert site_of_token(key) is None


@pytest.mark.integration  # the link's heartbeat process
def test_the_page_lists_reachable_sites_and_switches_unless_a_program_runs() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[endpoint])) as sites:
        tokens = {
            site: sites.liveliness().declare_token(f"telerobot/{site}/alive/work_site")
            for site in ("cell-a", "cell-b", "cell-c")
        }
        link = WorkSiteLink(make_config(connect=[endpoint]), "cell-a")
        page = OperatorPage(load_scene(), link, port=free_port(), initial_model="empty")
        try:

            def listed(expected: tuple[str, ...]) -> bool:
                page.update()
                return tuple(page.site_dropdown.options) == expected

            assert wait_until(lambda: listed(("cell-a", "cell-b", "cell-c")), 15.0)
            tokens.pop("cell-c").undeclare()  # a site gone is no longer offered
            assert wait_until(lambda: listed(("cell-a", "cell-b")), 15.0)
            assert page.link.status.work_site_alive

            # A program of ours not answered yet at cell-a: the page stays.
            page.link.send_program(one_move_program("still-running"))
            page.on_switch_site("cell-b")
            page.update()
            assert page.link is link and page.site_dropdown.value == "cell-a"
            said = html.unescape(page.site_md.content)  # markdown: outside text escaped
            assert "still-running has not ended at cell-a" in said and "STOP" in said

            # Once cell-a is gone, nothing of it waits for our heartbeats: it switches, to a new
            # link to cell-b, the old one closed.
            tokens.pop("cell-a").undeclare()
            assert wait_until(lambda: (page.update(), not link.status.work_site_alive)[1], 15.0)
            page.on_switch_site("cell-b")
            page.update()
            assert page.link is not link and page.link.site_id == "cell-b"
            assert page.link.operator_id == link.operator_id
            assert link.session.is_closed()
            assert "switched from cell-a" in html.unescape(page.site_md.content)
            assert wait_until(lambda: (page.update(), page.link.status.work_site_alive)[1], 15.0)
            assert "(cell-b)" in html.unescape(page.status_md.content)
            assert page.site_dropdown.value == "cell-b"
            assert page.op.link is page.link and page.frames_shown == 0
        finally:
            page.link.close()
            link.close()
            page.close()


@pytest.mark.browser
@pytest.mark.integration
def test_the_switch_in_chromium() -> None:
    """A person opens the dropdown in Debian's headless Chromium and picks the other site."""
    if not os.access(CHROMIUM, os.X_OK):
        print(f"skipping: {CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
        pytest.skip(f"{CHROMIUM} is missing (`make test` installs Debian's chromium as root)")
    playwright = pytest.importorskip("playwright.sync_api")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[endpoint])) as sites:
        tokens = [
            sites.liveliness().declare_token(f"telerobot/{site}/alive/work_site")
            for site in ("cell-a", "cell-b")
        ]
        link = WorkSiteLink(make_config(connect=[endpoint]), "cell-a")
        page = OperatorPage(load_scene(), link, port=free_port(), initial_model="empty")
        stop = run_page(page)
        try:
            assert wait_until(lambda: len(page.site_dropdown.options) == 2, 15.0)
            with playwright.sync_playwright() as pw, chromium_tab(pw, page) as tab:
                tab.get_by_role("combobox", name="work site").click()
                tab.get_by_role("option", name="cell-b").click()
                tab.get_by_text("switched from cell-a").wait_for(timeout=30_000)
            assert page.link.site_id == "cell-b" and link.session.is_closed()
        finally:
            stop()
            page.link.close()
            link.close()
            page.close()
            for token in tokens:
                token.undeclare()
