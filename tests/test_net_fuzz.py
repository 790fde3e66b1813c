"""Fuzzing the work site's decoder and command handling: ≥ 10,000 generated payloads.

Every payload goes (1) into ``protocol.decode``, which may only raise ``ProtocolError``, and
(2) into the real :class:`WorkSiteServer`'s command handling (``_handle_programs``, and the
stop inbox that validates stops as they arrive, then ``_handle_stops``) both as a program and as
a stop, in-process against a real pybullet world and task controller; only the zenoh program
ring and the report publisher are stand-ins. An invalid payload must be refused (counted,
answered with a "refused" report when it came as a program) and must start no motion: no
execution, no controller move, the joint targets unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.robot import load_robot
from models.scene import load_scene
from protocol import (
    ExecutionReport,
    MotionProgram,
    ProtocolError,
    Stop,
    claimed_program_id,
    decode,
    encode,
)
from tests.conftest import examples, one_move_program
from work_site.control.controller import TaskController
from work_site.inbox import stop_inbox
from work_site.intake import INVALID_REPORTS_PER_S
from work_site.options import ServerOptions
from work_site.server import WorkSiteServer
from work_site.world import World

EXAMPLES_PER_STRATEGY = 2600
"""Four strategies × 2,600 = 10,400 payloads, each into the decoder and both inboxes."""

FUZZ = settings(
    max_examples=examples(EXAMPLES_PER_STRATEGY),
    deadline=None,
    derandomize=True,  # the same payloads every run: a failure is reproducible
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


VALID_PROGRAM = encode(one_move_program("p"))
VALID_STOP = encode(Stop(reason="fuzz", stamp_s=1.0))


# ---------------------------------------------------------------------- the server under test


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:
    payload: _Payload


class _Inbox:
    """Stands in for a zenoh subscriber with a ring: ``try_recv`` until empty."""

    def __init__(self) -> None:
        self.items: list[_Sample] = []

    def push(self, data: bytes) -> None:
        self.items.append(_Sample(_Payload(data)))

    def try_recv(self) -> _Sample | None:
        return self.items.pop(0) if self.items else None


class _ReportPublisher:
    def __init__(self) -> None:
        self.reports: list[ExecutionReport] = []

    def put(self, payload: bytes) -> None:
        self.reports.append(decode(payload, ExecutionReport))


class Harness:
    """A real WorkSiteServer's command handling on a real world, without the network."""

    def __init__(self) -> None:
        scene = load_scene()
        self.world = World(scene)
        self.server = WorkSiteServer(scene, zenoh.Config(), ServerOptions(camera=False))
        self.controller = TaskController(self.world, load_robot(scene.robot.urdf_path))
        self.server._controller = self.controller
        self.publisher = _ReportPublisher()
        self.server._pub_report = self.publisher
        self.programs, self.stops = _Inbox(), stop_inbox(None, "stop")
        self.q_target0 = np.array(self.world.q_target, copy=True)

    def reset(self) -> None:
        self.server._execution = None
        self.server._reports.clear()
        self.server._seen.clear()
        self.server._ids.clear()
        self.server._busy = None
        self.server._ready.clear()
        self.controller.move = None
        self.world.q_target = self.q_target0.copy()
        self.publisher.reports.clear()
        self.server._invalid_report_budget = INVALID_REPORTS_PER_S  # one report each here

    def handle(self, program: bytes | None = None, stop: bytes | None = None) -> None:
        if program is not None:
            self.programs.push(program)
        if stop is not None:
            self.stops.offer(stop)
        self.server._handle_stops(self.stops.drain())
        self.server._handle_programs(self.programs)  # the checking thread's part
        self.server._start_ready()  # the control loop's

    def moving(self) -> bool:
        return (
            self.server._execution is not None
            or self.controller.move is not None
            or not np.array_equal(self.world.q_target, self.q_target0)
        )

    def close(self) -> None:
        self.world.close()


@pytest.fixture(scope="module")
def harness() -> Iterator[Harness]:
    h = Harness()
    yield h
    h.close()


def check_payload(harness: Harness, payload: bytes) -> None:
    """The decoder refuses or accepts cleanly; the server never crashes and an invalid payload
    moves nothing."""
    valid_program = valid_stop = True
    try:
        decode(payload, MotionProgram)
    except ProtocolError:
        valid_program = False
    try:
        decode(payload, Stop)
    except ProtocolError:
        valid_stop = False
    try:
        decode(payload)
    except ProtocolError:
        pass

    harness.reset()
    refused = harness.server.stats["refused"]
    harness.handle(program=payload)
    reports = harness.publisher.reports
    if not valid_program:
        assert not harness.moving(), payload
        assert harness.server.stats["refused"] == refused + 1
        # Refused under the id it claims, if a valid one, else "invalid".
        claimed = claimed_program_id(payload)
        assert [r.status for r in reports] == ["refused"]
        assert reports[0].program_id in {"invalid", claimed}, (reports[0].program_id, claimed)
    else:  # a well-formed program is either accepted or refused, with a report either way
        assert reports and reports[0].status in ("accepted", "refused")

    harness.reset()
    dropped = harness.stops.dropped.total
    harness.handle(stop=payload)
    assert not harness.moving()  # a stop never moves, valid or not
    assert harness.stops.dropped.total == dropped + (0 if valid_stop else 1)
    # A valid stop with nothing running is answered (at most once in a while); garbage never.
    replies = [(r.program_id, r.status) for r in harness.publisher.reports]
    assert replies in ([("stop", "stopped")], []) if valid_stop else replies == []


# ------------------------------------------------------------------------------ strategies


def msgpack_values() -> st.SearchStrategy[Any]:
    scalars = (
        st.none()
        | st.booleans()
        | st.integers(-(2**64), 2**64 - 1)
        | st.floats(allow_nan=True, allow_infinity=True)
        | st.text(max_size=40)
        | st.binary(max_size=64)
    )
    return st.recursive(
        scalars,
        lambda children: (
            st.lists(children, max_size=6)
            | st.dictionaries(st.text(max_size=8), children, max_size=6)
        ),
        max_leaves=30,
    )


def _pack(value: Any) -> bytes:
    try:
        return msgpack.packb(value, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        return b"\xc1"  # msgpack's "never used" byte


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (tuple of keys and indices) into a decoded msgpack document."""
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


_PROGRAM_DOC = msgpack.unpackb(VALID_PROGRAM, raw=False)
_STOP_DOC = msgpack.unpackb(VALID_STOP, raw=False)
_DOC_PATHS = [(doc, p) for doc in (_PROGRAM_DOC, _STOP_DOC) for p in _paths(doc) if p]


@st.composite
def mutated_envelopes(draw: st.DrawFn) -> bytes:
    """A valid program or stop with one value replaced, one key deleted or one key added."""
    doc, path = draw(st.sampled_from(_DOC_PATHS))
    doc = msgpack.unpackb(msgpack.packb(doc, use_bin_type=True), raw=False)  # a deep copy
    parent = doc
    for step in path[:-1]:
        parent = parent[step]
    last = path[-1]
    action = draw(st.sampled_from(["replace", "delete", "add"]))
    if action == "replace":
        parent[last] = draw(msgpack_values())
    elif action == "delete" and isinstance(parent, dict):
        del parent[last]
    elif action == "delete":
        parent.pop(last)
    elif isinstance(parent, dict):
        parent[draw(st.text(max_size=8))] = draw(msgpack_values())
    else:
        parent.append(draw(msgpack_values()))
    return _pack(doc)


@st.composite
def corrupted_bytes(draw: st.DrawFn) -> bytes:
    """A valid payload with bytes flipped, cut short or extended."""
    data = bytearray(draw(st.sampled_from([VALID_PROGRAM, VALID_STOP])))
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(data) - 1))
        data[i] ^= draw(st.integers(1, 255))
    cut = draw(st.integers(0, len(data)))
    tail = draw(st.binary(max_size=16))
    return bytes(data[:cut] + tail) if draw(st.booleans()) else bytes(data)


# ----------------------------------------------------------------------------------- tests


@FUZZ
@given(payload=st.binary(max_size=512))
def test_random_bytes(harness: Harness, payload: bytes) -> None:
    check_payload(harness, payload)


@FUZZ
@given(payload=msgpack_values().map(_pack))
def test_random_msgpack_documents(harness: Harness, payload: bytes) -> None:
    check_payload(harness, payload)


@FUZZ
@given(payload=mutated_envelopes())
def test_mutated_programs_and_stops(harness: Harness, payload: bytes) -> None:
    check_payload(harness, payload)


@FUZZ
@given(payload=corrupted_bytes())
def test_corrupted_programs_and_stops(harness: Harness, payload: bytes) -> None:
    check_payload(harness, payload)


def test_the_harness_can_see_motion(harness: Harness) -> None:
    """The check above could not fail if the harness never saw motion: a valid program moves,
    a valid stop halts it, a re-sent program only has its reports replayed."""
    harness.reset()
    harness.handle(program=VALID_PROGRAM)
    assert [r.status for r in harness.publisher.reports] == ["accepted"]
    assert harness.server._execution is not None
    for _ in range(3):
        harness.server._execution.tick()
    assert harness.moving()
    harness.handle(stop=VALID_STOP)
    assert harness.server._execution.finished
    harness.server._release_finished()
    harness.server._execution = None
    before = len(harness.publisher.reports)
    harness.handle(program=VALID_PROGRAM)  # the same id again: replayed, never run again
    replayed = harness.publisher.reports[before:]
    assert [r.status for r in replayed] == [r.status for r in harness.publisher.reports[:before]]
    assert harness.server._execution is None


def test_a_malformed_program_is_refused_under_the_id_it_claims(harness: Harness) -> None:
    """Its sender waits on that id: the refusal says why under it. An id the work site has
    seen before never gets another payload's refusal added to its reports."""
    envelope = msgpack.unpackb(encode(one_move_program("mine-1")), raw=False)
    envelope["b"]["speed"] = 1  # a field programs do not have
    harness.reset()
    harness.handle(program=msgpack.packb(envelope))
    reports = harness.publisher.reports
    assert [(r.program_id, r.status) for r in reports] == [("mine-1", "refused")]
    assert "speed" in reports[0].message and not harness.moving()
    harness.reset()
    harness.handle(program=VALID_PROGRAM)
    envelope["b"]["program_id"] = decode(VALID_PROGRAM, MotionProgram).program_id
    harness.handle(program=msgpack.packb(envelope))
    assert [(r.program_id, r.status) for r in harness.publisher.reports][-1] == (
        "invalid",
        "refused",
    )


def test_a_stop_with_nothing_running_is_answered_once_in_a_while(harness: Harness) -> None:
    harness.reset()
    harness.server._stop_replied_s = -math.inf
    harness.handle(stop=VALID_STOP)
    harness.handle(stop=VALID_STOP)  # at once again: held, not answered twice
    reports = harness.publisher.reports
    assert [(r.program_id, r.status) for r in reports] == [("stop", "stopped")]
    assert "no program was running" in reports[0].message
