"""The §V-A contact LCP solver: brute force, random contact problems, hand-worked blocks.

Convention (as in ``stepper.py``): p_i is contact i's point measured from the workpiece's
reference point (its centre), n_i the unit normal pointing into the workpiece (the direction of
the reaction), c_i ≥ 0 the reaction's magnitude and a_i = n_i·(v + ω × p_i) the normal velocity,
with v = d_t (f_a + Σ c_j n_j), ω = d_r (m_a + Σ c_j p_j × n_j). Hence
A_ij = d_t n_i·n_j + d_r (p_i×n_i)·(p_j×n_j) and b_i = d_t n_i·f_a + d_r (p_i×n_i)·m_a.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from operator_site.simulator import lcp
from operator_site.simulator.lcp import LcpResult, lcp_residual, solve_lcp

H = 0.025
"""Half the side of the 5 cm cube, m."""

STATS: dict[str, dict[str, float]] = {}
"""Per method: solves, the worst residual / (max|A|·max c + max|b|), the most iterations."""


def contact_lcp(
    P: np.ndarray, N: np.ndarray, d_t: float, d_r: float, f_a: np.ndarray, m_a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A (n, n) and b (n,) of §V-A for points P (n, 3) and unit normals N (n, 3)."""
    T = np.cross(P, N)
    return d_t * N @ N.T + d_r * T @ T.T, d_t * N @ f_a + d_r * T @ m_a


def face_corners() -> np.ndarray:
    """The 4 bottom corners (4, 3) of the cube: a face resting on a plane."""
    return np.array([[x, y, -H] for x in (-H, H) for y in (-H, H)])


def random_problem(
    rng: np.random.Generator, n: int, kind: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A, b, P, N like the simulator's: points in a 5 cm box, unit normals, d_t and d_r each
    log-uniform in 1e-6..1e6, b from a random applied force (N) and moment (N·m)."""
    d_t, d_r = 10.0 ** rng.uniform(-6, 6, size=2)
    P = rng.uniform(-H, H, size=(n, 3))
    N = rng.normal(size=(n, 3))
    if kind == "face":  # a face's 4 coplanar corners on a plane, plus random contacts
        k = min(n, 4)
        P[:k] = face_corners()[:k]
        N[:k] = [0.0, 0.0, 1.0]
    elif kind == "near_parallel":  # all normals within ~1e-9 rad of +z
        N[:] = [0.0, 0.0, 1.0]
        N[:, :2] += rng.normal(size=(n, 2)) * 1e-9
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    if kind == "duplicate" and n > 1:
        half = n // 2
        P[half:], N[half:] = P[: n - half], N[: n - half]
    f_a = rng.normal(size=3) * 10.0 ** rng.uniform(-3, 3)
    m_a = rng.normal(size=3) * 10.0 ** rng.uniform(-3, 3) * 2 * H
    A, b = contact_lcp(P, N, d_t, d_r, f_a, m_a)
    if kind == "room":  # the stepper adds gap/Δt ≥ 0 for contacts with room to spare
        b = b + np.where(rng.random(n) < 0.5, rng.random(n) * np.abs(b).max(), 0.0)
    return A, b, P, N


def check(result: LcpResult, A: np.ndarray, b: np.ndarray) -> None:
    """The laws every answer must satisfy; updates STATS."""
    n = len(b)
    A = 0.5 * (A + A.T)  # what the solver works with
    assert result.ok, result.message
    assert result.c.shape == result.a.shape == (n,)
    assert result.c.dtype == result.a.dtype == np.float64
    assert np.all(np.isfinite(result.c)) and np.all(np.isfinite(result.a))
    assert np.all(result.c >= 0.0)
    np.testing.assert_array_equal(result.a, A @ result.c + b)
    assert result.residual == lcp_residual(A, b, result.c)
    assert result.residual <= result.tolerance
    scale = np.abs(A).max() * result.c.max(initial=0.0) + np.abs(b).max(initial=0.0)
    assert result.tolerance == pytest.approx(lcp.LCP_TOL_REL * scale)
    # The residual bounds every violation: a ≥ 0, and c_i > 0 only where a_i ≈ 0.
    alpha = np.diag(A).max() if n else 1.0
    assert np.all(result.a >= -result.tolerance)
    assert np.all(np.minimum(result.a, alpha * result.c) <= result.tolerance)
    stats = STATS.setdefault(
        result.method, {"solves": 0, "max_relative_residual": 0.0, "max_iterations": 0}
    )
    stats["solves"] += 1
    if scale > 0:
        stats["max_relative_residual"] = max(
            stats["max_relative_residual"], result.residual / scale
        )
    stats["max_iterations"] = max(stats["max_iterations"], result.iterations)


def brute_force(A: np.ndarray, b: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """All (c, a) found by trying every active set S: A_SS c_S = −b_S (least squares when
    A_SS is singular), c elsewhere 0, kept when c ≥ 0, a_S = 0 and a ≥ 0 within tolerance."""
    n = len(b)
    A_max, b_max = np.abs(A).max(), np.abs(b).max()
    found = []
    for k in range(n + 1):
        for S in itertools.combinations(range(n), k):
            S = list(S)
            c = np.zeros(n)
            if S:
                c[S] = np.linalg.lstsq(A[np.ix_(S, S)], -b[S], rcond=None)[0]
            a = A @ c + b
            tol = 1e-9 * (A_max * np.abs(c).max() + b_max)
            if np.all(c >= -tol / max(A_max, 1e-300)) and np.all(a >= -tol):
                if np.all(np.abs(a[S]) <= tol):
                    found.append((c, a))
    return found


def test_matches_brute_force_on_small_random_contact_problems() -> None:
    """1,200 problems with n = 1..6 and 8: a (unique for PSD A) matches an enumerated
    solution; c too when A is well-conditioned positive definite."""
    rng = np.random.default_rng(20240611)
    kinds = ["generic", "face", "duplicate", "near_parallel", "room"]
    compared_c = 0
    for case in range(1200):
        n = 8 if case % 12 == 0 else int(rng.integers(1, 7))
        A, b, _, _ = random_problem(rng, n, kinds[case % len(kinds)])
        result = solve_lcp(A, b)
        check(result, A, b)
        reference = brute_force(A, b)
        assert reference, "brute force found no solution"
        scale = (
            np.abs(A).max() * max(result.c.max(), min(np.abs(c).max() for c, _ in reference))
            + np.abs(b).max()
        )
        err_a = min(np.abs(result.a - a).max() for _, a in reference)
        assert err_a <= 1e-8 * scale, (case, n, err_a / scale)
        eig = np.linalg.eigvalsh(A)
        if eig[0] > 1e-6 * eig[-1]:  # positive definite, cond < 1e6: c is unique too
            err_c = min(np.abs(result.c - c).max() for c, _ in reference)
            assert err_c <= 1e-7 * max(result.c.max(), 1e-300) + 1e-9 * np.abs(b).max() / eig[0]
            compared_c += 1
    assert compared_c > 100  # the c comparison must not be vacuous


@pytest.mark.parametrize("kind", ["generic", "face", "duplicate", "near_parallel", "room"])
def test_many_contacts_singular_and_redundant(kind: str) -> None:
    """60 problems per kind with 20..100 contacts (rank ≤ 6, so A is singular)."""
    rng = np.random.default_rng(len(kind))
    for _ in range(60):
        n = int(rng.integers(20, 101))
        A, b, _, _ = random_problem(rng, n, kind)
        check(solve_lcp(A, b), A, b)


def test_all_separating_contacts_get_no_force() -> None:
    rng = np.random.default_rng(7)
    for _ in range(100):
        n = int(rng.integers(1, 30))
        A, b, _, _ = random_problem(rng, n, "generic")
        b = np.abs(b)
        b[rng.random(n) < 0.2] = 0.0  # touching but not pushed
        result = solve_lcp(A, b)
        check(result, A, b)
        np.testing.assert_array_equal(result.c, 0.0)
        np.testing.assert_array_equal(result.a, b)
        assert result.iterations == 0 and result.method == lcp.METHOD_PIVOTING


def test_one_contact_is_the_closed_form() -> None:
    rng = np.random.default_rng(8)
    for _ in range(100):
        A, b, _, _ = random_problem(rng, 1, "generic")
        result = solve_lcp(A, b)
        check(result, A, b)
        expected = max(0.0, -b[0] / A[0, 0])
        assert result.c[0] == pytest.approx(expected, rel=1e-12)
        assert result.a[0] == pytest.approx(max(b[0], 0.0), abs=1e-12 * abs(b[0]))


def test_cube_on_the_table_balances_the_push() -> None:
    """A 5 cm cube on a table (4 bottom corners, normals +z) pushed down through its centre,
    and sideways: the table carries exactly the downward push, without a moment, and the
    cube slides (frictionless) at v = d_t f_horizontal without turning. A is singular here
    (rank 3): c is not unique, but Σc, the moment and a are."""
    P = face_corners()
    N = np.tile([0.0, 0.0, 1.0], (4, 1))
    T = np.cross(P, N)
    f_a, m_a = np.array([0.3, -0.2, -5.0]), np.zeros(3)
    d_t, d_r = 0.05, 80.0
    A, b = contact_lcp(P, N, d_t, d_r, f_a, m_a)
    result = solve_lcp(A, b)
    check(result, A, b)
    assert result.c.sum() == pytest.approx(5.0, rel=1e-14)
    np.testing.assert_allclose(f_a + N.T @ result.c, [0.3, -0.2, 0.0], atol=1e-14)
    np.testing.assert_allclose(T.T @ result.c, 0.0, atol=1e-14)
    np.testing.assert_allclose(result.a, 0.0, atol=1e-15)


@pytest.mark.parametrize(("d_t", "d_r"), [(1.0, 1.0), (1e-6, 1e6), (1e6, 1e-6)])
def test_cube_on_the_table_with_extreme_damping_ratios(d_t: float, d_r: float) -> None:
    """With d_r|p|²/d_t = 6e8 or 6e-16, the weak part of A is below rounding of the strong one:
    c is then only as accurate as the LCP tolerance allows, so assert what the tolerance is about,
    the velocities: v_z = d_t (f_z + Σc) and the corners' speeds from ω = d_r m are within it,
    and the horizontal slide is exact."""
    P = face_corners()
    N = np.tile([0.0, 0.0, 1.0], (4, 1))
    T = np.cross(P, N)
    f_a = np.array([0.3, -0.2, -5.0])
    A, b = contact_lcp(P, N, d_t, d_r, f_a, np.zeros(3))
    result = solve_lcp(A, b)
    check(result, A, b)
    v = d_t * (f_a + N.T @ result.c)
    w = d_r * (T.T @ result.c)
    np.testing.assert_allclose(v[:2], d_t * f_a[:2], rtol=1e-15)
    assert abs(v[2]) <= result.tolerance
    assert np.linalg.norm(w) * np.sqrt(2) * H <= result.tolerance


def test_cube_tips_about_an_edge_when_the_moment_is_too_large() -> None:
    """Push F down and a moment M = 2 F h about +y (more than F h, what the table can resist):
    the +x edge carries c = (d_t F + d_r h M) / (2 (d_t + d_r h²)) at each corner, the −x
    corners lift off at a = 2 h d_r (M − 2 h c)."""
    P = face_corners()
    N = np.tile([0.0, 0.0, 1.0], (4, 1))
    d_t, d_r, F = 0.05, 80.0, 5.0
    M = 2 * F * H
    A, b = contact_lcp(P, N, d_t, d_r, np.array([0.0, 0.0, -F]), np.array([0.0, M, 0.0]))
    result = solve_lcp(A, b)
    check(result, A, b)
    plus_x = P[:, 0] > 0
    c_edge = (d_t * F + d_r * H * M) / (2 * (d_t + d_r * H**2))
    np.testing.assert_allclose(result.c[plus_x], c_edge, rtol=1e-12)
    np.testing.assert_array_equal(result.c[~plus_x], 0.0)
    np.testing.assert_allclose(result.a[~plus_x], 2 * H * d_r * (M - 2 * H * c_edge), rtol=1e-12)
    np.testing.assert_allclose(result.a[plus_x], 0.0, atol=1e-12)


def cube_in_corner() -> tuple[np.ndarray, np.ndarray]:
    """12 contacts: the table under the cube (+z) and walls at x = −h (+x) and y = −h (+y)."""
    P, N = [], []
    for axis in range(3):
        others = [i for i in range(3) if i != axis]
        for u, v in itertools.product((-H, H), repeat=2):
            p = np.zeros(3)
            p[axis], p[others[0]], p[others[1]] = -H, u, v
            P.append(p)
            N.append(np.eye(3)[axis])
    return np.array(P), np.array(N)


def test_cube_pushed_into_a_corner_is_held_by_table_and_walls() -> None:
    P, N = cube_in_corner()
    T = np.cross(P, N)
    f_a = np.array([-1.0, -2.0, -3.0])
    A, b = contact_lcp(P, N, 0.05, 80.0, f_a, np.zeros(3))
    result = solve_lcp(A, b)
    check(result, A, b)
    np.testing.assert_allclose(N.T @ result.c + f_a, 0.0, atol=1e-12)  # the cube stays put
    np.testing.assert_allclose(T.T @ result.c, 0.0, atol=1e-12)
    for axis in range(3):  # each face carries its own component of the push
        assert result.c[N[:, axis] == 1].sum() == pytest.approx(-f_a[axis], rel=1e-12)
    np.testing.assert_allclose(result.a, 0.0, atol=1e-12)


def test_cube_pushed_away_from_one_wall_leaves_it() -> None:
    P, N = cube_in_corner()
    d_t = 0.05
    f_a = np.array([2.0, -2.0, -3.0])
    A, b = contact_lcp(P, N, d_t, 80.0, f_a, np.zeros(3))
    result = solve_lcp(A, b)
    check(result, A, b)
    x_wall = N[:, 0] == 1
    np.testing.assert_array_equal(result.c[x_wall], 0.0)
    np.testing.assert_allclose(result.a[x_wall], d_t * 2.0, rtol=1e-12)  # slides off at v_x
    np.testing.assert_allclose((N.T @ result.c + f_a)[1:], 0.0, atol=1e-12)


def test_empty_problem() -> None:
    result = solve_lcp(np.zeros((0, 0)), np.zeros(0))
    assert result.ok and result.c.shape == result.a.shape == (0,) and result.residual == 0.0


@pytest.mark.parametrize(
    ("A", "b", "match"),
    [
        (np.eye(2), np.zeros(3), "must be"),
        (np.eye(3)[:2], np.zeros(2), "must be"),
        (np.eye(2), np.zeros((2, 1)), "must be"),
        (np.eye(2), np.array([np.nan, 0.0]), "NaN"),
        (np.array([[1.0, np.inf], [np.inf, 1.0]]), np.zeros(2), "NaN"),
        (np.array([[1.0, 1.0], [0.0, 1.0]]), np.zeros(2), "symmetric"),
        (-np.eye(2), np.zeros(2), "PSD"),
    ],
)
def test_bad_input_is_refused(A: np.ndarray, b: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        solve_lcp(A, b)


def test_bad_tolerance_is_refused() -> None:
    for tol in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="tol"):
            solve_lcp(np.eye(1), np.ones(1), tol=tol)


def test_asymmetry_within_tolerance_is_accepted() -> None:
    A = np.array([[2.0, 1.0], [1.0 + 1e-12, 2.0]])
    check(solve_lcp(A, np.array([-1.0, -1.0])), A, np.array([-1.0, -1.0]))


def test_infeasible_lcp_says_so_instead_of_returning_garbage() -> None:
    """A = 0, b < 0; or two opposing contacts that both approach (a_1 + a_2 = −2 for all c)."""
    opposing = np.array([[1.0, -1.0], [-1.0, 1.0]])
    for A, b in [(np.zeros((1, 1)), np.array([-1.0])), (opposing, np.array([-1.0, -1.0]))]:
        result = solve_lcp(A, b)
        assert not result.ok
        assert "infeasible" in result.message and "NOT within tolerance" in result.message
        assert np.all(np.isfinite(result.c))


def test_fallback_answers_when_pivoting_is_cut_short() -> None:
    rng = np.random.default_rng(9)
    for _ in range(20):
        A, b, _, _ = random_problem(rng, 16, "face")
        if not np.any(b < 0):
            continue
        result = solve_lcp(A, b, max_pivots=0)
        assert result.method == lcp.METHOD_PGS
        assert "pivot cap 0" in result.message
        if result.ok:
            check(result, A, b)
        else:
            assert "NOT within tolerance" in result.message


def test_regularised_pivoting_answers_for_the_original_problem() -> None:
    """The first fallback pivots on A + δI; its answer is checked against A itself."""
    rng = np.random.default_rng(10)
    for _ in range(50):
        A, b, _, _ = random_problem(rng, 12, "duplicate")
        delta = lcp.REGULARISATION_REL * lcp.LCP_TOL_REL * np.abs(A).max()
        c, _, _ = lcp._pivoting(A + delta * np.eye(12), b, 1000, lcp.LCP_TOL_REL)
        tolerance = lcp.LCP_TOL_REL * (np.abs(A).max() * c.max() + np.abs(b).max())
        assert lcp_residual(A, b, c) <= tolerance


@pytest.mark.parametrize("kind", ["generic", "face", "duplicate", "room"])
def test_clamped_guess_answers_like_pivoting_or_falls_back(kind: str) -> None:
    """A clamped set from a similar LCP (the same contacts pushed a little differently) is one
    solve that meets the tolerance, with pivoting's a; a wrong guess changes nothing."""
    rng = np.random.default_rng(12 + len(kind))
    guessed = 0
    for _ in range(100):
        n = int(rng.integers(2, 9))
        A, b, _, _ = random_problem(rng, n, kind)
        first = solve_lcp(A, b)
        assert first.clamped is not None and first.clamped.shape == (n,)
        b2 = b + 1e-3 * np.abs(b).max() * rng.normal(size=n)
        plain = solve_lcp(A, b2)
        for guess in (first.clamped, rng.random(n) < 0.5):
            result = solve_lcp(A, b2, clamped_guess=guess)
            check(result, A, b2)
            scale = np.abs(A).max() * max(result.c.max(), plain.c.max()) + np.abs(b2).max()
            assert np.abs(result.a - plain.a).max() <= 1e-8 * scale
            if result.method == lcp.METHOD_GUESS:
                np.testing.assert_array_equal(result.clamped, guess)
                guessed += 1
            else:
                np.testing.assert_array_equal(result.c, plain.c)
    assert guessed > 50  # the guess must be taken, not only fall back


def test_tighter_tolerance_is_met_or_reported() -> None:
    rng = np.random.default_rng(11)
    for _ in range(100):
        A, b, _, _ = random_problem(rng, int(rng.integers(1, 20)), "generic")
        result = solve_lcp(A, b, tol=1e-12)
        assert result.ok == (result.residual <= result.tolerance)
        scale = np.abs(A).max() * result.c.max() + np.abs(b).max()
        assert result.tolerance == pytest.approx(1e-12 * scale)


def test_statistics_were_recorded() -> None:
    """Runs last in this module: the worst residual and iteration count of the solves above."""
    print(f"\nLCP solves by method: {STATS}")
    for stats in STATS.values():
        assert stats["max_relative_residual"] <= lcp.LCP_TOL_REL
