"""The dead-man's heartbeats from a process of their own, beside the operator site's thread.

An operator site's heartbeat thread shares the interpreter with the page, the contact
simulator and the program generator: a long call that holds the interpreter (a C extension
that does not release it), on a loaded machine, can keep the thread from running for longer
than the work site's dead-man timeout, and the robot stops though the operator is alive and
connected. The child started here beats from its own interpreter while its parent says a
program of its is unfinished, so such a stall stops nothing; it beats no more

- the moment the parent dies (its end of the pipe closes: the child sees end of file),
- :data:`OPERATOR_FROZEN_S` after the parent last said "beat" (a parent frozen that long, or
  whose heartbeat thread never runs, is treated as gone: its page answers no STOP meanwhile).

The parent's own thread goes on beating too (``operator_site/link.py``): while the child starts,
or if it cannot, the beats are as before. A cut link stops both, since both go the same way.

    python -m operator_site.heartbeats   # reads its set-up from the first line of stdin
"""

from __future__ import annotations

import json
import logging
import select
import signal
import subprocess
import sys
import threading
import time

import zenoh

from protocol import Heartbeat, alive_key, encode, key
from protocol.session import PeerWatch, renewal_config

log = logging.getLogger("operator-site")

HEARTBEAT_PERIOD_S = 0.1
"""Heartbeats go this often while a program of ours is unfinished: several within the work
site's dead-man timeout (``work-site serve --deadman-s``, 0.5 s by default), so that one lost
or late beat stops nothing."""
OPERATOR_FROZEN_S = 2.0
"""The child stops beating when its parent has not said "beat" for this long. The trade: a
longer time tolerates longer stalls of the operator's process (seen up to half a second on a
loaded two-core machine); a frozen operator keeps its robot moving, unstoppable from its page,
for this long plus the dead-man's timeout."""
MAX_STARTS = 3
"""A child that dies is started again when next needed, at most this many times per link."""
CLOSE_WAIT_S = 2.0
"""How long :meth:`HeartbeatProcess.close` waits for the child to end before killing it."""
SEQ_OFFSET = 1 << 40
"""The child's sequence numbers start here, apart from the parent thread's."""
READY_WAIT_S = 5.0
"""A program sent before the child is ready (started, connected, the work site seen: about a
second after the link opened) waits this long at most for it, once per link."""
SEE_WORK_SITE_S = 30.0
"""The child says it is ready once it sees the work site alive, or after this long anyway."""


class HeartbeatProcess:
    """The parent's handle on the heartbeat child of one link: :meth:`start`, :meth:`beat`
    while a program is unfinished (every :data:`HEARTBEAT_PERIOD_S` or so), :meth:`rest` when
    none is, then :meth:`close`. Never raises: a child that cannot be had leaves the parent's
    own beats; one that died is started again at the next :meth:`beat`, while
    :data:`MAX_STARTS` allows."""

    def __init__(self, zenoh_config: zenoh.Config, site_id: str, operator_id: str) -> None:
        # A session of its own: its own id, and no listening on the parent's ports.
        config = json.loads(renewal_config(zenoh_config))
        config.setdefault("listen", {})["endpoints"] = []
        self._setup = json.dumps(
            {"config": json.dumps(config), "site_id": site_id, "operator": operator_id}
        )
        self._proc: subprocess.Popen | None = None
        self._starts = 0
        self._resting = True
        self._ready: bool | None = None  # None: not known yet; False: given up waiting
        self._lock = threading.Lock()  # the link's thread and its caller's both tell
        self._ready_lock = threading.Lock()

    def start(self) -> None:
        """Start the child (resting) unless it runs."""
        with self._lock:
            if self._proc is not None and self._proc.poll() is not None:
                _end(self._proc)  # it died
                self._proc = None
            if self._proc is None:
                self._proc = self._start()

    def beat(self) -> None:
        """A program of ours is unfinished: the child is to beat (for :data:`OPERATOR_FROZEN_S`
        from now, unless told again)."""
        if self._starts and (self._proc is None or self._proc.poll() is not None):
            self.start()  # it died: again (a link without a child never gets one)
        with self._lock:
            self._resting = False
            self._tell("beat")

    def rest(self) -> None:
        """No program of ours is unfinished: the child stops beating."""
        with self._lock:
            if not self._resting:
                self._resting = True
                self._tell("rest")

    def close(self) -> None:
        """End the child (idempotent)."""
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is not None:
            _end(proc)

    def wait_ready(self) -> bool:
        """Whether the child is ready, waiting up to :data:`READY_WAIT_S` the first time it is
        asked (never again after that wait failed)."""
        # Not under the lock: the link's thread must go on telling meanwhile.
        with self._ready_lock:
            proc = self._proc
            if self._ready is None and proc is not None:
                ready = bool(select.select([proc.stdout], [], [], READY_WAIT_S)[0])
                self._ready = ready and proc.stdout.readline().strip() == "ready"
                if not self._ready:
                    log.warning("the heartbeat process is not ready: the thread beats alone")
            return bool(self._ready)

    @property
    def pid(self) -> int | None:
        """The running child's process id (None: none runs)."""
        return None if self._proc is None or self._proc.poll() is not None else self._proc.pid

    def _start(self) -> subprocess.Popen | None:
        if self._starts >= MAX_STARTS:
            return None
        self._starts += 1
        try:
            # A process group of its own: a Ctrl-C in the terminal never reaches it, not even
            # while it imports (before it can ignore SIGINT); the parent's end ends it.
            proc = subprocess.Popen(
                [sys.executable, "-m", "operator_site.heartbeats"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            proc.stdin.write(self._setup + "\n")
            proc.stdin.flush()
        except OSError as e:
            log.warning("no heartbeat process (the thread's beats go on alone): %s", e)
            return None
        return proc

    def _tell(self, word: str) -> None:
        if self._proc is None:
            return
        try:
            self._proc.stdin.write(word + "\n")
            self._proc.stdin.flush()
        except (OSError, ValueError) as e:  # it died (it says why on stderr)
            log.warning("the heartbeat process ended (%s); the thread's beats go on", e)
            _end(self._proc)
            self._proc = None


def _end(proc: subprocess.Popen) -> None:
    """Close the child's pipes (its end of file: it ends), wait for it, kill it if it lingers."""
    for pipe in (proc.stdin, proc.stdout):
        try:
            pipe.close()
        except OSError:  # a write that could not be flushed: it is gone
            pass
    try:
        proc.wait(CLOSE_WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _open(setup: dict) -> tuple[zenoh.Session, zenoh.Publisher, zenoh.Subscriber]:
    """A new session: its heartbeat publisher and its view of the work site's token."""
    session = zenoh.open(zenoh.Config.from_json5(setup["config"]))
    publisher = session.declare_publisher(
        key(setup["site_id"], "heartbeat"), priority=zenoh.Priority.REAL_TIME,
        congestion_control=zenoh.CongestionControl.BLOCK, express=True,
    )  # fmt: skip
    seen = session.liveliness().declare_subscriber(
        alive_key(setup["site_id"], "work_site"), zenoh.handlers.RingChannel(16), history=True
    )
    return session, publisher, seen


def _serve(setup: dict, stdin) -> int:
    """The child: say "ready" once the work site is seen, then beat while told, until end of
    file on ``stdin``; a new session when the work site was lost (``PeerWatch``)."""
    session, publisher, seen = _open(setup)
    work_site = PeerWatch()
    told_s = [None]  # monotonic time the parent last said "beat"; None: resting
    parent_gone = threading.Event()

    def listen() -> None:
        for line in stdin:
            told_s[0] = time.monotonic() if line.strip() == "beat" else None
        parent_gone.set()

    threading.Thread(target=listen, name="parent", daemon=True).start()
    try:  # the session closed on every way out: one left to the finalizers can hang the exit
        deadline_s = time.monotonic() + SEE_WORK_SITE_S
        while not work_site.drain(seen) and time.monotonic() < deadline_s:
            if parent_gone.wait(0.01):
                return 0  # no one to say "ready" to
        print("ready", flush=True)
        seq, frozen_said = SEQ_OFFSET, False
        while not parent_gone.wait(HEARTBEAT_PERIOD_S):
            work_site.drain(seen)
            if work_site.lost:
                work_site.lost = False
                session.close()
                session, publisher, seen = _open(setup)
            t = told_s[0]
            if t is None:
                continue
            if time.monotonic() - t > OPERATOR_FROZEN_S:
                if not frozen_said:
                    log.warning("operator site silent for %.1f s: beats stop", OPERATOR_FROZEN_S)
                    frozen_said = True
                continue
            frozen_said = False
            beat = Heartbeat(
                site_id=setup["site_id"], role="operator_site", seq=seq, stamp_s=time.time(),
                operator=setup["operator"],
            )  # fmt: skip
            seq += 1
            publisher.put(encode(beat))
    finally:
        session.close()
    return 0


def main() -> int:
    # The parent decides, and its end (the pipe's end of file) is what ends this process: a
    # SIGINT sent to it (started by hand in a terminal) is ignored.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s heartbeats %(message)s")
    first = sys.stdin.readline()
    try:
        setup = json.loads(first)
        return _serve(setup, sys.stdin)
    except (ValueError, KeyError, zenoh.ZError) as e:
        log.error("heartbeat process: bad set-up or no session: %s", e)
        return 2


if __name__ == "__main__":
    sys.exit(main())
