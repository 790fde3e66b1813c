"""The program journal: every program id the work site ever received, and the reports of the
newest ones, so that no id is run twice, also across restarts.

The file is JSON lines. ``{"program_id": id, "report": hex}`` is one report sent (appended as it
is sent); ``{"ids": [id, ...]}`` lists ids whose reports are no longer kept. Once the report lines
pass :data:`COMPACT_AFTER_LINES` the file is rewritten (to a temporary file, then renamed over
it): the ids in ``ids`` lines, the reports of the newest programs only. Its size, and the time to
read it at start-up, then grow with the number of ids alone, a few bytes each.

Lines are written and flushed by a thread of their own, so that the control loop never waits for
the disk.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol import ExecutionReport, ProtocolError, decode, encode

log = logging.getLogger("work-site")

WRITE_BATCH = 256
"""Lines written at most before each flush."""
COMPACT_AFTER_LINES = 20_000
"""Report lines appended since the last rewrite that make the journal rewrite itself."""
IDS_PER_LINE = 10_000
FINAL_STATUSES = ("done", "failed", "refused", "stopped")


def journal_line(program_id: str, payload: bytes) -> str:
    """One journal line: a program id and one of its encoded reports."""
    return json.dumps({"program_id": program_id, "report": payload.hex()}) + "\n"


def ids_lines(ids: list[str]) -> Iterable[str]:
    """Journal lines listing ``ids``, :data:`IDS_PER_LINE` to a line."""
    for i in range(0, len(ids), IDS_PER_LINE):
        yield json.dumps({"ids": ids[i : i + IDS_PER_LINE]}) + "\n"


@dataclass
class JournalState:
    """What a journal holds: ``reports`` of the newest ``kept`` programs (oldest first), every
    id ever received in ``ids`` (append order) and ``seen`` (the same, as a set), and the closing
    reports ``added`` for kept programs that a restart interrupted; ``report_lines``: report
    lines in the file."""

    reports: collections.OrderedDict[str, list[bytes]] = field(
        default_factory=collections.OrderedDict
    )
    ids: list[str] = field(default_factory=list)
    seen: set[str] = field(default_factory=set)
    added: list[tuple[str, bytes]] = field(default_factory=list)
    report_lines: int = 0


def load_journal(path: Path, kept: int) -> JournalState:
    """Read a journal (see the module's docstring). Unreadable lines are skipped (a crash may
    leave the last one half written), and so is a report already read (same program and seq:
    a rewrite may repeat one). A report an older schema wrote cannot be replayed to today's
    operators, but its program id is still remembered, so that a re-send never runs it."""
    state = JournalState()
    reports, seen = state.reports, state.seen
    last: dict[str, ExecutionReport | None] = {}
    if not path.exists():
        return state
    with path.open(errors="replace") as f:
        for line in f:
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if not isinstance(entry, dict):
                continue
            if isinstance(entry.get("ids"), list):
                new = [i for i in entry["ids"] if isinstance(i, str) and i not in seen]
                seen.update(new)
                state.ids.extend(new)
                continue
            try:
                pid, payload = str(entry["program_id"]), bytes.fromhex(entry["report"])
            except (ValueError, KeyError, TypeError):
                continue
            state.report_lines += 1
            if pid not in seen:
                seen.add(pid)
                state.ids.append(pid)
            payloads = reports.setdefault(pid, [])
            reports.move_to_end(pid)
            while len(reports) > kept:  # keep the newest only, as we go
                reports.popitem(last=False)
            try:
                report = decode(payload, expected=ExecutionReport)
            except ProtocolError:
                last.setdefault(pid, None)
                continue
            if report.seq < len(payloads):
                continue
            last[pid] = report
            payloads.append(payload)
    for pid, payloads in reports.items():
        final = last.get(pid)
        if final is not None and final.command_index == -1 and final.status in FINAL_STATUSES:
            continue
        message = (
            "interrupted: the work site restarted during this program"
            if final is not None
            else "run by an earlier version of the work site, whose reports cannot be "
            "replayed; not run again"
        )
        closing = encode(
            ExecutionReport(
                program_id=pid,
                command_index=-1,
                status="failed",
                wrench_S=np.zeros(6),
                message=message,
                stamp_s=time.time(),
                seq=len(payloads),
            )
        )
        payloads.append(closing)
        state.added.append((pid, closing))
    return state


def write_journal(path: Path, ids: list[str], reports: Iterable[tuple[str, list[bytes]]]) -> None:
    """Write a compacted journal atomically: ``ids`` (every id received, the kept ones among
    them) and the kept programs' ``reports``."""
    reports = list(reports)
    kept = {pid for pid, payloads in reports if payloads}
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as f:
        f.writelines(ids_lines([i for i in ids if i not in kept]))
        for pid, payloads in reports:
            f.writelines(journal_line(pid, payload) for payload in payloads)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


Snapshot = Callable[[], tuple[int, list[tuple[str, list[bytes]]]]]
"""Called with the writer's lock held: how many of the ids list are journaled, and the kept
programs' reports."""


class JournalWriter:
    """Appends :func:`journal_line`s to ``path`` on its own thread; :meth:`append` never
    blocks. Each line's ``then`` (the report's sending) is called once the line is written
    and flushed to the operating system, where a crash of the work site cannot lose it: a
    report the operators saw is one a restarted work site knows (a program it said it
    received is never run again). Past ``compact_after_lines`` report lines (default
    :data:`COMPACT_AFTER_LINES`) it rewrites the file from ``ids`` (the work site's append-only
    list of ids received) and ``snapshot``, taken with ``lock`` held: the lock under which the
    work site appends, so that the rewrite holds every report queued
    so far exactly once. :meth:`close` writes what is queued and closes the file."""

    def __init__(
        self,
        path: Path,
        ids: list[str] | None = None,
        snapshot: Snapshot | None = None,
        lock: threading.Lock | None = None,
        report_lines: int = 0,
        compact_after_lines: int | None = None,
    ) -> None:
        self.path = path
        self._ids, self._snapshot, self._lock = ids, snapshot, lock
        self._lines = report_lines
        self._compact_after = compact_after_lines or COMPACT_AFTER_LINES
        self.rewrites = 0
        self._file = path.open("a")
        self._queue: queue.SimpleQueue[tuple[str, Callable[[], None] | None] | None] = (
            queue.SimpleQueue()
        )
        self._thread = threading.Thread(target=self._run, name="journal", daemon=True)
        self._thread.start()

    def append(
        self, program_id: str, payload: bytes, then: Callable[[], None] | None = None
    ) -> None:
        """Journal report ``payload`` of ``program_id``; ``then`` once it is on file."""
        self._queue.put((journal_line(program_id, payload), then))

    def sync(self, timeout_s: float) -> bool:
        """Wait (at most ``timeout_s``) until everything appended so far is on file and sent
        on; whether it is."""
        done = threading.Event()
        self._queue.put(("", done.set))
        return done.wait(timeout_s)

    def _run(self) -> None:
        closing = False
        while not closing:
            items = [self._queue.get()]
            for _ in range(WRITE_BATCH - 1):  # whatever else is queued, in one flush
                try:
                    items.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            if None in items:
                closing = True
            entries = [item for item in items if item is not None]
            try:
                self._file.writelines(line for line, _ in entries)
                self._file.flush()
                self._lines += sum(1 for line, _ in entries if line)  # "": a sync
            except (OSError, ValueError):  # ValueError: the file closed by a failed rewrite
                # Not journaled: the reports still go out (holding them would hide the
                # robot's state from the operators); the log says why a restart may not know.
                log.exception("could not write the program journal %s", self.path)
            _call_each(then for _, then in entries)
            if self._lines > self._compact_after and self._snapshot is not None:
                try:
                    closing = self._compact() or closing
                except OSError:
                    log.exception("could not rewrite the program journal %s", self.path)

    def _compact(self) -> bool:
        """Rewrite the file from a snapshot; whether a close was queued meanwhile."""
        closing = False
        dropped: list[Callable[[], None] | None] = []
        with self._lock:
            # Everything queued now is in the snapshot: drop it rather than write it twice
            # (its reports are sent once the rewrite holds them).
            for _ in range(self._queue.qsize() + 1):
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    closing = True
                else:
                    dropped.append(item[1])
            n_ids, reports = self._snapshot()
        ids = self._ids[:n_ids]  # append-only: its prefix is stable without the lock
        try:
            self._file.close()
            write_journal(self.path, ids, reports)
        finally:
            _call_each(dropped)
            self._file = self.path.open("a")
        self._lines = sum(len(p) for _, p in reports)
        self.rewrites += 1
        log.info("program journal compacted: %d ids, %d programs' reports", len(ids), len(reports))
        return closing

    def close(self) -> None:
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._file.close()


def _call_each(callbacks: Iterable[Callable[[], None] | None]) -> None:
    """Call each callback given, in order; one that raises is logged and the rest still run."""
    for then in callbacks:
        if then is None:
            continue
        try:
            then()
        except Exception:
            log.exception("a journaled report could not be sent")
