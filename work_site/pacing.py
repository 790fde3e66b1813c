"""Pacing the work site's streams (robot states, camera frames) to what the operator's link carries.

A link slower than the streams (a long round trip with loss, a thin uplink) queues them: in
the work site's socket, in a router, at the bottleneck. Every frame then arrives seconds old,
and every state behind it too, however fresh each was when sent. The operator's heartbeats
echo the stamp of the newest robot state they had and when it arrived, on their own clock
(``Heartbeat.state_echo_s``, ``state_echo_held_s``). From these the work site measures

- the queue: the streams' round trip (out on the streams' link, back on the commands') less
  the smallest lately seen, LEDBAT's delay-based signal (RFC 6817), which sees a queue before
  any loss does;
- the share of what it sent that the link carries: states sent over an interval of its clock
  arrive spread over a longer one when the link is slower than the streams; the ratio of the
  two is that of the rates (BBR's delivery rate, without counting bytes).

A decision comes every :data:`MIN_SAMPLES` echoes (and no sooner than :data:`MIN_DECISION_S`).
Above :data:`QUEUE_TARGET_S`, unless the queue is already shrinking, the streams go at
:data:`DRAIN_GAIN` times the rate the link carried when they were sent: one step to below the
link's rate whatever the overload, and no second step for the same queue while it drains.
Below half of it they grow in proportion, fast up to near the rate at which the queue last
appeared and slowly past it (CUBIC's idea, in steps). One scale applies to both streams, never
below :data:`MIN_SCALE`. The smallest of a decision's echoes is what is judged, so that one
echo the operator read late (its process stalled) or one held behind a retransmission does
not thin the streams alone.

Times are the work site's ``time.time()`` (the clock of the echoed stamps) unless named the
operator's.
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
import threading
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

QUEUE_TARGET_S = 0.2
"""What the streams may wait in queues before the work site sends less (s): a camera period at
5 Hz, so that a frame never waits longer than skipping it would leave the view old."""
MIN_SCALE = 0.05
"""The thinnest the streams get: a 5 Hz camera's frame every 4 s and a 100 Hz arm's state 5 times
a second still show the operator that the robot moves."""
DRAIN_GAIN = 0.75
"""On a queue, the streams go at this fraction of the rate the link carried: the rest drains
the queue (in four times its length)."""
INCREASE_FACTOR = 1.25
"""Per decision without a queue, the scale grows by this factor: a step in proportion to the
rate, so that one step does not overfill a thin link (full rate from the thinnest in 14)..."""
PROBE_FACTOR = 1.05
"""... and by this one within :data:`CEILING_MARGIN` of the scale at which the queue last
appeared, so that the link is not overfilled again at once."""
CEILING_MARGIN = 0.8
MIN_DECISION_S = 0.25
"""Decisions come at most this often, whatever the round trip (s)."""
MIN_SAMPLES = 2
DELIVERY_SPAN_S = 1.0
"""The share the link carries is measured over echoes that arrived at least this far apart
(s, the operator's clock), and :data:`DELIVERY_SPAN_ROUND_TRIPS` base round trips: shorter, a
state's jitter or a retransmission's stall (about a round trip) would dominate it."""
DELIVERY_SPAN_ROUND_TRIPS = 2.0
DELIVERY_ECHOES = 256
FULL_SHARE = 0.8
"""A link that carried at least this share of the states sent is not too slow for them: their
queue is a stall (a retransmission on a lossy link, which fewer messages would not shorten),
unless it has grown for :data:`GROWING_DECISIONS` decisions in a row or stood for
:data:`STANDING_S` (the camera's frames, which zenoh sends after the states, may be what
overfills the link while the states pass)."""
GROWING_DECISIONS = 4
STANDING_S = 2.0
BASE_WINDOW_S = 60.0
"""The base round trip is the smallest over this long (s), in :data:`BASE_BUCKETS` buckets:
long enough to have seen the link empty, short enough to follow a route that got longer."""
BASE_BUCKETS = 6
FEEDBACK_STALE_S = 5.0
"""An operator not heard with an echo for this long no longer paces the streams (s); the
operator site echoes at least once a second while it receives them."""
MAX_OPERATORS = 64
PACED_JPEG_QUALITY = 50
"""The JPEG quality frames fall to as the streams thin: a noisy sensor's frame shrinks steeply
from the default 80 down to here and little below, while the blocks' edges stay plain to see."""
QUALITY_FLOOR_SCALE = 0.5
"""The scale at and below which frames go at :data:`PACED_JPEG_QUALITY`."""


def jpeg_quality(scale: float, full_quality: int) -> int:
    """The JPEG quality of frames sent at ``scale`` of the streams' full rates: ``full_quality``
    at full rate, falling linearly to :data:`PACED_JPEG_QUALITY` at :data:`QUALITY_FLOOR_SCALE`
    (never above ``full_quality``), so that a slow link gets smaller frames as well as fewer.
    The bytes a second fall monotonically with the scale: the pacing's loop sees a steeper link,
    not a different one."""
    if not 0.0 < scale <= 1.0:
        raise ValueError(f"stream scale {scale} outside (0, 1]")
    if full_quality <= PACED_JPEG_QUALITY:
        return full_quality
    fraction = max(0.0, (scale - QUALITY_FLOOR_SCALE) / (1.0 - QUALITY_FLOOR_SCALE))
    return round(PACED_JPEG_QUALITY + fraction * (full_quality - PACED_JPEG_QUALITY))


@dataclass
class _Operator:
    """One operator's feedback: the base round trip's bucket minima, the samples since the last
    decision, and its scale."""

    buckets: collections.deque[tuple[float, float]] = field(default_factory=collections.deque)
    samples: list[float] = field(default_factory=list)
    echoes: collections.deque[tuple[float, float]] = field(
        default_factory=lambda: collections.deque(maxlen=DELIVERY_ECHOES)
    )
    """Recent echoes: when the state was sent (ours) and when it arrived (the operator's)."""
    decided_s: float = -math.inf
    queue_s: float = 0.0
    """The queue the last decision saw (s)."""
    growing: int = 0
    """Decisions in a row that saw the queue grow."""
    above_s: float = math.inf
    """Since when the decisions have seen a queue above the target (inf: the last did not)."""
    ceiling: float = 1.0
    """The scale at which a queue last appeared (1: none did, or it was probed past)."""
    heard_s: float = -math.inf
    scale: float = 1.0

    def base_s(self) -> float:
        return min(m for _, m in self.buckets)

    def delivered(self) -> tuple[float, float] | None:
        """The share of what was sent that the link carried, and when the states it is
        measured on began to be sent; None until the echoes span long enough
        (:data:`DELIVERY_SPAN_S`). The best of the spans ending within the last one: a link
        too slow stretches every span, a retransmission's stall only those it ends in."""
        span_s = max(DELIVERY_SPAN_S, DELIVERY_SPAN_ROUND_TRIPS * self.base_s())
        echoes = self.echoes
        best: tuple[float, float] | None = None
        start = 0
        for end_sent_s, end_arrived_s in echoes:
            while start + 1 < len(echoes) and end_arrived_s - echoes[start + 1][1] >= span_s:
                start += 1
            sent_s, arrived_s = echoes[start]
            if end_arrived_s - arrived_s < span_s or end_arrived_s < echoes[-1][1] - span_s:
                continue
            share = (end_sent_s - sent_s) / (end_arrived_s - arrived_s)
            if best is None or share > best[0]:
                best = (share, sent_s)
        return best

    def add_base(self, now_s: float, round_trip_s: float) -> None:
        width_s = BASE_WINDOW_S / BASE_BUCKETS
        if self.buckets and now_s - self.buckets[-1][0] < width_s:
            start_s, low_s = self.buckets[-1]
            self.buckets[-1] = (start_s, min(low_s, round_trip_s))
        else:
            self.buckets.append((now_s, round_trip_s))
        while len(self.buckets) > BASE_BUCKETS:
            self.buckets.popleft()


class StreamPacer:
    """The fraction (:data:`MIN_SCALE`–1) of their nominal rates at which robot states and camera
    frames are sent, from the operators' echoes. Thread-safe: echoes arrive on zenoh's threads,
    the control loop asks for the scale."""

    def __init__(self) -> None:
        self._operators: collections.OrderedDict[str, _Operator] = collections.OrderedDict()
        self._lock = threading.Lock()
        self._applied: collections.deque[tuple[float, float]] = collections.deque(
            [(-math.inf, 1.0)], maxlen=1024
        )
        """The scale sent at since each time it changed, to know what an echoed state went at."""

    def heard(
        self,
        operator: str,
        now_s: float,
        round_trip_s: float,
        sent_s: float = math.nan,
        arrived_s: float = math.nan,
    ) -> None:
        """``operator`` echoed, heard at ``now_s``, a robot state whose round trip (out on the
        streams' link, back on the commands') was ``round_trip_s``; it was sent at ``sent_s``
        and arrived at ``arrived_s`` on the operator's clock (NaN: not said)."""
        if not operator or not math.isfinite(round_trip_s) or round_trip_s < 0.0:
            return
        with self._lock:
            op = self._operators.get(operator)
            if op is None:
                op = self._operators[operator] = _Operator()
                while len(self._operators) > MAX_OPERATORS:
                    self._operators.popitem(last=False)
            self._operators.move_to_end(operator)
            op.heard_s = now_s
            op.add_base(now_s, round_trip_s)
            if (
                math.isfinite(sent_s)
                and math.isfinite(arrived_s)
                and (not op.echoes or op.echoes[-1] < (sent_s, arrived_s))
            ):
                op.echoes.append((sent_s, arrived_s))
            op.samples.append(round_trip_s)
            if len(op.samples) >= MIN_SAMPLES and now_s - op.decided_s >= MIN_DECISION_S:
                self._decide(operator, op, now_s)

    def _decide(self, operator: str, op: _Operator, now_s: float) -> None:
        queue_s = min(op.samples) - op.base_s()
        op.growing = op.growing + 1 if queue_s > op.queue_s else 0
        op.above_s = min(op.above_s, now_s) if queue_s > QUEUE_TARGET_S else math.inf
        standing = now_s - op.above_s >= max(STANDING_S, DELIVERY_SPAN_ROUND_TRIPS * op.base_s())
        shrinking = queue_s < op.queue_s  # draining already: a cut would only idle the link
        delivered = op.delivered()
        share, sent_scale = (1.0, op.scale) if delivered is None else (
            min(1.0, delivered[0]), self._applied_at(delivered[1]))  # fmt: skip
        too_slow = (
            delivered is None or share < FULL_SHARE or op.growing >= GROWING_DECISIONS or standing
        )
        if (
            queue_s > QUEUE_TARGET_S
            and (standing or not shrinking)
            and too_slow
            and (op.scale > MIN_SCALE)
        ):
            new_queue = op.queue_s <= QUEUE_TARGET_S
            if new_queue:  # remember where it appeared
                op.ceiling = op.scale
            scale = max(MIN_SCALE, min(op.scale * DRAIN_GAIN if standing else op.scale,
                                       DRAIN_GAIN * share * sent_scale))  # fmt: skip
            op.above_s = now_s if standing else op.above_s  # one cut per standing period
            if scale < op.scale:
                op.scale = scale
                (log.info if new_queue else log.debug)(
                    "streams to %s paced to %.0f %% of their rates: its link queued them "
                    "%.2f s (base round trip %.2f s) and carried %.0f %% of them",
                    operator, 100 * op.scale, queue_s, op.base_s(), 100 * share,
                )  # fmt: skip
        elif queue_s < QUEUE_TARGET_S / 2 and op.scale < 1.0:
            near = op.scale * INCREASE_FACTOR > CEILING_MARGIN * op.ceiling
            op.scale = min(1.0, op.scale * (PROBE_FACTOR if near else INCREASE_FACTOR))
            if op.scale > op.ceiling:
                op.ceiling = 1.0  # the link carries more now than when it queued
            if op.scale == 1.0:
                log.info("streams to %s back at their full rates", operator)
        log.debug("pacing %s: queue %.3f s over %d echoes, scale %.3f, ceiling %.3f",
                  operator, queue_s, len(op.samples), op.scale, op.ceiling)  # fmt: skip
        op.samples.clear()
        op.decided_s = now_s
        op.queue_s = queue_s

    def scale(self, now_s: float, holder: str = "") -> float:
        """The scale to send at now: the lease holder's when it echoes, else the slowest
        operator's that does (1.0 when none does)."""
        with self._lock:
            fresh = {
                name: op.scale
                for name, op in self._operators.items()
                if now_s - op.heard_s <= FEEDBACK_STALE_S
            }
            scale = fresh[holder] if holder in fresh else min(fresh.values(), default=1.0)
            if scale != self._applied[-1][1]:
                self._applied.append((now_s, scale))
        return scale

    def _applied_at(self, when_s: float) -> float:
        """The scale the streams went at, at ``when_s`` (the lock held)."""
        i = bisect.bisect_right(self._applied, when_s, key=lambda change: change[0])
        return self._applied[max(0, i - 1)][1]
