"""Barrier potentials of §V-B (equation 6, Fig. 10).

``U(d) = K [δ − 1 − ln δ]`` for δ = d / ε_b < 1 and 0 beyond: zero with zero slope at d = ε_b,
infinite at contact. A captured object adds the mirror image at the outer bound ε_o, so that the
workpiece stays within (0, ε_o) of it (Fig. 10-B).
"""

from __future__ import annotations

import math


def barrier(d_m: float, eps_barrier_m: float, gain: float) -> float:
    """U_i(d) of equation (6) with K = ``gain``; ``inf`` at or below zero distance."""
    if d_m <= 0.0:
        return math.inf
    delta = d_m / eps_barrier_m
    return gain * (delta - 1.0 - math.log(delta)) if delta < 1.0 else 0.0


def capture_barrier(d_m: float, eps_barrier_m: float, eps_capture_m: float, gain: float) -> float:
    """Fig. 10-B: the barrier at 0 plus its mirror at ε_o (``inf`` outside (0, ε_o))."""
    return barrier(d_m, eps_barrier_m, gain) + barrier(eps_capture_m - d_m, eps_barrier_m, gain)
