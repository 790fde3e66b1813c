"""A minimal operator-site process (tests, benchmarks): connect, send one program, print its
reports.

    python -m bench.operator_process ENDPOINT SITE_ID PROGRAM_ID X,Y,Z [X,Y,Z ...]

Sends a program of straight moves of the gripper (pointing down) through the given points at
``--speed`` with ``operator_site.link.WorkSiteLink`` (which re-sends it until the work site
answers) and prints one JSON line per report as it is received,
``{"i": command_index, "status": ..., "stamp_s": ..., "message": ...}``, until the program's
final report; then ``{"end": true, "reports": [[i, status], ...], "pending": [...]}`` with the
reports in the order the link gives them. Killed at any point, it loses nothing
the work site keeps: a new process sending the same id gets every report again.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import sys
import time

from bench.netsafety import moves_program
from operator_site.link import FINAL_STATUSES, WorkSiteLink
from protocol import make_config


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="operator_process")
    parser.add_argument("endpoint")
    parser.add_argument("site_id")
    parser.add_argument("program_id")
    parser.add_argument("points", nargs="+", metavar="X,Y,Z")
    parser.add_argument("--speed", type=float, default=0.05)
    parser.add_argument("--timeout", type=float, default=120.0)
    parser.add_argument(
        "--send-after-a-report",
        action="store_true",
        help="send only once a live report of this program has arrived (an operator that "
        "comes back while its program runs: the replay then arrives after newer reports)",
    )
    parser.add_argument("--operator-id", help="who it is to the work site's control lease")
    parser.add_argument(
        "--hold-interpreter-s",
        type=float,
        default=0.0,
        help="once the program's first report has come, hold the interpreter this long (a C "
        "call that does not release it: a stall that the heartbeat thread cannot run through)",
    )
    args = parser.parse_args(argv)
    points = [[float(v) for v in p.split(",")] for p in args.points]
    program = moves_program(args.program_id, points, args.speed)
    link = WorkSiteLink(make_config(connect=[args.endpoint]), args.site_id, args.operator_id)
    try:
        deadline = time.monotonic() + args.timeout
        while link.status.label != "connected":
            if time.monotonic() > deadline:
                print(json.dumps({"error": "not connected"}), flush=True)
                return 1
            link.poll()
            time.sleep(0.01)
        if args.send_after_a_report:
            while not any(r.program_id == args.program_id for r in link.status.reports):
                if time.monotonic() > deadline:
                    print(json.dumps({"error": "no live report"}), flush=True)
                    return 1
                link.poll()
                time.sleep(0.005)
        link.send_program(program)
        printed: set[int] = set()
        while time.monotonic() < deadline:
            link.poll()
            mine = [r for r in link.status.reports if r.program_id == args.program_id]
            if mine and args.hold_interpreter_s > 0:
                # PyDLL keeps the interpreter lock through the call (CDLL would release it).
                ctypes.PyDLL(None).usleep(round(1e6 * args.hold_interpreter_s))
                args.hold_interpreter_s = 0.0
            for r in mine:
                if id(r) not in printed:
                    printed.add(id(r))
                    line = {"i": r.command_index, "status": r.status, "stamp_s": r.stamp_s,
                            "message": r.message}  # fmt: skip
                    print(json.dumps(line), flush=True)
            if any(r.command_index == -1 and r.status in FINAL_STATUSES for r in mine):
                end = {
                    "end": True,
                    "reports": [[r.command_index, r.status] for r in mine],
                    "pending": link.pending_programs(),
                }
                print(json.dumps(end), flush=True)
                return 0
            time.sleep(0.005)
        print(json.dumps({"error": "timeout"}), flush=True)
        return 1
    finally:
        link.close()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
