"""A zenoh router from the zenoh Python package (no zenohd needed), for several sites.

    python deploy/router.py deploy/zenoh/router.json5 [--listen tcp/0.0.0.0:7447]

Runs until SIGINT/SIGTERM. ``--listen`` replaces the config's listen endpoints.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

import zenoh


def main(argv: list[str] | None = None) -> int:
    """Open a session in router mode and keep it open until a signal."""
    parser = argparse.ArgumentParser(prog="router", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", type=Path, help="zenoh JSON5 config (mode: router)")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT", help="repeatable")
    args = parser.parse_args(argv)
    conf = zenoh.Config.from_file(str(args.config))
    if json.loads(conf.get_json("mode")) != "router":
        print(f"router: {args.config} does not say mode: router", file=sys.stderr)
        return 2
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with zenoh.open(conf):
        print(f"router: up on {conf.get_json('listen/endpoints')}", flush=True)
        while not stop.wait(0.5):  # a timeout, so that the signal handlers get to run
            pass
    print("router: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
