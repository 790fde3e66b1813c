"""The frictionless contact LCP of §V-A, solved with Baraff's pivoting method.

Find c with a = A c + b, a ≥ 0, c ≥ 0, aᵀc = 0, for symmetric positive *semi*-definite A (n, n)
and b (n,). In the simulator c_i is the normal force of contact i (N) and a_i its normal velocity
(m/s); A_ij = d_t n_i·n_j + d_r (p_i×n_i)·(p_j×n_j) has rank ≤ 6, so four coplanar points of a
face, duplicated contacts or more than six contacts make it singular.

Method (Baraff, "Fast contact force computation for nonpenetrating rigid bodies", SIGGRAPH 1994):
contacts with a_d < 0 are driven to complementarity one at a time. The clamped set C (a_i = 0,
c_i ≥ 0) and the not-clamped set NC (c_i = 0, a_i ≥ 0) are kept; the direction raises c_d by 1
and moves c_C so that a_C stays 0 (Δc_C = −A_CC⁻¹ A_Cd), and the max-step ratio test stops at
the first index that would leave its set, which then changes set. Only A_CC is ever solved.

Singular A, and where care is needed:

* Write A = G Gᵀ (G's rows g_i are the contacts' scaled wrenches). A_CC is nonsingular exactly
  when the g_i of C are independent. An index enters C either as d, when Δa_d > 0 (Δa_d *is* the
  Schur complement of d on C, so A_{C∪d} is nonsingular), or from NC when Δa_i < 0 (and
  Δa_i = ⟨P⊥g_i, P⊥g_d⟩ ≠ 0 means g_i is not in span g_C). In exact arithmetic A_CC therefore
  stays nonsingular, and |C| ≤ rank A ≤ 6 for contacts.
* In floating point a redundant contact (a duplicate, the fourth corner of a face, a normal
  parallel to within 1e-9 rad) has Δa_i that is rounding noise of either sign. Both tests above
  therefore ignore changes below ``DIRECTION_TOL_REL`` of their scale: a redundant contact never
  enters C on noise; it stays in NC, where its a_i is ≈ 0 anyway because a_i is the same
  combination of the a_C = 0.
* A_CC can still be ill-conditioned, so it is solved by least squares (SVD, min-norm, singular
  values below ``CLAMPED_RCOND`` dropped). For PSD A the clamped system A_CC x = −A_Cd is always
  consistent (A_Cd = G_C g_d lies in range G_C = range A_CC), so the min-norm solution is an exact
  direction even when rounding has made A_CC singular.
* If Δa_d ≈ 0 (d is redundant with C) the step is limited only by clamped forces reaching 0;
  if none does, a_d cannot be raised: the LCP is infeasible (Δc ≥ 0, A Δc = 0, bᵀΔc = a_d < 0
  is Farkas' certificate). Contact LCPs b = G g (+ nonnegative "room") are always solvable.

Every answer's residual (see :class:`LcpResult`) is checked against ``tol·(‖A‖‖c‖ + ‖b‖)``. If
pivoting fails (infeasible-looking direction, pivot cap, residual too big) it is retried on the
regularised A + δI (positive definite, so every A_CC is nonsingular, with δ small enough that the
answer still meets the tolerance for A), then projected Gauss–Seidel is run from the best answer
so far. The result names the method that answered and ``ok`` says whether it meets the
tolerance; nothing is returned silently wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

LCP_TOL_REL = 1e-9
"""Default ``tol`` (dimensionless): an answer is accepted when its residual (units of a) is at
most ``tol·(max|A_ij|·max c_i + max|b_i|)``, the scale of the terms of a = A c + b."""
SYMMETRY_TOL_REL = 1e-9
"""Largest accepted asymmetry max|A − Aᵀ| relative to max|A_ij| (dimensionless); A is then
symmetrised."""
DIAGONAL_TOL_REL = 1e-12
"""A diagonal entry below −DIAGONAL_TOL_REL·max|A_ij| means A is not PSD (dimensionless)."""
VIOLATION_TOL_REL = 1e-12
"""Inside pivoting, a_i < −VIOLATION_TOL_REL·(max|A_ij|·max c + max|b|) is a violation to drive
out; smaller negatives are rounding of a = A c + b (dimensionless)."""
DIRECTION_TOL_REL = 1e-13
"""A direction component with |Δc_i| < DIRECTION_TOL_REL·max|Δc| or |Δa_i| <
DIRECTION_TOL_REL·max|A_ij|·max|Δc| is rounding, not a change: it neither blocks the step nor
lets a redundant contact into C (dimensionless; about 1e6 ulps)."""
DIRECTION_NOISE_ULPS = 100.0
"""A change Δa_i = Σ_j A_ij Δc_j below DIRECTION_NOISE_ULPS·eps·Σ_j |A_ij Δc_j| is rounding."""
EPS = float(np.finfo(np.float64).eps)
UNRESOLVED_TOL_FRACTION = 0.01
"""A violation a_d < 0 that no direction above rounding can change is left alone if it is within
this fraction of the tolerance (dimensionless)."""
CLAMPED_RCOND = 1e-14
"""Singular values of A_CC below CLAMPED_RCOND × the largest are dropped in its least-squares
solve (dimensionless)."""
REGULARISATION_REL = 1e-4
"""The fallback pivots on A + δI with δ = REGULARISATION_REL·tol·max|A_ij| (dimensionless), so
its error δ·c in a is far inside the tolerance tol·max|A_ij|·max c."""
REGULARISATION_CHECK_FACTOR = 10.0
"""The regularised answer is re-solved with δ × REGULARISATION_CHECK_FACTOR. The tolerance grows
with c, so on an infeasible LCP the answer c ≈ violation/δ would "pass"; such forces shrink by
the factor, real ones do not. They are refused if max c falls below half (dimensionless)."""
MAX_PIVOTS_PER_CONTACT = 20
"""Pivot cap n·MAX_PIVOTS_PER_CONTACT + MAX_PIVOTS_EXTRA against cycling; typical problems use
fewer than 2 pivots per contact."""
MAX_PIVOTS_EXTRA = 50
PGS_MAX_SWEEPS = 5000
"""Sweep cap of the projected Gauss–Seidel fallback; its residual is checked every
``PGS_CHECK_EVERY`` sweeps."""
PGS_CHECK_EVERY = 25

METHOD_PIVOTING = "pivoting"
METHOD_REGULARISED = "pivoting-regularised"
METHOD_PGS = "pgs"
METHOD_GUESS = "clamped-guess"


@dataclass(frozen=True)
class LcpResult:
    """Solution of a = A c + b, a ≥ 0, c ≥ 0, aᵀc = 0.

    Attributes:
        c: (n,) float64, ≥ 0 (the contact force magnitudes, N, in the simulator).
        a: (n,) float64, A c + b recomputed from the returned ``c``, with A symmetrised as
            (A + Aᵀ)/2 (normal velocities, m/s).
        residual: max_i |min(a_i, α c_i)| in the units of a, with α = max_i A_ii (units of a
            per unit of c) making the two comparable. It is zero exactly when a ≥ 0, c ≥ 0 and
            aᵀc = 0, and it bounds every negativity violation: it is at least max(−a_i) and
            α·max(−c_i). 0 for n = 0.
        tolerance: ``tol·(max|A_ij|·max|c_i| + max|b_i|)``, units of a.
        iterations: pivots (pivoting methods, summed over the attempts) or sweeps (PGS).
        method: which method produced ``c``: "pivoting", "pivoting-regularised" or "pgs".
        ok: ``residual ≤ tolerance``.
        message: empty when the first method succeeded; otherwise why it failed and what answered.
    """

    c: np.ndarray
    a: np.ndarray
    residual: float
    tolerance: float
    iterations: int
    method: str
    ok: bool
    message: str = ""
    clamped: np.ndarray | None = None
    """(n,) bool: the clamped set C (a_i = 0) the answer was solved on, for the pivoting methods
    and a guess (None for PGS): a similar LCP may pass it as ``clamped_guess``."""


class _PivotingError(RuntimeError):
    """Pivoting cannot go on: pivot cap or no blocking index (infeasible-looking direction)."""

    def __init__(self, message: str, pivots: int) -> None:
        super().__init__(message)
        self.pivots = pivots


def lcp_residual(A: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """The :attr:`LcpResult.residual` of ``c`` for the LCP (A, b) (units of a)."""
    if len(b) == 0:
        return 0.0
    alpha = float(np.max(np.diag(A)))
    alpha = alpha if alpha > 0 else 1.0
    return float(np.max(np.abs(np.minimum(A @ c + b, alpha * c))))


def _tolerance(A_max: float, b_max: float, c: np.ndarray, tol: float) -> float:
    return tol * (A_max * float(np.max(np.abs(c), initial=0.0)) + b_max)


def _solve_clamped(M: np.ndarray, r: np.ndarray) -> np.ndarray:
    """M x = r for the clamped block A_CC: least squares, min-norm (see the module docstring)."""
    if len(r) == 1:
        return r / M[0, 0] if M[0, 0] > 0 else np.zeros(1)
    return np.linalg.lstsq(M, r, rcond=CLAMPED_RCOND)[0]


def _pivoting(
    A: np.ndarray, b: np.ndarray, max_pivots: int, tol: float
) -> tuple[np.ndarray, int, np.ndarray]:
    """Baraff's pivoting; returns (c, pivots, the clamped set) or raises :class:`_PivotingError`."""
    n = len(b)
    A_abs = np.abs(A)
    A_max = float(np.max(A_abs))
    b_max = float(np.max(np.abs(b)))
    c = np.zeros(n)
    a = b.copy()
    clamped = np.zeros(n, dtype=bool)  # C
    not_clamped = np.zeros(n, dtype=bool)  # NC
    unresolvable = np.zeros(n, dtype=bool)  # in NC with a_i < 0 below what directions resolve
    pivots = 0
    steps = np.empty(n)
    while True:
        violation_tol = VIOLATION_TOL_REL * (A_max * float(np.max(c)) + b_max)
        # Baraff drives the untouched indices; NC indices are driven again if changes ignored as
        # rounding by the ratio test have let their a_i fall (c_i = 0 there, so that is valid).
        candidates = ~clamped & ~unresolvable & (a < -violation_tol)
        if not candidates.any():
            break
        d = int(np.argmin(np.where(candidates, a, np.inf)))
        not_clamped[d] = False
        seen: set[bytes] = set()  # clamped sets met while driving d: a repeat is a cycle
        while True:  # drive a_d to zero
            if a[d] >= -violation_tol:  # reached in a tie with the last blocking index
                (clamped if c[d] > 0 else not_clamped)[d] = True
                break
            pivots += 1
            if pivots > max_pivots:
                raise _PivotingError(f"pivot cap {max_pivots} reached (cycling?)", pivots)
            key = clamped.tobytes()
            if key in seen:
                raise _PivotingError(f"cycling while driving contact {d}", pivots)
            seen.add(key)
            idx = np.flatnonzero(clamped)
            dc = np.zeros(n)
            dc[d] = 1.0
            if len(idx):
                dc[idx] = _solve_clamped(A[np.ix_(idx, idx)], -A[idx, d])
            da = A @ dc
            dc_tol = DIRECTION_TOL_REL * float(np.max(np.abs(dc)))
            # Per row: the rounding of Σ_j A_ij Δc_j is about eps·Σ_j |A_ij Δc_j|.
            da_tol = DIRECTION_NOISE_ULPS * EPS * (A_abs @ np.abs(dc))
            # Max-step ratio test, vectorised: the step at which each index would leave its set.
            steps.fill(np.inf)
            shrinking = clamped & (dc < -dc_tol)
            steps[shrinking] = -c[shrinking] / dc[shrinking]
            falling = not_clamped & (da < -da_tol)
            steps[falling] = -a[falling] / da[falling]
            if da[d] > da_tol[d]:
                steps[d] = -a[d] / da[d]
            j = int(np.argmin(steps))
            step = float(steps[j])
            if not np.isfinite(step):
                # No direction above rounding moves a_d: d is redundant with C. A violation
                # far inside the tolerance is structure below the resolution of A (e.g. d_r·|p|²
                # 1e-12 of d_t): leave it. A real one means the LCP is infeasible.
                if a[d] >= -UNRESOLVED_TOL_FRACTION * tol * (A_max * float(np.max(c)) + b_max):
                    not_clamped[d] = unresolvable[d] = c[d] == 0.0
                    clamped[d] = c[d] > 0.0
                    break
                raise _PivotingError(
                    f"contact {d} cannot be driven to a_{d} ≥ 0 (a_{d} = {a[d]:.3g}); "
                    "the LCP looks infeasible",
                    pivots,
                )
            step = max(step, 0.0)
            c += step * dc
            if j == d:
                c[d] = max(c[d], 0.0)
                clamped[d] = True
                a = A @ c + b
                break
            if clamped[j]:
                clamped[j], not_clamped[j] = False, True
                c[j] = 0.0
            else:
                not_clamped[j], clamped[j] = False, True
            # Recomputed rather than updated, so a and c never drift apart.
            a = A @ c + b
    # The increments carry rounding from every pivot; one solve on the final C removes it.
    np.maximum(c, 0.0, out=c)
    if clamped.any():
        polished = _on_clamped(A, b, clamped)
        if lcp_residual(A, b, polished) <= lcp_residual(A, b, c):
            c = polished
    return c, pivots, clamped


def _on_clamped(A: np.ndarray, b: np.ndarray, clamped: np.ndarray) -> np.ndarray:
    """c with a_C = 0 on the clamped set C and c = 0 elsewhere (negative forces cut to 0)."""
    idx = np.flatnonzero(clamped)
    c = np.zeros(len(b))
    c[idx] = np.maximum(_solve_clamped(A[np.ix_(idx, idx)], -b[idx]), 0.0)
    return c


def _pgs(A: np.ndarray, b: np.ndarray, c0: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """Projected Gauss–Seidel from ``c0`` until the residual meets ``tol`` or the sweep cap."""
    c = c0.copy()
    diag = np.diag(A)
    rows = np.flatnonzero(diag > 0)
    A_max, b_max = float(np.max(np.abs(A))), float(np.max(np.abs(b)))
    for sweep in range(1, PGS_MAX_SWEEPS + 1):
        for i in rows:  # Gauss–Seidel is sequential by nature
            c[i] = max(0.0, c[i] - (A[i] @ c + b[i]) / diag[i])
        if sweep % PGS_CHECK_EVERY == 0 and lcp_residual(A, b, c) <= _tolerance(
            A_max, b_max, c, tol
        ):
            return c, sweep
    return c, PGS_MAX_SWEEPS


def _real_forces(
    A: np.ndarray, b: np.ndarray, c: np.ndarray, delta: float, cap: int, tol: float
) -> bool:
    """Whether the regularised answer ``c`` survives more regularisation (see
    ``REGULARISATION_CHECK_FACTOR``)."""
    M = A + REGULARISATION_CHECK_FACTOR * delta * np.eye(len(b))
    try:
        c_more, _, _ = _pivoting(M, b, cap, tol)
    except _PivotingError:
        return False
    return bool(np.max(c_more) >= 0.5 * np.max(c))


def _validated(A: np.ndarray, b: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if b.ndim != 1 or A.shape != (len(b), len(b)):
        raise ValueError(f"solve_lcp: A must be (n, n) and b (n,), got A {A.shape} and b {b.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise ValueError("solve_lcp: A or b contains NaN or infinity")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"solve_lcp: tol must be a positive finite number, got {tol}")
    if len(b) == 0:
        return A, b
    A_max = float(np.max(np.abs(A)))
    asymmetry = float(np.max(np.abs(A - A.T)))
    if asymmetry > SYMMETRY_TOL_REL * A_max:
        raise ValueError(
            f"solve_lcp: A is not symmetric (max |A − Aᵀ| = {asymmetry:.3g}, "
            f"allowed {SYMMETRY_TOL_REL:g}·max|A| = {SYMMETRY_TOL_REL * A_max:.3g})"
        )
    if float(np.min(np.diag(A))) < -DIAGONAL_TOL_REL * A_max:
        raise ValueError("solve_lcp: A has a negative diagonal entry, so it is not PSD")
    return 0.5 * (A + A.T), b


def solve_lcp(
    A: np.ndarray,
    b: np.ndarray,
    *,
    tol: float = LCP_TOL_REL,
    max_pivots: int | None = None,
    clamped_guess: np.ndarray | None = None,
) -> LcpResult:
    """Solve a = A c + b, a ≥ 0, c ≥ 0, aᵀc = 0 for symmetric PSD ``A`` (n, n) and ``b`` (n,).

    ``tol`` is the relative tolerance of :attr:`LcpResult.tolerance`; ``max_pivots`` overrides the
    pivot cap (n·MAX_PIVOTS_PER_CONTACT + MAX_PIVOTS_EXTRA) of each pivoting attempt.
    ``clamped_guess`` (n,) bool: a clamped set to try first (the :attr:`LcpResult.clamped` of a
    similar LCP, e.g. the same contacts a little further on): its one solve is the answer if
    that meets the tolerance, as pivoting's would (pivoting ends with the same solve on its final
    clamped set); otherwise pivoting runs as without it. Raises
    ValueError for a wrong shape, NaN/inf, asymmetry beyond ``SYMMETRY_TOL_REL`` or a negative
    diagonal. Never raises for an unsolvable LCP: the result then has ``ok=False``.
    """
    A, b = _validated(A, b, tol)
    n = len(b)
    if n == 0:
        return LcpResult(np.zeros(0), np.zeros(0), 0.0, 0.0, 0, METHOD_PIVOTING, True)
    A_max, b_max = float(np.max(np.abs(A))), float(np.max(np.abs(b)))
    cap = n * MAX_PIVOTS_PER_CONTACT + MAX_PIVOTS_EXTRA if max_pivots is None else max_pivots

    failures: list[str] = []

    def result(c: np.ndarray, iterations: int, method: str) -> LcpResult:
        residual = lcp_residual(A, b, c)
        tolerance = _tolerance(A_max, b_max, c, tol)
        if residual > tolerance:
            failures.append(f"{method}: residual {residual:.3g} > tolerance {tolerance:.3g}")
        return LcpResult(
            c, A @ c + b, residual, tolerance, iterations, method, residual <= tolerance
        )

    if clamped_guess is not None and len(clamped_guess) == n and np.any(clamped_guess):
        guess = np.asarray(clamped_guess, dtype=bool)
        r = result(_on_clamped(A, b, guess), 0, METHOD_GUESS)
        if r.ok:
            return replace(r, clamped=guess)
        failures.clear()  # a guess that misses is no failure: pivoting answers as usual
    best: LcpResult | None = None
    iterations = 0
    delta = REGULARISATION_REL * tol * A_max
    for method, M in ((METHOD_PIVOTING, A), (METHOD_REGULARISED, A + delta * np.eye(n))):
        try:
            c, pivots, clamped = _pivoting(M, b, cap, tol)
        except _PivotingError as e:
            iterations += e.pivots
            failures.append(f"{method}: {e}")
            continue
        iterations += pivots
        r = replace(result(c, iterations, method), clamped=clamped)
        if r.ok and method == METHOD_REGULARISED and not _real_forces(A, b, c, delta, cap, tol):
            failures.append(
                f"{method}: its forces scale as 1/δ, made by the regularisation (the LCP is "
                "infeasible, or A has lost rank to rounding)"
            )
            r = replace(r, ok=False)
        if r.ok:
            note = "; ".join([*failures, f"answer from {method}"]) if failures else ""
            return replace(r, message=note)
        if best is None or r.residual < best.residual:
            best = r
    start = np.zeros(n)
    if best is not None and best.method == METHOD_PIVOTING:
        start = best.c  # warm start, but never from the regularisation's forces
    c, sweeps = _pgs(A, b, start, tol)
    r = result(c, sweeps, METHOD_PGS)
    if not r.ok and best is not None and best.residual < r.residual:
        r = best
    answer = "answer from " + r.method + ("" if r.ok else ", NOT within tolerance")
    return replace(r, message="; ".join([*failures, answer]))
