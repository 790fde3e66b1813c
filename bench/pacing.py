"""``python -m bench pacing``: how old camera frames arrive on links too slow for the streams,
with the work site's stream pacing (``work_site/pacing.py``) and without it.

Each run joins a fresh ``work-site serve`` (camera at its default rate, vision off) in one
network namespace and an operator site's link (``deploy/operator_probe.py streams``, a
``WorkSiteLink`` as the page holds it) in another by the emulated link of ``deploy/netns.py``,
shaped as a profile says (``--profiles``):

- ``clear``: 25 ms each way, no bottleneck: pacing must cost nothing here;
- ``thin``: 25 ms each way through 0.3 Mbit/s with a 1 s queue (a loaded uplink; the streams
  at full rate need about 0.75 Mbit/s);
- ``thin-far``: the same with 250 ms each way;
- ``far-lossy``: 500 ms each way, 1 % loss each way (TCP's rate falls with both).

Each profile is run paced and unpaced (``--no-stream-pacing``), ``--runs`` times each. The
probe counts the frames that arrive after ``--settle`` seconds of a ``--seconds`` watch and how
old each was (the work site took it → it arrived; one machine, one clock).

Needs root (network namespaces). Prints progress on stderr and a JSON summary as the last line
of stdout; writes ``pacing.json``, ``pacing.csv`` (one row per run) and ``pacing.png`` (the
median age per profile; the age of each frame over a watch of the ``thin`` profile) into
``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from deploy import netns

REPO = Path(__file__).resolve().parents[1]
SITE_ID = "pacing"
PORT = 7447
PROFILES: dict[str, dict[str, float]] = {
    "clear": {"delay_ms": 25.0},
    "thin": {"delay_ms": 25.0, "rate_mbit": 0.3, "queue_ms": 1000.0},
    "thin-far": {"delay_ms": 250.0, "rate_mbit": 0.3, "queue_ms": 1000.0},
    "far-lossy": {"delay_ms": 500.0, "loss": 0.01},
}
"""Each profile's link parameters (``deploy.netns.link_args``), both ways."""
MODES = ("paced", "unpaced")
PROBE_GRACE_S = 120.0
"""A probe gets this long beyond its watch to connect and finish before the run is failed."""
CSV_FIELDS = [
    "profile", "mode", "run", "frames", "frame_age_s_median", "frame_age_s_p90",
    "frame_rate_hz", "state_rate_hz", "error",
]  # fmt: skip


def run_once(profile: str, mode: str, index: int, args: argparse.Namespace, log_dir: Path
             ) -> tuple[dict[str, Any], list[list[float]]]:  # fmt: skip
    """One watch against a fresh work site; its CSV row and the frames' [time, age] series."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    endpoint = f"tcp/{netns.WORK_ADDR}:{PORT}"
    row: dict[str, Any] = {"profile": profile, "mode": mode, "run": index, "error": ""}
    prefix = f"pc{uuid.uuid4().hex[:6]}"
    with netns.emulated_link(prefix=prefix, **PROFILES[profile]) as link:
        site_argv = [
            sys.executable, str(REPO / "deploy" / "serve_work_site.py"), "--listen", endpoint,
            "--site-id", SITE_ID, "--insecure", "--vision-rate=0",
        ]  # fmt: skip
        if mode == "unpaced":
            site_argv.append("--no-stream-pacing")
        name = f"{profile}_{mode}_{index}"
        with (log_dir / f"work_site_{name}.log").open("w") as site_log:
            site = subprocess.Popen(
                link.pair.exec_argv(link.pair.work, site_argv), cwd=REPO, stdout=site_log,
                stderr=subprocess.STDOUT, start_new_session=True, env=env,
            )  # fmt: skip
        try:
            done = subprocess.run(
                link.pair.exec_argv(link.pair.ops, [
                    sys.executable, str(REPO / "deploy" / "operator_probe.py"), "streams",
                    f"--connect={endpoint}", f"--site-id={SITE_ID}", "--series",
                    f"--seconds={args.seconds}", f"--settle={args.settle}",
                ]),
                cwd=REPO, capture_output=True, text=True, env=env,
                timeout=args.seconds + PROBE_GRACE_S,
            )  # fmt: skip
            (log_dir / f"operator_{name}.log").write_text(done.stderr)
            lines = done.stdout.strip().splitlines()
            result = json.loads(lines[-1]) if lines else {"error": "the probe printed nothing"}
        except subprocess.TimeoutExpired:
            result = {"error": "the probe did not finish"}
        finally:
            site.terminate()
            try:
                site.wait(timeout=10)
            except subprocess.TimeoutExpired:
                site.kill()
                site.wait()
    series = result.pop("series", [])
    if "error" in result:
        row["error"] = str(result["error"])
    for field in CSV_FIELDS[3:-1]:
        row[field] = result.get(field)
    return row, series


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One point per profile and mode: medians over its runs."""
    points = []
    for profile in dict.fromkeys(r["profile"] for r in rows):
        for mode in MODES:
            mine = [r for r in rows if r["profile"] == profile and r["mode"] == mode]
            ok = [r for r in mine if not r["error"]]
            if not mine:
                continue

            def median(field: str, ok: list[dict[str, Any]] = ok) -> float | None:
                return float(np.median([r[field] for r in ok])) if ok else None

            points.append({
                "profile": profile, "mode": mode, "runs": len(mine),
                "failed_runs": len(mine) - len(ok),
                **PROFILES[profile],
                **{f: median(f) for f in ("frames", "frame_age_s_median", "frame_age_s_p90",
                                         "frame_rate_hz", "state_rate_hz")},
            })  # fmt: skip
    return points


def plot(points: list[dict[str, Any]], series: dict[str, list[list[float]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_age, ax_t) = plt.subplots(1, 2, figsize=(10, 3.8))
    profiles = list(dict.fromkeys(p["profile"] for p in points))
    x = np.arange(len(profiles))
    for k, mode in enumerate(MODES):
        ages = [next((p["frame_age_s_median"] for p in points
                      if p["profile"] == name and p["mode"] == mode), None) or np.nan
                for name in profiles]  # fmt: skip
        ax_age.bar(x + (k - 0.5) * 0.38, ages, width=0.38, label=mode)
    ax_age.set_xticks(x, profiles)
    ax_age.set_yscale("log")
    ax_age.set_ylabel("frame age at arrival, median (s)")
    for mode, points_t in series.items():
        if points_t:
            t, age = np.array(points_t).T
            ax_t.plot(t, age, ".-", ms=3, label=mode)
    ax_t.set_xlabel("time since the probe connected (s)")
    ax_t.set_ylabel("frame age at arrival (s)")
    ax_t.set_title("thin: 0.3 Mbit/s, 1 s queue, 25 ms", fontsize=9)
    for ax in (ax_age, ax_t):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--profiles", type=lambda t: [_profile(p) for p in t.split(",")], default=list(PROFILES),
        help=f"link profiles, comma-separated (default {','.join(PROFILES)})",
    )  # fmt: skip
    parser.add_argument("--runs", type=int, default=2, help="runs per profile and mode (default 2)")
    parser.add_argument("--seconds", type=float, default=45.0,
                        help="each watch's length (s, default 45)")  # fmt: skip
    parser.add_argument("--settle", type=float, default=15.0,
                        help="count frames from this long on (s, default 15)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("docs/bench"))
    parser.add_argument(
        "--logs", type=Path,
        help="keep each run's work-site and probe logs here (default: a temporary directory)",
    )  # fmt: skip


def _profile(name: str) -> str:
    if name not in PROFILES:
        raise argparse.ArgumentTypeError(f"no profile {name!r}; known: {', '.join(PROFILES)}")
    return name


def main(args: argparse.Namespace) -> int:
    if args.runs < 1 or not 0.0 <= args.settle < args.seconds:
        print("pacing: --runs must be ≥ 1 and 0 ≤ --settle < --seconds", file=sys.stderr)
        return 2
    if (reason := netns.unavailable_reason()) is not None:
        print(f"pacing: network namespaces unavailable: {reason}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    thin_series: dict[str, list[list[float]]] = {}
    total = len(args.profiles) * len(MODES) * args.runs
    with tempfile.TemporaryDirectory(prefix="bench-pacing-") as tmp:
        log_dir = args.logs or Path(tmp)
        log_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        for index in range(args.runs):
            for profile in args.profiles:
                for mode in MODES:
                    row, series = run_once(profile, mode, index, args, log_dir)
                    rows.append(row)
                    if profile == "thin" and mode not in thin_series:
                        thin_series[mode] = series
                    print(
                        f"[{len(rows)}/{total}, {time.monotonic() - t0:.0f} s] {profile} {mode}: "
                        + (row["error"] or f"{row['frames']} frames, median age "
                           f"{row['frame_age_s_median']:.2f} s"),
                        file=sys.stderr, flush=True,
                    )  # fmt: skip
    with (args.out / "pacing.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    points = summarise(rows)
    summary = {"seconds": args.seconds, "settle_s": args.settle, "runs": args.runs,
               "load_average": os.getloadavg(), "points": points}  # fmt: skip
    (args.out / "pacing.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot(points, thin_series, args.out / "pacing.png")
    print(json.dumps(summary))
    return 0 if all(not r["error"] for r in rows) else 1
