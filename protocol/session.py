"""The one place that builds ``zenoh.Config`` objects.

Loopback demo: the work site listens on :data:`DEFAULT_WORK_SITE_ENDPOINT` and the operator site
connects to it; multicast scouting is off. Each site pair uses two links (see
:func:`link_endpoints`): priorities 0-3 (stops, heartbeats, programs, reports, recognitions) on
the given port, 4-7 (robot state, camera frames) on the next one, so that neither image bytes
queued in one TCP connection nor a lost robot state's resend holds a command or a report back.
Behaviour worth knowing (zenoh 1.10): with multicast off, gossip scouting still runs over
established links; a peer whose ``connect`` endpoint is down keeps retrying in the background
rather than failing ``zenoh.open``; always ``close()`` sessions.
"""

from __future__ import annotations

import ipaddress
import json
import random
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from .errors import ProtocolError
from .keys import check_site_id

DEFAULT_WORK_SITE_ENDPOINT = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")
PRIORITY_RANGES = ("0-3", "4-7")
"""zenoh priorities carried by each link of a split: 0-3 (control, real_time, interactive_high
and _low: liveliness, stops, heartbeats, programs, reports, recognitions) and 4-7 (data_high …
background: robot state, ground truth, camera frames). TCP delivers in order, so over a lossy
link each lost packet holds up all that follows it on its connection for about a round trip:
robot states (a hundred a second) lose one often enough to hold many reports up, and a camera
frame holds back what follows it by its size. The streams go on a link of their own; zenoh's
queues still send a robot state before a camera frame waiting beside it. (A third link, state
apart from camera frames, was tried: zenoh 1.10 then noticed a cut link long after its lease;
deploy/README.md.) zenoh sends a priority that no link of a transport covers on the nearest
one, so a peer with a single link still gets everything."""
SPLIT_PROTOCOLS = ("tcp", "tls")
"""Link protocols whose endpoint can be split into two ports."""


def _endpoints(name: str, endpoints: Sequence[str]) -> list[str]:
    if isinstance(endpoints, str):  # a lone string would be split into characters
        raise ProtocolError(f"{name}: expected a sequence of endpoints, got a str")
    result = list(endpoints)
    for e in result:
        if not isinstance(e, str) or "/" not in e:
            raise ProtocolError(f"{name}: endpoint must look like 'tcp/host:port', got {e!r}")
    return result


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one site for zenoh's ``tls/`` endpoints.

    ``certificate``/``private_key`` identify this site both when it listens and when it
    connects; ``root_ca_certificate`` is the CA that the other side's certificate must chain to.
    ``mutual``: mutual TLS (zenoh's ``enable_mtls``; it must be true on BOTH sides, else the
    handshake fails with "peer sent no certificates"). The peer's certificate common name is
    the identity that :func:`operator_only_access_control` matches.
    """

    root_ca_certificate: str | Path
    certificate: str | Path
    private_key: str | Path
    mutual: bool = True

    @classmethod
    def in_dir(cls, directory: str | Path, name: str, ca: str = "ca.pem") -> TlsFiles:
        """``name``'s certificate and key in ``directory`` (``NAME.pem``, ``NAME.key``, as
        ``deploy/make-certs.sh`` writes them), with the CA's certificate ``ca`` there."""
        directory = Path(directory)
        return cls(directory / ca, directory / f"{name}.pem", directory / f"{name}.key")

    def __post_init__(self) -> None:
        for name in ("root_ca_certificate", "certificate", "private_key"):
            path = Path(getattr(self, name))
            if not path.is_file():
                raise ProtocolError(f"tls.{name}: no such file {str(path)!r}")


def operator_only_access_control(
    site_id: str, operators: Sequence[str] = ("operator",)
) -> dict[str, Any]:
    """zenoh ``access_control`` for a work site: only peers whose TLS certificate common name is
    in ``operators`` may put on ``telerobot/<site_id>/{program,stop,heartbeat}``; every
    authenticated peer may subscribe and receive what the work site publishes.

    Default deny: a message kind not listed is refused (zenoh 1.10 rule/subject/policy schema).
    """
    if isinstance(operators, str) or not operators:
        raise ProtocolError("operators: expected a non-empty sequence of common names")
    site = f"telerobot/{site_id}"
    observe = [
        "declare_subscriber",
        "declare_liveliness_subscriber",
        "liveliness_token",
        "liveliness_query",
    ]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "observe",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": observe,
                "key_exprs": [f"{site}/**"],
            },
            {
                "id": "telemetry",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put", "delete"],
                "key_exprs": [f"{site}/**"],
            },
            {
                "id": "command",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": [f"{site}/program", f"{site}/stop", f"{site}/heartbeat"],
            },
        ],
        "subjects": [
            {"id": "operators", "cert_common_names": list(operators)},
            {"id": "tls-peers", "link_protocols": ["tls"]},
        ],
        "policies": [
            {"id": "operators-command", "rules": ["command"], "subjects": ["operators"]},
            {"id": "peers-observe", "rules": ["observe", "telemetry"], "subjects": ["tls-peers"]},
        ],
    }


COMMAND_TOPICS = ("program", "stop", "heartbeat")
"""What an operator puts on a work site's keys (a work site's access control admits these)."""
TELEMETRY_TOPICS = ("camera", "recognitions", "robot_state", "report", "heartbeat", "truth")
"""What a work site puts on its own keys."""


@dataclass(frozen=True)
class Cell:
    """One work site behind a router: its ``site_id``, the common name of its certificate
    (``work_site``), those of the operators allowed to command it, and those of viewers allowed
    only to watch it. Nobody else sees anything of it."""

    site_id: str
    work_site: str
    operators: tuple[str, ...]
    viewers: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Cell:
        """``SITE=WORK_SITE_CN:OPERATOR_CN[,...][:VIEWER_CN[,...]]`` (the router's ``--cell``)."""
        site, eq, rest = text.partition("=")
        parts = rest.split(":")
        names = [tuple(n for n in part.split(",") if n) for part in parts[1:]]
        if not (eq and site and len(parts) in (2, 3) and parts[0] and names[0]):
            raise ProtocolError(
                "cell: expected SITE=WORK_SITE_CN:OPERATOR_CN[,...][:VIEWER_CN[,...]], "
                f"got {text!r}"
            )
        return cls(check_site_id(site), parts[0], *names)

    @property
    def members(self) -> tuple[str, ...]:
        """Every common name that may watch the cell."""
        return tuple(dict.fromkeys((self.work_site, *self.operators, *self.viewers)))


_OBSERVE_MESSAGES = (
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_token",
    "liveliness_query",
)


def router_access_control(cells: Sequence[Cell], relays: Sequence[str] = ()) -> dict[str, Any]:
    """zenoh ``access_control`` for a router joining several cells, with mutual TLS.

    Default deny, per cell: its members (:attr:`Cell.members`) may subscribe to its keys, see
    its liveliness and receive what is put on them; only its work site (certificate CN
    ``work_site``) may put on its :data:`TELEMETRY_TOPICS`, and only its ``operators`` on its
    :data:`COMMAND_TOPICS`. Anyone else's puts are dropped at the router, and a certificate
    that is in no cell sees nothing. A work site behind the router sees routed commands as
    coming from the router, so it admits the router's CN (``work-site serve --operators
    router``) and leaves the per-operator check to this. ``relays``: the common names of other
    routers meshed with this one, which pass everything on every cell both ways (each of them
    checks its own sites).
    """
    if not cells:
        raise ProtocolError("cells: expected at least one cell")
    if len({cell.site_id for cell in cells}) != len(cells):
        raise ProtocolError("cells: a site id is given twice")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def allow(
        name: str,
        flows: list[str],
        messages: Sequence[str],
        key_exprs: list[str],
        names: Sequence[str],
    ) -> None:
        rules.append(
            {"id": name, "permission": "allow", "flows": flows, "messages": list(messages),
             "key_exprs": key_exprs}
        )  # fmt: skip
        subjects.append({"id": name, "cert_common_names": list(names)})
        policies.append({"id": name, "rules": [name], "subjects": [name]})

    if relays:
        messages = [*_OBSERVE_MESSAGES, "put", "delete"]
        allow("relay", ["ingress", "egress"], messages, ["telerobot/**"], relays)
    for i, cell in enumerate(cells):
        site = f"telerobot/{cell.site_id}"
        allow(f"watch-{i}", ["ingress", "egress"], _OBSERVE_MESSAGES, [f"{site}/**"], cell.members)
        allow(f"receive-{i}", ["egress"], ["put", "delete"], [f"{site}/**"], cell.members)
        allow(f"telemetry-{i}", ["ingress"], ["put"], [f"{site}/{t}" for t in TELEMETRY_TOPICS],
              [cell.work_site])  # fmt: skip
        allow(f"command-{i}", ["ingress"], ["put"], [f"{site}/{t}" for t in COMMAND_TOPICS],
              cell.operators)  # fmt: skip
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def split_endpoints(
    host: str, ports: tuple[int, int], split: bool = True, protocol: str = "tcp"
) -> list[str]:
    """One endpoint, or two: priorities 0-3 on ``ports[0]`` and 4-7 on ``ports[1]`` (see
    :data:`PRIORITY_RANGES`)."""
    if not split:
        return [f"{protocol}/{host}:{ports[0]}"]
    return [
        f"{protocol}/{host}:{port}?prio={prio}"
        for port, prio in zip(ports, PRIORITY_RANGES, strict=True)
    ]


def derive_split(endpoint: str) -> list[str]:
    """``proto/host:port`` → ``[proto/host:port?prio=0-3, proto/host:port+1?prio=4-7]``.

    Raises :class:`ProtocolError` saying why when it cannot: a protocol other than tcp/tls, an
    endpoint that already carries metadata or config (``?``/``#``), or port 0 (the second port
    of an ephemeral one is unknown) or 65535.
    """
    protocol, _, address = endpoint.partition("/")
    if protocol not in SPLIT_PROTOCOLS:
        raise ProtocolError(f"{endpoint}: only {'/'.join(SPLIT_PROTOCOLS)} endpoints are split")
    if "?" in address or "#" in address:
        raise ProtocolError(f"{endpoint}: has its own metadata or config; used as given")
    host, sep, port_text = address.rpartition(":")
    if not sep or not host or not port_text.isdigit():
        raise ProtocolError(f"{endpoint}: expected {protocol}/host:port")
    port = int(port_text)
    if not 1 <= port <= 65534:
        raise ProtocolError(
            f"{endpoint}: port {port} has no next port to put robot state and camera frames on"
        )
    return split_endpoints(host, (port, port + 1), protocol=protocol)


def link_endpoints(endpoints: Sequence[str], single_link: bool = False) -> tuple[list[str], str]:
    """The endpoints a site uses for the user's ``endpoints``, and a note saying what it did.

    Each ``tcp``/``tls`` endpoint without metadata becomes two links (:func:`derive_split`:
    priorities 0-3 on its port, 4-7 on the next port), e.g. each of two meshed routers'. With
    ``single_link`` all are used as given; so is one that cannot be split (the note says why).
    Both sides must split alike to get two links; a site that does not still talks to one that
    does, over one link.
    """
    given = _endpoints("endpoints", endpoints)
    if single_link:
        return given, "one link for all priorities (--single-link)"
    used: list[str] = []
    unsplit: list[str] = []
    for endpoint in given:
        try:
            used += derive_split(endpoint)
        except ProtocolError as e:
            used.append(endpoint)
            unsplit.append(str(e))
    if not unsplit:
        return used, (
            "commands and reports on priorities 0-3, robot state and camera frames on 4-7 "
            "(port + 1)"
        )
    if len(given) == 1:
        return used, f"one link for all priorities: {unsplit[0]}"
    return used, f"split where possible; one link for all priorities: {'; '.join(unsplit)}"


LISTEN_PORTS_LOWEST = 10000
"""The lowest port :func:`free_port_pair` draws (below: well-known and registered services)."""
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Linux's range of ports given to outgoing connections."""


def free_port_pair(host: str = "127.0.0.1", tries: int = 100) -> int:
    """A TCP port on ``host`` such that nothing listens on it nor on the next one right now (a
    split site listens on both, :func:`derive_split`); RuntimeError after ``tries`` draws.

    Drawn below the kernel's ephemeral range where it is known: a port checked free there can
    still be taken by another process's outgoing connection before our listener binds it."""
    lo, hi = _listen_range()
    rng = random.Random()
    for _ in range(tries):
        if hi > lo:
            port = rng.randrange(lo, hi)
        else:  # no room below the ephemeral range: let the kernel choose
            with socket.socket() as probe:
                probe.bind((host, 0))
                port = int(probe.getsockname()[1])
            if port >= 65535:
                continue
        if _bindable(host, port) and _bindable(host, port + 1):
            return port
    raise RuntimeError(f"no two free consecutive TCP ports on {host} in {tries} tries")


def _listen_range() -> tuple[int, int]:
    """``[lo, hi)`` for the first port of a pair: from :data:`LISTEN_PORTS_LOWEST` up to the
    ephemeral range's start less one (its pair's second port stays below it); an empty range
    where the ephemeral range is not known."""
    try:
        first = int(EPHEMERAL_RANGE_FILE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0, 0
    return LISTEN_PORTS_LOWEST, first - 1


def _bindable(host: str, port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


SECURE_PROTOCOLS = ("tls", "quic")
"""Link protocols that carry TLS (with :class:`TlsFiles` they authenticate both sites)."""
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
"""Link protocols that never leave the machine."""


def is_loopback_endpoint(endpoint: str) -> bool:
    """Whether ``endpoint`` listens on this machine only: ``127.0.0.0/8``, ``::1``,
    ``localhost`` or a local-only protocol. Any other host (``0.0.0.0``, an interface's
    address, a name) counts as reachable from the network."""
    protocol, _, address = endpoint.partition("/")
    if protocol in LOCAL_PROTOCOLS:
        return True
    host = address.split("?", 1)[0].split("#", 1)[0].rpartition(":")[0].strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listeners(listen: Sequence[str], tls: TlsFiles | None, insecure: bool = False) -> None:
    """Refuse (:class:`ProtocolError`, one line naming the options to use) a listener on a
    non-loopback address that is not a TLS endpoint with certificates; ``insecure`` allows it
    (an isolated lab network). Loopback listeners need nothing."""
    if insecure:
        return
    for endpoint in listen:
        if is_loopback_endpoint(endpoint):
            continue
        protocol, _, address = endpoint.partition("/")
        if protocol in SECURE_PROTOCOLS and tls is not None:
            continue
        address = address.split("?", 1)[0].split("#", 1)[0]
        raise ProtocolError(
            f"refusing to listen on {endpoint} without TLS: a listener reachable from the "
            f"network must authenticate its peers; use --listen tls/{address} --certs DIR "
            "(make DIR with deploy/make-certs.sh), or --insecure on an isolated lab network"
        )


def max_links_for(listen: Sequence[str], connect: Sequence[str]) -> int:
    """Links one transport needs: 1, or as many as endpoints with a ``prio=`` range."""
    n = max(sum("prio=" in e for e in eps) for eps in (listen, connect))
    return max(n, 2) if n else 1


def add_security(
    conf: zenoh.Config,
    tls: TlsFiles | None = None,
    access_control: Mapping[str, Any] | None = None,
) -> None:
    """Put ``tls`` (certificates for ``tls/`` endpoints, :class:`TlsFiles`) and
    ``access_control`` (zenoh's section) into ``conf``; ProtocolError if zenoh refuses them."""
    if tls is not None:
        files = {
            "root_ca_certificate": tls.root_ca_certificate,
            "listen_certificate": tls.certificate,
            "listen_private_key": tls.private_key,
            "connect_certificate": tls.certificate,
            "connect_private_key": tls.private_key,
        }
        for name, path in files.items():
            conf.insert_json5(f"transport/link/tls/{name}", json.dumps(str(path)))
        conf.insert_json5("transport/link/tls/enable_mtls", json.dumps(bool(tls.mutual)))
    if access_control is not None:
        try:
            conf.insert_json5("access_control", json.dumps(dict(access_control)))
        except Exception as e:  # zenoh checks the schema here
            raise ProtocolError(f"access_control: {e}") from None


def make_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    shared_memory: bool = False,
    *,
    tls: TlsFiles | None = None,
    access_control: Mapping[str, Any] | None = None,
    lease_ms: int | None = None,
) -> zenoh.Config:
    """A zenoh config: ``mode``, the exact ``listen``/``connect`` endpoints, scouting and SHM.

    An empty ``listen`` means the session listens nowhere (zenoh's default would be every
    interface on a random port). Optional: ``tls`` (certificates for ``tls/`` endpoints, see
    :class:`TlsFiles`), ``access_control`` (zenoh's ``access_control`` section, e.g.
    :func:`operator_only_access_control`), ``lease_ms`` (link lease: a silent peer, e.g. behind a
    cut link, is declared gone after this long; zenoh's default is 10 s). Endpoints with a
    ``?prio=`` range (:func:`split_endpoints`) raise ``transport/unicast/max_links`` to their
    number, so that one transport may hold that many links.
    """
    if mode not in MODES:
        raise ProtocolError(f"mode: must be one of {list(MODES)}, got {mode!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(_endpoints("listen", listen)))
    conf.insert_json5("connect/endpoints", json.dumps(_endpoints("connect", connect)))
    if (links := max_links_for(listen, connect)) > 1:
        conf.insert_json5("transport/unicast/max_links", json.dumps(links))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(bool(shared_memory)))
    add_security(conf, tls, access_control)
    if lease_ms is not None:
        if not (isinstance(lease_ms, int) and 100 <= lease_ms <= 3_600_000):
            raise ProtocolError(f"lease_ms: expected an int in [100, 3600000], got {lease_ms!r}")
        conf.insert_json5("transport/link/tx/lease", json.dumps(lease_ms))
    return conf


def work_site_config(
    endpoint: str = DEFAULT_WORK_SITE_ENDPOINT, single_link: bool = False
) -> zenoh.Config:
    """The work site's config for the loopback demo: a peer listening on ``endpoint`` (split
    into two links by :func:`link_endpoints` unless ``single_link``)."""
    return make_config(listen=link_endpoints([endpoint], single_link)[0])


def operator_site_config(
    endpoint: str = DEFAULT_WORK_SITE_ENDPOINT, single_link: bool = False
) -> zenoh.Config:
    """The operator site's config for the loopback demo: a peer connecting to ``endpoint``
    (split into two links by :func:`link_endpoints` unless ``single_link``)."""
    return make_config(connect=link_endpoints([endpoint], single_link)[0])


def renewal_config(config: zenoh.Config) -> str:
    """``config`` as JSON5 for :func:`zenoh.Config.from_json5`, without a fixed session id: each
    session opened from it is a new peer to the others (see :class:`PeerWatch`)."""
    conf = json.loads(str(config))
    conf.pop("id", None)
    return json.dumps(conf)


class PeerWatch:
    """A peer's liveliness token as seen by one of our sessions, and whether that session is to
    be replaced by a new one.

    A peer that came back after a cut link must be met by a new session of ours, not the old
    one reconnecting. zenoh expires the links of a transport one by one: the side that gave up
    first reconnects under the same session id, and the other side, still holding a link of
    the old transport, adds the new links to it. That side then never declares its entities to
    us again (its liveliness token, its subscribers), and the key-expression ids each side uses
    differ: samples arrive under another key, or not at all, until a restart. A session with a
    new id is a new transport on both sides. So: the token was there, it went, and it is not
    back by the end of a drain: :attr:`lost` is set, and the owner opens a new session.
    """

    def __init__(self) -> None:
        self.alive = False
        self.lost = False

    def drain(self, subscriber) -> bool:
        """Take the liveliness samples waiting in ``subscriber``'s ring; returns whether the
        peer came (back) in them. Sets :attr:`lost` as the class says (until the owner
        clears it)."""
        came = went = False
        while (sample := subscriber.try_recv()) is not None:
            alive = sample.kind == zenoh.SampleKind.PUT
            came |= alive and not self.alive
            went |= self.alive and not alive
            self.alive = alive
        if went and not self.alive:
            self.lost = True
        return came
