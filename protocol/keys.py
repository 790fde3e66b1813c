"""Zenoh key expressions: ``telerobot/<site_id>/<topic>`` and ``telerobot/<site_id>/alive/<role>``.

One site id names one work cell (one robot and the operator programming it); every topic of that
cell lives under ``telerobot/<site_id>/``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from .errors import ProtocolError
from .messages import (
    MAX_NAME_LEN,
    ROLES,
    SITE_ID_PATTERN,
    CameraFrame,
    ExecutionReport,
    Heartbeat,
    Message,
    MotionProgram,
    Recognitions,
    RobotState,
    Stop,
    TruthPoses,
)

KEY_PREFIX = "telerobot"
DEFAULT_SITE_ID = "site1"

TOPIC_MESSAGE_TYPES: Mapping[str, type[Message]] = {
    "camera": CameraFrame,
    "recognitions": Recognitions,
    "robot_state": RobotState,
    "program": MotionProgram,
    "report": ExecutionReport,
    "stop": Stop,
    "heartbeat": Heartbeat,
    "truth": TruthPoses,
}
"""The one message type published on each topic."""

TOPICS: tuple[str, ...] = tuple(TOPIC_MESSAGE_TYPES)

_SITE_ID_RE = re.compile(SITE_ID_PATTERN)


def check_site_id(site_id: str) -> str:
    """Return ``site_id`` if it is a valid site id (``[A-Za-z0-9_-]+``, ≤ 256 characters)."""
    if not isinstance(site_id, str):
        raise ProtocolError(f"site_id: expected str, got {type(site_id).__name__}")
    if len(site_id) > MAX_NAME_LEN or _SITE_ID_RE.fullmatch(site_id) is None:
        raise ProtocolError(
            f"site_id: must match {SITE_ID_PATTERN} (at most {MAX_NAME_LEN} characters), "
            f"got {site_id[:40]!r}"
        )
    return site_id


def key(site_id: str, topic: str) -> str:
    """The key expression ``telerobot/<site_id>/<topic>`` for one of :data:`TOPICS`."""
    check_site_id(site_id)
    if topic not in TOPIC_MESSAGE_TYPES:
        raise ProtocolError(f"topic: must be one of {list(TOPICS)}, got {topic!r}")
    return f"{KEY_PREFIX}/{site_id}/{topic}"


def alive_key(site_id: str, role: str) -> str:
    """The liveliness token key ``telerobot/<site_id>/alive/<role>`` for one of ``ROLES``."""
    check_site_id(site_id)
    if role not in ROLES:
        raise ProtocolError(f"role: must be one of {list(ROLES)}, got {role!r}")
    return f"{KEY_PREFIX}/{site_id}/alive/{role}"
