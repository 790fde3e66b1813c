"""Line extraction: sub-pixel straight edges from grey images, and sane output on bad ones."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from work_site.vision.lines import (
    FAINT_LINE_PARAMS,
    KINK_MIN_SAMPLES,
    KINK_SIGNIFICANCE,
    LineParams,
    _split_at_corners,
    check_grey_image,
    detect_lines,
)

SCALE = 8


def _polygon_image(corners_px: np.ndarray, shape=(240, 320), fg=200, bg=60) -> np.ndarray:
    """A filled polygon drawn 8× larger and averaged down: exact area coverage at its edges."""
    h, w = shape
    big = np.full((h * SCALE, w * SCALE), bg, np.uint8)
    pts = np.round(((corners_px + 0.5) * SCALE - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(big, [pts], fg, lineType=cv2.LINE_8, shift=4)
    return cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)


def _edge_errors(segs: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Perpendicular distances (px) of detected end points from the nearest true edge line."""
    errs = []
    for s in segs:
        best = None
        for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
            u = (b - a) / np.linalg.norm(b - a)
            n = np.array([-u[1], u[0]])
            v = s[2:] - s[:2]
            if abs(u @ v) / np.linalg.norm(v) < np.cos(np.deg2rad(3)):
                continue
            d = np.abs([(s[:2] - a) @ n, (s[2:] - a) @ n])
            if best is None or d.max() < best.max():
                best = d
        assert best is not None, f"segment {s} lies on no edge"
        errs.extend(best)
    return np.array(errs)


def test_edges_of_a_polygon_are_found_to_a_tenth_of_a_pixel() -> None:
    rng = np.random.default_rng(0)
    corners = np.array([[60.3, 50.7], [250.2, 70.1], [230.8, 190.4], [80.6, 170.9]])
    image = _polygon_image(corners)
    noisy = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
    segs = detect_lines(noisy)
    assert len(segs) == 4  # one per side: fragments merged, nothing spurious
    errs = _edge_errors(segs, corners)
    assert np.median(errs) < 0.1
    assert errs.max() < 0.3
    lengths = np.linalg.norm(segs[:, 2:] - segs[:, :2], axis=1)
    perimeter = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1).sum()
    assert lengths.sum() > 0.9 * perimeter  # LSD stops short of corners by a pixel or two


def test_refinement_is_more_accurate_than_lsd_alone() -> None:
    rng = np.random.default_rng(1)
    errs = {True: [], False: []}
    for _ in range(5):
        c = np.array([[60, 50], [250, 70], [230, 190], [80, 170]]) + rng.uniform(-8, 8, (4, 2))
        image = _polygon_image(c)
        image = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
        for refine in (True, False):
            errs[refine].extend(_edge_errors(detect_lines(image, LineParams(refine=refine)), c))
    assert np.mean(errs[True]) < np.mean(errs[False])


@pytest.mark.parametrize(
    "image",
    [np.zeros((1, 1), np.uint8), np.zeros((480, 640), np.uint8), np.full((50, 50), 255, np.uint8)],
    ids=["1x1", "black", "white"],
)
def test_featureless_images_give_no_lines(image: np.ndarray) -> None:
    assert detect_lines(image).shape == (0, 4)


def test_bad_arrays_are_refused() -> None:
    with pytest.raises(ValueError, match="8-bit"):
        check_grey_image(np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match="2-D"):
        check_grey_image(np.zeros((2, 3, 5, 7), np.uint8))


def _merge_reference(segs: np.ndarray, params) -> np.ndarray:
    """The greedy merge one segment at a time, as first written (longest first)."""
    order = np.argsort(-np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]))
    segs = segs[order].copy()
    alive = np.ones(len(segs), dtype=bool)
    changed = True
    while changed:
        changed = False
        for i in range(len(segs)):
            if not alive[i]:
                continue
            a, b = segs[i, :2], segs[i, 2:]
            L = np.linalg.norm(b - a)
            u = (b - a) / L
            n = np.array([-u[1], u[0]])
            others = np.flatnonzero(alive)
            others = others[others != i]
            S = segs[others]
            du = S[:, 2:] - S[:, :2]
            cosang = np.abs(du @ u) / np.maximum(np.linalg.norm(du, axis=1), 1e-9)
            off = np.maximum(np.abs((S[:, :2] - a) @ n), np.abs((S[:, 2:] - a) @ n))
            t0, t1 = (S[:, :2] - a) @ u, (S[:, 2:] - a) @ u
            gap = np.maximum(np.minimum(t0, t1) - L, -np.maximum(t0, t1))
            ok = (
                (cosang > np.cos(params.merge_angle_rad))
                & (off < params.merge_offset_px)
                & (gap < params.merge_gap_px)
            )
            for j in others[ok]:
                t = [0.0, L, *((segs[j, :2] - a) @ u, (segs[j, 2:] - a) @ u)]
                segs[i] = np.concatenate([a + min(t) * u, a + max(t) * u])
                alive[j] = False
                changed = True
                a, b = segs[i, :2], segs[i, 2:]
                L = np.linalg.norm(b - a)
    return segs[alive]


def test_merge_collinear_equals_the_greedy_merge_one_by_one() -> None:
    """Pairs tested all at once give exactly the greedy one-at-a-time result, on lines split
    into fragments (with chains that only join after an earlier merge) among clutter."""
    from work_site.vision.lines import LineParams, merge_collinear

    params = LineParams()
    rng = np.random.default_rng(12)
    for _ in range(20):
        rows = []
        for _ in range(6):  # lines broken into 2–5 fragments with small gaps, jittered
            p = rng.uniform(50, 550, 2)
            ang = rng.uniform(0, np.pi)
            u = np.array([np.cos(ang), np.sin(ang)])
            t = 0.0
            for _ in range(rng.integers(2, 6)):
                length = rng.uniform(8, 40)
                off = rng.normal(0, 0.15, 2)
                rows.append([*(p + t * u + off[0]), *(p + (t + length) * u + off[1])])
                t += length + rng.uniform(0.5, 6.0)
        rows.extend(rng.uniform(0, 600, (30, 4)))  # clutter
        segs = np.array(rows)
        merged = merge_collinear(segs, params)
        expected = _merge_reference(segs, params)
        assert merged.shape == expected.shape
        np.testing.assert_allclose(merged, expected, atol=1e-9)
    assert len(merged) < len(segs)  # merges happened


def test_the_faint_pass_finds_a_low_contrast_edge_the_first_misses_and_no_lines_in_noise():
    """A 15-grey-level edge, blurred and in σ = 3 noise (a block's face-to-face edge in flat
    light): the first pass covers little of it, the faint pass (smoothed, finer quantisation)
    most; in noise alone the faint pass finds no line as long as a block's edge."""
    rng = np.random.default_rng(0)
    covered = np.zeros(2)
    for _ in range(10):
        img = np.full((120, 160), 100.0)
        img[:, 80:] += 15.0
        img = cv2.GaussianBlur(img, (0, 0), 1.2) + rng.normal(0.0, 3.0, img.shape)
        img = np.clip(img, 0, 255).astype(np.uint8)
        for j, params in enumerate((LineParams(), FAINT_LINE_PARAMS)):
            segs = detect_lines(img, params)
            on_edge = (np.abs(segs[:, 0] - 79.5) < 2) & (np.abs(segs[:, 2] - 79.5) < 2)
            covered[j] += np.sum(np.abs(segs[on_edge, 3] - segs[on_edge, 1])) / 120 / 10
    assert covered[0] < 0.2 and covered[1] > 0.5, covered
    noise = np.clip(100.0 + rng.normal(0.0, 3.0, (120, 160)), 0, 255).astype(np.uint8)
    segs = detect_lines(noise, FAINT_LINE_PARAMS)
    lengths = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    assert np.all(lengths < 20.0), lengths


def _bent_polygon(bend_deg: float, arm_px: float, rng: np.random.Generator) -> np.ndarray:
    """A pentagon one of whose sides bends by ``bend_deg`` halfway (two edges ``arm_px``
    long): the outline of a block whose side face is seen nearly edge on."""
    b = np.array([250.3, 60.2]) + rng.uniform(-3, 3, 2)
    u = np.array([0.08 + rng.uniform(-0.05, 0.05), 1.0])
    u /= np.linalg.norm(u)
    t = np.deg2rad(bend_deg)
    turn = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    c = b + arm_px * u
    return np.array([[60.4, 50.6], b, c, c + arm_px * (turn @ u), [70.7, 190.2]])


def test_a_line_grown_across_a_shallow_corner_is_split_at_the_corner() -> None:
    """LSD may grow one region across a corner of a few degrees, and one line fitted to both
    edges misplaces each by a pixel or more. Split where two lines fit, the pieces lie on their
    edges: never a worse line, and most of those corners mended (the others' bend is lost in
    the sub-pixel fit's own ripple)."""
    merged = mended = 0
    for bend in (2.5, 3.0, 3.5):
        for seed in range(4):
            rng = np.random.default_rng(seed)
            corners = _bent_polygon(bend, 40.0, rng)
            image = _polygon_image(corners)
            image = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
            whole = _edge_errors(detect_lines(image, LineParams(kink_px=0.0)), corners).max()
            split = _edge_errors(detect_lines(image), corners).max()
            assert split <= whole + 1e-9, (bend, seed, whole, split)
            if whole > 1.0:  # LSD took the two edges for one
                merged += 1
                mended += split < 0.5
    assert merged >= 6 and mended >= merged // 2, (merged, mended)


def test_straight_edges_in_noise_are_not_split() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        corners = np.array([[60, 50], [250, 70], [230, 190], [80, 170]]) + rng.uniform(
            -8, 8, (4, 2)
        )
        image = _polygon_image(corners)
        noisy = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        assert len(detect_lines(noisy)) == len(detect_lines(noisy, LineParams(kink_px=0.0)))


def _split_one_by_one(points: np.ndarray, seg: np.ndarray):
    """The corner split of one segment written plainly (every split point tried, each line
    fitted by SVD): the reference for the batched :func:`_split_at_corners`."""
    n, least = len(points), KINK_MIN_SAMPLES

    def fit(p: np.ndarray):
        c = p.mean(axis=0)
        d = np.linalg.svd(p - c)[2][0]
        r = (p - c) @ np.array([-d[1], d[0]])
        return c, d, r, (p - c) @ d

    if n < 2 * least:
        return None
    k = min(range(least, n - least + 1), key=lambda k: sum(
        float(np.sum(fit(part)[2] ** 2)) for part in (points[:k], points[k:])
    ))  # fmt: skip
    (c1, d1, r1, a1), (c2, d2, r2, a2) = fit(points[:k]), fit(points[k:])
    if max(np.abs(r1).max(), np.abs(r2).max()) > 0.5 * np.abs(fit(points)[2]).max():
        return None
    se = np.hypot(*(np.sqrt(np.mean(r**2) / np.sum(a**2)) for r, a in ((r1, a1), (r2, a2))))
    if np.arccos(min(abs(float(d1 @ d2)), 1.0)) < KINK_SIGNIFICANCE * se:
        return None

    def foot(c, d, p):
        return c + ((p - c) @ d) * d

    corner = 0.5 * (points[k - 1] + points[k])
    return (
        np.concatenate([foot(c1, d1, seg[:2]), foot(c1, d1, corner)]),
        np.concatenate([foot(c2, d2, corner), foot(c2, d2, seg[2:])]),
    )


def test_the_batched_corner_split_matches_the_split_done_one_segment_at_a_time() -> None:
    rng = np.random.default_rng(3)
    runs, segs = [], []
    for i in range(60):
        n = int(rng.integers(5, 60))  # some too short for two pieces
        t = np.sort(rng.uniform(0, 40, n))
        corner = rng.uniform(5, 35)
        bend = rng.choice([0.0, rng.uniform(0.01, 0.2)])  # straight or bent (rad)
        d1 = np.array([np.cos(i), np.sin(i)])
        d2 = np.array([np.cos(i + bend), np.sin(i + bend)])
        p = np.where(
            (t < corner)[:, None], t[:, None] * d1, corner * d1 + (t - corner)[:, None] * d2
        )
        p += rng.normal(0, 0.05, p.shape) + rng.uniform(-300, 300, 2)
        runs.append(p)
        segs.append(np.concatenate([p[0], p[-1]]))
    points = np.vstack(runs)
    owner = np.repeat(np.arange(len(runs)), [len(r) for r in runs])
    first, second, split = _split_at_corners(points, owner, np.array(segs))
    expected = {i: _split_one_by_one(r, s) for i, (r, s) in enumerate(zip(runs, segs, strict=True))}
    assert list(split) == [i for i, e in expected.items() if e is not None]
    assert 5 <= len(split) < len(runs)  # both outcomes were tried
    for a, b, i in zip(first, second, split, strict=True):
        np.testing.assert_allclose(a, expected[i][0], atol=1e-9)
        np.testing.assert_allclose(b, expected[i][1], atol=1e-9)
