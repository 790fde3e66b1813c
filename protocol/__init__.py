"""The wire protocol shared by both sites: messages, the msgpack codec, key expressions and the
zenoh session configuration. See ``protocol/README.md`` for frames, units and the wire format."""

from ._spec import HOMOGENEOUS_ROW_TOL, ROTATION_ORTHONORMAL_TOL, UNIT_NORMAL_TOL
from .codec import MAX_PAYLOAD_BYTES, decode, encode
from .errors import ProtocolError
from .keys import (
    DEFAULT_SITE_ID,
    KEY_PREFIX,
    TOPIC_MESSAGE_TYPES,
    TOPICS,
    alive_key,
    check_site_id,
    key,
)
from .messages import (
    MESSAGE_TYPES,
    MOTION_KINDS,
    REPORT_STATUSES,
    ROLES,
    SCHEMA_VERSION,
    CameraFrame,
    ContactState,
    ExecutionReport,
    Heartbeat,
    Message,
    MotionCommand,
    MotionProgram,
    Recognition,
    Recognitions,
    RobotState,
    Stop,
)
from .session import (
    DEFAULT_WORK_SITE_ENDPOINT,
    make_config,
    operator_site_config,
    work_site_config,
)

__all__ = [
    "DEFAULT_SITE_ID",
    "DEFAULT_WORK_SITE_ENDPOINT",
    "HOMOGENEOUS_ROW_TOL",
    "KEY_PREFIX",
    "MAX_PAYLOAD_BYTES",
    "MESSAGE_TYPES",
    "MOTION_KINDS",
    "REPORT_STATUSES",
    "ROLES",
    "ROTATION_ORTHONORMAL_TOL",
    "SCHEMA_VERSION",
    "TOPICS",
    "TOPIC_MESSAGE_TYPES",
    "UNIT_NORMAL_TOL",
    "CameraFrame",
    "ContactState",
    "ExecutionReport",
    "Heartbeat",
    "Message",
    "MotionCommand",
    "MotionProgram",
    "ProtocolError",
    "Recognition",
    "Recognitions",
    "RobotState",
    "Stop",
    "alive_key",
    "check_site_id",
    "decode",
    "encode",
    "key",
    "make_config",
    "operator_site_config",
    "work_site_config",
]
