"""The link emulator (deploy/linkemu.py): its seeded schedule, and the real thing in namespaces
measured with UDP round trips (it must delay, drop and reorder what it claims)."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from deploy import netns
from deploy.linkemu import LinkParams, LinkSchedule

REPO = Path(__file__).resolve().parents[1]
UDPPROBE = REPO / "deploy" / "udpprobe.py"
CROSS_CPU_CLOCK_DISAGREEMENT_MS = 2.0


# ------------------------------------------------------------------ schedule (no root needed)


def fates(params: LinkParams, seed: int, n: int, gap_s: float = 0.001) -> list[float | None]:
    schedule = LinkSchedule(params, seed)
    return [schedule.decide(i * gap_s, 100) for i in range(n)]


def test_same_seed_same_schedule_other_seed_other_schedule() -> None:
    params = LinkParams(delay_s=0.05, jitter_s=0.01, loss=0.1)
    assert fates(params, 7, 2000) == fates(params, 7, 2000)
    assert fates(params, 7, 2000) != fates(params, 8, 2000)


def test_loss_fraction_and_delay_band() -> None:
    params = LinkParams(delay_s=0.05, jitter_s=0.01, loss=0.1)
    n = 20000
    out = fates(params, 3, n)
    lost = sum(f is None for f in out) / n
    # Binomial: σ = sqrt(0.1·0.9/20000) ≈ 0.0021; 5σ.
    assert abs(lost - 0.1) < 0.011
    delays = [f - i * 0.001 for i, f in enumerate(out) if f is not None]
    assert min(delays) >= 0.04 - 1e-12 and max(delays) <= 0.06 + 1e-12
    assert statistics.mean(delays) == pytest.approx(0.05, abs=0.0005)


def test_jitter_reorders_unless_fifo() -> None:
    jittery = LinkParams(delay_s=0.05, jitter_s=0.01)
    out = [f for f in fates(jittery, 1, 1000) if f is not None]
    assert out != sorted(out)
    fifo = LinkParams(delay_s=0.05, jitter_s=0.01, reorder=False)
    out = [f for f in fates(fifo, 1, 1000) if f is not None]
    assert out == sorted(out)


def test_rate_limit_spaces_packets_and_tail_drops() -> None:
    # 1500-byte packets at 1.2 Mbit/s take 10 ms each; a 50 ms queue holds about 5.
    schedule = LinkSchedule(LinkParams(rate_bps=1.2e6, queue_s=0.05), seed=1)
    out = [schedule.decide(0.0, 1500) for _ in range(20)]
    kept = [f for f in out if f is not None]
    assert kept[:3] == pytest.approx([0.01, 0.02, 0.03])
    assert 5 <= len(kept) <= 7 and schedule.overflowed == 20 - len(kept)


def test_cut_drops_everything() -> None:
    schedule = LinkSchedule(LinkParams(delay_s=0.01), seed=1)
    schedule.cut = True
    assert all(schedule.decide(0.0, 100) is None for _ in range(100))


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        LinkParams(loss=1.0)
    with pytest.raises(ValueError):
        LinkParams(delay_s=-1.0)


@pytest.mark.integration
def test_help_explains_the_options() -> None:
    out = subprocess.run(
        [sys.executable, str(REPO / "deploy" / "linkemu.py"), "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for option in ("--delay-ms", "--jitter-ms", "--loss", "--seed", "--rate-mbit", "SIGUSR1"):
        assert option in out


# --------------------------------------------------------------- the real link (root needed)


def require_netns() -> None:
    reason = netns.unavailable_reason()
    if reason is not None:
        print(f"skipping network-namespace test: {reason}")
        pytest.skip(f"network namespaces unavailable: {reason}")


@pytest.fixture
def link_factory() -> Iterator:
    """Namespaces with a unique prefix and a UDP echo in the work namespace; all removed."""
    require_netns()
    stack: list = []

    def make(**params):
        cm = netns.emulated_link(prefix=f"tt{uuid.uuid4().hex[:6]}", **params)
        link = cm.__enter__()
        stack.append(cm)
        echo = subprocess.Popen(
            link.pair.exec_argv(link.pair.work, [sys.executable, str(UDPPROBE), "echo"]),
            stdout=subprocess.PIPE,
            text=True,
        )
        stack.append(echo)
        assert echo.stdout is not None and echo.stdout.readline().strip() == "ready"
        return link

    yield make
    for item in reversed(stack):
        if isinstance(item, subprocess.Popen):
            item.kill()
            item.wait()
            if item.stdout is not None:
                item.stdout.close()
        else:
            item.__exit__(None, None, None)


def run_probe(link, count: int, interval_ms: float = 1.0) -> dict:
    out = subprocess.run(
        link.pair.exec_argv(
            link.pair.ops,
            [
                sys.executable,
                str(UDPPROBE),
                "probe",
                netns.WORK_ADDR,
                f"--count={count}",
                f"--interval-ms={interval_ms}",
            ],
        ),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_link_delays_by_the_configured_amount(link_factory) -> None:
    link = link_factory(delay_ms=30.0)
    result = run_probe(link, count=300, interval_ms=2.0)
    assert result["received"] == 300
    # Round trip = 2 × 30 ms; the relay and scheduler add well under a few ms here.
    assert 60.0 <= result["rtt_ms_median"] <= 65.0, result
    # The relay never releases early by its own clock, but the probe's round trip is read on
    # whichever CPUs its process ran on, and a VM's per-CPU clocks may disagree by about a
    # millisecond; a direction left undelayed would cost 30 ms.
    assert result["rtt_ms_min"] >= 60.0 - CROSS_CPU_CLOCK_DISAGREEMENT_MS, result
    assert result["reordered"] == 0


def test_link_drops_the_configured_fraction(link_factory) -> None:
    link = link_factory(delay_ms=5.0, loss=0.1, seed=11)
    result = run_probe(link, count=3000, interval_ms=0.5)
    # A datagram survives both directions with probability 0.9² = 0.81; σ ≈ 0.007 for 3000.
    assert abs(result["received_fraction"] - 0.81) < 0.035, result
    assert link.counters == {}  # still running; counters come when it stops


def test_link_jitter_spreads_and_reorders(link_factory) -> None:
    link = link_factory(delay_ms=20.0, jitter_ms=8.0, seed=5)
    result = run_probe(link, count=500, interval_ms=1.0)
    assert result["received"] == 500
    # Each direction is 12..28 ms: the round trip lies in 24..56 ms, plus the relay's and the
    # scheduler's latency, which only a median bounds on a loaded machine (the median of the
    # sum of two uniform delays is 40 ms).
    assert 23.9 <= result["rtt_ms_min"] < 32.0, result
    assert result["rtt_ms_max"] > 48.0, result
    assert 36.0 <= result["rtt_ms_median"] <= 46.0, result
    assert result["reordered"] > 10, result


def test_cut_partitions_and_restore_heals(link_factory) -> None:
    link = link_factory(delay_ms=1.0)
    assert run_probe(link, count=50)["received"] == 50
    link.cut()
    assert run_probe(link, count=50)["received"] == 0
    link.restore()
    assert run_probe(link, count=50)["received"] == 50


def test_namespaces_are_removed_afterwards() -> None:
    require_netns()
    prefix = f"tt{uuid.uuid4().hex[:6]}"
    with netns.emulated_link(prefix=prefix, delay_ms=1.0) as link:
        listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        assert link.pair.ops in listed and link.pair.work in listed
        relay_pid = link.relay.pid
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert link.pair.ops not in listed and link.pair.work not in listed
    assert link.counters["a_to_b_dropped"] == 0
    with pytest.raises(ProcessLookupError):
        os.kill(relay_pid, 0)
