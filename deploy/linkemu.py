"""linkemu: a user-space link emulator between two TUN devices (this kernel has no ``netem``).

It attaches to one TUN device in each of two network namespaces (made by ``deploy/netns.py``),
reads every IP packet that one side sends, and writes it into the other side after a delay drawn
from a seeded schedule: ``delay ± jitter`` (uniform), dropped with probability ``loss``, optionally
through a rate-limited FIFO with a bounded queue (tail drop). With jitter, packets may overtake
each other (reordering) unless ``--fifo`` is given. The same seed gives the same schedule: packet
number n of a direction always gets the same fate.

Signals: SIGUSR1 cuts the link (every packet dropped, no FIN, no RST: a partition), SIGUSR2
restores it, SIGTERM/SIGINT stop the relay and print its counters as one JSON line.

Run as root (``setns`` and ``/dev/net/tun``); ``python deploy/linkemu.py --help``.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import errno
import fcntl
import heapq
import json
import os
import random
import select
import signal
import struct
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
CLONE_NEWNET = 0x40000000
MAX_PACKET = 65536
READ_BURST = 64
"""Packets read from one device per wake-up at most, so the other direction is not starved."""


@dataclass(frozen=True)
class LinkParams:
    """One direction's behaviour: delay and jitter (s), loss fraction, rate (bit/s, 0 = none)."""

    delay_s: float = 0.0
    jitter_s: float = 0.0
    loss: float = 0.0
    rate_bps: float = 0.0
    queue_s: float = 0.1
    reorder: bool = True

    def __post_init__(self) -> None:
        if self.delay_s < 0 or self.jitter_s < 0:
            raise ValueError("delay and jitter must be ≥ 0")
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {self.loss}")
        if self.rate_bps < 0 or self.queue_s <= 0:
            raise ValueError("rate must be ≥ 0 and the queue length > 0")


@dataclass
class LinkSchedule:
    """The seeded fate of each packet of one direction: ``None`` (dropped) or its release time.

    Deterministic: the n-th call draws the n-th numbers of ``random.Random(seed)``, whatever the
    packet sizes and times, so a seed names one loss/jitter pattern.
    """

    params: LinkParams
    seed: int
    cut: bool = False
    sent: int = 0
    dropped: int = 0
    overflowed: int = 0
    _rng: random.Random = field(init=False, repr=False)
    _last_release_s: float = field(default=0.0, init=False, repr=False)
    _tx_free_s: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def decide(self, now_s: float, size_bytes: int) -> float | None:
        """Release time (s, same clock as ``now_s``) of a packet that arrives now, or None."""
        p = self.params
        # Draw both numbers for every packet so the pattern does not depend on earlier fates.
        u_loss = self._rng.random()
        u_jitter = self._rng.random()
        if self.cut or u_loss < p.loss:
            self.dropped += 1
            return None
        start_s = now_s
        if p.rate_bps > 0:
            if self._tx_free_s - now_s > p.queue_s:  # the bottleneck queue is full: tail drop
                self.overflowed += 1
                return None
            self._tx_free_s = max(self._tx_free_s, now_s) + size_bytes * 8.0 / p.rate_bps
            start_s = self._tx_free_s
        release_s = start_s + max(0.0, p.delay_s + (2.0 * u_jitter - 1.0) * p.jitter_s)
        if not p.reorder:
            release_s = max(release_s, self._last_release_s)
        self._last_release_s = max(self._last_release_s, release_s)
        self.sent += 1
        return release_s


# ----------------------------------------------------------------------------- TUN devices

_libc = ctypes.CDLL(None, use_errno=True)


def _setns(fd: int) -> None:
    if _libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"setns: {os.strerror(err)}")


@contextlib.contextmanager
def in_netns(name: str | None) -> Iterator[None]:
    """Run the body in network namespace ``name`` (``ip netns`` name; None: stay). Only this
    thread moves, and it moves back afterwards."""
    if name is None:
        yield
        return
    home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
    try:
        target = os.open(f"/var/run/netns/{name}", os.O_RDONLY)
        try:
            _setns(target)
        finally:
            os.close(target)
        try:
            yield
        finally:
            _setns(home)
    finally:
        os.close(home)


def open_tun(device: str, netns: str | None = None) -> int:
    """Attach to (or create) TUN device ``device`` in namespace ``netns``; a non-blocking fd
    carrying bare IP packets (no packet-information header)."""
    if len(device.encode()) >= 16:
        raise ValueError(f"device name too long: {device!r}")
    with in_netns(netns):
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
        try:
            fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH22x", device.encode(), IFF_TUN | IFF_NO_PI))
        except OSError:
            os.close(fd)
            raise
    return fd


# ----------------------------------------------------------------------------------- relay


class Relay:
    """Moves packets between two TUN fds through one :class:`LinkSchedule` per direction."""

    def __init__(self, fd_a: int, fd_b: int, a_to_b: LinkSchedule, b_to_a: LinkSchedule) -> None:
        self._fds = (fd_a, fd_b)
        self._schedules = (a_to_b, b_to_a)
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._count = 0
        self._stop = False
        self.write_errors = 0

    @property
    def schedules(self) -> tuple[LinkSchedule, LinkSchedule]:
        return self._schedules

    def set_cut(self, cut: bool) -> None:
        """Cut (drop everything, also what is in flight) or restore the link."""
        # Only flags here: this runs in a signal handler, between any two bytecodes of run().
        for s in self._schedules:
            s.cut = cut

    def stop(self) -> None:
        self._stop = True

    def _read(self, side: int, now_s: float) -> None:
        fd, out_fd, schedule = self._fds[side], self._fds[1 - side], self._schedules[side]
        for _ in range(READ_BURST):
            try:
                packet = os.read(fd, MAX_PACKET)
            except BlockingIOError:
                return
            except OSError as e:  # EIO while the other end of the device is not up yet
                if e.errno in (errno.EIO, errno.EBADFD):
                    return
                raise
            release_s = schedule.decide(now_s, len(packet))
            if release_s is not None:
                self._count += 1
                heapq.heappush(self._heap, (release_s, self._count, out_fd, packet))

    def _release_due(self, now_s: float) -> None:
        if self._schedules[0].cut:  # a cut loses what is in flight too
            self._heap.clear()
        while self._heap and self._heap[0][0] <= now_s:
            _, _, out_fd, packet = heapq.heappop(self._heap)
            try:
                os.write(out_fd, packet)
            except OSError:  # device down or its queue full: the packet is lost, like on a wire
                self.write_errors += 1

    def run(self) -> None:
        """Relay until :meth:`stop` (e.g. from a signal handler)."""
        while not self._stop:
            now_s = time.monotonic()
            self._release_due(now_s)
            timeout_s = max(0.0, self._heap[0][0] - now_s) if self._heap else 0.5
            try:
                readable, _, _ = select.select(self._fds, [], [], timeout_s)
            except InterruptedError:
                continue
            now_s = time.monotonic()
            for side, fd in enumerate(self._fds):
                if fd in readable:
                    self._read(side, now_s)

    def counters(self) -> dict[str, int]:
        """Packets sent, dropped (loss or cut) and overflowed (queue full), per direction."""
        out: dict[str, int] = {"write_errors": self.write_errors}
        for name, s in zip(("a_to_b", "b_to_a"), self._schedules, strict=True):
            out[f"{name}_sent"] = s.sent
            out[f"{name}_dropped"] = s.dropped
            out[f"{name}_overflowed"] = s.overflowed
        return out


def params_from_args(args: argparse.Namespace) -> LinkParams:
    """The :class:`LinkParams` of one direction from the parsed command line."""
    return LinkParams(
        delay_s=args.delay_ms / 1000.0,
        jitter_s=args.jitter_ms / 1000.0,
        loss=args.loss,
        rate_bps=args.rate_mbit * 1e6,
        queue_s=args.queue_ms / 1000.0,
        reorder=not args.fifo,
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="linkemu",
        description="Relay IP packets between TUN device A (in namespace --ns-a) and TUN device B "
        "(in --ns-b), each direction delayed by DELAY ± JITTER ms (uniform), dropped with "
        "probability LOSS, optionally rate-limited, by a schedule fixed by --seed. Needs root. "
        "SIGUSR1 cuts the link (a partition: no FIN, no RST), SIGUSR2 restores it; SIGTERM "
        "stops and prints the counters as JSON. Usually started by deploy/netns.py.",
    )
    parser.add_argument("--ns-a", default=None, help="namespace of device A (default: this one)")
    parser.add_argument("--dev-a", required=True, help="TUN device A (created if missing)")
    parser.add_argument("--ns-b", default=None, help="namespace of device B (default: this one)")
    parser.add_argument("--dev-b", required=True, help="TUN device B (created if missing)")
    parser.add_argument(
        "--delay-ms", type=float, default=0.0, help="one-way delay, each direction (default 0)"
    )
    parser.add_argument(
        "--jitter-ms",
        type=float,
        default=0.0,
        help="one-way delay varies uniformly in ±JITTER around DELAY (default 0)",
    )
    parser.add_argument(
        "--loss",
        type=float,
        default=0.0,
        help="fraction of packets dropped, each direction independently (0..1, default 0)",
    )
    parser.add_argument("--seed", type=int, default=1, help="schedule seed (default 1)")
    parser.add_argument(
        "--rate-mbit",
        type=float,
        default=0.0,
        help="bottleneck rate per direction in Mbit/s (default 0: unlimited)",
    )
    parser.add_argument(
        "--queue-ms",
        type=float,
        default=100.0,
        help="bottleneck queue length in ms of transmission at --rate-mbit; packets beyond it "
        "are dropped (default 100)",
    )
    parser.add_argument(
        "--fifo", action="store_true", help="never reorder: jitter only delays later packets"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the relay until SIGTERM/SIGINT; prints ``linkemu: ready`` once both devices are up."""
    args = build_parser().parse_args(argv)
    try:
        params = params_from_args(args)
    except ValueError as e:
        print(f"linkemu: {e}", file=sys.stderr)
        return 2
    fd_a = open_tun(args.dev_a, args.ns_a)
    fd_b = open_tun(args.dev_b, args.ns_b)
    # Separate generators per direction, both fixed by the one seed.
    relay = Relay(
        fd_a, fd_b, LinkSchedule(params, 2 * args.seed), LinkSchedule(params, 2 * args.seed + 1)
    )
    signal.signal(signal.SIGTERM, lambda *_: relay.stop())
    signal.signal(signal.SIGINT, lambda *_: relay.stop())
    signal.signal(signal.SIGUSR1, lambda *_: relay.set_cut(True))
    signal.signal(signal.SIGUSR2, lambda *_: relay.set_cut(False))
    print("linkemu: ready", flush=True)
    try:
        relay.run()
    finally:
        os.close(fd_a)
        os.close(fd_b)
        print(json.dumps(relay.counters()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
