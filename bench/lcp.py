"""Time per :func:`solve_lcp` on random contact problems (§V-A); prints JSON.

Run: ``.venv/bin/python -m bench lcp``. Problems are built like the simulator's: points in a
5 cm box measured from the workpiece centre, unit normals (a quarter of them 4 coplanar corners of
a face on a plane), d_t = 0.05, d_r = 80, a random applied force and moment.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from operator_site.simulator.lcp import solve_lcp

SIZES = (4, 8, 16, 32, 100)
PROBLEMS_PER_SIZE = 300


def contact_problem(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A (n, n), b (n,) of §V-A for a random contact set."""
    h = 0.025
    P = rng.uniform(-h, h, size=(n, 3))
    N = rng.normal(size=(n, 3))
    k = min(n, 4)
    P[:k] = np.array([[x, y, -h] for x in (-h, h) for y in (-h, h)])[:k]
    N[:k] = [0.0, 0.0, 1.0]
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    T = np.cross(P, N)
    d_t, d_r = 0.05, 80.0
    f_a, m_a = rng.normal(size=3) * 5.0, rng.normal(size=3) * 0.1
    return d_t * N @ N.T + d_r * T @ T.T, d_t * N @ f_a + d_r * T @ m_a


def run() -> dict[str, dict[str, float]]:
    """Per problem size: median and p99 µs per solve, median and max pivots."""
    rng = np.random.default_rng(0)
    report: dict[str, dict[str, float]] = {}
    for n in SIZES:
        times, pivots = [], []
        for _ in range(PROBLEMS_PER_SIZE):
            A, b = contact_problem(rng, n)
            t0 = time.perf_counter()
            result = solve_lcp(A, b)
            times.append(time.perf_counter() - t0)
            assert result.ok, result.message
            pivots.append(result.iterations)
        t_us = np.array(times) * 1e6
        report[str(n)] = {
            "median_us": round(float(np.median(t_us)), 1),
            "p99_us": round(float(np.percentile(t_us, 99)), 1),
            "median_pivots": float(np.median(pivots)),
            "max_pivots": int(np.max(pivots)),
        }
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``python -m bench lcp`` has no options."""


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; print its JSON (indented: ``make bench`` keeps it as lcp.json)."""
    print(json.dumps(run(), indent=1))
    return 0
