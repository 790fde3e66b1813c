"""The simulator at the extremes of its knobs: each of the six blocks free, sliding on the table,
pushed into the frame's inside corner and captured round its outside corner, with every knob
drawn log-uniformly over the range :class:`SimParams` accepts (``params.RANGES``).

``make test`` draws 200 examples a test, ``make test-extremes`` 5,000."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from models.scene import Scene, load_scene
from models.transforms import make_pose, rpy_to_R, so3_exp, so3_log
from operator_site.simulator.params import RANGES, STEP_GAIN_RANGE, SimParams
from operator_site.simulator.stepper import (
    BARRIER_RESOLUTION,
    MAX_COLLISION_SAMPLES,
    Simulator,
    StepResult,
)
from tests.conftest import examples

BLOCKS = ("cube", "tall_block", "plank", "wedge", "l_block", "hex_prism")
OPENING_MIN_XY = np.array([0.35, -0.10])
"""The frame's opening starts here (DESIGN.md: 0.20 m square centred at (0.45, 0))."""
OUTER_CORNER_XY = np.array([0.33, -0.12])
"""The frame's outer corner at its smallest x and y (bars 20 mm wide)."""
ORTHONORMAL_TOL = 1e-12
MOTION_REL_TOL = 1e-9
"""Relative tolerance on a step's distance left, against its exact first-order value."""
ROUNDING_M = 1e-15
"""Coordinates within a metre of the origin round to about a tenth of this."""
BALANCE_REL_TOL = 1e-3
"""A block is held in balance by its contacts when forces along their normals meet the
spring's pull but for this fraction of it."""
STILL_FLOOR_M = 1e-12
"""A pose that changes by less than this (ten thousand times coordinates' rounding) is still."""
ONE_WAY_STEPS = 50
"""The steps over which a block's path is compared with the distance it covered."""
ROCKING_PATH_RATIO = 2.0
"""A block whose path is longer than this many times the distance it covered rocks (a block
swinging between two poses covers none of its path; one settling or tipping, about all)."""
CONTACT_CHAR_LENGTH_M = (0.01, 1.0)
"""The contact cases' characteristic lengths: within a decade of the blocks' sizes. Shorter,
turning is over a hundred times as mobile as moving, and a tall block pushed at its centre
into a 30 mm bar rightly tips over it (equation 1 has no inertia to keep it upright); the
free pull covers the whole range."""
PROPERTY = settings(
    max_examples=examples(200),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
CORNER_PROPERTY = settings(PROPERTY, max_examples=examples(100))
"""The corner cases run hundreds of steps an example and are the suite's slowest; it runs them
derandomized (hypothesis's CI profile), the same examples every run, so fewer of them cost
the suite less every time; the extremes tier draws 2,500 each."""
CAPTURE_PROPERTY = settings(PROPERTY, max_examples=examples(30))
"""Round the outside corner with two captures held, an example costs several times an inside
corner's: fewer of them, the suite's longest unit test otherwise (the extremes tier draws 750)."""


class _Scenes(dict):
    """Block name → scene; a short repr, for hypothesis's report of a failing example."""

    def __repr__(self) -> str:
        return "<a scene per block>"


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    """Per block: table, frame and that block alone."""
    scene = load_scene()
    keep = {"table", "frame"}
    return _Scenes(
        (
            b,
            dataclasses.replace(
                scene, objects=tuple(o for o in scene.objects if o.name in keep | {b})
            ),
        )
        for b in BLOCKS
    )


def _log(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Log-uniform in [lo, hi] (the power's rounding kept inside the range)."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: min(max(10.0**e, lo), hi))


@st.composite
def sim_params(
    draw,
    min_step_gain: float = STEP_GAIN_RANGE[0],
    min_step_m: float = 0.0,
    char_length_m: tuple[float, float] | None = None,
):
    """Every float knob drawn over its accepted range, except that the spring's step gain is at
    least ``min_step_gain``, a step may carry the workpiece ``min_step_m`` at full speed (the
    contact cases need to reach their walls within a bounded number of steps), and
    ``char_length_m`` may narrow the characteristic length."""
    r = {name: (lo, hi) for name, (lo, hi, _) in RANGES.items()}
    if char_length_m is not None:
        r["char_length_m"] = char_length_m
    speed_hi = r["max_speed_mps"][1]
    dt = draw(_log(max(r["dt_s"][0], min_step_m / speed_hi), r["dt_s"][1]))
    speed = draw(_log(max(r["max_speed_mps"][0], min_step_m / dt), speed_hi))
    # A hair inside the gain's range: the product of the three knobs rounds.
    x = draw(_log(max(STEP_GAIN_RANGE[0], min_step_gain) * 1.000001, STEP_GAIN_RANGE[1] / 1.000001))
    (d_lo, d_hi), (k_lo, k_hi) = r["d_t"], r["k_t"]
    d_t = draw(_log(max(d_lo, x / (dt * k_hi)), min(d_hi, x / (dt * k_lo))))
    k_t = min(max(x / (dt * d_t), k_lo), k_hi)
    eps_b = draw(_log(*r["eps_barrier_m"]))
    eps_c = draw(_log(max(r["eps_contact_m"][0], 5 * eps_b), r["eps_contact_m"][1]))
    eps_o = draw(_log(max(r["eps_capture_m"][0], 2 * eps_c), r["eps_capture_m"][1]))
    return SimParams(
        dt_s=dt,
        max_speed_mps=speed,
        d_t=d_t,
        k_t=k_t,
        char_length_m=draw(_log(*r["char_length_m"])),
        eps_barrier_m=eps_b,
        eps_contact_m=eps_c,
        eps_capture_m=eps_o,
        golden_rel_tol=draw(_log(*r["golden_rel_tol"])),
        barrier_gain=draw(_log(*r["barrier_gain"])),
        tunnel_fraction=draw(_log(*r["tunnel_fraction"])),
    )


def _simulator(scene: Scene, block: str, params: SimParams, X_WO: np.ndarray) -> Simulator | None:
    """The simulator, or None when the scene refuses the tunnelling fraction (the message then
    names the fraction's range)."""
    try:
        return Simulator(scene, block, params, X_WO={block: X_WO})
    except ValueError as e:
        assert "tunnel_fraction" in str(e) and f"at most {MAX_COLLISION_SAMPLES}" in str(e)
        return None


def _resting(scene: Scene, block: str, yaw_rad: float, xy: np.ndarray, gap_m: float):
    """The block upright on the table at yaw ``yaw_rad``, its footprint's low corner at ``xy``,
    ``gap_m`` above the table; and its footprint's size (m)."""
    obj = scene.object(block)
    R = rpy_to_R(np.array([0.0, 0.0, yaw_rad]))
    V = np.vstack([p.vertices_O for p in obj.model.parts]) @ R.T
    lo, hi = V.min(axis=0), V.max(axis=0)
    p = np.array([xy[0] - lo[0], xy[1] - lo[1], gap_m - lo[2]])
    return make_pose(R, p), hi[:2] - lo[:2]


def _check_step(sim: Simulator, r: StepResult) -> None:
    """What holds after every step, whatever the knobs: a finite pose, a rotation, no point
    closer to anything than the simulator's floor (half of ε_b), and no more queries than the
    step's bound."""
    assert np.all(np.isfinite(r.X_WO))
    R = r.X_WO[:3, :3]
    assert np.max(np.abs(R.T @ R - np.eye(3))) < ORTHONORMAL_TOL
    assert r.min_distance_m >= sim.params.floor_m * (1 - 1e-12)
    assert r.queries <= sim.max_queries_per_step


def _centre(sim: Simulator, X: np.ndarray) -> np.ndarray:
    return X[:3, :3] @ sim.c_O + X[:3, 3]


# ------------------------------------------------------------------------------------- free


@PROPERTY
@given(
    block=st.sampled_from(BLOCKS),
    params=sim_params(),
    offset=st.tuples(*[st.floats(-0.2, 0.2)] * 3),
    turn=st.tuples(*[st.floats(-1.7, 1.7)] * 3),
)
def test_a_free_pull_contracts_on_the_target_at_the_springs_exact_rate(
    scenes, block, params, offset, turn
) -> None:
    """In free space each step leaves e^(−x) of the way (x = Δt·d_t·k_t), in translation and in
    rotation alike; at the speed limit it moves exactly max_speed·Δt and no faster than that.
    Never past the target: the centre stays on the segment to it."""
    X0 = make_pose(np.eye(3), (0.45, 0.3, 0.5))  # 0.24 m above anything, whatever the pull
    sim = _simulator(scenes[block], block, params, X0)
    if sim is None:
        return
    X_D = make_pose(so3_exp(np.array(turn)) @ X0[:3, :3], X0[:3, 3] + np.array(offset))
    sim.set_target(X_D)
    c_D = _centre(sim, X_D)
    c0 = _centre(sim, X0)
    e = float(np.linalg.norm(c_D - c0))
    th = float(np.linalg.norm(so3_log(X_D[:3, :3] @ X0[:3, :3].T)))
    keep = math.exp(-params.step_gain)
    for _ in range(25):
        r = sim.step()
        _check_step(sim, r)
        c = _centre(sim, r.X_WO)
        e1 = float(np.linalg.norm(c_D - c))
        th1 = float(np.linalg.norm(so3_log(X_D[:3, :3] @ r.X_WO[:3, :3].T)))
        # Never past the target (but for the rounding of coordinates near 0.5 m).
        assert (c_D - c) @ (c_D - c0) >= -ROUNDING_M * float(np.linalg.norm(c_D - c0))
        if r.s_fraction == 0.0:  # at rest: what is left moves no point by a picometre
            assert (e + th * sim.r_max_m) * (1 - keep) < 1e-11
        elif not r.speed_limited:
            assert e1 == pytest.approx(e * keep, rel=MOTION_REL_TOL, abs=1e-15)
            assert th1 == pytest.approx(th * keep, rel=MOTION_REL_TOL, abs=1e-13)
        else:
            moved = (e - e1) + (th - th1) * sim.r_max_m
            assert moved == pytest.approx(params.max_speed_mps * params.dt_s, rel=MOTION_REL_TOL)
            assert e1 >= e * keep * (1 - MOTION_REL_TOL) - ROUNDING_M
            assert th1 >= th * keep - 1e-13
        e, th = e1, th1


@pytest.mark.parametrize("block", BLOCKS)
@pytest.mark.parametrize("x", [1e-4, 1e-2, 1.0, 2.0, 1e2, 1e4])
def test_a_free_pull_converges_without_overshoot_at_any_step_gain(scenes, block, x) -> None:
    """Δt·d_t·k_t from 1e-4 to 1e4: the way left shrinks by e^(−x) a step, and a pull the
    steps can finish ends on the target (an explicit step swings for ever from x = 2)."""
    params = SimParams(d_t=x / (SimParams().dt_s * SimParams().k_t), max_speed_mps=10.0)
    X0 = make_pose(np.eye(3), (0.45, 0.3, 0.5))
    sim = Simulator(scenes[block], block, params, X_WO={block: X0})
    X_D = make_pose(rpy_to_R(np.array([0.3, -0.2, 1.0])), (0.5, 0.27, 0.53))
    sim.set_target(X_D)
    steps = 40
    left = [
        float(np.linalg.norm(_centre(sim, X_D) - _centre(sim, r.X_WO)))
        for r in (sim.step() for _ in range(steps))
    ]
    assert np.all(np.diff(left) <= 0.0)
    if x <= 1e-2:
        left0 = float(np.linalg.norm(_centre(sim, X_D) - _centre(sim, X0)))
        assert left[-1] == pytest.approx(left0 * math.exp(-x * steps), rel=MOTION_REL_TOL)
    else:
        np.testing.assert_allclose(sim.X_WO, X_D, atol=1e-9)


# --------------------------------------------------------------------------------- contacts


@PROPERTY
@given(
    block=st.sampled_from(BLOCKS),
    params=sim_params(min_step_gain=0.2, min_step_m=1e-3, char_length_m=CONTACT_CHAR_LENGTH_M),
    heading=st.floats(-math.pi, math.pi),
    distance=st.floats(0.0, 0.05),
    yaw=st.floats(-0.5, 0.5),
    press=st.floats(0.0, 5e-3),
)
def test_a_block_slid_on_the_table_follows_without_overshoot_and_stays_on_it(
    scenes, block, params, heading, distance, yaw, press
) -> None:
    """Pressed onto the table and pulled along it, the block keeps the table contact, stays
    upright, and its centre approaches the target's across the table without passing it."""
    scene = scenes[block]
    gap = (params.eps_barrier_m + params.eps_contact_m) / 2
    X0, _ = _resting(scene, block, 0.0, np.array([0.10, 0.30]), gap)
    sim = _simulator(scene, block, params, X0)
    if sim is None:
        return
    X_D = make_pose(
        rpy_to_R(np.array([0.0, 0.0, yaw])),
        X0[:3, 3] + [distance * math.cos(heading), distance * math.sin(heading), -gap - press],
    )
    sim.set_target(X_D)
    c_D, c0 = _centre(sim, X_D)[:2], _centre(sim, X0)[:2]
    left = float(np.linalg.norm(c_D - c0))
    for _ in range(60):
        r = sim.step()
        _check_step(sim, r)
        assert "table" in {c.object for c in r.contacts}
        up = r.X_WO[:3, 2]
        assert up[2] >= math.cos(1e-6)  # upright: a microradian of tilt at most
        c = _centre(sim, r.X_WO)[:2]
        left1 = float(np.linalg.norm(c_D - c))
        assert left1 <= left + 1e-12
        assert (c_D - c) @ (c_D - c0) >= -1e-12
        left = left1


def _push_into_corner(scene, block, params, gaps, yaw, beyond, press, steps):
    """The block started off square within ``gaps`` of both walls of the frame's inside corner
    and pushed ``beyond`` past it and ``press`` into the table: the simulator and its steps,
    each checked against :func:`_check_step`."""
    eps_b, eps_c = params.eps_barrier_m, params.eps_contact_m
    X0, _ = _resting(
        scene, block, yaw, OPENING_MIN_XY + 2 * eps_b + np.array(gaps), (eps_b + eps_c) / 2
    )
    sim = _simulator(scene, block, params, X0)
    if sim is None:
        return None, []
    X_D, _ = _resting(scene, block, 0.0, OPENING_MIN_XY - beyond, -press)
    sim.set_target(X_D)
    results = []
    for _ in range(steps):
        results.append(sim.step())
        _check_step(sim, results[-1])
    return sim, results


def _tilt_rad(results: list[StepResult], X_rest: np.ndarray) -> np.ndarray:
    """How far each result's pose has tipped (rad): the angle between the world's vertical and
    the block's axis that is vertical when it rests as in ``X_rest``."""
    up_O = X_rest[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    return np.array([math.acos(min(1.0, float((r.X_WO[:3, :3] @ up_O)[2]))) for r in results])


def _still_m(sim: Simulator) -> float:
    """A block no point of which moves further than this is still: the line search's
    resolution at ε_b."""
    return max(sim.params.golden_rel_tol * sim.params.eps_barrier_m, STILL_FLOOR_M)


def _moved_m(sim: Simulator, X_a: np.ndarray, X_b: np.ndarray) -> float:
    """How far a point of the block moves at most from ``X_a`` to ``X_b`` (translation plus
    reach × turn)."""
    turned_rad = float(np.linalg.norm(so3_log(X_b[:3, :3] @ X_a[:3, :3].T)))
    return float(np.linalg.norm(X_b[:3, 3] - X_a[:3, 3])) + sim.r_max_m * turned_rad


def _unbalanced_fraction(sim: Simulator) -> float:
    """How much of the spring's pull (force, and moment over the characteristic length) no
    non-negative forces along the contacts' normals can meet, as a fraction of it."""
    p, st = sim.params, sim.state
    R, R_D = st.X_WO[:3, :3], st.X_WD[:3, :3]
    c = R @ sim.c_O + st.X_WO[:3, 3]
    f = p.k_t * (R_D @ sim.c_O + st.X_WD[:3, 3] - c)
    m = p.k_r * so3_log(R_D @ R.T)
    pull = np.concatenate([f, m / p.char_length_m])
    J = np.array(
        [
            np.concatenate([n, np.cross(q - c, n) / p.char_length_m])
            for contact in st.contacts
            for q, n in zip(contact.points_W, contact.normals_W, strict=True)
        ]
    ).reshape(-1, 6)
    residual = nnls(J.T, -pull)[1] if len(J) else float(np.linalg.norm(pull))
    return residual / float(np.linalg.norm(pull))


def _assert_rests_against_both_walls(
    sim: Simulator, results: list[StepResult], balanced_on_the_frame: bool = False
) -> None:
    """The last steps still (no point of the block moved further than the line search's
    resolution), touching frame and table, at least ε_b/2 and less than ε_c from each; or, if
    ``balanced_on_the_frame``, touching the frame alone in balance (a block tipped onto the
    bar can stand on its edges off the table, the spring's pull met by its contacts)."""
    params = sim.params
    for r in results[-5:-1]:
        moved_m = _moved_m(sim, r.X_WO, results[-1].X_WO)
        assert moved_m < _still_m(sim), (moved_m, _still_m(sim))
    gaps_m = {c.object: c.distance_m for c in results[-1].contacts}
    if balanced_on_the_frame and gaps_m.keys() == {"frame"}:
        assert _unbalanced_fraction(sim) <= BALANCE_REL_TOL, _unbalanced_fraction(sim)
    else:
        assert gaps_m.keys() == {"table", "frame"}
    assert all(params.eps_barrier_m / 2 <= d < params.eps_contact_m for d in gaps_m.values())


def _assert_never_rocks(sim: Simulator, results: list[StepResult]) -> None:
    """Over the last :data:`ONE_WAY_STEPS` steps the block's path (each step's move, the
    centre's plus the turn's at the block's reach) is at most :data:`ROCKING_PATH_RATIO` times
    as long as the distance it covered, give or take what the line search resolves: a block
    settling or tipping covers about its path, a rocking one covers none of it. The search
    places a step of sweep S to min(golden_rel_tol·S, BARRIER_RESOLUTION·ε_b), and a step that
    moved d at a fraction f of Δt had S = d/f."""
    p = sim.params
    last = results[-ONE_WAY_STEPS - 1 :]
    path_m = resolved_m = 0.0
    for a, b in itertools.pairwise(last):
        moved_m = _moved_m(sim, a.X_WO, b.X_WO)
        path_m += moved_m
        if b.s_fraction > 0.0:
            sweep_m = moved_m / b.s_fraction
            resolved_m += min(p.golden_rel_tol * sweep_m, BARRIER_RESOLUTION * p.eps_barrier_m)
    covered_m = _moved_m(sim, last[0].X_WO, last[-1].X_WO)
    allowed_m = ROCKING_PATH_RATIO * covered_m + resolved_m + ONE_WAY_STEPS * _still_m(sim)
    assert path_m <= allowed_m, ("rocks", path_m, covered_m, resolved_m)


@CORNER_PROPERTY
@given(
    block=st.sampled_from(BLOCKS),
    params=sim_params(min_step_gain=0.2, min_step_m=2e-3, char_length_m=CONTACT_CHAR_LENGTH_M),
    gaps=st.tuples(st.floats(0.0, 5e-3), st.floats(0.0, 5e-3)),
    yaw=st.floats(-0.1, 0.1),
    beyond=st.floats(2e-3, 0.02),
    press=st.floats(1e-3, 5e-3),
)
def test_a_block_pushed_into_the_inside_corner_never_rocks_and_rests_once_still(
    scenes, block, params, gaps, yaw, beyond, press
) -> None:
    """Pushed past the inside corner with any knobs: a finite pose, a rotation, nowhere under
    the floor, each step within its cost bound; it never turns back, and once still it rests
    touching the frame and the table, or the frame alone in balance. (A tall block may tip
    onto the bar and rest leaning on it: from near its balance on the bar's edge it leaves
    first-order slowly, for as many steps as it started near that balance, so that no number
    of steps bounds coming to rest.)"""
    sim, results = _push_into_corner(scenes[block], block, params, gaps, yaw, beyond, press, 300)
    if sim is None:
        return
    _assert_never_rocks(sim, results)
    if all(_moved_m(sim, r.X_WO, results[-1].X_WO) < _still_m(sim) for r in results[-5:-1]):
        _assert_rests_against_both_walls(sim, results, balanced_on_the_frame=True)


def _far_corner(**eps_m: float) -> SimParams:
    """The far corner of four knobs where blocks tipped onto the bar fail to settle: Δt = 1 s
    (the top of its range), unit gains, a coarse golden tolerance (0.1) and a 1 cm
    characteristic length (the contact cases' shortest); ``eps_m`` sets ε_b, ε_c and ε_o."""
    return SimParams(
        dt_s=1.0,
        d_t=1.0,
        k_t=1.0,
        max_speed_mps=1.0,
        char_length_m=0.01,
        golden_rel_tol=0.1,
        tunnel_fraction=1.0,
        **eps_m,
    )


def test_a_tall_block_leaning_on_the_bar_comes_to_rest_at_the_extremes(scenes) -> None:
    """Δt = 1 s and ε_b = 1 mm (the tops of their ranges), a coarse golden tolerance (0.1) and
    a 1 cm characteristic length (the contact cases' shortest): the tall block pushed past the
    corner tips onto the bar and comes to rest leaning on it. (With §V-B's U_v linear in s,
    a whole step turned it past where the spring's energy is least, and it rocked between 46°
    and 55° for ever.)"""
    params = _far_corner(eps_barrier_m=1e-3, eps_contact_m=1e-2, eps_capture_m=0.0316)
    block = "tall_block"
    sim, results = _push_into_corner(
        scenes[block], block, params, (0.0, 0.0), 0.0, 0.0195, 0.0039, 200
    )
    tilt = _tilt_rad(results, _resting(scenes[block], block, 0.0, np.zeros(2), 0.0)[0])
    assert tilt[-1] > math.radians(30.0)  # it did tip onto the bar
    _assert_rests_against_both_walls(sim, results)


def test_an_l_block_leaning_on_the_bar_comes_to_rest_at_a_coarse_search(scenes) -> None:
    """Δt = 1 s, a 1 cm characteristic length and a coarse golden tolerance (0.1), ε_b = 10 µm
    and ε_c = 50 µm: the L-block pushed past the corner tips onto the bar; it should then come
    to rest against it and the table within 300 steps, not swing about that rest (with §V-B's
    U_v linear in s it swung 3.3 µm a step at step 300, the swing dying away by 2.5 % a step)."""
    params = _far_corner(eps_barrier_m=1e-5, eps_contact_m=5e-5, eps_capture_m=0.01)
    block = "l_block"
    sim, results = _push_into_corner(
        scenes[block], block, params, (0.0, 0.0), 0.0, 0.017578125, 0.00390625, 300
    )
    _assert_rests_against_both_walls(sim, results)


@pytest.mark.parametrize("block", BLOCKS)
@pytest.mark.parametrize("x", [0.25, 2.5, 250.0])
def test_a_block_pushed_into_the_inside_corner_comes_to_rest_against_both_walls(
    scenes, block, x
) -> None:
    """Each block, at step gains where an explicit step rests, swings and swings for ever:
    it comes to rest (to the line search's resolution) touching the frame and the table, at
    least ε_b/2 and less than ε_c from each."""
    base = SimParams()
    params = dataclasses.replace(base, d_t=x / (base.dt_s * base.k_t))
    sim, results = _push_into_corner(
        scenes[block], block, params, (2e-3, 1e-3), 0.05, 0.01, 3e-3, 200
    )
    _assert_rests_against_both_walls(sim, results)


@CAPTURE_PROPERTY
@given(
    block=st.sampled_from(BLOCKS),
    params=sim_params(min_step_gain=0.2, min_step_m=1e-2, char_length_m=CONTACT_CHAR_LENGTH_M),
    press=st.floats(1e-3, 4e-3),
)
def test_a_block_captured_round_the_outside_corner_stays_within_the_capture(
    scenes, block, params, press
) -> None:
    """Frame and table captured, the block is dragged along the −y bar's outer face, round the
    frame's outer corner and along the −x bar's: at every step within ε_o of both, and never
    nearer than ε_b/2. (Whether it gets round depends on the drag as well as the knobs: a
    capture can stick at the corner, §VII-B; the defaults' own test checks it goes round.)"""
    scene = scenes[block]
    eps_b, eps_c, eps_o = params.eps_barrier_m, params.eps_contact_m, params.eps_capture_m
    gap = (eps_b + eps_c) / 2
    _, size = _resting(scene, block, 0.0, np.zeros(2), 0.0)
    start_xy = np.array([0.45 - size[0] / 2, OUTER_CORNER_XY[1] - gap - size[1]])
    X0, _ = _resting(scene, block, 0.0, start_xy, gap)
    sim = _simulator(scene, block, params, X0)
    if sim is None:
        return
    sim.capture("frame")
    sim.capture("table")
    assert {"frame", "table"} <= sim.state.held
    # Footprint's low corner at each waypoint: along the −y bar (pressed into it) until the
    # block's middle is at the corner, round it, then up the −x bar (pressed into it).
    x_face = OUTER_CORNER_XY[0] - size[0]
    y_face = OUTER_CORNER_XY[1] - size[1]
    waypoints = [
        (OUTER_CORNER_XY[0] - size[0] / 2, y_face + press),
        (x_face + 0.01, y_face + 0.01),
        (x_face + press, OUTER_CORNER_XY[1] + 0.01),
        (x_face + press, OUTER_CORNER_XY[1] + 0.06),
    ]
    step_m = min(1e-2, 0.5 * params.max_speed_mps * params.dt_s)
    xy = start_xy.copy()
    targets = []
    for w in waypoints:
        n = max(1, math.ceil(np.linalg.norm(np.subtract(w, xy)) / step_m))
        targets += [xy + (np.subtract(w, xy)) * k / n for k in range(1, n + 1)]
        xy = np.array(w, dtype=float)
    targets += [xy] * 15
    for t in targets:
        X_D, _ = _resting(scene, block, 0.0, t, -press)
        sim.set_target(X_D)
        r = sim.step()
        _check_step(sim, r)
        d = {c.object: c.distance_m for c in r.contacts}
        assert d.keys() >= {"frame", "table"} and max(d.values()) <= eps_o, d


def test_knobs_outside_their_ranges_are_refused_naming_the_range() -> None:
    for name, (lo, hi, _) in RANGES.items():
        for bad in (lo / 10, hi * 10, math.nan):
            with pytest.raises(ValueError, match=rf"SimParams\.{name} must be a number in \["):
                SimParams(**{name: bad})
    with pytest.raises(ValueError, match=r"step gain dt_s·d_t·k_t must be in \[1e-06, 1e\+06\]"):
        SimParams(d_t=1e-6, k_t=1e-2)
    with pytest.raises(ValueError, match=r"max_points_per_pair must be an integer in \[3, 128\]"):
        SimParams(max_points_per_pair=2)
