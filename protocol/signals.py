"""Signals for a site's process: Ctrl-C and SIGTERM ask it to stop, and never deadlock it;
SIGUSR1 prints its stacks."""

from __future__ import annotations

import faulthandler
import logging
import queue
import signal
import threading


def install_stop_signals(stop: threading.Event, who: str) -> None:
    """SIGINT and SIGTERM set ``stop`` (call from the main thread), logged to logger ``who``.

    Not from the handler itself: a handler runs in the main thread between two of its steps,
    and setting the event takes the event's lock, which the main thread holds while it waits
    on that event (``stop.wait``), so a signal at that moment hung the process for good. The
    handler only puts the signal in a queue whose ``put`` is reentrant, and a thread of its own
    sets the event."""
    received: queue.SimpleQueue[int] = queue.SimpleQueue()

    def relay() -> None:
        signum = received.get()
        logging.getLogger(who).info("%s received, stopping", signal.Signals(signum).name)
        stop.set()

    threading.Thread(target=relay, name="stop-signals", daemon=True).start()

    def on_signal(signum: int, _frame: object) -> None:
        received.put(signum)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)


def dump_stacks_on_sigusr1() -> None:
    """`kill -USR1 <pid>` prints every thread's stack to stderr: what a site that does not stop
    or answer is doing, without a debugger."""
    faulthandler.register(signal.SIGUSR1, all_threads=True)
