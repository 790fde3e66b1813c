"""The operator site's link to one work site over zenoh: latest state, latest frame, liveliness.

zenoh delivers into bounded rings (the newest samples win, so nothing goes stale behind a slow
reader); :meth:`WorkSiteLink.poll` drains them on the caller's thread and decodes there. A payload
that fails validation is counted and logged once per kind, never raised.

While a program of this link's is unfinished, a thread of the link's sends the work site a
heartbeat every :data:`HEARTBEAT_PERIOD_S`, and so does a child process of its
(``operator_site/heartbeats.py``: beats that a stall of this interpreter does not hold up): the
work site's dead-man stops the robot when they stop coming (the operator's process died or
froze, the link was cut).

When the work site's liveliness token goes and is not back, the link opens a new zenoh session
in the background and drops the old one (``protocol.session.PeerWatch`` says why).
"""

from __future__ import annotations

import collections
import dataclasses
import getpass
import itertools
import logging
import math
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from operator_site.heartbeats import HEARTBEAT_PERIOD_S, HeartbeatProcess
from protocol import (
    CameraFrame,
    ExecutionReport,
    Heartbeat,
    MotionProgram,
    ProtocolError,
    Recognitions,
    RobotState,
    RoundTrips,
    Stop,
    alive_key,
    check_site_id,
    decode,
    encode,
    key,
)
from protocol.keys import KEY_PREFIX
from protocol.messages import MAX_CANCELS
from protocol.session import PeerWatch, renewal_config

log = logging.getLogger("operator-site")

RATE_WINDOW_S = 2.0
"""Messages are counted over this trailing window to report rates (Hz)."""
SHARE_WINDOW_S = 10.0
"""The share of the streams that arrives is measured over this long (s): long enough to span
several frames of a camera thinned to one every few seconds."""
STALE_AFTER_S = 1.0
"""A link whose work site is alive but has sent no robot state for this long is 'stale'."""
RESEND_AFTER_S = 1.0
"""A program the work site has not answered is sent again (same id) this often, and a round
trip more once one is measured: its answer takes the round trip and the work site's check."""
GIVE_UP_AFTER_S = 30.0
"""A program still unanswered this long after it was first sent is given up (and logged)."""
REMEMBERED_REPORTS = 10_000
LATE_WAKE_S = 0.25
"""The heartbeat thread warns when it wakes this much later than asked (half the dead-man's
default): the heartbeat process's beats covered the gap, unless the stall outlasted
:data:`~operator_site.heartbeats.OPERATOR_FROZEN_S`."""
LEASE_BEAT_PERIOD_S = 1.0
"""While this operator holds the work site's control lease and runs nothing, it beats this
often, so that the lease stays its own while its page is open (``work_site/lease.py``)."""
STREAM_ECHO_PERIOD_S = 0.25
"""While it receives the work site's streams and runs nothing, it beats this often, so that
the work site hears soon how late they arrive (``work_site/pacing.py``)."""
STATE_ARRIVALS = 64
"""Robot states kept between two polls, with when each arrived: every one is counted, the newest
is read (0.64 s of a 100 Hz arm: a page's poll comes sooner)."""
FRAME_ARRIVALS = 8
"""The same for camera frames (1.6 s of a 5 Hz camera)."""
HEARTBEAT_ARRIVALS = 64
"""Heartbeats kept between two polls, with when each arrived: the round trips the work site's
measure, and the time ours say we held its latest, run from their arrival, so that neither
includes this reader's poll period or a stall of its thread (a dead-man waiting for round trips
that long would stop a cut-off robot that much later). Every operator's beats share the key
(ours ten a second while a program runs): room for a few seconds of them between two polls,
lest the work site's own be pushed out."""
FINAL_STATUSES = ("done", "failed", "refused", "stopped")


ALL_WORK_SITES = f"{KEY_PREFIX}/*/alive/work_site"
"""Every work site's liveliness token."""
MAX_LISTED_SITES = 256
"""Work sites a link lists at most (the tokens' queue: more changes between two polls drop the
oldest, and a new session's history lists the rest)."""


def site_of_token(token_key: str) -> str | None:
    """The site id in a work site's liveliness token key (None: not one)."""
    parts = token_key.split("/")
    if len(parts) != 4 or parts[0] != KEY_PREFIX or parts[2:] != ["alive", "work_site"]:
        return None
    try:
        return check_site_id(parts[1])
    except ProtocolError:
        return None


_LINKS = itertools.count(1)


def default_operator_id() -> str:
    """A new link's id for the control lease and the dead-man: user, host, process and link.
    One per link, because the work site's dead-man hears a program's operator by its beats:
    another link of the same user beating for its lease must not keep a dead one's program
    going. ``operator-site recover --operator-id`` acts as a page's id."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no user name to be had (a container without one)
        user = str(os.getuid())
    words = f"{user}.{socket.gethostname()}.{os.getpid()}.{next(_LINKS)}"
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", words).strip("-.")[:128] or "operator"


class ArrivalRing:
    """A zenoh subscriber's handler that keeps the newest samples with when each arrived
    (monotonic s), so that what the heartbeats echo does not include the reader's poll period
    or a stall of its thread."""

    def __init__(self, capacity: int) -> None:
        self._ring: collections.deque[tuple[float, zenoh.Sample]] = collections.deque(
            maxlen=capacity
        )

    def __call__(self, sample: zenoh.Sample) -> None:  # zenoh's thread
        self._ring.append((time.monotonic(), sample))

    def drain(self) -> list[tuple[float, zenoh.Sample]]:
        """What arrived since the last drain, oldest first."""
        out = []
        while True:
            try:
                out.append(self._ring.popleft())
            except IndexError:
                return out


class RateMeter:
    """Messages that arrived per second over the last :data:`RATE_WINDOW_S` seconds: what the
    link delivered (the work site sends fewer than it makes while the link is slow), counted
    as they arrive (:class:`ArrivalRing`), not as a reader happens to keep them."""

    def __init__(self) -> None:
        self._stamps: collections.deque[float] = collections.deque()
        self._arrived = 0
        self._marks: collections.deque[tuple[float, int, int]] = collections.deque()
        """For each message read: when it arrived, its ``seq`` and the arrivals counted then."""

    def tick(self, arrived_s: float) -> None:
        """A message arrived at ``arrived_s`` (monotonic s)."""
        self._stamps.append(arrived_s)
        self._arrived += 1

    def read(self, arrived_s: float, seq: int) -> None:
        """The newest message that arrived so far (already counted by :meth:`tick`) is the
        sender's number ``seq``: its numbers count every message it made, sent or not."""
        if self._marks and seq <= self._marks[-1][1]:  # the sender restarted
            self._marks.clear()
        self._marks.append((arrived_s, seq, self._arrived))

    def rate_hz(self, now_s: float) -> float:
        while self._stamps and self._stamps[0] < now_s - RATE_WINDOW_S:
            self._stamps.popleft()
        return len(self._stamps) / RATE_WINDOW_S

    def share(self, now_s: float) -> float | None:
        """The share of the messages the sender made over the last :data:`SHARE_WINDOW_S`
        seconds that arrived (None: fewer than two read to say): under 1 when it sends fewer
        than it makes (the work site does while the link queues its streams) or they are
        lost."""
        while self._marks and self._marks[0][0] < now_s - SHARE_WINDOW_S:
            self._marks.popleft()
        if len(self._marks) < 2:
            return None
        (_, seq0, arrived0), (_, seq1, arrived1) = self._marks[0], self._marks[-1]
        return (arrived1 - arrived0) / (seq1 - seq0)


@dataclass
class LinkStatus:
    """What the operator is shown about the link: up/down, rates (Hz), ages (s), counts."""

    work_site_alive: bool = False
    state_rate_hz: float = 0.0
    frame_rate_hz: float = 0.0
    frame_share: float | None = None
    """The share of the camera frames the work site took lately that arrived (None: not
    known): under 1 while it sends fewer to fit this link."""
    last_state_age_s: float | None = None
    last_frame_age_s: float | None = None
    """How long ago the latest camera frame arrived (s)."""
    frame_age_s: float | None = None
    """How old the latest camera frame was when it arrived, from the moment the work site took
    it (s, its clock brought to ours by the heartbeats' echoes; None: not measured, like
    ``round_trip_s``)."""
    rejected: int = 0
    holder: str = ""
    """The operator holding the work site's control lease, as its heartbeat says ("": none)."""
    sites: list[str] = field(default_factory=list)
    """Every work site this link can reach now, its own among them when alive (what the
    routers' access control lets this operator see), sorted."""
    round_trip_s: float | None = None
    """The round trip to the work site, measured by its heartbeats echoing ours (the median of
    the last few; None: not measured, e.g. while this operator holds no control)."""
    reports: list[ExecutionReport] = field(default_factory=list)
    """The last 100 reports, each once; a program's reports in the order the work site sent
    them (by their stamps), also when its replay of earlier ones arrives after newer ones."""

    @property
    def label(self) -> str:
        """``connected``, ``stale`` (alive but silent) or ``not connected``."""
        if not self.work_site_alive:
            return "not connected"
        if self.last_state_age_s is None or self.last_state_age_s > STALE_AFTER_S:
            return "stale"
        return "connected"


@dataclass
class _Wire:
    """One zenoh session of a link and what the link declared on it."""

    session: zenoh.Session
    sub_state: zenoh.Subscriber
    state_arrivals: ArrivalRing
    frame_arrivals: ArrivalRing
    sub_camera: zenoh.Subscriber
    sub_report: zenoh.Subscriber
    sub_recognitions: zenoh.Subscriber
    sub_heartbeat: zenoh.Subscriber
    heartbeat_arrivals: ArrivalRing
    sub_alive: zenoh.Subscriber
    sub_sites: zenoh.Subscriber
    pub_program: zenoh.Publisher
    pub_stop: zenoh.Publisher
    pub_heartbeat: zenoh.Publisher
    followed: list[zenoh.Subscriber] = field(default_factory=list)
    """The subscribers of :meth:`WorkSiteLink.follow`, declared on this session."""

    @classmethod
    def open(cls, zenoh_config: zenoh.Config, site_id: str) -> _Wire:
        session = zenoh.open(zenoh_config)
        ring = zenoh.handlers.RingChannel
        # Stops and beats are never dropped by this side's queue (zenoh's DROP gives a message
        # up when the queue has not moved within a millisecond, which a loaded machine allows)
        # and never batched: they wait for room instead, on the caller's thread (the page's
        # for a stop, the beating thread's own for a beat), and go at once.
        block = zenoh.CongestionControl.BLOCK
        state_arrivals, frame_arrivals = ArrivalRing(STATE_ARRIVALS), ArrivalRing(FRAME_ARRIVALS)
        heartbeat_arrivals = ArrivalRing(HEARTBEAT_ARRIVALS)
        return cls(
            session=session,
            sub_state=session.declare_subscriber(key(site_id, "robot_state"), state_arrivals),
            state_arrivals=state_arrivals,
            sub_camera=session.declare_subscriber(key(site_id, "camera"), frame_arrivals),
            frame_arrivals=frame_arrivals,
            sub_report=session.declare_subscriber(key(site_id, "report"), ring(256)),
            sub_recognitions=session.declare_subscriber(key(site_id, "recognitions"), ring(1)),
            sub_heartbeat=session.declare_subscriber(key(site_id, "heartbeat"), heartbeat_arrivals),
            heartbeat_arrivals=heartbeat_arrivals,
            sub_alive=session.liveliness().declare_subscriber(
                alive_key(site_id, "work_site"), ring(16), history=True
            ),
            sub_sites=session.liveliness().declare_subscriber(
                ALL_WORK_SITES, ring(MAX_LISTED_SITES), history=True
            ),
            pub_program=session.declare_publisher(
                key(site_id, "program"), priority=zenoh.Priority.INTERACTIVE_HIGH
            ),
            pub_stop=session.declare_publisher(
                key(site_id, "stop"), priority=zenoh.Priority.REAL_TIME,
                congestion_control=block, express=True,
            ),
            pub_heartbeat=session.declare_publisher(
                key(site_id, "heartbeat"), priority=zenoh.Priority.REAL_TIME,
                congestion_control=block, express=True,
            ),
        )  # fmt: skip


class WorkSiteLink:
    """Subscribes to one work site's topics; open with a zenoh config, close when done."""

    def __init__(
        self,
        zenoh_config: zenoh.Config,
        site_id: str,
        operator_id: str | None = None,
        *,
        heartbeat_process: bool = True,
    ) -> None:
        """``heartbeat_process=False``: no child process beats for this link (a link that only
        watches; its programs, if any, then live on its thread's beats alone)."""
        self.site_id = site_id
        self.operator_id = operator_id or default_operator_id()
        """Who this operator site is to the work site's control lease."""
        self._renewal_config = renewal_config(zenoh_config)
        self._wire = _Wire.open(zenoh_config, site_id)
        self._wire_lock = threading.Lock()  # a renewal's swap against close()
        self._renewing: threading.Thread | None = None
        self._work_site = PeerWatch()
        self._heartbeat_seq = 0
        self._work_site_beat: tuple[float, float] | None = None
        """The work site's latest heartbeat: its stamp (its clock) and when it arrived
        (monotonic s), echoed by ours."""
        self._round_trips = RoundTrips()
        self._sites: set[str] = set()
        self._sites_wire: _Wire | None = None
        self._followers: list[tuple[str, Callable[[zenoh.Sample], None]]] = []
        self.status = LinkStatus()
        self.robot_state: RobotState | None = None
        self.camera_frame: CameraFrame | None = None
        self.recognitions: Recognitions | None = None
        """The latest recognitions the work site published (with its frame's ``seq``)."""
        self._state_rate, self._frame_rate = RateMeter(), RateMeter()
        self._newest_state: tuple[float, float] | None = None
        """The newest robot state's stamp (the work site's clock) and when it arrived
        (monotonic s), echoed by our beats."""
        self._last_frame_s: float | None = None
        self._warned: set[str] = set()
        self._unanswered: dict[str, tuple[bytes, float, float]] = {}
        """Programs sent but not answered yet: payload, when first and when last sent."""
        self._unfinished: dict[str, bytes] = {}
        """Programs answered but not finished: sent again when the work site comes back, which
        replays their reports (the work site never runs an id twice)."""
        self._seen_reports: set[tuple] = set()
        self._seen_order: collections.deque[tuple] = collections.deque()
        self._closing = threading.Event()
        # Started now, so that it is up (about a second) before a program needs it.
        self._beats = HeartbeatProcess(zenoh_config, site_id, self.operator_id)
        if heartbeat_process:
            self._beats.start()
        self._beating = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._beating.start()

    def _beat(self) -> None:
        """The heartbeat thread, until closed: beat while a program of ours is unfinished (the
        dead-man), and now and then while we hold the control lease (to keep it)."""
        idle_s, woke_s = 0.0, time.monotonic()
        while not self._closing.wait(HEARTBEAT_PERIOD_S):
            now = time.monotonic()
            late_s, woke_s = now - woke_s - HEARTBEAT_PERIOD_S, now
            if late_s > LATE_WAKE_S:
                # This process did not run this thread for that long (the machine, or another
                # thread holding the interpreter): the child's beats went on meanwhile.
                log.warning("heartbeat thread woke %.3f s late", late_s)
            idle_s += HEARTBEAT_PERIOD_S
            running = bool(self._unanswered or self._unfinished)
            newest_state = self._newest_state
            receiving = newest_state is not None and now - newest_state[1] < STALE_AFTER_S
            if (
                running
                or (self.holds_control and idle_s >= LEASE_BEAT_PERIOD_S)
                or (receiving and idle_s >= STREAM_ECHO_PERIOD_S)
            ):
                self._send_heartbeat()
                idle_s = 0.0
            if running:
                self._beats.beat()
            else:
                self._beats.rest()
        self._beats.close()

    @property
    def holds_control(self) -> bool:
        """Whether the work site says this operator holds its control lease."""
        return self.status.holder == self.operator_id

    @property
    def watching(self) -> bool:
        """Whether another operator holds the work site's control lease."""
        return self.status.holder not in ("", self.operator_id)

    def _send_heartbeat(self) -> None:
        echo_stamp_s = echo_held_s = 0.0
        if (work_site_beat := self._work_site_beat) is not None:
            echo_stamp_s = work_site_beat[0]
            echo_held_s = max(0.0, time.monotonic() - work_site_beat[1])
        state_echo_s = state_held_s = 0.0
        if (newest_state := self._newest_state) is not None:
            state_echo_s = newest_state[0]
            state_held_s = max(0.0, time.monotonic() - newest_state[1])
        beat = Heartbeat(
            site_id=self.site_id,
            role="operator_site",
            seq=self._heartbeat_seq,
            stamp_s=time.time(),
            operator=self.operator_id,
            echo_stamp_s=echo_stamp_s,
            echo_held_s=echo_held_s,
            state_echo_s=state_echo_s,
            state_echo_held_s=state_held_s,
        )
        self._heartbeat_seq += 1
        t0 = time.monotonic()
        try:
            self._put("pub_heartbeat", encode(beat))
        except zenoh.ZError:  # the link is closing
            return
        took_s = time.monotonic() - t0
        if took_s > LATE_WAKE_S:  # the publisher blocks while the link is congested
            log.warning("heartbeat #%d took %.3f s to send", beat.seq, took_s)
        log.debug("heartbeat #%d sent", beat.seq)

    def _decode(self, sample: zenoh.Sample, expected: type, what: str):
        try:
            return decode(sample.payload.to_bytes(), expected=expected)
        except ProtocolError as e:
            self.status.rejected += 1
            if what not in self._warned:  # once per kind: a bad stream must not flood the log
                self._warned.add(what)
                log.warning("rejected a %s message from %s: %s", what, sample.key_expr, e)
            return None

    def poll(self) -> tuple[bool, bool]:
        """Drain the rings; returns (new robot state?, new camera frame?). Never blocks."""
        now = time.monotonic()
        new_state = new_frame = False
        wire = self._wire
        if self._work_site.drain(wire.sub_alive):
            for pid, payload in self._unfinished.items():  # back: ask for what we missed
                self._unanswered[pid] = (payload, now, -math.inf)
        self.status.work_site_alive = self._work_site.alive
        if self._work_site.lost:
            self._work_site.lost = False
            self._renew()
        self._poll_sites(wire)
        arrivals = wire.state_arrivals.drain()
        for arrived_s, _ in arrivals:  # every state counts; only the newest is read
            self._state_rate.tick(arrived_s)
        for arrived_s, sample in reversed(arrivals):
            if (msg := self._decode(sample, RobotState, "robot state")) is not None:
                self.robot_state, new_state = msg, True
                self._newest_state = (msg.stamp_s, arrived_s)
                break
        arrivals = wire.frame_arrivals.drain()
        for arrived_s, _ in arrivals:
            self._frame_rate.tick(arrived_s)
        for arrived_s, sample in reversed(arrivals):
            if (msg := self._decode(sample, CameraFrame, "camera frame")) is not None:
                self.camera_frame, new_frame = msg, True
                self._frame_rate.read(arrived_s, msg.seq)
                self._last_frame_s = now
                offset_s = self._round_trips.clock_offset_s()
                arrived_unix_s = time.time() - (now - arrived_s)
                self.status.frame_age_s = (
                    None if offset_s is None else arrived_unix_s + offset_s - msg.stamp_s
                )
                break
        while (sample := wire.sub_report.try_recv()) is not None:
            if (msg := self._decode(sample, ExecutionReport, "execution report")) is not None:
                self._on_report(msg)
        while (sample := wire.sub_recognitions.try_recv()) is not None:
            if (msg := self._decode(sample, Recognitions, "recognitions")) is not None:
                self.recognitions = msg
        for arrived_s, sample in wire.heartbeat_arrivals.drain():
            beat = self._decode(sample, Heartbeat, "heartbeat")
            if beat is not None and beat.role == "work_site" and beat.site_id == self.site_id:
                self.status.holder = beat.operator
                self._work_site_beat = (beat.stamp_s, arrived_s)
                if beat.echo_operator == self.operator_id:
                    self._round_trips.add_beat(beat, time.time() - (now - arrived_s))
                    self.status.round_trip_s = self._round_trips.median_s()
        if self.status.work_site_alive:
            for pid, (payload, first_s, sent_s) in list(self._unanswered.items()):
                if now - first_s > GIVE_UP_AFTER_S:
                    log.warning("program %s: no answer from the work site in %.0f s; given up",
                                pid, GIVE_UP_AFTER_S)  # fmt: skip
                    self._unanswered.pop(pid, None)  # (a stop may have taken it meanwhile)
                elif now - sent_s >= RESEND_AFTER_S + (self.status.round_trip_s or 0.0):
                    self._put("pub_program", payload)
                    self._unanswered[pid] = (payload, first_s, now)
        s = self.status
        s.state_rate_hz = self._state_rate.rate_hz(now)
        s.frame_rate_hz = self._frame_rate.rate_hz(now)
        s.frame_share = self._frame_rate.share(now)
        newest_state = self._newest_state
        s.last_state_age_s = None if newest_state is None else now - newest_state[1]
        s.last_frame_age_s = None if self._last_frame_s is None else now - self._last_frame_s
        return new_state, new_frame

    def _poll_sites(self, wire: _Wire) -> None:
        changed = wire is not self._sites_wire
        if changed:  # a new session: its history lists who is alive now
            self._sites_wire, self._sites = wire, set()
        while (sample := wire.sub_sites.try_recv()) is not None:
            site = site_of_token(str(sample.key_expr))
            if site is None:
                continue
            if sample.kind == zenoh.SampleKind.PUT:
                self._sites.add(site)
            else:
                self._sites.discard(site)
            changed = True
        if changed:
            self.status.sites = sorted(self._sites)

    @property
    def running_programs(self) -> list[str]:
        """Programs this link sent that have not ended (a re-send may still be due)."""
        return sorted({*self._unanswered, *self._unfinished})

    def to_site(self, site_id: str) -> WorkSiteLink:
        """A new link to work site ``site_id``, through the same zenoh config, as the same
        operator (ProtocolError: not a site id)."""
        check_site_id(site_id)
        config = zenoh.Config.from_json5(self._renewal_config)
        return WorkSiteLink(config, site_id, self.operator_id)

    def _on_report(self, msg: ExecutionReport) -> None:
        """Track the program's answer, and keep the report once (replays repeat them)."""
        pid = msg.program_id
        if pid in self._unanswered:
            self._unfinished[pid] = self._unanswered.pop(pid)[0]
        if msg.command_index == -1 and msg.status in FINAL_STATUSES:
            self._unfinished.pop(pid, None)
        ident = (pid, msg.command_index, msg.status, msg.stamp_s)
        if ident in self._seen_reports:
            return
        self._seen_reports.add(ident)
        self._seen_order.append(ident)
        if len(self._seen_order) > REMEMBERED_REPORTS:
            self._seen_reports.discard(self._seen_order.popleft())
        # Each program's reports in the work site's order (their seq), whatever the arrival
        # order: an operator that comes back mid-program hears newer reports live before the
        # work site's replay of the earlier ones answers its re-send.
        reports = self.status.reports
        later = next(
            (i for i, r in enumerate(reports) if r.program_id == pid and r.seq > msg.seq),
            None,
        )
        if later is None:
            reports.append(msg)
        else:
            reports.insert(later, msg)
        del reports[:-100]

    def send_program(self, program: MotionProgram) -> None:
        """Publish a motion program to the work site, as this operator (its ``operator``
        unless the program names one); sent again (same id) every :data:`RESEND_AFTER_S` (and a
        round trip) until the work site answers, and again whenever it comes back before the
        program has finished. The work site runs each id at most once."""
        if not program.operator:  # sent as this operator: the lease goes by it
            program = dataclasses.replace(program, operator=self.operator_id)
        payload = encode(program)
        now = time.monotonic()
        self._unanswered[program.program_id] = (payload, now, now)
        self._beats.wait_ready()  # at once, but for a program sent as the link opened
        self._send_heartbeat()  # the dead-man's clock starts with the program, not a beat later
        self._beats.beat()  # from now, not from the thread's next turn
        self._put("pub_program", payload)

    def pending_programs(self) -> list[str]:
        """Ids of programs sent and not finished (answered or not)."""
        return sorted({*self._unanswered, *self._unfinished})

    def send_stop(self, reason: str) -> None:
        """Publish a stop to the work site. It cancels the programs sent and not yet answered
        (a stop can reach the work site before them), which are not sent again."""
        unanswered = list(self._unanswered)[-MAX_CANCELS:]
        self._put(
            "pub_stop", encode(Stop(reason=reason, stamp_s=time.time(), cancels=tuple(unanswered)))
        )
        for pid in unanswered:
            self._unanswered.pop(pid, None)

    def close(self) -> None:
        """Stop beating, undeclare everything and close the session (idempotent)."""
        self._closing.set()
        if self._beating.is_alive():
            self._beating.join()
        renewing = self._renewing
        if renewing is not None:
            renewing.join()
        with self._wire_lock:
            if not self._wire.session.is_closed():
                self._wire.session.close()

    def follow(self, topic: str, callback: Callable[[zenoh.Sample], None]) -> None:
        """Call ``callback`` (on zenoh's thread) with every sample on this work site's
        ``topic``: subscribed on the link's session now, and again on each new one after the
        work site was lost (see :meth:`session`)."""
        with self._wire_lock:
            self._followers.append((topic, callback))
            wire = self._wire
            wire.followed.append(
                wire.session.declare_subscriber(key(self.site_id, topic), callback)
            )

    @property
    def session(self) -> zenoh.Session:
        """The link's zenoh session now: a new one after the work site was lost, so that what a
        caller declares on it lasts until then only."""
        return self._wire.session

    def _put(self, publisher: str, payload: bytes) -> None:
        """Put ``payload`` on the current session's ``publisher``: again on the new session
        if a renewal closed the old one meanwhile. Raises ``zenoh.ZError`` once closed."""
        for _ in range(2):
            wire = self._wire
            try:
                getattr(wire, publisher).put(payload)
                return
            except zenoh.ZError:
                if wire is self._wire:
                    raise

    def _renew(self) -> None:
        """Replace the session by a new one (a new peer id), in a thread of its own, since
        opening waits for the work site (see ``protocol.session.PeerWatch``)."""
        if self._closing.is_set() or (self._renewing is not None and self._renewing.is_alive()):
            return
        self._renewing = threading.Thread(target=self._open_new_wire, name="renew", daemon=True)
        self._renewing.start()

    def _open_new_wire(self) -> None:
        try:
            wire = _Wire.open(zenoh.Config.from_json5(self._renewal_config), self.site_id)
        except zenoh.ZError as e:  # the old session goes on: better than none
            log.warning("work site %s lost; no new session (%s)", self.site_id, e)
            return
        with self._wire_lock:
            if self._closing.is_set():
                old = wire
            else:
                for topic, callback in self._followers:
                    wire.followed.append(
                        wire.session.declare_subscriber(key(self.site_id, topic), callback)
                    )
                old, self._wire = self._wire, wire
        old.session.close()
        log.info("work site %s lost: a new session (%s) waits for it", self.site_id,
                 wire.session.info.zid())  # fmt: skip
