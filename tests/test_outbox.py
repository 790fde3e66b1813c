"""The work site's report outbox: in order, never blocking the writer, nothing lost while the
link is slow (a stand-in publisher; over zenoh: tests/test_net_*)."""

from __future__ import annotations

import threading
import time

from work_site.outbox import Outbox


class _SlowPublisher:
    """Holds every put until ``release`` is set, as a congested link with BLOCK does."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.release.wait(10.0)
        self.sent.append(payload)


def test_reports_queue_while_the_link_blocks_and_all_go_in_order() -> None:
    publisher = _SlowPublisher()
    outbox = Outbox(publisher)
    payloads = [f"report {i}".encode() for i in range(500)]
    for p in payloads:
        outbox.put(p)  # returns at once although the publisher blocks
    assert publisher.sent == []
    publisher.release.set()
    outbox.close()
    assert publisher.sent == payloads


def test_a_full_outbox_counts_what_it_could_not_queue() -> None:
    publisher = _SlowPublisher()
    outbox = Outbox(publisher, capacity=3)
    outbox.put(b"0")
    deadline = time.monotonic() + 5.0
    while not outbox._queue.empty() and time.monotonic() < deadline:
        time.sleep(0.01)  # the sender has taken it and waits on the link
    for i in range(1, 10):
        outbox.put(b"%d" % i)
    # One is in the publisher's hands, three queued, the other six refused and counted.
    assert outbox.not_queued == 6
    publisher.release.set()
    outbox.close()
    assert publisher.sent == [b"0", b"1", b"2", b"3"]
