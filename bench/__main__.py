"""``python -m bench NAME [options]``: run one benchmark (``python -m bench NAME --help``)."""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

BENCHMARKS: dict[str, str] = {
    "sim": "the task simulator's speed and accuracy, MuJoCo beside it, its knobs swept",
    "deform": "the program generator's path deformation on the paper's figures",
    "control": "the arm executing moves, guarded moves and contact programs",
    "vision": "recognition and pose accuracy, speed and their trades on rendered scenes",
    "net": "round trips and camera frames over zenoh beside plain TCP, loopback and emulated link",
    "step_gain": "free pulls of each block: steps to settle against the spring's step gain",
    "lcp": "time per contact LCP solve on random contact sets",
    "program_sweeps": "the deformation's sweep cap: generator CPU time against program change",
    "latency": "a shipped task across an emulated long link: success and time against delay",
    "linkcut": "a link cut and restored: the work site seen gone, then alive again",
    "fleet": "many cells through one router: command round trips and camera rates against N",
    "pacing": "camera frames' age on links too slow for the streams, paced and unpaced",
    "safety": "STOP latency (also through a flood), the dead-man, state rate during a check",
    "e2e": "the scripted tasks end to end, each seed against its own work site",
    "trade": "each user knob's effect on a scripted task end to end",
    "tasks": "every shipped task file end to end on seeded layouts",
    "ui": "a first task in the operator's page in Chromium, timed step by step",
    "report": "rebuild the summary of docs/benchmarks.md from the benchmarks' JSON",
}
"""Each benchmark's name, the module bench.NAME that runs it, and what it measures."""


def build_parser() -> argparse.ArgumentParser:
    listing = "\n".join(f"  {name:15s} {what}" for name, what in BENCHMARKS.items())
    parser = argparse.ArgumentParser(
        prog="python -m bench",
        description="Run a benchmark from the repository root. Each prints a JSON summary as its "
        "last line and writes CSV and PNG files into --out.",
        epilog=f"benchmarks:\n{listing}\n\n'python -m bench NAME --help' gives NAME's options; "
        "'python -m bench.vision_dataset --help' renders the vision dataset alone.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "name",
        choices=list(BENCHMARKS),
        metavar="NAME",
        help="which benchmark to run (listed below)",
    )
    return parser


def _exit(signum: int, _frame) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str]) -> int:
    """Parse ``argv`` (without the program name): NAME, then NAME's own options; run it."""
    # A bench stopped by SIGTERM (kill, a job's time limit) unwinds as on Ctrl-C: the work
    # sites, network namespaces and temporary directories it started go with it.
    signal.signal(signal.SIGTERM, _exit)
    args = build_parser().parse_args(argv[:1])  # only NAME: its options are its own
    if args.name == "vision":
        # Times are one core's, as at the work site (work_site/recognition.py): numpy's BLAS
        # must not spread a frame's products over threads; it reads this when imported.
        from work_site.child import BLAS_THREAD_VARIABLES

        os.environ.update(dict.fromkeys(BLAS_THREAD_VARIABLES, "1"))
    module = importlib.import_module(f"bench.{args.name}")
    summary = module.__doc__.split("\n\n")[0].split("``: ", 1)[-1]  # without "``python -m …``"
    parser = argparse.ArgumentParser(
        prog=f"python -m bench {args.name}",
        description=summary[:1].upper() + summary[1:],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    module.add_arguments(parser)
    return module.main(parser.parse_args(argv[1:]))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
