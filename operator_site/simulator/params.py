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

STEP_GAIN_RANGE = (1e-6, 1e6)
"""Accepted x = Δt·d_t·k_t, the fraction (before :func:`~.stepper.spring_step_factor`) of the
way to the dragger a free step covers. Below, the workpiece needs millions of steps to follow
the dragger; above, a step lands on the target whatever x is, so larger values buy nothing."""

REST_GAP_FRACTION = 0.9
"""With ``barrier_gain`` 1 the barrier holds a workpiece pressed into an obstacle this fraction
of ε_b from it: near ε_b, clear of the floor (ε_b/2 by default)."""


def rest_gap_fraction(barrier_gain: float) -> float:
    """Where the barrier holds a workpiece the spring presses straight into an obstacle, as a
    fraction δ of ε_b: the barrier's force K/ε_b·(1/δ − 1) equals the spring's pull P there,
    K = barrier_gain × P × ε_b / (1/:data:`REST_GAP_FRACTION` − 1)."""
    return 1.0 / (1.0 + (1.0 / REST_GAP_FRACTION - 1.0) / barrier_gain)


def barrier_gain_for(rest_fraction: float) -> float:
    """The ``barrier_gain`` that holds a pressed workpiece ``rest_fraction`` of ε_b away."""
    return (1.0 / REST_GAP_FRACTION - 1.0) / (1.0 / rest_fraction - 1.0)


RANGES: dict[str, tuple[float, float, str]] = {
    "dt_s": (1e-4, 1.0, "from a 10 kHz step to one a second"),
    "eps_contact_m": (1e-6, 1e-2, "contact within a micrometre (above ε_b) to 1 cm"),
    "eps_barrier_m": (
        1e-6,
        1e-3,
        "tested from a micrometre (distances are exact to a picometre, but pushed into a "
        "corner with a barrier of nanometres blocks were seen to stop short of a wall when "
        "distances were GJK's); a barrier wider than a millimetre keeps blocks visibly apart",
    ),
    "eps_capture_m": (
        1e-6,
        5e-2,
        "above ε_c; a capture looser than 5 cm no longer holds a contact",
    ),
    "golden_rel_tol": (
        MIN_GOLDEN_REL_TOL,
        0.5,
        "below 1e-12 the bracket stops shrinking in float64; at 0.5 the search makes one cut",
    ),
    "max_speed_mps": (1e-4, 10.0, "0.1 mm/s to 10 m/s"),
    "d_t": (1e-6, 1e6, "m/(N·s)"),
    "char_length_m": (1e-5, 10.0, "the lever arm that weighs turning against moving"),
    "k_t": (1e-6, 1e6, "N/m"),
    "barrier_gain": (
        barrier_gain_for(0.75),
        1e6,
        "multiples of the spring's pull on the workpiece; below, at the default "
        "floor, the barrier holds it nearer the floor than ε_b, and a workpiece on the floor "
        "cannot turn or slide (any move along its contact nears it by the move's square); "
        "above, it is held within a millionth of ε_b",
    ),
    "tunnel_fraction": (
        0.01,
        1.0,
        "samples further apart than the thinnest obstacle could step over it; closer than a "
        "hundredth of it they only cost (the scene may bound it from below too: Simulator)",
    ),
}
"""Each float knob's accepted range (inclusive) and why; a value outside is refused, naming it.
The extremes are exercised by ``tests/test_simulator_extremes.py``."""


def refuse_out_of_range(owner: str, obj: object, ranges: dict[str, tuple]) -> None:
    """ValueError naming the first field of ``obj`` that is not a finite number within its
    ``ranges`` entry (lo, hi, why): the check of every parameter dataclass's float knobs."""
    for name, (lo, hi, why) in ranges.items():
        value = getattr(obj, name)
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and lo <= value <= hi):
            raise ValueError(
                f"{owner}.{name} must be a number in [{lo:g}, {hi:g}] ({why}), got {value!r}"
            )


POINTS_PER_PAIR_RANGE = (3, 128)
"""Contact points per pair of convex parts: fewer than three cannot hold a face flat against a
face; more only repeat rows of the LCP."""


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
    """Golden-section search stops when its bracket is below this fraction of Δt (§VII-B)."""
    max_speed_mps: float = 0.4
    """Fastest any point of the workpiece may move (§VII-B: 400 mm/s); faster commands are
    scaled down and the step says so."""
    d_t: float = 0.05
    char_length_m: float = 0.025
    k_t: float = 100.0
    barrier_gain: float = 1.0
    """K of equation (6) in multiples of the spring's pull on the workpiece (its moment counted
    at the workpiece's reach), scaled so that 1 holds a workpiece pressed straight into an
    obstacle at :data:`REST_GAP_FRACTION` × ε_b (:func:`rest_gap_fraction`): the barrier's
    effect does not depend on how hard the workpiece is pressed."""
    min_separation_fraction: float = 0.5
    """No step ends closer to anything than this fraction of ε_b: the search treats this floor
    as a wall, so that no rounding of a distance can carry a workpiece into an obstacle."""
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

    @property
    def floor_m(self) -> float:
        """No step ends closer to anything than this: ``min_separation_fraction`` × ε_b (m)."""
        return self.min_separation_fraction * self.eps_barrier_m

    @property
    def step_gain(self) -> float:
        """x = Δt·d_t·k_t (= Δt·d_r·k_r): the spring's gain over one step, dimensionless."""
        return self.dt_s * self.d_t * self.k_t

    def __post_init__(self) -> None:
        refuse_out_of_range("SimParams", self, RANGES)
        if not self.eps_barrier_m < self.eps_contact_m < self.eps_capture_m:
            raise ValueError(
                "SimParams needs eps_barrier_m < eps_contact_m < eps_capture_m, got "
                f"{self.eps_barrier_m}, {self.eps_contact_m}, {self.eps_capture_m}"
            )
        if not 0 < self.min_separation_fraction < 1:
            raise ValueError(
                "SimParams.min_separation_fraction must be in (0, 1), got "
                f"{self.min_separation_fraction!r}"
            )
        rest, floor = rest_gap_fraction(self.barrier_gain), self.min_separation_fraction
        if rest < (1.0 + floor) / 2:
            raise ValueError(
                f"SimParams.barrier_gain {self.barrier_gain:g} holds a pressed workpiece at "
                f"{rest:.3g} ε_b, less than halfway from the floor ({floor:g} ε_b) to ε_b: on "
                f"the floor it could not turn or slide. With min_separation_fraction {floor:g} "
                f"it must be at least {barrier_gain_for((1.0 + floor) / 2):.3g}"
            )
        lo, hi = STEP_GAIN_RANGE
        if not lo <= self.step_gain <= hi:
            raise ValueError(
                f"SimParams: the spring's step gain dt_s·d_t·k_t must be in [{lo:g}, {hi:g}], "
                f"got {self.dt_s:g}·{self.d_t:g}·{self.k_t:g} = {self.step_gain:g}"
            )
        lo_n, hi_n = POINTS_PER_PAIR_RANGE
        n = self.max_points_per_pair
        if not (isinstance(n, int) and not isinstance(n, bool) and lo_n <= n <= hi_n):
            raise ValueError(
                f"SimParams.max_points_per_pair must be an integer in [{lo_n}, {hi_n}], got {n!r}"
            )
