import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from guidedmatch.bruteforce import block_rows, knn2, match_bruteforce


def naive(d1, d2, ratio=0.8, mutual=False, max_distance=None):
    """Reference: full distance matrix (float64 / explicit bit counts), first index wins ties."""
    if d1.dtype == np.uint8:
        x = np.unpackbits(d1[:, None, :] ^ d2[None, :, :], axis=2).sum(axis=2).astype(np.float64)
    else:
        x = np.sqrt(((d1[:, None, :].astype(np.float64) - d2[None, :, :]) ** 2).sum(axis=2))
    pairs, dists = [], []
    for i in range(len(d1)):
        if len(d2) == 0:
            continue
        order = np.argsort(x[i], kind="stable")
        j1 = order[0]
        dd1 = x[i, j1]
        dd2 = x[i, order[1]] if len(d2) > 1 else np.inf
        if ratio is not None and not dd1 < ratio * dd2:
            continue
        if max_distance is not None and dd1 > max_distance:
            continue
        if mutual and np.argmin(x[:, j1]) != i:
            continue
        pairs.append((i, j1))
        dists.append(dd1)
    return np.array(pairs, np.int64).reshape(-1, 2), np.array(dists)


def _float_desc(rng, n, d, lo=0, hi=6):
    # integer-valued floats (like SIFT): blocked GEMM is exact, so results must match bit for bit
    return rng.integers(lo, hi, (n, d)).astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(n1=st.integers(0, 40), n2=st.integers(0, 40), d=st.sampled_from([1, 4, 16]),
       ratio=st.sampled_from([None, 0.8, 0.95]), mutual=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_float_matches_naive_reference(n1, n2, d, ratio, mutual, seed):
    rng = np.random.default_rng(seed)
    d1, d2 = _float_desc(rng, n1, d), _float_desc(rng, n2, d)  # small ranges force many ties
    res = match_bruteforce(d1, d2, ratio=ratio, mutual=mutual)
    ref_p, ref_d = naive(d1, d2, ratio, mutual)
    np.testing.assert_array_equal(res.pairs, ref_p)
    np.testing.assert_allclose(res.distances, ref_d, rtol=1e-6)
    assert res.stats.comparisons == n1 * n2


@settings(max_examples=40, deadline=None)
@given(n1=st.integers(0, 30), n2=st.integers(0, 30), nbytes=st.sampled_from([1, 8, 32, 61]),
       ratio=st.sampled_from([None, 0.8]), mutual=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_binary_matches_naive_reference(n1, n2, nbytes, ratio, mutual, seed):
    rng = np.random.default_rng(seed)
    d1 = rng.integers(0, 256, (n1, nbytes), dtype=np.uint8)
    d2 = rng.integers(0, 256, (n2, nbytes), dtype=np.uint8)
    if n1 and n2:
        d2[: min(n1, n2) // 2] = d1[: min(n1, n2) // 2]  # some exact duplicates
    res = match_bruteforce(d1, d2, ratio=ratio, mutual=mutual)
    ref_p, ref_d = naive(d1, d2, ratio, mutual)
    np.testing.assert_array_equal(res.pairs, ref_p)
    np.testing.assert_array_equal(res.distances, ref_d)
    assert res.stats.metric == "hamming"


def test_arbitrary_floats_agree_within_rounding(rng):
    d1 = rng.normal(size=(200, 64)).astype(np.float32)
    d2 = np.vstack([d1[:100] + 0.05 * rng.normal(size=(100, 64)), rng.normal(size=(150, 64))]).astype(np.float32)
    res = match_bruteforce(d1, d2, ratio=0.8)
    ref_p, ref_d = naive(d1, d2, 0.8)
    np.testing.assert_array_equal(res.pairs, ref_p)
    np.testing.assert_allclose(res.distances, ref_d, rtol=1e-4, atol=1e-4)


def test_max_distance(rng):
    d1, d2 = _float_desc(rng, 50, 8, 0, 20), _float_desc(rng, 60, 8, 0, 20)
    res = match_bruteforce(d1, d2, ratio=None, max_distance=12.0)
    ref_p, _ = naive(d1, d2, None, False, 12.0)
    np.testing.assert_array_equal(res.pairs, ref_p)
    assert np.all(res.distances <= 12.0)


def test_blocking_gives_identical_results(rng):
    d1, d2 = _float_desc(rng, 700, 32, 0, 50), _float_desc(rng, 900, 32, 0, 50)
    (a, b) = knn2(d1, d2, memory_budget_mb=256, want_column_best=True)
    (c, e) = knn2(d1, d2, memory_budget_mb=0.01, want_column_best=True)  # a few rows per block
    assert block_rows(900, 0.01) < 10
    for x, y in zip(a + b, c + e):
        np.testing.assert_array_equal(x, y)


def test_block_size_bounds_memory_at_150k():
    rows = block_rows(150_000, 256)
    assert rows * 150_000 * 4 <= 256 * 2**20
    assert rows > 100


def test_empty_inputs_return_empty_result():
    for n1, n2 in ((0, 5), (5, 0), (0, 0)):
        res = match_bruteforce(np.zeros((n1, 128), np.float32), np.zeros((n2, 128), np.float32))
        assert res.pairs.shape == (0, 2) and res.distances.shape == (0,)
        assert res.stats.comparisons == 0


def test_single_candidate_passes_ratio():
    res = match_bruteforce(np.ones((3, 4), np.float32), np.zeros((1, 4), np.float32))
    assert len(res) == 3


@pytest.mark.parametrize("d1,d2,msg", [
    (np.zeros((3, 128), np.float32), np.zeros((3, 64), np.float32), "lengths differ"),
    (np.zeros((3, 32), np.uint8), np.zeros((3, 32), np.float32), "types differ"),
    (np.full((3, 8), np.nan, np.float32), np.zeros((3, 8), np.float32), "NaN"),
    (np.zeros(8, np.float32), np.zeros((3, 8), np.float32), "2-D"),
])
def test_bad_descriptors_raise_clear_errors(d1, d2, msg):
    with pytest.raises(ValueError, match=msg):
        match_bruteforce(d1, d2)


def test_accepts_features_objects(small_scene_features):
    f1, f2 = small_scene_features
    a = match_bruteforce(f1, f2)
    b = match_bruteforce(f1.descriptors, f2.descriptors)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    assert a.stats.comparisons == len(f1) * len(f2)
