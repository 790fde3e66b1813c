"""Grouping and indexing: invariant index vectors, the model index and its on-disk cache."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.scene import load_scene
from work_site.vision.index import (
    GroupParams,
    IndexParams,
    group_segments,
    index_key,
    load_or_build_index,
)
from work_site.vision.model import vision_model

# A "Y" junction with a tail: the projection of a box corner and one more edge.
SEGS = np.array(
    [
        [100.0, 100.0, 160.0, 80.0],
        [100.0, 100.0, 60.0, 70.0],
        [100.0, 100.0, 102.0, 160.0],
        [102.0, 160.0, 150.0, 150.0],
        [160.0, 80.0, 165.0, 140.0],
    ]
)


def _similar(segs: np.ndarray, scale: float, angle: float, shift: np.ndarray) -> np.ndarray:
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    pts = segs.reshape(-1, 2) @ R.T * scale + shift
    return pts.reshape(-1, 4)


def _by_chain(groups) -> dict[tuple[int, ...], np.ndarray]:
    return {tuple(g): v for g, v in zip(groups.segs.tolist(), groups.vectors, strict=True)}


def test_groups_are_chains_of_four_connected_segments() -> None:
    g = group_segments(SEGS)
    assert len(g.segs) > 0
    for chain, J in zip(g.segs, g.junctions, strict=True):
        assert len(set(chain.tolist())) == 4
        # Consecutive segments meet at the stored junction (within the tolerance).
        for k in range(3):
            for s in chain[k : k + 2]:
                ends = SEGS[s].reshape(2, 2)
                assert np.min(np.linalg.norm(ends - J[k], axis=1)) < 4.0


@settings(max_examples=60, deadline=None)
@given(
    scale=st.floats(0.4, 3.0),
    angle=st.floats(-np.pi, np.pi),
    dx=st.floats(-200, 200),
    dy=st.floats(-200, 200),
)
def test_index_vectors_are_invariant_to_2d_similarity(scale, angle, dx, dy) -> None:
    params = GroupParams(junction_tol_px=0.5, junction_tol_frac=0.0)
    base = _by_chain(group_segments(SEGS, params))
    moved = _by_chain(group_segments(_similar(SEGS, scale, angle, np.array([dx, dy])), params))
    assert base.keys() == moved.keys()
    for chain, v in base.items():
        np.testing.assert_allclose(moved[chain], v, atol=1e-9)


def test_index_vectors_change_with_the_shape() -> None:
    other = SEGS.copy()
    other[3] = [102.0, 160.0, 150.0, 190.0]  # the tail turns the other way
    a, b = _by_chain(group_segments(SEGS)), _by_chain(group_segments(other))
    common = a.keys() & b.keys()
    assert any(np.linalg.norm(a[c] - b[c]) > 0.1 for c in common)


@pytest.fixture(scope="module")
def small_models():
    scene = load_scene()
    return [vision_model(scene.object(n).model) for n in ("cube", "wedge")], [
        scene.object(n).model.urdf_path for n in ("cube", "wedge")
    ]


def test_index_finds_each_models_own_views(small_models, tmp_path) -> None:
    models, files = small_models
    index = load_or_build_index(models, files, IndexParams(n_views=60), cache_dir=tmp_path)
    assert set(np.unique(index.model)) == {0, 1}
    _ids, d2 = index.query(index.vectors[:50].astype(np.float64))
    assert np.all(d2[:, 0] < 1e-6)  # an indexed vector is its own nearest neighbour


def test_index_is_cached_and_keyed_by_file_contents(small_models, tmp_path) -> None:
    models, files = small_models
    params = IndexParams(n_views=40)
    first = load_or_build_index(models, files, params, cache_dir=tmp_path)
    cached = sorted(tmp_path.glob("index-*.npz"))
    assert len(cached) == 1
    again = load_or_build_index(models, files, params, cache_dir=tmp_path)
    np.testing.assert_array_equal(first.vectors, again.vectors)
    # Another model file content gives another key.
    copy = tmp_path / "cube.urdf"
    copy.write_text(files[0].read_text() + "\n<!-- changed -->\n")
    key_a = index_key(models, files, params, GroupParams())
    key_b = index_key(models, [copy, files[1]], params, GroupParams())
    assert key_a != key_b
    # A corrupt cache file is rebuilt, not trusted.
    cached[0].write_bytes(b"not an npz")
    rebuilt = load_or_build_index(models, files, params, cache_dir=tmp_path)
    np.testing.assert_array_equal(first.vectors, rebuilt.vectors)


def test_index_query_is_exact_within_max_distance(small_models, tmp_path) -> None:
    models, files = small_models
    index = load_or_build_index(models, files, IndexParams(n_views=60), cache_dir=tmp_path)
    rng = np.random.default_rng(0)
    V = index.vectors.astype(np.float64)
    # Near an indexed vector (its neighbours within reach) and far from all of them
    queries = np.vstack([V[rng.integers(len(V), size=20)] + rng.normal(0, 0.02, (20, V.shape[1])),
                         V[:3] + 10.0])  # fmt: skip
    ids, d2 = index.query(queries)
    brute = np.sum((queries[:, None, :] - V[None]) ** 2, axis=2)
    k = index.params.neighbours
    nearest = np.sort(brute, axis=1)[:, :k]
    reach = index.params.max_distance**2
    np.testing.assert_allclose(d2[nearest < reach], nearest[nearest < reach], rtol=1e-9)
    assert np.all(np.isinf(d2[nearest >= reach]))
    assert np.all(ids[np.isinf(d2)] == 0)
    found = np.isfinite(d2)
    np.testing.assert_allclose(brute[np.nonzero(found)[0], ids[found]], d2[found], rtol=1e-9)
    assert np.isinf(d2[-3:]).all()
