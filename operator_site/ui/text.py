"""Text from outside the program made safe to show in the page's markdown.

viser renders markdown with its embedded HTML as is, and its markdown makes links, images and
web addresses live. So the one rule of this package: every text that comes from the wire
(reports, ids, names in recognitions), from a file (scene and task files, their names and paths)
or from an exception about either reaches ``add_markdown``/``.content`` only through
:func:`plain`. Labels, hints, dropdown options and notifications are shown by viser as plain
text: they take the text as it is (escaping them would show the escapes).
"""

from __future__ import annotations

import re
import string
import unicodedata

_ACTIVE = frozenset(string.punctuation)
"""Every ASCII punctuation character: HTML's and markdown's active ones are all among them."""
WORD_JOINER = "\u2060"
_AUTOLINK_STARTS = re.compile(r"www(?=\.)|(?=[:@])", re.IGNORECASE)
"""Where a web or mail address could start to be linked: GFM links ``www.``, ``scheme:`` and
``name@domain`` found in the text itself, after character references are decoded."""


def _safe_char(c: str) -> str:
    if c in _ACTIVE:
        # A numeric character reference is always literal text to markdown, never syntax.
        return f"&#{ord(c)};"
    if unicodedata.category(c) == "Cc":
        return "\ufffd"
    return c


def plain(text: object) -> str:
    """``text`` (``str()`` of it) as markdown that shows exactly its characters as text.

    Punctuation becomes numeric character references (no HTML, emphasis, link, image or table
    can start), an invisible word joiner goes before each ``:`` and ``@`` and after ``www``
    before a dot (no web or mail address becomes a link), whitespace runs become one space (a
    newline would start a markdown block), other control characters become U+FFFD. Not for
    code spans, where markdown shows character references as they are written.
    """
    words = " ".join(str(text).split())
    words = _AUTOLINK_STARTS.sub(lambda m: m.group(0) + WORD_JOINER, words)
    return "".join(_safe_char(c) for c in words)
