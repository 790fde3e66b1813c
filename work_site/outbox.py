"""Execution reports leave the work site through an outbox: a thread of its own publishes them
in order with congestion control BLOCK, so that a congested link delays reports and never loses
one, and the control loop, which writes most of them, never waits on the network."""

from __future__ import annotations

import logging
import queue
import threading

log = logging.getLogger(__name__)

MAX_QUEUED_REPORTS = 100_000
"""Reports waiting for the link, at most (a few tens of MB). Beyond, a report is not queued and
a warning says so: it stays journaled, and the operator's re-send of its program replays it."""
CLOSE_DRAIN_S = 2.0
"""On close, the reports still queued are sent for at most this long."""
_POLL_S = 0.1


class Outbox:
    """``put(payload)`` queues a report for ``publisher`` (a zenoh publisher, or anything with
    ``put``) and returns at once; :meth:`close` sends what is left, within
    :data:`CLOSE_DRAIN_S`."""

    def __init__(self, publisher, capacity: int = MAX_QUEUED_REPORTS) -> None:
        self._publisher = publisher
        self._queue: queue.Queue[bytes] = queue.Queue(maxsize=capacity)
        self._closing = threading.Event()
        self.not_queued = 0
        self._thread = threading.Thread(target=self._send, name="report-outbox", daemon=True)
        self._thread.start()

    def put(self, payload: bytes) -> None:
        """Queue ``payload`` for sending (never blocks)."""
        try:
            self._queue.put_nowait(payload)
        except queue.Full:
            self.not_queued += 1
            if self.not_queued == 1 or self.not_queued % 1000 == 0:
                log.warning(
                    "%d reports not sent: %d wait for the link already (they are journaled; "
                    "a re-send of their program replays them)",
                    self.not_queued,
                    self._queue.maxsize,
                )

    def _send(self) -> None:
        while not (self._closing.is_set() and self._queue.empty()):
            try:
                payload = self._queue.get(timeout=_POLL_S)
            except queue.Empty:
                continue
            try:
                self._publisher.put(payload)
            except Exception:  # the session closing under us: nothing left to send to
                log.exception("could not publish a report")
                return

    def close(self) -> None:
        """Send the reports still queued (within :data:`CLOSE_DRAIN_S`), then stop."""
        self._closing.set()
        self._thread.join(CLOSE_DRAIN_S)
        if self._thread.is_alive() or not self._queue.empty():
            log.warning("%d reports not sent before closing", self._queue.qsize())
