"""A zenoh router from the zenoh Python package (no zenohd needed), for several sites.

    python deploy/router.py deploy/zenoh/router.json5 [--listen ENDPOINT] [--connect ENDPOINT]
        [--single-link]
        [--certs DIR [--cert-name router] --cell SITE=WORK_SITE_CN:OPERATORS[:VIEWERS] ...]
        [--insecure]

Runs until SIGINT/SIGTERM. ``--listen`` replaces the config's listen endpoints. Like the sites
(protocol/session.py, ``link_endpoints``), one tcp/tls endpoint HOST:PORT becomes two listeners:
priorities 0-3 (commands, reports) on PORT and 4-7 (robot state, camera frames) on PORT+1, so
that the sites' default split links reach it; ``--single-link`` keeps the one port.
``--connect`` meshes it with another router, over one link (everything shares it between
routers): a site connected to either reaches the sites of both, and a site given both routers'
endpoints goes on through one when the other fails.

Like a work site, the router refuses a listener reachable from the network unless it is a
``tls/`` endpoint with ``--certs`` (mutual TLS: only holders of the CA's certificates connect),
or ``--insecure`` (an isolated lab). ``--cell`` turns on access control
(``protocol.session.router_access_control``, default deny): per cell, only its work site's
certificate may publish its telemetry, only its operators' certificates (comma-separated common
names) may send it programs and stops, and only they and its viewers may watch it.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

import zenoh

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from protocol.errors import ProtocolError  # noqa: E402
from protocol.session import (  # noqa: E402
    Cell,
    TlsFiles,
    add_security,
    check_listeners,
    link_endpoints,
    max_links_for,
    router_access_control,
)


def _cell(text: str) -> Cell:
    try:
        return Cell.parse(text)
    except ProtocolError as e:  # argparse prints an ArgumentTypeError's own message
        raise argparse.ArgumentTypeError(str(e)) from None


def main(argv: list[str] | None = None) -> int:
    """Open a session in router mode and keep it open until a signal."""
    parser = argparse.ArgumentParser(prog="router", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", type=Path, help="zenoh JSON5 config (mode: router)")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT", help="repeatable")
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="another router to mesh with, over one link (repeatable)",
    )
    parser.add_argument(
        "--single-link",
        action="store_true",
        help="listen on one port for all priorities (sites must then use --single-link too)",
    )
    parser.add_argument(
        "--certs",
        type=Path,
        metavar="DIR",
        help="mutual TLS with DIR/ca.pem and DIR/NAME.{pem,key} (deploy/make-certs.sh)",
    )
    parser.add_argument(
        "--cert-name", default="router", help="the router's certificate (default: %(default)s)"
    )
    parser.add_argument(
        "--cell",
        action="append",
        type=_cell,
        default=[],
        metavar="SITE=WORK_SITE_CN:OPERATOR_CN[,...][:VIEWER_CN[,...]]",
        help="access control for one cell: who publishes its telemetry, who commands it, who "
        "may only watch it; nobody else sees it (repeatable; needs --certs)",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow a plain listener on the network (an isolated lab network only)",
    )
    args = parser.parse_args(argv)
    try:
        conf = zenoh.Config.from_file(str(args.config))
    except Exception as e:  # zenoh raises its own error type for a missing or bad file
        print(f"router: cannot read {args.config}: {e}", file=sys.stderr)
        return 2
    if json.loads(conf.get_json("mode")) != "router":
        print(f"router: {args.config} does not say mode: router", file=sys.stderr)
        return 2
    given = args.listen or json.loads(conf.get_json("listen/endpoints"))
    listen, note = link_endpoints(given, args.single_link)
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    # Routers mesh over one link each: over two (split by priority, like the sites'), the
    # routers' link-state messages were seen to lose their order under TLS ("unknown link
    # mapping", "unknown routing context") and a meshed router never learnt a cell.
    connect, _ = link_endpoints(args.connect, single_link=True)
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    if (links := max_links_for(listen, connect)) > 1:
        conf.insert_json5("transport/unicast/max_links", json.dumps(links))
    try:
        tls = None
        if args.certs is not None:
            tls = TlsFiles.in_dir(args.certs, args.cert_name)
        if args.cell and tls is None:
            raise ProtocolError("--cell needs --certs (identities come from TLS certificates)")
        check_listeners(given, tls, args.insecure)
        # Peers presenting this router's own certificate are the other routers of its mesh.
        acl = router_access_control(args.cell, relays=[args.cert_name]) if args.cell else None
        add_security(conf, tls, acl)
    except ProtocolError as e:
        print(f"router: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:  # e.g. a port in use
        print(f"router: cannot start on {', '.join(listen)}: {e}", file=sys.stderr)
        return 2
    with session:
        print(
            f"router: up on {', '.join(listen)} ({note})"
            + (f"; meshed with {', '.join(connect)}" if connect else "")
            + ("; mutual TLS" if tls else "")
            + (f"; cells {', '.join(c.site_id for c in args.cell)}" if args.cell else "")
            + ("; --insecure" if args.insecure else ""),
            flush=True,
        )
        while not stop.wait(0.5):  # a timeout, so that the signal handlers get to run
            pass
    print("router: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
