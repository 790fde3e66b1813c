"""``work-site serve`` with deployment options: TLS certificates, access control, link lease.

Until ``work-site serve`` has these options itself, this runs the same server::

    python deploy/serve_work_site.py --listen tls/0.0.0.0:7447 --certs certs/ \\
        --operators operator --lease-ms 3000

``--certs DIR`` (made by ``deploy/make-certs.sh``) uses ``DIR/ca.pem`` and
``DIR/work-site.{pem,key}`` with mutual TLS; ``--operators CN ...`` turns on zenoh access control
so that only peers whose certificate common name is listed may send programs and stops. Every
option of ``work-site serve`` (``--site-id``, ``--no-camera``, ...) works as there.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from models.scene import load_scene  # noqa: E402
from protocol import DEFAULT_WORK_SITE_ENDPOINT  # noqa: E402
from protocol.session import (  # noqa: E402
    TlsFiles,
    link_endpoints,
    make_config,
    operator_only_access_control,
)
from work_site.cli import add_serve_arguments  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="serve_work_site", description=__doc__.split("\n\n")[0])
    add_serve_arguments(parser)
    parser.add_argument("--certs", type=Path, help="directory of deploy/make-certs.sh's output")
    parser.add_argument(
        "--cert-name", default="work-site", help="this site's certificate name (default work-site)"
    )
    parser.add_argument(
        "--operators",
        nargs="+",
        metavar="CN",
        help="certificate common names allowed to command (turns access control on)",
    )
    parser.add_argument("--lease-ms", type=int, help="zenoh link lease (ms; default 10000)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Serve until SIGINT/SIGTERM."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    from work_site.server import ServerOptions, WorkSiteServer

    listen, links_note = link_endpoints(
        args.listen if args.listen is not None else [DEFAULT_WORK_SITE_ENDPOINT], args.single_link
    )
    tls = None
    if args.certs is not None:
        tls = TlsFiles(
            args.certs / "ca.pem",
            args.certs / f"{args.cert_name}.pem",
            args.certs / f"{args.cert_name}.key",
        )
    acl = operator_only_access_control(args.site_id, args.operators) if args.operators else None
    if acl is not None and tls is None:
        print(
            "serve_work_site: --operators needs --certs (identities come from TLS)", file=sys.stderr
        )
        return 2
    config = make_config(
        listen=listen, connect=args.connect, tls=tls, access_control=acl, lease_ms=args.lease_ms
    )
    options = ServerOptions(
        site_id=args.site_id,
        physics_rate_hz=args.physics_rate,
        state_rate_hz=args.state_rate,
        camera=not args.no_camera,
        camera_supersample=args.camera_supersample,
    )
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    security = ("; mutual TLS" if tls else "") + (
        "; commands only from " + ", ".join(args.operators) if acl else ""
    )
    print(
        f"serve_work_site: site {args.site_id!r} on {', '.join(listen)} ({links_note}){security}",
        flush=True,
    )
    WorkSiteServer(load_scene(args.scene), config, options).run(stop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
