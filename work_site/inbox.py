"""The work site's command inboxes: what it reads off the wire (stops, operator heartbeats,
programs), each on its own subscriber, so that no flood on one key can delay or drop another.

Stops and heartbeats are small: each sample is size-checked and decoded in zenoh's callback
(bounded work of microseconds, nothing that blocks), and only valid messages are queued. Garbage
therefore never takes a valid stop's place, however fast it comes. Programs may be megabytes:
their samples go to a bounded ring and are decoded by whoever drains it. Every dropped sample is
counted; the log gets one summary line per key and interval, never one line per sample.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

import zenoh

from protocol import Heartbeat, Message, ProtocolError, Stop, decode
from protocol.messages import MAX_NAME_LEN, MAX_TEXT_LEN

log = logging.getLogger("work-site")

ENVELOPE_BYTES = 512
"""Room for the msgpack envelope and the fixed fields of a small message (bytes)."""
MAX_STOP_BYTES = ENVELOPE_BYTES + 4 * MAX_TEXT_LEN
"""Largest valid stop: its reason is at most MAX_TEXT_LEN characters of ≤ 4 UTF-8 bytes."""
MAX_HEARTBEAT_BYTES = ENVELOPE_BYTES + 4 * MAX_NAME_LEN
DROP_SUMMARY_PERIOD_S = 5.0
"""Dropped samples are summed up in the log at most this often, per key (s)."""
KEPT_STOPS = 16
"""Valid stops waiting for the control loop; any one of them stops the arm."""


class DropCounter:
    """Samples dropped on one key: a total, and a log line per interval with the newest reason."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.total = 0
        self._reported = 0
        self._last_reason = ""
        self._next_summary_s = 0.0

    def add(self, reason: str) -> None:
        self.total += 1
        self._last_reason = reason

    def summarize(self, now_s: float) -> None:
        """Log the drops since the last summary, at most every :data:`DROP_SUMMARY_PERIOD_S`."""
        if now_s < self._next_summary_s or self.total == self._reported:
            return
        new, self._reported = self.total - self._reported, self.total
        self._next_summary_s = now_s + DROP_SUMMARY_PERIOD_S
        log.warning(
            "dropped %d malformed %s message(s) (%d in all; the last: %s)",
            new,
            self.what,
            self.total,
            self._last_reason[:200],
        )


class ValidatedInbox:
    """Valid messages of one small type from one key, newest ``keep`` of them; ``accept`` may
    filter them further (it runs in zenoh's callback too: keep it cheap). ``wake`` is set
    whenever one is queued, so that the control loop can act before its next period.

    With ``ring`` > 0 the samples wait in zenoh's own ring of that size, with no Python callback,
    until :meth:`pull` checks them: their arrival never waits for the interpreter, which a busy
    control loop holds."""

    def __init__(
        self,
        session: zenoh.Session | None,
        key_expr: str,
        expected: type[Message],
        max_bytes: int,
        keep: int,
        wake: threading.Event | None = None,
        accept: Callable[[Message], bool] | None = None,
        ring: int = 0,
    ) -> None:
        self.expected, self.max_bytes = expected, max_bytes
        self.dropped = DropCounter(expected.TYPE)
        self.last_s: float | None = None
        """When the newest valid message arrived (time.monotonic())."""
        self.last: Message | None = None
        """The newest valid message."""
        self._queue: collections.deque = collections.deque(maxlen=keep)
        self._wake, self._accept = wake, accept
        self._ring = ring
        if session is None:
            self._sub = None
        elif ring:  # held by zenoh until :meth:`pull`: arrival needs no interpreter
            self._sub = session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(ring))
        else:
            self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: check the size before reading or decoding, never block.
        payload = sample.payload
        size = len(payload)
        if size > self.max_bytes:
            self.dropped.add(f"{size} bytes, more than the {self.max_bytes} a valid one takes")
            return
        self.offer(payload.to_bytes())

    def offer(self, payload: bytes) -> bool:
        """Queue ``payload`` if it is a valid message that ``accept`` takes; whether it was.
        (A session of None feeds the inbox through this only.)"""
        if len(payload) > self.max_bytes:
            self.dropped.add(f"{len(payload)} bytes, more than the {self.max_bytes} allowed")
            return False
        try:
            msg = decode(payload, expected=self.expected)
        except ProtocolError as e:
            self.dropped.add(str(e))
            return False
        if self._accept is not None and not self._accept(msg):
            return False
        self._queue.append(msg)
        self.last, self.last_s = msg, time.monotonic()
        if self._wake is not None:
            self._wake.set()
        return True

    def pull(self) -> int:
        """With a ``ring``: check and queue what zenoh holds (the newest ``ring`` samples);
        how many samples there were."""
        if not self._ring or self._sub is None:
            return 0
        for n in range(self._ring):
            sample = self._sub.try_recv()
            if sample is None:
                return n
            self._on_sample(sample)
        return self._ring

    def drain(self) -> list[Message]:
        """The messages queued since the last drain, oldest first (at most ``keep``)."""
        out = []
        for _ in range(self._queue.maxlen or 0):
            try:
                out.append(self._queue.popleft())
            except IndexError:
                break
        return out

    def undeclare(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()


def stop_inbox(
    session: zenoh.Session | None, key_expr: str, wake: threading.Event | None = None
) -> ValidatedInbox:
    """Valid stops from ``key_expr``."""
    return ValidatedInbox(session, key_expr, Stop, MAX_STOP_BYTES, KEPT_STOPS, wake)


HEARTBEAT_RING = 256
"""Heartbeat samples zenoh keeps between two pulls by the control loop: a garbage flood on the
key fills it, the newest valid beat is among them."""
LATE_BEAT_S = 0.25
"""A heartbeat that arrives this long after its operator sent it (by the operator's clock:
on two machines, their clocks' offset counts too) is logged: half the dead-man's default."""
LATE_BEAT_LOG_PERIOD_S = 10.0


class LateBeats:
    """Heartbeats that arrived late, logged at most every :data:`LATE_BEAT_LOG_PERIOD_S`: the
    reason a dead-man stop came without the operator going quiet."""

    def __init__(self) -> None:
        self.count = 0
        self._next_log_s = 0.0

    def add(self, beat: Message) -> None:
        age_s = time.time() - beat.stamp_s
        log.debug("heartbeat #%d of %s, sent %.1f ms ago", beat.seq, beat.operator, 1e3 * age_s)
        if age_s < LATE_BEAT_S:
            return
        self.count += 1
        now = time.monotonic()
        if now >= self._next_log_s:
            self._next_log_s = now + LATE_BEAT_LOG_PERIOD_S
            log.warning(
                "heartbeat #%d of operator %s arrived %.0f ms after it was sent (%d late so "
                "far): the link or this machine is slow, or the clocks differ",
                beat.seq, beat.operator or "-", 1e3 * age_s, self.count,
            )  # fmt: skip


def heartbeat_inbox(
    session: zenoh.Session,
    key_expr: str,
    site_id: str,
    heard: Callable[[Message], None] = lambda _beat: None,
) -> ValidatedInbox:
    """Valid heartbeats of operator sites of ``site_id`` (a work site hears its own too: those
    are left out); ``heard`` is told of each as it comes (zenoh's thread: keep it cheap)."""

    def from_operator(beat: Message) -> bool:
        if beat.role != "operator_site" or beat.site_id != site_id:
            return False
        heard(beat)
        late.add(beat)
        return True

    late = LateBeats()
    return ValidatedInbox(
        session, key_expr, Heartbeat, MAX_HEARTBEAT_BYTES, 1, accept=from_operator,
        ring=HEARTBEAT_RING,
    )  # fmt: skip
