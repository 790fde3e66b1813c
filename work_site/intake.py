"""Programs off the wire, for the work-site server: decoded and checked whole on a thread of
their own, each program id run at most once (a re-send gets its reports replayed, or a refusal
when they are no longer kept), refusals of undecodable ones rate-limited.

:class:`ProgramIntake` is a part of :class:`~work_site.server.WorkSiteServer`, kept apart for
size: it works on the server's state (``_lock``, ``_reports``, ``_ids``, ``_seen``, ``_busy``,
``_ready``, ``_stops_seen``, ``_cancelled``) and reports through its ``_report``.
"""

from __future__ import annotations

import logging
import threading
import time

from protocol import (
    INVALID_PROGRAM_ID,
    RESERVED_PROGRAM_IDS,
    ExecutionReport,
    MotionProgram,
    ProtocolError,
    claimed_program_id,
    decode,
    encode,
)
from work_site.control.executor import (
    CheckCancelledError,
    Execution,
    program_refusal,
    same_program,
)

log = logging.getLogger("work-site")

INBOX_CAPACITY = 64
"""Program samples waiting to be decoded; beyond it the oldest are dropped (and counted)."""
INVALID_REPORTS_PER_S = 10.0
"""Undecodable programs answered with a "refused" report at most this often: a flood of
garbage must not turn into a flood of reports; the rest are counted and summed up in the log."""
REMEMBERED_PROGRAMS = 100
"""Programs whose reports are kept to replay to a re-send; every id is remembered (and never
run again), these with their reports."""
REMEMBERED_CANCELS = 1000
"""Program ids cancelled by stops before they arrived, kept so that they never start."""
CHECK_IDLE_S = 0.002
"""The checking thread looks for new programs this often when there are none (s)."""
CHECK_YIELD_S = 1e-4
"""The checking thread sleeps this long before each command it checks (s)."""


class ProgramIntake:
    """The server's methods that take programs off the wire (see the module docstring)."""

    def _remember(self, program_id: str) -> None:
        """(With the lock held.)"""
        self._reports[program_id] = []
        while len(self._reports) > REMEMBERED_PROGRAMS:
            self._reports.popitem(last=False)
        if program_id not in self._seen:
            self._seen.add(program_id)
            self._ids.append(program_id)

    def _journal_snapshot(self) -> tuple[int, list[tuple[str, list[bytes]]]]:
        """(Called by the journal's writer with the lock held.) The ids journaled, and the
        kept programs' reports."""
        return len(self._ids), [(pid, list(p)) for pid, p in self._reports.items()]

    def _refuse_invalid(self, error: ProtocolError, payload: bytes) -> None:
        """Count an undecodable program; answer it while the report budget lasts, under the
        program id it claims if it claims a valid one (its sender is waiting on that id),
        else under ``invalid``."""
        self.stats["refused"] += 1
        self._invalid_programs.add(str(error))
        now = time.monotonic()
        self._invalid_report_budget = min(
            INVALID_REPORTS_PER_S,
            self._invalid_report_budget + (now - self._invalid_report_s) * INVALID_REPORTS_PER_S,
        )
        self._invalid_report_s = now
        if self._invalid_report_budget >= 1.0:
            self._invalid_report_budget -= 1.0
            pid = claimed_program_id(payload)
            with self._lock:
                known = pid is None or pid in self._seen
            pid = INVALID_PROGRAM_ID if known else pid  # never add to a real program's reports
            self._report(pid, -1, "refused", f"program refused: {error}", fresh=False)

    def _resumed(self, program: MotionProgram) -> tuple[Execution | None, str]:
        """For a program that resumes a stopped one: the stopped execution, or why it may not
        run (the one it names must be the last to have run, stopped, with the same grasp and
        commands)."""
        if not program.continues:
            return None, ""
        last = self._execution
        if last is None or last.program.program_id != program.continues:
            ran = "no program" if last is None else f"program {last.program.program_id}"
            return None, (
                f"cannot resume program {program.continues}: {ran} ran last on this work "
                "site (a program resumes only the last one, when nothing moved the arm since)"
            )
        if last.end_status != "stopped":
            how = {"done": "ran to its end", "": "is still running"}.get(
                last.end_status, last.end_status
            )
            return None, f"cannot resume program {program.continues}: it {how}, not stopped"
        if not same_program(last.program, program):
            return None, (
                f"cannot resume program {program.continues}: this program's grasp or commands "
                "are not that program's"
            )
        return last, ""

    def _check_programs(self, inbox_program, done: threading.Event) -> None:
        """The checking thread: take programs off the wire until ``done``."""
        while not done.is_set():
            try:
                if not self._handle_programs(inbox_program):
                    time.sleep(CHECK_IDLE_S)
            except Exception:  # a fault of ours: log it, keep checking
                log.exception("internal fault while checking a program")
                with self._lock:
                    self._busy = None

    def _handle_programs(self, inbox_program) -> int:
        """Decode and check the programs received (at most a ring's worth); how many."""
        for n in range(INBOX_CAPACITY):
            sample = inbox_program.try_recv()
            if sample is None:
                return n
            payload = sample.payload.to_bytes()
            try:
                program = decode(payload, expected=MotionProgram)
            except ProtocolError as e:
                self._refuse_invalid(e, payload)
                continue
            self._take_program(program)
        return INBOX_CAPACITY

    def _cancel_ahead(self, program_ids, reason: str) -> None:
        """A stop named these programs: any of them not yet received never starts (a stop
        can overtake the program sent just before it)."""
        with self._lock:
            for pid in program_ids:
                if pid not in self._seen:
                    self._cancelled[pid] = reason
                    self._cancelled.move_to_end(pid)
            while len(self._cancelled) > REMEMBERED_CANCELS:
                self._cancelled.popitem(last=False)

    def _take_program(self, program: MotionProgram) -> None:
        """Answer a re-send from the reports kept, refuse a program while another is checked
        or runs, else check it whole and hand it to the control loop."""
        pid = program.program_id
        if pid in RESERVED_PROGRAM_IDS:
            self.stats["refused"] += 1
            self._report(
                INVALID_PROGRAM_ID, -1, "refused",
                f"program id {pid!r} is the work site's own (it answers under "
                f"{', '.join(sorted(RESERVED_PROGRAM_IDS))}): choose another",
                fresh=False,
            )  # fmt: skip
            return
        with self._lock:
            replay = list(self._reports.get(pid, ())) if pid in self._reports else None
            forgotten = replay is None and pid in self._seen
            busy = self._busy
            cancelled = self._cancelled.pop(pid, None)
            if replay is None and not forgotten:
                self._remember(pid)
                if busy is None and cancelled is None:
                    self._busy, stops_seen = pid, self._stops_seen
        if cancelled is not None and replay is None and not forgotten:
            self._report(
                pid, -1, "stopped", f"stop: {cancelled} (sent before it, arrived after it)",
                fresh=False,
            )  # fmt: skip
            log.info("program %s arrived after a stop that cancelled it: not run", pid)
            return
        if forgotten:
            # Received long ago: its reports are no longer kept, but it never runs again.
            self.stats["duplicates"] = self.stats.get("duplicates", 0) + 1
            self._pub_report.put(
                encode(
                    ExecutionReport(
                        program_id=pid,
                        command_index=-1,
                        status="refused",
                        wrench_S=self._wrench_S,
                        message="received before (its reports are no longer kept): "
                        "a program id runs at most once",
                        stamp_s=time.time(),
                    )
                )
            )
            log.info("program %s received again, long after: refused", pid)
            return
        if replay is not None:
            # A re-send (the operator missed our answer, or reconnected): never run twice;
            # replay every report so far, in order.
            for payload in replay:
                self._pub_report.put(payload)
            self.stats["duplicates"] = self.stats.get("duplicates", 0) + 1
            log.info("program %s received again: %d reports replayed", pid, len(replay))
            return
        holder = self._lease.take(program.operator, time.monotonic())
        if holder:
            if busy is None:
                with self._lock:
                    self._busy = None
            self.stats["refused"] += 1
            who = f"operator {program.operator}" if program.operator else "an unnamed operator"
            self._report(
                pid, -1, "refused",
                f"the robot is controlled by operator {holder}: {who} may watch until it lets "
                "go (its page closed or idle); a STOP is honoured from anyone",
                fresh=False,
            )  # fmt: skip
            return
        if busy is not None:
            self.stats["refused"] += 1
            self._report(pid, -1, "refused", f"busy with program {busy}", fresh=False)
            return
        resumed, why_not = self._resumed(program)
        if why_not:
            with self._lock:
                self._busy = None
            self.stats["refused"] += 1
            self._report(pid, -1, "refused", why_not, fresh=False)
            return
        try:

            def cancelled() -> bool:
                # Between commands, let the control loop have the interpreter if it waits for
                # it: the switch interval alone has let a check hold it up for periods.
                time.sleep(CHECK_YIELD_S)
                return self._stops_seen != stops_seen

            approaches: dict = {}
            reason = program_refusal(
                program,
                self._controller,
                cancelled=cancelled,
                holding=resumed is not None and resumed.holding,
                start=0 if resumed is None else resumed.index,
                approaches=approaches,
            )
        except CheckCancelledError:
            self._cancel(pid, "while it was being checked")
            return
        if reason:
            self.stats["refused"] += 1
            self._report(pid, -1, "refused", reason, fresh=False)
            with self._lock:
                self._busy = None
            return
        self._report(pid, -1, "accepted", f"{len(program.commands)} commands", fresh=False)
        with self._lock:
            self._ready.append((program, stops_seen, approaches))
        wake = getattr(self, "_wake", None)
        if wake is not None:
            wake.set()

    def _cancel(self, program_id: str, when: str) -> None:
        """A stop came for a program that had not started: it never will."""
        reason = self._last_stop_reason
        self._report(program_id, -1, "stopped", f"stop: {reason} ({when})", fresh=False)
        with self._lock:
            if self._busy == program_id:
                self._busy = None
