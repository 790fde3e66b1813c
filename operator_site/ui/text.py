"""Text from outside the program made safe to show in the page's markdown.

viser renders markdown with its embedded HTML as is, and its markdown makes links, images and
web addresses live. So the one rule of this package: every text that comes from the wire
(reports, ids, names in recognitions), from a file (scene and task files, their names and paths)
or from an exception about either reaches ``add_markdown``/``.content`` only through
:func:`plain`. Labels, hints, dropdown options and notifications are shown by viser as plain
text: they take the text as it is (escaping them would show the escapes).
"""

from __future__ import annotations

import string
import unicodedata

_ACTIVE = frozenset(string.punctuation)
"""Every ASCII punctuation character: HTML's and markdown's active ones are all among them."""


def _safe_char(c: str) -> str:
    if c in _ACTIVE:
        # A numeric character reference is always literal text to markdown, never syntax.
        return f"&#{ord(c)};"
    if unicodedata.category(c) == "Cc":
        return "\ufffd"
    return c


def plain(text: object) -> str:
    """``text`` (``str()`` of it) as markdown that shows exactly its characters as text.

    Punctuation becomes numeric character references (no HTML, emphasis, link, image, table or
    web address can start), whitespace runs become one space (a newline would start a markdown
    block), other control characters become U+FFFD. Not for code spans, where markdown shows
    character references as they are written.
    """
    return "".join(_safe_char(c) for c in " ".join(str(text).split()))
