"""Tests of guidedmatch.prepared (per-image state reused across pairs)."""
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch import kernels
from guidedmatch.errors import ConfigError, InputError
from guidedmatch.features import Features
from guidedmatch.prepared import PreparedConfig, PreparedImage, as_prepared, prepare


def _sift_like(n, seed=0, size=(640, 480)):
    rng = np.random.default_rng(seed)
    # clustered byte-valued descriptors (as SIFT: integers 0..255), so IVF cells are uneven
    centres = rng.integers(0, 200, (20, 32))
    d = np.clip(centres[rng.integers(0, 20, n)] + rng.integers(-30, 30, (n, 32)), 0, 255).astype(np.float32)
    return Features(rng.uniform(0, size[0] - 1, (n, 2)) * [1, size[1] / size[0]], d, size, "sift")


def _exact_top2(q, d):
    s = ((q[:, None, :].astype(np.float64) - d[None].astype(np.float64)) ** 2).sum(-1)
    o = np.lexsort((np.broadcast_to(np.arange(len(d)), s.shape), s), axis=1)[:, :2]
    r = np.arange(len(q))[:, None]
    return o[:, 0], s[r[:, 0], o[:, 0]], o[:, 1], s[r[:, 0], o[:, 1]]


def test_kernel_forms():
    f = _sift_like(1500)
    p = prepare(f)
    assert p.byte_exact and p.kdesc.dtype == np.uint8 and np.array_equal(p.kdesc, f.descriptors.astype(np.uint8))
    np.testing.assert_allclose(p.sqnorms, (f.descriptors.astype(np.float64) ** 2).sum(1), rtol=1e-6)
    g = Features(f.keypoints, f.descriptors + 0.5, f.image_size, "sift")  # not byte-valued: float32 kept
    pg = prepare(g)
    assert not pg.byte_exact and pg.kdesc.dtype == np.float32
    rng = np.random.default_rng(1)
    b = Features(f.keypoints, rng.integers(0, 256, (1500, 32), dtype=np.uint8), f.image_size, "orb")
    pb = prepare(b)
    assert pb.binary and not pb.has_index and pb.index() is None and pb.sqnorms is None
    assert np.array_equal(pb.kdesc, kernels.pack_bits_u64(b.descriptors))
    with pytest.raises(InputError):
        pb.search2(f.descriptors[:2])
    assert as_prepared(p) is p and isinstance(as_prepared(f), PreparedImage)
    with pytest.raises(InputError):
        prepare(np.zeros((3, 2)))


def test_search2_is_exact_when_every_cell_is_probed():
    f = _sift_like(1200, seed=2)
    q = _sift_like(100, seed=3).descriptors
    p = prepare(f, PreparedConfig(nprobe=10_000))
    assert p.nlist == round(2 * np.sqrt(1200))
    i1, s1, i2, s2, comp = p.search2(q)
    e1, es1, e2, es2 = _exact_top2(q, f.descriptors)
    np.testing.assert_array_equal(s1, es1.astype(np.float32))
    np.testing.assert_array_equal(s2, es2.astype(np.float32))
    assert np.all(i1 == e1) or np.all(s1 == es1)  # ties may pick another index at the same distance
    assert comp == len(q) * (p.nlist + len(f))


def test_search2_approximate_distances_exact_and_counted():
    f = _sift_like(3000, seed=4)
    q = _sift_like(200, seed=5).descriptors
    p = prepare(f)  # nprobe 4 of 110 cells
    i1, s1, i2, s2, comp = p.search2(q)
    ok = i1 >= 0
    ref = ((q[ok] - f.descriptors[i1[ok]]).astype(np.float64) ** 2).sum(1)
    np.testing.assert_array_equal(s1[ok], ref.astype(np.float32))  # distances of what it found are exact
    e1, es1, _, _ = _exact_top2(q, f.descriptors)
    assert np.all(s1 >= es1.astype(np.float32))  # never better than the true nearest neighbour
    assert np.mean(s1 == es1.astype(np.float32)) > 0.5
    # comparisons = centroids + the probed cells' sizes, and far below brute force
    assert len(q) * p.nlist < comp < 0.25 * len(q) * len(f)
    assert p.index_build_s > 0


def test_search2_probes_the_cells_faiss_quantizer_would():
    """search2's coarse step (GEMM + kernels.topk_gemm) picks the cells faiss's own flat quantizer picks, so the
    search is the same IVF search; only near-ties of two centroid distances (float32 rounding of two different
    GEMMs) may order differently."""
    f = _sift_like(4000, seed=8)
    q = _sift_like(3000, seed=9).descriptors
    p = prepare(f)
    index = p.index()
    Dq, Iq = index.quantizer.search(np.ascontiguousarray(q, np.float32), index.nprobe)
    cent, cn = p._centroids()
    mine_i, mine_d = kernels.topk_gemm(q, cent, cn, index.nprobe)
    np.testing.assert_allclose(mine_d, Dq, rtol=1e-5, atol=1e-2)
    differ = (mine_i != Iq).any(1)
    gaps = np.diff(np.sort(Dq, 1), axis=1).min(1) if index.nprobe > 1 else np.full(len(q), np.inf)
    assert np.all(gaps[differ] <= 1e-3 * Dq[differ].max(1))  # only near-ties differ
    assert differ.mean() < 0.01
    # and search2 returns what faiss's search over those cells returns
    D, I = index.search(np.ascontiguousarray(q, np.float32), 2)
    i1, s1, i2, s2, _ = p.search2(q)
    same = ~differ
    assert np.array_equal(i1[same], I[same, 0]) and np.array_equal(s1[same], D[same, 0])
    # the centroids survive pickling (rebuilt with the index)
    p2 = pickle.loads(pickle.dumps(p))
    assert p2._coarse is None and np.array_equal(p2.search2(q[:50])[0], i1[:50])


def test_index_deterministic_and_rebuilt_after_pickle():
    f = _sift_like(2500, seed=6)
    q = _sift_like(50, seed=7).descriptors
    p = prepare(f)
    a = p.search2(q)
    p2 = pickle.loads(pickle.dumps(p))
    assert p2._index is None  # the index is not pickled ...
    b = p2.search2(q)  # ... and rebuilt identically
    for x, y in zip(a[:4], b[:4]):
        np.testing.assert_array_equal(x, y)
    assert a[4] == b[4]
    assert p.index() is p.index()  # built once


def test_small_image_has_no_index():
    p = prepare(_sift_like(500))
    assert not p.has_index and p.index() is None


@pytest.mark.parametrize("kw", [dict(index="hnsw"), dict(nprobe=0), dict(nlist_factor=0.0), dict(seed=-1),
                                dict(nprobe=1.5)])
def test_config_validation(kw):
    with pytest.raises(ConfigError):
        PreparedConfig(**kw)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_prepared_non_finite_descriptors_are_still_refused(bad):
    """match() skips its NaN/inf scan only for prepared images whose squared norms are finite."""
    import guidedmatch as gm
    from guidedmatch.errors import InputError
    from guidedmatch.features import Features

    rng = np.random.default_rng(0)
    d = rng.integers(0, 255, (300, 32)).astype(np.float32)
    good = prepare(Features(rng.uniform(0, 100, (300, 2)), d, (100, 100)))
    assert good.finite
    f2 = Features(rng.uniform(0, 100, (300, 2)), d.copy(), (100, 100))  # Features refuses NaN/inf when built;
    f2.descriptors[7, 3] = bad                                         # an array changed in place afterwards
    p = prepare(f2)
    assert not p.finite
    with pytest.raises(InputError, match="NaN/inf"):
        gm.match(good, p)
    with pytest.raises(InputError, match="NaN/inf"):
        gm.match(p, good)


@settings(max_examples=60)
@given(seed=st.integers(0, 2**31 - 1), rows=st.integers(1, 12), nlist=st.integers(2, 40), nprobe=st.integers(1, 6),
       dupes=st.booleans(), slack=st.sampled_from([0.0, 1e-3, 10.0, 1e9]))
def test_exact_cells_equal_the_per_row_exact_top(seed, rows, nlist, nprobe, dupes, slack):
    """search2's near-tie step, one pass for all rows, against exact_top_among row by row (the slow reference),
    with repeated centroids (exact ties: the lower index first) and bounds from none to every centroid."""
    from guidedmatch.exact import exact_top_among
    from guidedmatch.prepared import _exact_cells

    rng = np.random.default_rng(seed)
    nprobe = min(nprobe, nlist)
    cent = rng.integers(0, 4, (nlist, 8)).astype(np.float32)  # few values: many equal distances
    if dupes:
        cent[nlist // 2:] = cent[:nlist - nlist // 2]
    q = rng.integers(0, 4, (rows, 8)).astype(np.float32)
    approx = ((q[:, None, :] - cent[None]) ** 2).sum(-1) + rng.uniform(-0.5, 0.5, (rows, nlist))
    delta = np.full(rows, slack)
    idx, sq = _exact_cells(q, cent, approx, delta, nprobe)
    for r in range(rows):
        near = np.flatnonzero(approx[r] <= np.sort(approx[r])[nprobe - 1] + 2.0 * delta[r])
        want_i, want_d = exact_top_among(q[r], cent, near, nprobe)
        assert idx[r].tolist() == want_i.tolist() and sq[r].tolist() == want_d.tolist()
