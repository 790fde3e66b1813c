"""A site's Ctrl-C: it sets the stop event, and never waits on that event's lock."""

from __future__ import annotations

import signal
import threading

from protocol.signals import install_stop_signals


def test_a_stop_signal_never_waits_on_the_lock_of_the_event_it_sets() -> None:
    stop = threading.Event()
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    install_stop_signals(stop, "test")
    try:
        handler = signal.getsignal(signal.SIGINT)
        # As the main thread holds it inside stop.wait() when the signal comes: a handler
        # that set the event itself never returned from here.
        with stop._cond:
            handler(signal.SIGINT, None)
            assert not stop.is_set()
        assert stop.wait(10.0)
    finally:
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])
