"""Outside text on the page: :func:`plain` shows any string as text, never as markup, and the
status and log panels put wire text through it."""

from __future__ import annotations

import html
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from operator_site.link import LinkStatus
from operator_site.ui.status import log_markdown, status_markdown
from operator_site.ui.text import WORD_JOINER, plain
from protocol import ExecutionReport
from tests.conftest import examples

PAYLOADS = (
    '<img src=x onerror="window.__pwned=1">',
    '<iframe srcdoc="<script>parent.__pwned=2</script>"></iframe>',
    "<script>window.__pwned=3</script>",
    "[click](http://203.0.113.7/) ![x](http://203.0.113.7/a.png) www.example.com a@b.example",
    "**bold** _em_ `code` ~~gone~~ | a | b |\n|---|---|\n# heading\n    indented\n> quote",
    "&lt;img src=x&gt; &#60;b&#62; \\<b\\>",
    "mailto:x@y.example HTTPS://A.EXAMPLE/ xmpp:a@b.example WWW.EXAMPLE.COM",
)


GFM_AUTOLINKS = (
    re.compile(r"(https?://|www(?=\.))([-.\w]+)([^ \t\r\n]*)", re.IGNORECASE | re.ASCII),
    re.compile(r"([-.\w+]+)@([-\w]+(?:\.[-\w]+)+)", re.ASCII),
    re.compile(r"(mailto|xmpp):", re.IGNORECASE),
)
"""What GFM (mdast-util-gfm-autolink-literal, as viser's markdown runs it) links in a text
node after character references are decoded: web addresses, mail addresses, protocols."""


def rendered(markdown: str) -> str:
    """``markdown`` as HTML by a CommonMark parser that passes raw HTML through, as viser's
    does, with GFM's tables and strikethrough."""
    markdown_it = pytest.importorskip("markdown_it")
    md = markdown_it.MarkdownIt("commonmark", {"html": True}).enable(["table", "strikethrough"])
    return md.render(markdown)


def shown_as_text(text: str) -> None:
    """Assert that ``plain(text)`` renders as one paragraph holding exactly ``text``'s words."""
    out = rendered(plain(text))
    words = " ".join(text.split())
    if not words:
        assert out == ""
        return
    m = re.fullmatch(r"<p>(.*)</p>\n", out, flags=re.DOTALL)
    assert m is not None, out
    assert "<" not in m.group(1), out  # no element at all inside the paragraph
    text_node = html.unescape(m.group(1))
    assert text_node.replace(WORD_JOINER, "") == words
    assert not any(r.search(text_node) for r in GFM_AUTOLINKS), text_node


@pytest.mark.parametrize("text", PAYLOADS)
def test_markup_in_outside_text_is_shown_as_text(text: str) -> None:
    shown_as_text(text)


@settings(max_examples=examples(500))
@given(st.text(alphabet=st.characters(blacklist_categories=("Cc", "Cf", "Cs")), max_size=80))
def test_any_text_is_shown_as_its_own_words(text: str) -> None:
    shown_as_text(text)


@settings(max_examples=examples(500))
@given(st.text(max_size=80))
def test_plain_leaves_no_active_character(text: str) -> None:
    # Outside its numeric character references, no ASCII punctuation or control character.
    rest = re.sub(r"&#\d+;", "", plain(text))
    assert not re.search(r"[!-/:-@\[-`{-~\x00-\x1f\x7f]", rest), rest


def test_control_characters_are_replaced_and_whitespace_collapsed() -> None:
    assert plain("a\x00b\x1bc") == "a\ufffdb\ufffdc"
    assert plain("  two\n\nlines\tand  tabs ") == "two lines and tabs"
    assert plain(ValueError("bad <x>")) == "bad &#60;x&#62;"
    assert plain("www.a.b x@y.z") == f"www{WORD_JOINER}&#46;a&#46;b x{WORD_JOINER}&#64;y&#46;z"


def report(message: str, program_id: str = "p-1") -> ExecutionReport:
    return ExecutionReport(
        program_id=program_id,
        command_index=-1,
        status="refused",
        wrench_S=np.zeros(6),
        message=message,
        stamp_s=1.0,
    )


@pytest.mark.parametrize("text", PAYLOADS[:4])
def test_status_and_log_show_report_messages_as_text(text: str) -> None:
    status = LinkStatus(reports=[report(text, program_id=f"p-{len(text)}")])
    # The log shows the message; the status line, redrawn twice a second, only the program.
    for markdown, shown in (
        (status_markdown("site_1", status), f"p-{len(text)}"),
        (log_markdown(status.reports), " ".join(text.split())),
    ):
        out = rendered(markdown)
        assert not re.search(r"<(img|iframe|script|a)\b", out), out
        text_nodes = html.unescape(re.sub(r"<[^>]+>", "", out)).replace(WORD_JOINER, "")
        assert shown in text_nodes


def test_the_log_says_what_to_do_after_a_program_ends_badly() -> None:
    refused = report("command 3 is out of reach")
    assert "Nothing moved" in log_markdown([refused])
    ended = {
        status: ExecutionReport(program_id="p", command_index=-1, status=status,
                                wrench_S=np.zeros(6), message="", stamp_s=1.0)
        for status in ("failed", "stopped", "done")
    }  # fmt: skip
    assert "*back off*" in log_markdown([ended["failed"]])
    assert "*go home*" in log_markdown([ended["stopped"]])
    assert "➜" not in log_markdown([refused, ended["done"]])


def test_the_status_shows_the_round_trip_once_measured() -> None:
    status = LinkStatus(work_site_alive=True, state_rate_hz=100.0, frame_rate_hz=5.0)
    assert "round trip" not in status_markdown("site_1", status)
    status.round_trip_s = 0.5123
    assert "camera 5.0 Hz · round trip 512 ms" in status_markdown("site_1", status)
    status.work_site_alive = False  # a stale figure is not shown for a site that went
    assert "round trip" not in status_markdown("site_1", status)


def test_the_status_says_when_the_link_gets_fewer_frames_than_the_camera_takes() -> None:
    status = LinkStatus(work_site_alive=True, state_rate_hz=40.0, frame_rate_hz=1.5)
    assert "slower than the camera" not in status_markdown("site_1", status)  # not known yet
    status.frame_share = 0.95  # a frame lost now and then: not worth a line
    assert "slower than the camera" not in status_markdown("site_1", status)
    status.frame_share = 0.3
    assert "1 frame in 3 reaches you" in status_markdown("site_1", status)


def test_the_status_shows_how_old_the_camera_image_is_once_measured() -> None:
    status = LinkStatus(work_site_alive=True, last_frame_age_s=0.25)
    assert "last camera frame 0.2 s ago" in status_markdown("site_1", status)
    assert "taken" not in status_markdown("site_1", status)
    status.frame_age_s = 0.5  # it was that old when it arrived: now older by the wait since
    assert "last camera frame 0.2 s ago, taken 0.8 s ago" in status_markdown("site_1", status)
