"""The task simulator's parameters: the paper's constants (§V, §VII-B) with their units.

Every knob trades speed for accuracy; ``bench/`` measures each trade. Defaults follow the paper
unless a comment says why not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MIN_GOLDEN_REL_TOL = 1e-12
"""The golden-section search's bracket cannot shrink much below float64's relative precision
(2.2e-16) times Δt: a smaller tolerance would never be met."""


@dataclass(frozen=True)
class SimParams:
    """Constants of the first-order contact simulation. SI units throughout.

    ``d_t`` and ``d_r`` are the damping constants of equation (1): v = d_t f (m/(N·s)) and
    ω = d_r m (rad/(N·m·s)); ``d_r = d_t / char_length_m²`` so that a force at a typical lever
    arm turns the workpiece as much as it moves it. The dragger spring (Fig. 8) has stiffness
    ``k_t`` (N/m) and ``k_r = k_t · char_length_m²`` (N·m/rad): both time constants are
    ``1 / (d_t k_t)`` seconds.
    """

    dt_s: float = 0.05
    """Time step Δt (§V-A: 50 ms)."""
    eps_contact_m: float = 0.5e-3
    """ε_c: parts closer than this are in contact (§VII-B: 0.5 mm)."""
    eps_barrier_m: float = 0.1e-3
    """ε_b: the barrier keeps the workpiece about this far from everything (§VII-B: 0.1 mm)."""
    eps_capture_m: float = 2e-3
    """ε_o: a captured object stays within this distance (§VII-B: 2 mm)."""
    golden_rel_tol: float = 1e-5
    """Golden-section search stops when its bracket is below this fraction of Δt (§VII-B); at
    least :data:`MIN_GOLDEN_REL_TOL`, where the bracket still shrinks in float64."""
    max_speed_mps: float = 0.4
    """Fastest any point of the workpiece may move (§VII-B: 400 mm/s); faster commands are
    scaled down and the step says so."""
    d_t: float = 0.05
    char_length_m: float = 0.025
    k_t: float = 100.0
    barrier_gain: float = 1.0
    """K of equation (6) as a multiple of the step's work |U_v(Δt)|, which makes the barrier's
    effect independent of how hard the workpiece is pushed."""
    min_separation_fraction: float = 0.5
    """No step ends closer to anything than this fraction of ε_b. The barrier alone lets a
    slow, mostly sideways approach sink deep into it (its push grows with the approach speed),
    so the search also treats this floor as a wall."""
    max_points_per_pair: int = 8
    """Contact points kept per pair of convex parts (the manifold is reduced beyond this)."""
    tunnel_fraction: float = 0.5
    """Collision samples along a step are at most this fraction of the thinnest obstacle apart
    (§VII-B's 4 tests per step, made adaptive)."""

    @property
    def d_r(self) -> float:
        return self.d_t / self.char_length_m**2

    @property
    def k_r(self) -> float:
        return self.k_t * self.char_length_m**2

    def __post_init__(self) -> None:
        positive = (
            "dt_s",
            "eps_contact_m",
            "eps_barrier_m",
            "eps_capture_m",
            "golden_rel_tol",
            "max_speed_mps",
            "d_t",
            "char_length_m",
            "k_t",
            "barrier_gain",
            "tunnel_fraction",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"SimParams.{name} must be a finite number > 0, got {value!r}")
        if not self.eps_barrier_m < self.eps_contact_m < self.eps_capture_m:
            raise ValueError(
                "SimParams needs eps_barrier_m < eps_contact_m < eps_capture_m, got "
                f"{self.eps_barrier_m}, {self.eps_contact_m}, {self.eps_capture_m}"
            )
        if not 0 < self.min_separation_fraction < 1:
            raise ValueError("min_separation_fraction must be in (0, 1)")
        if not MIN_GOLDEN_REL_TOL <= self.golden_rel_tol < 1:
            raise ValueError(
                f"SimParams.golden_rel_tol must be in [{MIN_GOLDEN_REL_TOL:g}, 1), got "
                f"{self.golden_rel_tol!r}"
            )
        if self.tunnel_fraction > 1:
            raise ValueError(f"SimParams.tunnel_fraction must be ≤ 1, got {self.tunnel_fraction!r}")
        if not isinstance(self.max_points_per_pair, int) or self.max_points_per_pair < 1:
            raise ValueError("max_points_per_pair must be an integer ≥ 1")
