"""Two network namespaces joined by the emulated link of ``deploy/linkemu.py``.

``<prefix>-ops`` (the operator site, 10.77.0.1) and ``<prefix>-work`` (the work site, 10.77.0.2)
each hold a persistent TUN device ``trlink`` (plus ``lo``); the relay, running in the root
namespace, carries packets between the two devices with the configured delay, jitter and loss.
The relay can be restarted with other parameters while the namespaces stay.

Command line (root)::

    python deploy/netns.py up --delay-ms 50 --loss 0.01     # until Ctrl-C, then tears down
    ip netns exec tr-work .venv/bin/work-site serve --listen tcp/10.77.0.2:7447
    ip netns exec tr-ops  .venv/bin/operator-site ... --connect tcp/10.77.0.2:7447
    python deploy/netns.py down                             # removes leftovers

From Python: ``with emulated_link(delay_ms=50, loss=0.01) as link: ...``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

LINKEMU = Path(__file__).resolve().with_name("linkemu.py")
DEVICE = "trlink"
OPS_ADDR = "10.77.0.1"
WORK_ADDR = "10.77.0.2"
PREFIX_LEN = 24
READY_TIMEOUT_S = 10.0


def unavailable_reason() -> str | None:
    """Why namespaces with the emulated link cannot be made here, or None if they can."""
    if os.geteuid() != 0:
        return "needs root (ip netns, setns, /dev/net/tun)"
    if not os.path.exists("/dev/net/tun"):
        return "no /dev/net/tun"
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    if not os.path.isdir("/proc/self/ns"):
        return "no network namespaces (/proc/self/ns)"
    return None


@dataclass(frozen=True)
class NetnsPair:
    """The names and addresses of one pair of namespaces."""

    prefix: str = "tr"

    @property
    def ops(self) -> str:
        """The operator site's namespace."""
        return f"{self.prefix}-ops"

    @property
    def work(self) -> str:
        """The work site's namespace."""
        return f"{self.prefix}-work"

    def exec_argv(self, ns: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside namespace ``ns``."""
        return ["ip", "netns", "exec", ns, *argv]


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def create(pair: NetnsPair, mtu: int = 1500) -> None:
    """Make both namespaces with ``lo`` up and an addressed, persistent TUN device each.
    Leftovers of an earlier run with the same prefix are removed first."""
    destroy(pair)
    try:
        for ns, addr in ((pair.ops, OPS_ADDR), (pair.work, WORK_ADDR)):
            _ip("netns", "add", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "tuntap", "add", "dev", DEVICE, "mode", "tun")
            _ip("-n", ns, "link", "set", DEVICE, "mtu", str(mtu))
            _ip("-n", ns, "addr", "add", f"{addr}/{PREFIX_LEN}", "dev", DEVICE)
            _ip("-n", ns, "link", "set", DEVICE, "up")
    except subprocess.CalledProcessError as e:
        destroy(pair)
        raise RuntimeError(f"netns: `{' '.join(e.cmd)}` failed: {e.stderr.strip()}") from e


def destroy(pair: NetnsPair) -> None:
    """Remove both namespaces (and with them their devices); missing ones are fine."""
    for ns in (pair.ops, pair.work):
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)


def link_args(
    delay_ms: float = 0.0,
    jitter_ms: float = 0.0,
    loss: float = 0.0,
    seed: int = 1,
    rate_mbit: float = 0.0,
    queue_ms: float = 100.0,
    fifo: bool = False,
) -> list[str]:
    """linkemu's options for these link parameters."""
    args = [
        f"--delay-ms={delay_ms}",
        f"--jitter-ms={jitter_ms}",
        f"--loss={loss}",
        f"--seed={seed}",
        f"--rate-mbit={rate_mbit}",
        f"--queue-ms={queue_ms}",
    ]
    return [*args, "--fifo"] if fifo else args


def start_relay(pair: NetnsPair, args: Sequence[str]) -> subprocess.Popen:
    """Start linkemu between the pair's devices; returns once it says it is ready."""
    proc = subprocess.Popen(
        [
            sys.executable,
            str(LINKEMU),
            f"--ns-a={pair.ops}",
            f"--dev-a={DEVICE}",
            f"--ns-b={pair.work}",
            f"--dev-b={DEVICE}",
            *args,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline() if proc.stdout else ""
    if line.strip() != "linkemu: ready":
        proc.kill()
        _, err = proc.communicate(timeout=READY_TIMEOUT_S)
        raise RuntimeError(f"linkemu did not start: {line.strip()} {err.strip()}")
    return proc


def stop_relay(proc: subprocess.Popen) -> dict[str, int]:
    """Stop linkemu; returns its packet counters (empty if it died)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=5.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    lines = [ln for ln in (out or "").splitlines() if ln.startswith("{")]
    return json.loads(lines[-1]) if lines else {}


class EmulatedLink:
    """A live pair of namespaces and its relay; see :func:`emulated_link`."""

    def __init__(self, pair: NetnsPair, relay: subprocess.Popen) -> None:
        self.pair = pair
        self.relay = relay
        self.counters: dict[str, int] = {}

    def cut(self) -> None:
        """Partition the link: every packet dropped from now on (no FIN, no RST)."""
        self.relay.send_signal(signal.SIGUSR1)

    def restore(self) -> None:
        """Undo :meth:`cut`."""
        self.relay.send_signal(signal.SIGUSR2)

    def reconfigure(self, **params: float | int | bool) -> None:
        """Restart the relay with other :func:`link_args` (the namespaces stay; packets in
        flight are lost)."""
        self.counters = stop_relay(self.relay)
        self.relay = start_relay(self.pair, link_args(**params))  # type: ignore[arg-type]


@contextlib.contextmanager
def emulated_link(prefix: str = "tr", mtu: int = 1500, **params: float | int | bool):
    """Namespaces ``<prefix>-ops``/``<prefix>-work`` joined by linkemu with ``params``
    (:func:`link_args`); everything is removed on exit, also after an error."""
    pair = NetnsPair(prefix)
    create(pair, mtu)
    link: EmulatedLink | None = None
    try:
        link = EmulatedLink(pair, start_relay(pair, link_args(**params)))  # type: ignore[arg-type]
        yield link
    finally:
        if link is not None:
            link.counters = stop_relay(link.relay)
        destroy(pair)


def _iter_params(args: argparse.Namespace) -> Iterator[tuple[str, float | int | bool]]:
    for name in ("delay_ms", "jitter_ms", "loss", "seed", "rate_mbit", "queue_ms", "fifo"):
        yield name, getattr(args, name)


def main(argv: list[str] | None = None) -> int:
    """``up``: make the namespaces and relay until Ctrl-C; ``down``: remove them."""
    parser = argparse.ArgumentParser(
        prog="netns",
        description=f"Two network namespaces, PREFIX-ops ({OPS_ADDR}) and PREFIX-work "
        f"({WORK_ADDR}), joined by an emulated link (deploy/linkemu.py). Needs root.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    up = sub.add_parser("up", help="create them and run the link until Ctrl-C, then tear down")
    down = sub.add_parser("down", help="remove them (after a crash)")
    for p in (up, down):
        p.add_argument("--prefix", default="tr", help="namespace name prefix (default: tr)")
    up.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay (ms)")
    up.add_argument("--jitter-ms", type=float, default=0.0, help="± uniform jitter (ms)")
    up.add_argument("--loss", type=float, default=0.0, help="drop fraction per direction")
    up.add_argument("--seed", type=int, default=1, help="schedule seed")
    up.add_argument("--rate-mbit", type=float, default=0.0, help="rate limit (0: none)")
    up.add_argument("--queue-ms", type=float, default=100.0, help="bottleneck queue (ms)")
    up.add_argument("--fifo", action="store_true", help="no reordering")
    up.add_argument("--mtu", type=int, default=1500, help="TUN MTU (default 1500)")
    args = parser.parse_args(argv)
    if (reason := unavailable_reason()) is not None:
        print(f"netns: {reason}", file=sys.stderr)
        return 2
    pair = NetnsPair(args.prefix)
    if args.command == "down":
        destroy(pair)
        return 0
    stopped = False

    def on_signal(*_: object) -> None:
        nonlocal stopped
        stopped = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    with emulated_link(args.prefix, args.mtu, **dict(_iter_params(args))) as link:
        print(
            f"netns: {pair.ops} ({OPS_ADDR}) <-> {pair.work} ({WORK_ADDR}) up; relay pid "
            f"{link.relay.pid} (SIGUSR1 cuts, SIGUSR2 restores); Ctrl-C tears down",
            flush=True,
        )
        while not stopped and link.relay.poll() is None:
            time.sleep(0.2)
    print(f"netns: down; relay counters {json.dumps(link.counters)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
