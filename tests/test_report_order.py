"""Execution reports carry their number within their program (``seq``): the operator's link
orders and de-duplicates by it whatever the arrival order, and the work site's journal replays
keep it across a restart."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np

from operator_site.link import WorkSiteLink
from protocol import ExecutionReport, decode, encode, make_config
from protocol.messages import OLDEST_READ_VERSION
from work_site.server import read_journal


def report(pid: str, seq: int, index: int, status: str, stamp_s: float) -> ExecutionReport:
    return ExecutionReport(pid, index, status, np.zeros(6), "", stamp_s, seq)


def test_the_link_orders_each_programs_reports_by_seq_and_drops_replays() -> None:
    link = WorkSiteLink(make_config(), "order")  # a lone session: reports are fed by hand
    try:
        # A reconnecting operator hears live reports before the replay of earlier ones; the
        # work site's clock may also step back (stamps are not an order).
        arrivals = [
            report("p", 3, 1, "done", 10.0),
            report("q", 0, -1, "accepted", 11.0),
            report("p", 0, -1, "accepted", 12.0),
            report("p", 2, 1, "started", 5.0),
            report("p", 1, 0, "done", 13.0),
            report("p", 0, -1, "accepted", 12.0),  # a replay: kept once
            report("p", 4, -1, "done", 1.0),
        ]
        for r in arrivals:
            link._on_report(r)
        mine = [(r.seq, r.status) for r in link.status.reports if r.program_id == "p"]
        assert mine == [(0, "accepted"), (1, "done"), (2, "started"), (3, "done"), (4, "done")]
        assert [r.program_id for r in link.status.reports].count("q") == 1
    finally:
        link.close()


def test_the_journal_keeps_seq_and_remembers_what_it_cannot_replay(tmp_path: Path) -> None:
    journal = tmp_path / "journal.jsonl"
    old_schema = msgpack.unpackb(encode(report("old", 0, -1, "accepted", 1.0)), raw=False)
    old_schema["v"] = OLDEST_READ_VERSION - 1  # written by a release too old to read
    lines = [
        {"program_id": "old", "report": msgpack.packb(old_schema, use_bin_type=True).hex()},
        {"program_id": "p", "report": encode(report("p", 0, -1, "accepted", 2.0)).hex()},
        {"program_id": "p", "report": encode(report("p", 1, 0, "started", 3.0)).hex()},
    ]
    journal.write_text(
        "".join(json.dumps(line) + "\n" for line in lines) + '{"program_id": "p", "rep'
    )  # the last line half written by a crash
    reports, added = read_journal(journal)
    assert list(reports) == ["old", "p"]  # "old" is remembered: a re-send never runs it again
    assert [pid for pid, _ in added] == ["old", "p"]  # both closed as failed
    old = decode(added[0][1], expected=ExecutionReport)
    assert (old.seq, old.status) == (0, "failed") and "earlier version" in old.message
    closing = decode(added[1][1], expected=ExecutionReport)  # interrupted by the restart
    assert (closing.seq, closing.command_index, closing.status) == (2, -1, "failed")
    assert len(reports["p"]) == 3 and len(reports["old"]) == 1
