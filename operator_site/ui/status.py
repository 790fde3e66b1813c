"""The page's status panel, execution log and camera placeholder: text and images made from
the link's state, free of viser."""

from __future__ import annotations

import cv2
import numpy as np

from operator_site.link import LinkStatus
from operator_site.ui.text import plain

LOG_LINES = 8


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
        lines.append(
            f"robot state {status.state_rate_hz:.0f} Hz · camera {status.frame_rate_hz:.1f} Hz"
        )
    if status.last_frame_age_s is not None:
        lines.append(f"last camera frame {status.last_frame_age_s:.1f} s ago")
    if status.rejected:
        lines.append(f"⚠ {status.rejected} invalid messages rejected")
    if status.reports:
        r = status.reports[-1]
        lines.append(
            f"last report: program {plain(r.program_id)} {plain(r.status)}: {plain(r.message)}"
        )
    return "  \n".join(lines)


NEXT_STEP = {
    "failed": "The robot holds where it stopped. Next: *back off* if it presses something, "
    "*open the gripper* to let the block go, *go home*; then check the camera and the model.",
    "stopped": "The robot holds where it stopped. Next: *back off*, *open the gripper* or "
    "*go home* (Program panel), or make a new program from here.",
    "refused": "Nothing moved. The line above says why; change the task or the model, and make "
    "the program again.",
}
"""What the operator may do after a program ends so, shown under the log."""


def log_markdown(reports) -> str:
    """The execution log: the last :data:`LOG_LINES` reports, newest last, and what to do
    next when the newest program ended badly."""
    if not reports:
        return "no program sent yet"
    lines = []
    for r in reports[-LOG_LINES:]:
        where = "program" if r.command_index < 0 else f"command {r.command_index}"
        lines.append(f"{plain(r.program_id)} {where}: **{plain(r.status)}** {plain(r.message)}")
    last = reports[-1]
    if last.command_index == -1 and last.status in NEXT_STEP:
        lines.append(f"➜ {NEXT_STEP[last.status]}")
    return "  \n".join(lines)
