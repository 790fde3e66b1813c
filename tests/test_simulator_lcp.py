"""The contact LCP solver against brute-force enumeration of active sets (§V-A)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from operator_site.simulator.lcp import solve_lcp


def contact_problem(
    rng: np.random.Generator,
    n: int,
    *,
    coplanar: bool = False,
    duplicate: bool = False,
    near_parallel: bool = False,
):
    """A and b as the simulator builds them: points in a 5 cm box, unit normals, log-uniform
    damping constants, a random applied force and moment."""
    d_t = 10.0 ** rng.uniform(-6, 6)
    d_r = d_t / 0.025**2 * 10.0 ** rng.uniform(-3, 3)
    P = rng.uniform(-0.025, 0.025, size=(n, 3))
    N = rng.normal(size=(n, 3))
    if coplanar:  # a face on a plane: points at z = −h, all normals +z
        P[:, 2] = -0.025
        N[:] = [0.0, 0.0, 1.0]
    if near_parallel:
        N[:] = [0.0, 0.0, 1.0]
        N[:, 0] += rng.normal(size=n) * 1e-9
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    if duplicate and n > 1:
        P[n // 2 :] = P[: n - n // 2]
        N[n // 2 :] = N[: n - n // 2]
    T = np.cross(P, N)
    A = d_t * N @ N.T + d_r * T @ T.T
    A = 0.5 * (A + A.T)
    f = rng.normal(size=3) * 10.0 ** rng.uniform(-9, 6)
    m = rng.normal(size=3) * 10.0 ** rng.uniform(-9, 6) * 0.025
    return A, d_t * N @ f + d_r * T @ m


def brute_force_accelerations(A: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """Every a = Ac + b of a complementary solution found by trying each active set."""
    n = len(b)
    tol = 1e-7 * (np.abs(A).max() + np.abs(b).max())
    found = []
    for k in range(n + 1):
        for S in itertools.combinations(range(n), k):
            S = list(S)
            c = np.zeros(n)
            if S:
                c[S] = np.linalg.lstsq(A[np.ix_(S, S)], -b[S], rcond=None)[0]
            a = A @ c + b
            if np.all(c >= -tol) and np.all(a >= -tol) and abs(a @ c) <= tol * max(1, c.max()):
                found.append(a)
    return found


@pytest.mark.parametrize("seed", range(4))
def test_matches_brute_force_on_random_small_problems(seed: int) -> None:
    rng = np.random.default_rng(seed)
    worst = 0.0
    for case in range(300):
        n = int(rng.integers(1, 7))
        kind = case % 4
        A, b = contact_problem(
            rng, n, coplanar=kind == 1, duplicate=kind == 2, near_parallel=kind == 3
        )
        result = solve_lcp(A, b)
        assert result.ok, result.message
        assert np.all(np.isfinite(result.c))
        reference = brute_force_accelerations(A, b)
        assert reference, "brute force found no solution"
        scale = np.abs(A).max() * max(np.abs(result.c).max(), 1.0) + np.abs(b).max()
        # For PSD A the accelerations of all solutions agree (c may not be unique).
        err = min(np.abs(result.a - a).max() for a in reference) / scale
        worst = max(worst, err)
        assert err < 1e-6
    assert worst < 1e-6


def test_block_resting_on_the_table_balances_the_push() -> None:
    h = 0.025
    P = np.array([[x, y, -h] for x in (-h, h) for y in (-h, h)])
    N = np.tile([0.0, 0.0, 1.0], (4, 1))
    T = np.cross(P, N)
    d_t, d_r = 0.05, 80.0
    f = np.array([0.3, -0.2, -5.0])
    A = d_t * N @ N.T + d_r * T @ T.T
    result = solve_lcp(A, d_t * N @ f)
    assert result.ok
    total = N.T @ result.c + f
    np.testing.assert_allclose(total[2], 0.0, atol=1e-12)  # the table cancels the push
    moment = T.T @ result.c
    np.testing.assert_allclose(moment, 0.0, atol=1e-12)  # ... without turning the block
    assert np.all(result.c >= 0)


def test_cube_in_a_corner_is_held_by_table_and_two_walls() -> None:
    h = 0.025
    faces = {(0, 0, 1): 2, (1, 0, 0): 0, (0, 1, 0): 1}
    P, N = [], []
    for normal, axis in faces.items():
        for u in (-h, h):
            for v in (-h, h):
                p = [u, v, u]
                p[axis] = -h
                others = [i for i in range(3) if i != axis]
                p[others[0]], p[others[1]] = u, v
                P.append(p)
                N.append(normal)
    P, N = np.array(P, dtype=float), np.array(N, dtype=float)
    T = np.cross(P, N)
    A = 0.05 * N @ N.T + 80.0 * T @ T.T
    f = np.array([-1.0, -1.0, -1.0])
    result = solve_lcp(A, 0.05 * N @ f)
    assert result.ok
    np.testing.assert_allclose(N.T @ result.c + f, 0.0, atol=1e-12)


def test_separating_contacts_get_no_force_and_bad_input_is_refused() -> None:
    A = np.eye(3)
    result = solve_lcp(A, np.array([1.0, 2.0, 0.0]))
    assert result.ok and np.all(result.c == 0)
    assert solve_lcp(np.zeros((0, 0)), np.zeros(0)).ok
    with pytest.raises(ValueError, match="NaN"):
        solve_lcp(A, np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="symmetric"):
        solve_lcp(np.array([[1.0, 1.0], [0.0, 1.0]]), np.zeros(2))
    with pytest.raises(ValueError, match="must be"):
        solve_lcp(np.eye(2), np.zeros(3))


@pytest.mark.parametrize("n", [20, 50, 100])
def test_many_redundant_contacts(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(20):
        A, b = contact_problem(rng, n, coplanar=True, duplicate=True)
        result = solve_lcp(A, b)
        assert result.ok, result.message
