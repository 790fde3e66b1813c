"""The control lease: one operator site controls the robot at a time; the others watch.

An operator takes the lease by sending a program when nobody holds it, and keeps it while its
heartbeats keep coming (its page open); :data:`LEASE_IDLE_S` after its last beat or program the
lease is free again. Programs from anyone else are refused, naming the holder; a STOP is
honoured from any operator. Operators name themselves (``MotionProgram.operator``,
``Heartbeat.operator``): with TLS and ``--operators`` only admitted operators reach the work site
at all, and among them the lease keeps two from driving the arm at once, as a convention, not a
defence against an admitted operator that lies about its name.
"""

from __future__ import annotations

import collections
import threading

from protocol import RoundTrips

LEASE_IDLE_S = 5.0
"""The lease lapses this long after its holder's last heartbeat or program (s): several of the
operator's idle beats (one a second), short enough that a closed page frees the robot soon."""
MAX_TRACKED_OPERATORS = 64
"""Operators whose last heartbeat is remembered; the oldest is forgotten first."""


class ControlLease:
    """Who holds the robot, and when each operator was last heard from (thread-safe: beats
    arrive on zenoh's threads, programs on the checking thread, the dead-man reads it on the
    control loop's)."""

    def __init__(self, idle_s: float = LEASE_IDLE_S) -> None:
        self.idle_s = idle_s
        self._holder = ""
        self._last_s: collections.OrderedDict[str, float] = collections.OrderedDict()
        self._round_trips: dict[str, RoundTrips] = {}
        self._stamps_s: dict[str, float] = {}
        self._echoed = ""
        """The operator whose beat our last heartbeat echoed."""
        self._lock = threading.Lock()

    def heard(
        self,
        operator: str,
        now_s: float,
        round_trip_s: float | None = None,
        stamp_s: float | None = None,
        echo_stamp_s: float = 0.0,
    ) -> None:
        """Operator ``operator`` was heard from at ``now_s`` (monotonic s): a heartbeat stamped
        ``stamp_s`` (its clock), which echoed our beat stamped ``echo_stamp_s`` and measured
        the round trip ``round_trip_s`` (s; None: it echoed nothing)."""
        if not operator:
            return
        with self._lock:
            self._last_s[operator] = now_s
            self._last_s.move_to_end(operator)
            while len(self._last_s) > MAX_TRACKED_OPERATORS:
                forgotten, _ = self._last_s.popitem(last=False)
                self._round_trips.pop(forgotten, None)
                self._stamps_s.pop(forgotten, None)
            if stamp_s is not None:
                self._stamps_s[operator] = stamp_s
            if round_trip_s is not None:
                self._round_trips.setdefault(operator, RoundTrips()).add(round_trip_s, echo_stamp_s)

    def echo(self, now_s: float) -> tuple[str, float, float]:
        """What our next heartbeat echoes: whose beat, its stamp and how long ago (s) it was
        heard; ("", 0, 0) when no operator's beat was heard within :attr:`idle_s`. The
        operators heard within it take turns, in the order of their names: one echo is all a
        beat carries, and every operator (a watcher too) needs some to know its round trip."""
        with self._lock:
            recent = sorted(
                name
                for name, heard_s in self._last_s.items()
                if name in self._stamps_s and now_s - heard_s <= self.idle_s
            )
            if not recent:
                return "", 0.0, 0.0
            later = [name for name in recent if name > self._echoed]
            self._echoed = operator = later[0] if later else recent[0]
            return operator, self._stamps_s[operator], max(0.0, now_s - self._last_s[operator])

    def round_trip_s(self, operator: str) -> float | None:
        """``operator``'s round trip as its heartbeats measured it lately (None: not known)."""
        with self._lock:
            round_trips = self._round_trips.get(operator)
            return None if round_trips is None else round_trips.median_s()

    def last_heard_s(self, operator: str) -> float | None:
        """When ``operator`` was last heard from (None: not lately)."""
        with self._lock:
            return self._last_s.get(operator)

    def holder(self, now_s: float) -> str:
        """The operator holding the lease at ``now_s`` ("" when nobody does)."""
        with self._lock:
            return self._holder_locked(now_s)

    def _holder_locked(self, now_s: float) -> str:
        last = self._last_s.get(self._holder)
        if self._holder and (last is None or now_s - last > self.idle_s):
            self._holder = ""
        return self._holder

    def take(self, operator: str, now_s: float) -> str:
        """``operator`` asks for the robot (it sent a program): "" if it may have it (it then
        holds the lease, unless it is anonymous), else the holder's name."""
        with self._lock:
            holder = self._holder_locked(now_s)
            if holder and holder != operator:
                return holder
            if operator:
                self._holder = operator
                self._last_s[operator] = now_s
                self._last_s.move_to_end(operator)
            return ""
