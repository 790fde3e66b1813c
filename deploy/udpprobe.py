"""udpprobe: measure a link's round-trip delay, loss and reordering with UDP datagrams.

``python deploy/udpprobe.py echo --port 9999`` answers every datagram with itself;
``python deploy/udpprobe.py probe HOST --port 9999 --count 2000`` sends numbered datagrams at a
fixed interval and prints one JSON line: round trips (ms: median, p99, min, max), the fraction
that came back, and how many came back out of order. Used to test ``linkemu`` and to check a
deployed link (``ip netns exec tr-ops python deploy/udpprobe.py probe 10.77.0.2``).
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import struct
import sys
import time

HEADER = struct.Struct("!Qd")  # sequence number, send time (perf_counter, s)


def echo(port: int, host: str = "0.0.0.0") -> None:
    """Answer every datagram on ``host:port`` with itself, forever. Prints ``ready`` once bound,
    so that a caller can wait for it instead of racing the first probe."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, port))
        print("ready", flush=True)
        while True:
            data, addr = sock.recvfrom(65536)
            sock.sendto(data, addr)


def probe(
    host: str, port: int, count: int, interval_s: float, size: int, wait_s: float
) -> dict[str, float | int]:
    """Send ``count`` datagrams of ``size`` bytes every ``interval_s`` to an echo; then wait
    ``wait_s`` for stragglers. Returns the figures described in the module docstring."""
    size = max(size, HEADER.size)
    rtts_ms: list[float] = []
    reordered = 0
    highest = -1
    seen: set[int] = set()

    def receive(sock: socket.socket) -> None:
        nonlocal reordered, highest
        while True:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return
            except ConnectionRefusedError:  # ICMP "port unreachable": that datagram is lost
                continue
            seq, sent = HEADER.unpack_from(data)
            if seq in seen:  # a duplicate is not a second answer
                continue
            seen.add(seq)
            rtts_ms.append((time.perf_counter() - sent) * 1000.0)
            if seq < highest:
                reordered += 1
            highest = max(highest, seq)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((host, port))
        sock.setblocking(False)
        pad = b"\0" * (size - HEADER.size)
        next_s = time.perf_counter()
        for seq in range(count):
            sock.send(HEADER.pack(seq, time.perf_counter()) + pad)
            next_s += interval_s
            while (now := time.perf_counter()) < next_s:
                receive(sock)
                time.sleep(min(0.0005, next_s - now))
        deadline = time.perf_counter() + wait_s
        while time.perf_counter() < deadline and len(seen) < count:
            receive(sock)
            time.sleep(0.001)
        receive(sock)
    rtts_ms.sort()
    n = len(rtts_ms)
    return {
        "sent": count,
        "received": n,
        "received_fraction": n / count if count else 0.0,
        "reordered": reordered,
        "rtt_ms_median": statistics.median(rtts_ms) if n else float("nan"),
        "rtt_ms_p99": rtts_ms[min(n - 1, int(0.99 * n))] if n else float("nan"),
        "rtt_ms_min": rtts_ms[0] if n else float("nan"),
        "rtt_ms_max": rtts_ms[-1] if n else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    """``echo`` or ``probe``; see the module docstring."""
    parser = argparse.ArgumentParser(prog="udpprobe", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    e = sub.add_parser("echo", help="answer datagrams forever")
    e.add_argument("--port", type=int, default=9999)
    p = sub.add_parser("probe", help="measure round trips, loss and reordering to an echo")
    p.add_argument("host")
    p.add_argument("--port", type=int, default=9999)
    p.add_argument("--count", type=int, default=1000, help="datagrams to send (default 1000)")
    p.add_argument("--interval-ms", type=float, default=1.0, help="between sends (default 1)")
    p.add_argument("--size", type=int, default=100, help="datagram bytes (default 100)")
    p.add_argument("--wait-ms", type=float, default=1000.0, help="wait for the last answers")
    args = parser.parse_args(argv)
    if args.command == "echo":
        echo(args.port)
        return 0
    result = probe(
        args.host, args.port, args.count, args.interval_ms / 1000.0, args.size, args.wait_ms / 1e3
    )
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
