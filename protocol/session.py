"""The one place that builds ``zenoh.Config`` objects.

Loopback demo: the work site listens on :data:`DEFAULT_WORK_SITE_ENDPOINT` and the operator site
connects to it; multicast scouting is off. Behaviour worth knowing (zenoh 1.10): with multicast off,
gossip scouting still runs over established links; a peer whose ``connect`` endpoint is down keeps
retrying in the background rather than failing ``zenoh.open``; always ``close()`` sessions.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

from .errors import ProtocolError

DEFAULT_WORK_SITE_ENDPOINT = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")


def _endpoints(name: str, endpoints: Sequence[str]) -> list[str]:
    if isinstance(endpoints, str):  # a lone string would be split into characters
        raise ProtocolError(f"{name}: expected a sequence of endpoints, got a str")
    result = list(endpoints)
    for e in result:
        if not isinstance(e, str) or "/" not in e:
            raise ProtocolError(f"{name}: endpoint must look like 'tcp/host:port', got {e!r}")
    return result


def make_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    shared_memory: bool = False,
) -> zenoh.Config:
    """A zenoh config: ``mode``, the exact ``listen``/``connect`` endpoints, scouting and SHM.

    An empty ``listen`` means the session listens nowhere (zenoh's default would be every
    interface on a random port).
    """
    if mode not in MODES:
        raise ProtocolError(f"mode: must be one of {list(MODES)}, got {mode!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(_endpoints("listen", listen)))
    conf.insert_json5("connect/endpoints", json.dumps(_endpoints("connect", connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(bool(shared_memory)))
    return conf


def work_site_config(endpoint: str = DEFAULT_WORK_SITE_ENDPOINT) -> zenoh.Config:
    """The work site's config for the loopback demo: a peer listening on ``endpoint``."""
    return make_config(listen=(endpoint,))


def operator_site_config(endpoint: str = DEFAULT_WORK_SITE_ENDPOINT) -> zenoh.Config:
    """The operator site's config for the loopback demo: a peer connecting to ``endpoint``."""
    return make_config(connect=(endpoint,))
