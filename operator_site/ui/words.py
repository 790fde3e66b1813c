"""The work site's reports in words an operator understands, free of viser.

A report's message is engineering output ("command 3: contact with frame not verified: 0.0 N
along its normal, below 1.0 N (wrist force …)"). :func:`in_words` turns the ones the work site
sends into a sentence about the block and the robot, and keeps the message itself as the
detail, which the page shows one click away. A message it does not know is shown as it is:
never hidden, never guessed at.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from operator_site.ui.text import plain

STEP = re.compile(r"^command (\d+)(?: \([a-z_]+\))?: ")
"""How the work site names the command a message is about (0-based)."""

# (pattern on the message after its command prefix, sentence; ``{0}`` … are the groups, each
# through plain()). First match wins.
_FAILURES: tuple[tuple[re.Pattern[str], str], ...] = tuple(
    (re.compile(p), s)
    for p, s in (
        (
            r"^contact with (\S+) not verified",
            "the block did not press on the {0} as the program expected: the wrist felt too "
            "little force there. The block or the {0} may lie a little off from where the "
            "model has them.",
        ),
        (
            r"^reached its target without contact",
            "the block reached the end of a move without touching what it should have "
            "touched: the model is off by more than the program allows.",
        ),
        (
            r"^nothing between the\s+fingers",
            "the gripper closed on nothing: the block is not where the model has it.",
        ),
        (
            r"^the fingers closed to [\d.]+ mm where the (\S+) is",
            "the gripper closed on something narrower or wider than the {0}: it holds the "
            "{0} across an edge or a corner, or another block. It opened again and withdrew; "
            "the {0} is likely not where the model has it.",
        ),
        (
            r"^holding \d+ g where the (\S+) weighs",
            "the gripper lifted something that does not weigh what the {0} does: another "
            "block, most likely, where the model has the {0}. The robot set it back down and "
            "withdrew.",
        ),
        (
            r"^the (\S+)'s weight pulls",
            "the {0} hangs in the gripper off from where the model has it: it is held "
            "elsewhere along it, or lies turned from the model's pose. The robot set it back "
            "down and withdrew.",
        ),
        (
            r"^the fingers touched something on the way down",
            "the gripper touched something on its way down to the block, so it stopped "
            "before grasping.",
        ),
        (
            r"^external force [\d.]+ N exceeds the limit",
            "the robot met more force than it may push with and stopped: something was in "
            "the way or pressed too hard.",
        ),
        (
            r"^contact did not settle",
            "the block did not come to rest against what it should touch in the time allowed.",
        ),
        (
            r"^on the way[:,] .*would swing",
            "the arm cannot follow this path without swinging to another arm configuration.",
        ),
        (
            r"^on the way[:,] ",
            "the arm cannot reach every pose along this path.",
        ),
        (
            r"^gripper target .* is outside the\s+workspace",
            "a pose of the program lies outside the robot's work area.",
        ),
        (
            r"^the program's moves would take more than",
            "the program is longer than the work site runs in one go; make a shorter task.",
        ),
        (
            r"^nothing is held",
            "the program moves a block before it grasps one.",
        ),
        (
            r"^busy with program",
            "the robot is busy with another program: wait for it to end, or stop it.",
        ),
    )
)

_STOPS: tuple[tuple[re.Pattern[str], str], ...] = tuple(
    (re.compile(p), s)
    for p, s in (
        (r"operator pressed stop", "You stopped the robot."),
        (
            r"^no heartbeat from the operator",
            "The work site heard nothing from this page for too long, so it stopped the robot "
            "itself (the network link or this page stalled).",
        ),
        (r"^work-site fault", "The work site had an internal fault and stopped the robot."),
        (r"^stop: ", "A stop was sent to the work site."),
    )
)


@dataclass(frozen=True)
class Words:
    """A report in words: ``sentence`` for the operator (markdown, outside text escaped),
    ``detail`` the work site's own message (escaped), empty when the sentence says it all."""

    sentence: str
    detail: str = ""


def step_of(message: str) -> int | None:
    """The 1-based step a message is about (the page numbers commands from 1), or None."""
    m = STEP.match(message)
    return int(m.group(1)) + 1 if m else None


def failure_words(message: str) -> str:
    """Why a program failed or was refused, as a sentence about the block and the robot; the
    message itself (escaped) when it is not one the work site is known to send."""
    step = step_of(message)
    rest = STEP.sub("", message, count=1)
    where = f"At step {step}, " if step is not None else ""
    for pattern, sentence in _FAILURES:
        m = pattern.search(rest)
        if m:
            text = sentence.format(*(plain(g) for g in m.groups()))
            return where + text if where else text[0].upper() + text[1:]
    return (where + plain(rest)) if where else plain(message)


def in_words(status: str, message: str) -> Words:
    """A whole-program report (``status`` done, failed, refused or stopped) in words."""
    detail = plain(message)
    if status == "done":
        return Words("Done: the robot did the whole program.")
    if status == "failed":
        return Words("The robot stopped the program. " + failure_words(message), detail)
    if status == "refused":
        return Words(
            "The work site refused the program before moving. " + failure_words(message), detail
        )
    if status == "stopped":
        for pattern, sentence in _STOPS:
            if pattern.search(message):
                return Words(sentence, detail)
        return Words("The robot was stopped.", detail)
    return Words(f"{plain(status)}: {detail}")


SHORT_ID = re.compile(r"^(?P<label>.+?)-\d{9,}-(?P<n>\d+)$")
"""The ids :meth:`~operator_site.session.OperatorSession.new_program_id` makes:
label, the session's start in epoch seconds, a running number."""


def short_program_name(program_id: str) -> str:
    """A program's name as the page shows it ("cube #2" for ``cube-1795746506-2``), escaped;
    an id made elsewhere as it is."""
    m = SHORT_ID.match(program_id)
    if not m:
        return plain(program_id)
    return f"{plain(m.group('label'))} #{m.group('n')}"
