"""``python -m bench safety``: how soon the work site stops the arm, over real zenoh on loopback.

Each scenario runs against a fresh ``work-site serve`` process (``--no-camera``: the camera is
not what is measured here), with an observer (``bench.netsafety.Observer``) that sends nothing
and sees every report and robot state. All times are on one machine clock: a latency is the
work site's report stamp (``stamp_s``, its ``time.time()`` when it acted) minus our
``time.time()`` just before the event.

- ``stop``: a long free-move program running, a STOP sent at a random moment while the arm
  moves (``--trials``): to the "stopped" report, and to the arm being still (the first robot
  state from which the joints move less than 2e-4 rad a control period).
- ``stop_flood``: the same while another zenoh peer floods garbage at ``--flood-hz`` on every
  key the work site reads (``stop``, ``program``, ``heartbeat``), from 0.2 s before the STOP.
- ``deadman_kill``: an operator process (``bench/operator_process.py``) SIGKILLed while its
  program moves the arm (``--deadman-trials``): from the kill to the "stopped" report.
- ``deadman_cut``: an operator linked through a TCP relay that stops forwarding (a partition:
  no FIN, no RST) while its program moves the arm: from the cut to the "stopped" report.
- ``check``: a 1,000-command program sent and checked (``--check-trials``): the robot-state
  rate over every 0.2 s window within the check (by the work site's stamps), and a STOP sent
  20 ms after a second such program: to its "stopped" report (it never starts).

Prints progress on stderr and a JSON summary as the last line of stdout; writes
``safety.json``, ``safety.csv`` (one row per trial) and ``safety.png`` into ``--out``. The
machine's load average is recorded at the start, at each trial and at the end.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.netsafety import (
    FLOOD_KEYS,
    FLOOD_RATE_HZ,
    REPO,
    Flood,
    Observer,
    Relay,
    WorkSiteProcess,
    long_check_program,
    motion_per_period,
    moves_program,
    start_work_site,
    still_since,
    wait_until,
)
from operator_site.link import HEARTBEAT_PERIOD_S, WorkSiteLink
from protocol import make_config
from protocol.messages import MAX_COMMANDS
from work_site.lease import LEASE_IDLE_S

STILL_RAD = 2e-4
"""Joint motion a control period that counts as still (rad)."""
CONTROL_PERIOD_S = 0.01
DEADMAN_S = 0.5
STOP_GOAL_S = 0.05
"""A STOP acts within this (the net tests' bound)."""
TRANSPORT_ALLOWANCE_S = 0.005
"""Loopback delivery of the last beat, on top of the work site's dead-man bound."""
RATE_WINDOW_S = 0.2
RATE_STEP_S = 0.01
MIN_STATE_RATE_HZ = 95.0
FLOOD_BEFORE_STOP_S = 0.2
STOP_DELAY_S = (0.15, 0.4)
"""A STOP (or kill, or cut) comes this long after the program's first move started, drawn
uniformly (seeded), so that it falls anywhere in the work site's control period."""
DEADMAN_DELAY_S = (0.3, 0.6)
"""The dead-man's events come later: the program has run well past a dead-man's timeout."""
AFTER_STOP_S = 0.3
"""Robot state watched this long after the stop, to see the arm still."""
TARGETS = ((0.30, 0.10, 0.25), (0.45, -0.10, 0.15))
"""Reachable with the gripper down, 0.27 m apart: 5 s a move at 5 cm/s."""
STARTUP_S = 90.0
SITE_ID = "bench"
SEED = 20261127
CSV_COLUMNS = (
    "scenario", "trial", "program_id", "latency_ms", "still_ms", "state_hz_min",
    "state_gap_ms_max", "states_lost", "check_s", "flood_hz", "ws_silent_ms", "ws_loop_gap_ms",
    "timeout_ms", "message", "error", "loadavg_1min",
)  # fmt: skip
DEADMAN_MESSAGE = re.compile(r"no heartbeat from the operator for ([0-9.]+) s")
"""A dead-man stop's report, naming the timeout the work site waited: ``--deadman-s`` and, once
the operator's round trip is measured, a few round trips more (``deadman_timeout_s``)."""
DEADMAN_LOG = re.compile(
    r"dead-man: ([0-9.]+) s without a heartbeat .*this loop's last iteration ([0-9.]+) s ago"
)
"""The work site's own account of a dead-man stop: the silence it saw, its loop's last gap."""
LATE_LOG = re.compile(r"([0-9.]+) s of simulated time late so far")


def say(text: str) -> None:
    """Progress on stderr (stdout ends with the JSON summary)."""
    print(f"safety: {text}", file=sys.stderr, flush=True)


def _ms(x_s: float | None) -> float:
    return float("nan") if x_s is None else 1e3 * x_s


def _program(pid: str, trial: int) -> Any:
    a, b = TARGETS[trial % 2], TARGETS[(trial + 1) % 2]
    return moves_program(pid, [a, b, a, b], 0.05)


def _wait_moving(observer: Observer, until_s: float, timeout_s: float = 3.0) -> float:
    """Wait past ``until_s`` (monotonic) until the newest two states show the arm moving;
    returns that motion (rad a period; below STILL_RAD if it never moved in ``timeout_s``)."""
    deadline = until_s + timeout_s
    moved = 0.0
    while time.monotonic() < deadline:
        observer.poll()
        if len(observer.states) >= 2:
            moved = motion_per_period(observer.states[-2], observer.states[-1])
            if time.monotonic() >= until_s and moved >= STILL_RAD:
                break
        time.sleep(0.002)
    return moved


def _still_ms(observer: Observer, event_s: float, stopped_stamp_s: float) -> float:
    observer.wait_states_until(stopped_stamp_s + AFTER_STOP_S)
    return _ms(None if (t := still_since(observer.states, event_s, STILL_RAD)) is None
               else t - event_s)  # fmt: skip


LATE_S: dict[str, float] = {}
"""Each scenario's work site: simulated time its loop fell behind real time, by its log (s)."""


class Scenario:
    """One fresh work site and its observer, for the trials of scenario ``name``."""

    def __init__(self, run_dir: Path, index: int, name: str, *extra: str) -> None:
        self.name = name
        self.ws: WorkSiteProcess = start_work_site(
            run_dir, index, "--no-camera", "--deadman-s", f"{DEADMAN_S:g}", *extra,
            site_id=SITE_ID,
        )  # fmt: skip
        try:
            self.observer = Observer(self.ws, STARTUP_S)
        except TimeoutError:
            say(f"the work site did not come up; its log:\n{self.ws.log()[-3000:]}")
            self.ws.kill()
            raise

    def operator(self, endpoint: str | None = None) -> WorkSiteLink:
        """An operator link (polled with the observer, so that it re-sends as a page would)."""
        link = WorkSiteLink(make_config(connect=[endpoint or self.ws.endpoint]), SITE_ID)
        if not wait_until(lambda: (link.poll(), link.status.label == "connected")[1], 30):
            link.close()
            raise TimeoutError("the operator link did not connect")
        self.observer.also_poll.append(link)
        return link

    def drop(self, link: WorkSiteLink) -> None:
        self.observer.also_poll.remove(link)
        link.close()

    def late_s(self) -> float:
        """Simulated time the work site's loop fell behind real time, by its log (s)."""
        late = LATE_LOG.findall(self.ws.log())
        return float(late[-1]) if late else 0.0

    def close(self) -> None:
        LATE_S[self.name] = self.late_s()
        for link in self.observer.also_poll:
            link.close()
        self.observer.close()
        self.ws.kill()


def _row(scenario: str, trial: int, pid: str, **values: Any) -> dict[str, Any]:
    row = {c: "" for c in CSV_COLUMNS}
    row.update(scenario=scenario, trial=trial, program_id=pid, loadavg_1min=os.getloadavg()[0])
    row.update(values)
    return row


def _trials(
    name: str,
    n: int,
    trial: Callable[[int], dict[str, Any]],
    rows: list[dict[str, Any]],
    site: Scenario,
) -> None:
    """Run ``trial(i)`` n times, each a row; a trial that raises is a row with its error (and
    the work site's log's end on stderr)."""
    for i in range(n):
        try:
            row = trial(i)
        except (TimeoutError, RuntimeError) as e:
            row = _row(name, i, "", latency_ms=float("nan"), error=str(e)[:300])
            say(f"  {name} {i + 1}/{n} failed; the work site's log ends:\n"
                + "\n".join(site.ws.log().splitlines()[-15:]))  # fmt: skip
        rows.append(row)
        shown = {k: row[k] for k in ("latency_ms", "still_ms", "state_hz_min", "error")
                 if row.get(k) not in ("", None)}  # fmt: skip
        say(
            f"  {name} {i + 1}/{n}: "
            + ", ".join(
                f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in shown.items()
            )
        )


def run_stops(run_dir: Path, index: int, trials: int, flood_hz: float | None, rng) -> list[dict]:
    """The STOP trials, with a garbage flood when ``flood_hz`` is given."""
    name = "stop" if flood_hz is None else "stop_flood"
    site = Scenario(run_dir, index, name)
    operator = site.operator()
    flood = None if flood_hz is None else Flood(site.ws.endpoint, SITE_ID, rate_hz=flood_hz)
    observer, rows = site.observer, []

    def trial(i: int) -> dict[str, Any]:
        pid = f"{name}{i}"
        operator.send_program(_program(pid, i))
        observer.wait_report(pid, 0, "started", 20)
        at_s = time.monotonic() + rng.uniform(*STOP_DELAY_S)
        if flood is not None:
            time.sleep(max(0.0, at_s - FLOOD_BEFORE_STOP_S - time.monotonic()))
            flood.on.set()
        try:
            moving = _wait_moving(observer, at_s)
            sent_s = time.time()
            operator.send_stop(f"{name} trial {i}")
            stopped = observer.wait_report(pid, -1, "stopped", 5)
            still_ms = _still_ms(observer, sent_s, stopped.stamp_s)
        finally:
            if flood is not None:
                flood.on.clear()
        error = "" if moving >= STILL_RAD else f"not moving at the stop ({moving:.1e} rad)"
        return _row(name, i, pid, latency_ms=_ms(stopped.stamp_s - sent_s), still_ms=still_ms,
                    message=stopped.message, error=error,
                    flood_hz="" if flood is None else round(flood.rate_achieved_hz))  # fmt: skip

    try:
        _trials(name, trials, trial, rows, site)
        if flood is not None:
            for row in rows:
                row["flood_hz"] = round(flood.rate_achieved_hz)
    finally:
        if flood is not None:
            flood.close()
        site.close()
    return rows


def _deadman_row(name: str, i: int, pid: str, site: Scenario, event_s: float) -> dict[str, Any]:
    stopped = site.observer.wait_report(pid, -1, "stopped", 5 + 4 * DEADMAN_S)
    still_ms = _still_ms(site.observer, event_s, stopped.stamp_s)
    said = DEADMAN_MESSAGE.match(stopped.message)
    error = "" if said else f"stopped for another reason: {stopped.message}"
    timeout_s = float(said.group(1)) if said else math.nan
    accounts = DEADMAN_LOG.findall(site.ws.log())
    silent_s, loop_gap_s = (float(v) for v in accounts[-1]) if accounts else (math.nan, math.nan)
    return _row(name, i, pid, latency_ms=_ms(stopped.stamp_s - event_s), still_ms=still_ms,
                message=stopped.message, error=error, ws_silent_ms=_ms(silent_s),
                ws_loop_gap_ms=_ms(loop_gap_s), timeout_ms=_ms(timeout_s))  # fmt: skip


def _wait_lease_free(observer) -> None:
    """Until the work site's heartbeat names no lease holder: a dead operator's lease lapses
    :data:`~work_site.lease.LEASE_IDLE_S` after its last beat, and the next trial's operator,
    a new one, is refused until then."""
    if not wait_until(
        lambda: (observer.poll(), observer.link.status.holder == "")[1], LEASE_IDLE_S + 5.0
    ):
        raise TimeoutError(f"the lease is still held by {observer.link.status.holder!r}")


def run_deadman_kill(run_dir: Path, index: int, trials: int, rng) -> list[dict]:
    """An operator process SIGKILLed mid-program, each trial a new process."""
    site, rows = Scenario(run_dir, index, "deadman_kill"), []

    def trial(i: int) -> dict[str, Any]:
        pid = f"killed{i}"
        _wait_lease_free(site.observer)
        a, b = TARGETS[i % 2], TARGETS[(i + 1) % 2]
        points = [",".join(f"{v:g}" for v in p) for p in (a, b, a, b)]
        proc = subprocess.Popen(
            [sys.executable, "-m", "bench.operator_process", site.ws.endpoint, SITE_ID, pid,
             *points],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        try:
            site.observer.wait_report(pid, 0, "started", 60)
            _wait_moving(site.observer, time.monotonic() + rng.uniform(*DEADMAN_DELAY_S))
            if site.observer.report(pid, -1, "stopped") is not None:
                raise RuntimeError("stopped before the kill (the operator was beating)")
            kill_s = time.time()
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return _deadman_row("deadman_kill", i, pid, site, kill_s)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()

    try:
        _trials("deadman_kill", trials, trial, rows, site)
    finally:
        site.close()
    return rows


def run_deadman_cut(run_dir: Path, index: int, trials: int, rng) -> list[dict]:
    """An operator linked through a relay that stops forwarding mid-program, each trial a new
    relay and a new operator session."""
    site, rows = Scenario(run_dir, index, "deadman_cut"), []

    def trial(i: int) -> dict[str, Any]:
        pid = f"cut{i}"
        _wait_lease_free(site.observer)
        relay = Relay.to(site.ws.endpoint)
        operator = None
        try:
            operator = site.operator(relay.endpoint)
            operator.send_program(_program(pid, i))
            site.observer.wait_report(pid, 0, "started", 20)
            _wait_moving(site.observer, time.monotonic() + rng.uniform(*DEADMAN_DELAY_S))
            if site.observer.report(pid, -1, "stopped") is not None:
                raise RuntimeError("stopped before the cut (the operator was beating)")
            cut_s = relay.cut()
            return _deadman_row("deadman_cut", i, pid, site, cut_s)
        finally:
            if operator is not None:
                site.drop(operator)
            relay.close()

    try:
        _trials("deadman_cut", trials, trial, rows, site)
    finally:
        site.close()
    return rows


def window_rates_hz(stamps_s: list[float], from_s: float, to_s: float) -> list[float]:
    """The state rate in each RATE_WINDOW_S window within [from_s, to_s], RATE_STEP_S apart
    (the whole span as one window when it is shorter): the states in the window, less one,
    over the time from the first to the last (a count over the window would move in 5 Hz
    steps with where the window falls)."""
    t = np.sort(np.asarray(stamps_s))
    starts = np.arange(from_s, max(from_s, to_s - RATE_WINDOW_S) + 1e-9, RATE_STEP_S)
    rates = []
    for a in starts:
        inside = t[(t >= a) & (t <= min(to_s, a + RATE_WINDOW_S))]
        if inside.size >= 2:
            rates.append(float((inside.size - 1) / (inside[-1] - inside[0])))
        else:
            rates.append(0.0)
    return rates


def run_checks(run_dir: Path, index: int, trials: int) -> tuple[list[dict], list[list[float]]]:
    """A 1,000-command program checked while we watch the state rate, then a STOP 20 ms after
    another: rows, and each trial's window rates (for the plot)."""
    site = Scenario(run_dir, index, "check")
    operator = site.operator()
    observer, rows, curves = site.observer, [], []

    def first_report(pid: str, timeout_s: float):
        def answered() -> bool:
            observer.poll()
            return any(r.program_id == pid for r in observer.link.status.reports)

        if not wait_until(answered, timeout_s, poll_s=0.002):
            raise TimeoutError(f"no report for {pid}")
        return next(r for r in observer.link.status.reports if r.program_id == pid)

    def trial(i: int) -> dict[str, Any]:
        pid = f"long{i}"
        observer.wait_states_until(time.time())  # a fresh state: the loop runs
        sent_s = time.time()
        operator.send_program(long_check_program(pid))
        answer = first_report(pid, 60)
        if answer.status != "accepted":
            raise RuntimeError(f"the long program was {answer.status}: {answer.message}")
        observer.wait_states_until(answer.stamp_s)
        during = [s for s in observer.states if sent_s <= s.stamp_s <= answer.stamp_s]
        stamps = [s.stamp_s for s in during]
        lost = (during[-1].seq - during[0].seq + 1 - len(during)) if during else 0
        rates = window_rates_hz(stamps, sent_s, answer.stamp_s)
        curves.append(rates)
        gaps = np.diff(sorted([sent_s, *stamps, answer.stamp_s]))
        operator.send_stop("enough")
        observer.wait_report(pid, -1, "stopped", 5)
        # A STOP 20 ms after another long program: the check is cancelled, never started.
        cancelled = f"cancelled{i}"
        operator.send_program(long_check_program(cancelled))
        time.sleep(0.02)
        stop_s = time.time()
        operator.send_stop("changed my mind")
        reply = first_report(cancelled, 5)
        error = ""
        if (reply.command_index, reply.status) != (-1, "stopped"):
            error = f"the cancelled program answered {reply.status} at {reply.command_index}"
        check_row = _row("check", i, pid, state_hz_min=min(rates) if rates else float("nan"),
                         state_gap_ms_max=1e3 * float(gaps.max()), states_lost=lost,
                         check_s=answer.stamp_s - sent_s)  # fmt: skip
        rows.append(check_row)
        return _row("stop_during_check", i, cancelled, latency_ms=_ms(reply.stamp_s - stop_s),
                    message=reply.message, error=error)  # fmt: skip

    try:
        _trials("stop_during_check", trials, trial, rows, site)
    finally:
        site.close()
    return rows, curves


# ------------------------------------------------------------------------ summary and outputs


def _stats(values: list[float]) -> dict[str, float]:
    v = [x for x in values if not math.isnan(x)]
    if not v:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan"),
                "min": float("nan")}  # fmt: skip
    return {"median": float(np.median(v)), "p99": float(np.percentile(v, 99)),
            "max": float(max(v)), "min": float(min(v))}  # fmt: skip


def _commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                             capture_output=True, text=True, check=True)  # fmt: skip
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=REPO, capture_output=True, text=True, check=True)  # fmt: skip
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def summarise(rows: list[dict]) -> dict[str, Any]:
    """The JSON summary: per scenario counts, failures, median / p99 / max (ms)."""

    def of(name: str, column: str = "latency_ms") -> list[float]:
        return [float(r[column]) for r in rows if r["scenario"] == name and r[column] != ""]

    out: dict[str, Any] = {}
    for name in ("stop", "stop_flood", "deadman_kill", "deadman_cut", "stop_during_check"):
        lat, still = _stats(of(name)), _stats(of(name, "still_ms"))
        trial_rows = [r for r in rows if r["scenario"] == name]
        out[f"{name}_trials"] = len(trial_rows)
        out[f"{name}_failures"] = sum(1 for r in trial_rows if r["error"])
        for k in ("median", "p99", "max"):
            out[f"{name}_ms_{k}"] = lat[k]
        if name.startswith("deadman"):
            out[f"{name}_ms_min"] = lat["min"]
        if name != "stop_during_check":
            for k in ("median", "p99", "max"):
                out[f"{name}_still_ms_{k}"] = still[k]
    low_s = DEADMAN_S - HEARTBEAT_PERIOD_S - CONTROL_PERIOD_S
    high_s = DEADMAN_S + CONTROL_PERIOD_S + TRANSPORT_ALLOWANCE_S
    for name in ("deadman_kill", "deadman_cut"):
        # Each stop against the timeout its work site waited (the round trips it adds, a few
        # ms on loopback, are the work site's rule; their size is reported apart).
        stops = [
            (float(r["latency_ms"]), float(r["timeout_ms"]))
            for r in rows
            if r["scenario"] == name and r["latency_ms"] != "" and r["timeout_ms"] != ""
        ]
        out[f"{name}_outside_bounds"] = sum(
            1 for v, t_ms in stops if not 1e3 * low_s <= v <= t_ms + 1e3 * (high_s - DEADMAN_S)
        )
        out[f"{name}_timeout_ms_max"] = max((t for _, t in stops), default=float("nan"))
    flood = of("stop_flood", "flood_hz")
    rates, gaps = of("check", "state_hz_min"), of("check", "state_gap_ms_max")
    lost = of("check", "states_lost")
    out.update(
        stop_goal_ms=1e3 * STOP_GOAL_S,
        deadman_s=DEADMAN_S,
        deadman_bounds_ms=[1e3 * low_s, 1e3 * high_s],
        flood_keys=list(FLOOD_KEYS),
        flood_hz_per_key=min(flood) if flood else float("nan"),
        check_trials=len(rates),
        check_commands=MAX_COMMANDS,
        check_s_median=float(np.median(of("check", "check_s"))) if rates else float("nan"),
        state_hz_min_during_check=min(rates) if rates else float("nan"),
        state_hz_window_s=RATE_WINDOW_S,
        state_gap_ms_max_during_check=max(gaps) if gaps else float("nan"),
        states_lost_during_check=int(sum(lost)),
    )
    return out


def write_outputs(out_dir: Path, summary: dict, rows: list[dict], curves: list) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "safety.json").write_text(json.dumps(summary, indent=1) + "\n")
    with (out_dir / "safety.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v)
                             for k, v in row.items()})  # fmt: skip
    try:
        _plot(out_dir / "safety.png", summary, rows, curves)
    except ImportError:
        say("matplotlib missing (pip install -e '.[bench]'): no plot")


def _plot(path: Path, summary: dict, rows: list[dict], curves: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)

    def values(name: str, column: str) -> np.ndarray:
        v = [float(r[column]) for r in rows if r["scenario"] == name and r[column] != ""]
        return np.array([x for x in v if not math.isnan(x)])

    fig, axes = plt.subplots(1, 3, figsize=(15, 5), gridspec_kw={"width_ratios": [3, 2, 2.2]})
    # 1. STOP latencies: report and still, per scenario.
    ax = axes[0]
    stops = (("stop", "no flood"),
             ("stop_flood", f"flood {summary['flood_hz_per_key']:,.0f} msg/s a key"),
             ("stop_during_check", "during a 1,000-cmd check"))  # fmt: skip
    for x, (name, _) in enumerate(stops):
        for column, dx, style in (("latency_ms", -0.15, "o"), ("still_ms", 0.15, "^")):
            v = values(name, column)
            if v.size == 0:
                continue
            jitter = rng.uniform(-0.07, 0.07, v.size)
            color = "C0" if column == "latency_ms" else "C2"
            ax.scatter(x + dx + jitter, v, s=22, marker=style, color=color, alpha=0.75,
                       label=None if x else {"latency_ms": "\"stopped\" report",
                                             "still_ms": "arm still"}[column])  # fmt: skip
            ax.hlines(np.median(v), x + dx - 0.12, x + dx + 0.12, color="k", lw=1.5)
    ax.axhline(1e3 * STOP_GOAL_S, color="C3", ls="--", lw=1, label="50 ms")
    ax.set_yscale("log")
    ax.set_ylim(0.2, 1000)
    ax.set_xticks(range(len(stops)), [label for _, label in stops])
    ax.set_ylabel("ms after the STOP was sent (log)")
    ax.set_title(f"STOP (n = {summary['stop_trials']}, {summary['stop_flood_trials']}, "
                 f"{summary['stop_during_check_trials']}; bars: medians)")  # fmt: skip
    ax.legend(loc="upper right", fontsize=8, ncol=3)
    # 2. The dead-man: kill and cut.
    ax = axes[1]
    low, high = summary["deadman_bounds_ms"]
    ax.axhspan(low, high, color="C1", alpha=0.12, label="expected: dead-man − a beat … + a period")
    for x, name in enumerate(("deadman_kill", "deadman_cut")):
        for column, dx, marker, color in (("latency_ms", -0.12, "o", "C0"),
                                          ("still_ms", 0.12, "^", "C2")):  # fmt: skip
            v = values(name, column)
            if v.size:
                ax.scatter(x + dx + rng.uniform(-0.05, 0.05, v.size), v, s=28, marker=marker,
                           color=color, alpha=0.8)  # fmt: skip
    ax.axhline(1e3 * DEADMAN_S, color="C1", lw=1)
    ax.set_xticks([0, 1], ["operator SIGKILLed", "link cut (relay)"])
    ax.set_xlim(-0.6, 1.6)
    ax.set_ylabel("ms after the kill / cut")
    ax.set_title(f"Dead-man {DEADMAN_S:g} s (n = {summary['deadman_kill_trials']}, "
                 f"{summary['deadman_cut_trials']})")  # fmt: skip
    ax.scatter([], [], marker="o", color="C0", label='"stopped" report')
    ax.scatter([], [], marker="^", color="C2", label="arm still")
    ax.legend(loc="lower center", fontsize=8)
    # 3. Robot-state rate during the checks.
    ax = axes[2]
    for i, rates in enumerate(curves):
        t = RATE_WINDOW_S / 2 + RATE_STEP_S * np.arange(len(rates))
        ax.plot(t, rates, marker=".", lw=1, label=f"trial {i + 1}")
    ax.axhline(MIN_STATE_RATE_HZ, color="C3", ls="--", lw=1, label=f"{MIN_STATE_RATE_HZ:g} Hz")
    ax.set_ylim(0, 200)  # a catch-up after a stall publishes a burst: higher rates are clipped
    ax.set_xlabel(f"s since the program was sent (middle of a {RATE_WINDOW_S:g} s window)")
    ax.set_ylabel("robot states a second within the window")
    ax.set_title(f"State rate, {MAX_COMMANDS:,} commands being checked")
    ax.legend(loc="upper right", fontsize=8, ncol=3)
    load = summary["loadavg_start"][0], summary["loadavg_end"][0]
    fig.suptitle(f"Safety over zenoh on loopback, real processes ({summary['date_utc']}, "
                 f"{summary['commit']}; load average {load[0]:.1f} → {load[1]:.1f} on "
                 f"{summary['cpus']} cores)", fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> dict[str, Any]:
    started = time.monotonic()
    load_start = os.getloadavg()
    say(f"load average {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}; "
        f"{args.trials} STOP trials, the same under a flood, {args.deadman_trials} kills, "
        f"{args.deadman_trials} cuts, {args.check_trials} checks")  # fmt: skip
    rng = np.random.default_rng(SEED)
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench-safety-") as tmp:
        run_dir = Path(tmp)
        say("1/5 STOP, no flood")
        rows += run_stops(run_dir, 0, args.trials, None, rng)
        say(f"2/5 STOP through a {args.flood_hz:,.0f} msg/s flood on each of {FLOOD_KEYS}")
        rows += run_stops(run_dir, 1, args.trials, args.flood_hz, rng)
        say("3/5 dead-man: operator SIGKILLed")
        rows += run_deadman_kill(run_dir, 2, args.deadman_trials, rng)
        say("4/5 dead-man: link cut")
        rows += run_deadman_cut(run_dir, 3, args.deadman_trials, rng)
        say(f"5/5 state rate while a {MAX_COMMANDS}-command program is checked")
        check_rows, curves = run_checks(run_dir, 4, args.check_trials)
        rows += check_rows
    summary = summarise(rows)
    summary.update(
        work_site_late_s=dict(LATE_S),
        loadavg_start=list(load_start),
        loadavg_end=list(os.getloadavg()),
        cpus=os.cpu_count(),
        wall_s=round(time.monotonic() - started, 1),
        date_utc=dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        commit=_commit(),
        command="python -m bench safety " + " ".join(sys.argv[2:]),
    )
    write_outputs(args.out, summary, rows, curves)
    say(f"wrote {args.out}/safety.json, safety.csv, safety.png in {summary['wall_s']:.0f} s")
    return summary


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m bench safety``."""
    parser.description = (
        (parser.description or "")
        + "\n\n"
        + textwrap.fill(
            "Scenarios, each against a fresh `work-site serve --no-camera` on loopback: a STOP "
            "while a program moves the arm; the same through a garbage flood on every key the work "
            "site reads; an operator process SIGKILLed mid-program and an operator's link cut "
            "mid-program (the dead-man, 0.5 s); the robot-state rate while a 1,000-command program "
            "is checked, and a STOP during that check. Progress goes to stderr; the last line of "
            "stdout is the JSON summary. Takes about a minute with the defaults.",
            width=88,
        )
    )
    parser.add_argument(
        "--trials",
        type=_positive_int,
        default=20,
        help="STOP trials, without and with the flood (default: %(default)s)",
    )
    parser.add_argument(
        "--deadman-trials",
        type=_positive_int,
        default=5,
        help="trials of each dead-man scenario, kill and cut (default: %(default)s)",
    )
    parser.add_argument(
        "--check-trials",
        type=_positive_int,
        default=5,
        help="1,000-command programs checked, each followed by a STOP during a second one "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--flood-hz",
        type=float,
        default=FLOOD_RATE_HZ,
        help="garbage messages a second on each key the work site reads (default: %(default)g; "
        "the rate reached is recorded)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/bench"),
        help="directory for safety.json, safety.csv and safety.png (default: %(default)s)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (one line) last."""
    summary = run(args)
    print(json.dumps(summary), flush=True)
    return 0
