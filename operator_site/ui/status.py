"""The page's status panel, execution log and camera placeholder: text and images made from
the link's state, free of viser."""

from __future__ import annotations

import re

import cv2
import numpy as np

from operator_site.link import LinkStatus
from operator_site.ui.text import plain
from operator_site.ui.words import in_words, short_program_name

LOG_LINES = 40
"""Reports the log shows: a whole run of a long program."""
THINNED_SHARE = 0.9
"""Below this share of the camera's frames arriving, the status says the link thins them (a
frame lost now and then is not worth a line)."""


def waiting_image(width: int, height: int, text: str) -> np.ndarray:
    """A dark grey placeholder with ``text`` centred, (h, w, 3) uint8."""
    img = np.full((height, width, 3), 40, dtype=np.uint8)
    scale = width / 640
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
    cv2.putText(
        img,
        text,
        ((width - tw) // 2, (height + th) // 2),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        (200, 200, 200),
        2,
        cv2.LINE_AA,
    )
    return img


def control_words(status: LinkStatus, operator_id: str) -> str:
    """Who controls the robot, in words, for operator ``operator_id``."""
    if not status.holder:
        return "control: free (the next program sent takes it)"
    if status.holder == operator_id:
        return f"control: **you** (operator {plain(operator_id)})"
    return (
        f"control: operator **{plain(status.holder)}**; you watch (STOP still acts) until "
        "it lets go"
    )


def status_markdown(site_id: str, status: LinkStatus, operator_id: str = "") -> str:
    """The status panel's text for the link state ``status``, seen by ``operator_id``."""
    lines = [f"**work site: {status.label}** ({plain(site_id)})"]
    if status.work_site_alive:
        lines.append(control_words(status, operator_id))
    if status.work_site_alive:
        rates = f"robot state {status.state_rate_hz:.0f} Hz · camera {status.frame_rate_hz:.1f} Hz"
        if status.round_trip_s is not None:
            rates += f" · round trip {status.round_trip_s * 1e3:.0f} ms"
        lines.append(rates)
        if status.frame_share is not None and status.frame_share < THINNED_SHARE:
            lines.append(
                f"your link is slower than the camera: 1 frame in "
                f"{1.0 / status.frame_share:.0f} reaches you (the work site sends "
                "fewer and smaller frames until it keeps up)"
            )
    if status.last_frame_age_s is not None:
        # What the operator sees is this old: taken this long before it arrived, plus since.
        seen = f"last camera frame {status.last_frame_age_s:.1f} s ago"
        if status.frame_age_s is not None:
            seen += f", taken {status.frame_age_s + status.last_frame_age_s:.1f} s ago"
        lines.append(seen)
    if status.rejected:
        lines.append(f"⚠ {status.rejected} invalid messages rejected")
    if status.reports:
        r = status.reports[-1]
        # The status, not the message: the log below says it all, and this line is redrawn
        # twice a second.
        step = "" if r.command_index < 0 else f" step {r.command_index + 1}"
        lines.append(f"last report: {short_program_name(r.program_id)}{step} {plain(r.status)}")
    return "  \n".join(lines)


NEXT_STEP = {
    "failed": "The robot holds where it stopped. Next: *back off* if it presses something, "
    "*open the gripper* to let the block go, *go home*; then look at the camera, update the "
    "model from vision, and make the program again.",
    "stopped": "The robot holds where it stopped. Next: *resume*, *back off*, *open the "
    "gripper* or *go home* (below), or make a new program from here.",
    "refused": "Nothing moved. The line above says why; change the task or the model, and make "
    "the program again.",
}
"""What the operator may do after a program ends so, shown under its outcome."""

COMMAND_WORDS = {
    "guarded_grasp": "grasp the block",
    "move": "move",
    "guarded_move": "move into contact",
    "contact_move": "move keeping contact",
    "release": "let go",
    "open_gripper": "open the gripper",
}
"""A command's kind as the log says it."""
_FELT = re.compile(r"([A-Za-z0-9_.-]+) (-?[0-9.]+) N along")


def report_words(r) -> str:
    """One report as a line of the log (outside text escaped)."""
    if r.command_index < 0:
        if r.status == "accepted":
            return "checked and accepted by the work site"
        if r.status in NEXT_STEP or r.status == "done":
            return in_words(r.status, r.message).sentence
        return f"{plain(r.status)} {plain(r.message)}"
    step = f"step {r.command_index + 1}"
    if r.status == "started":
        if r.message in COMMAND_WORDS:
            return f"{step}: {COMMAND_WORDS[r.message]}"
        return f"{step}: {plain(r.message)}"  # e.g. "holding 54 g" after weighing the grasp
    if r.status == "contact_verified":
        felt = ", ".join(f"{plain(n)} {float(f):.1f} N" for n, f in _FELT.findall(r.message))
        return f"{step}: contact felt ({felt})" if felt else f"{step}: contact felt"
    if r.status == "done":
        return f"{step} done"
    return f"{step}: {plain(r.status)} {plain(r.message)}"


def log_markdown(reports) -> str:
    """The execution log, newest first: the newest program's outcome in words and what to do
    next when it ended badly, then the last :data:`LOG_LINES` reports."""
    if not reports:
        return "no program sent yet"
    lines = []
    last = reports[-1]
    if last.command_index == -1 and (last.status in NEXT_STEP or last.status == "done"):
        lines.append(f"**{short_program_name(last.program_id)}: {plain(last.status)}**")
        if last.status in NEXT_STEP:
            lines.append(f"➜ {NEXT_STEP[last.status]}")
    for r in reversed(reports[-LOG_LINES:]):
        lines.append(f"{short_program_name(r.program_id)} · {report_words(r)}")
    return "  \n".join(lines)


def log_details_markdown(reports) -> str:
    """The work site's own words for the same reports, newest first (the engineering detail
    behind the log's sentences)."""
    if not reports:
        return "nothing yet"
    lines = []
    for r in reversed(reports[-LOG_LINES:]):
        where = "program" if r.command_index < 0 else f"command {r.command_index}"
        lines.append(f"{plain(r.program_id)} {where}: **{plain(r.status)}** {plain(r.message)}")
    return "  \n".join(lines)
