"""Results do not depend on the CPU, the BLAS, the thread counts or the backend (guidedmatch.exact).

The same pairs -- byte-valued SIFT, non-integer float (RootSIFT-like), binary ORB (uint8 packed bits) from rendered
scenes, synthetic multi-view float features with an unrelated view, and an adversarial set of near-tied float
descriptors -- are matched with 1 and 2 BLAS threads (threadpoolctl), 1 and 2 Numba threads, directly, through
``match_collection`` in-process with 1 and 3 pair threads and on a one-worker Dask cluster; every run must return the
same pairs and bit-identical distances and verdicts. The exact recompute itself is checked against a slow, obviously
correct reference (a Python float64 loop per pair, in the documented order), and the certificate's fallback is exercised by near-ties.

This machine has one CPU type; what makes the results CPU-independent is argued in guidedmatch/exact.py: every
reported distance is a float64 sum in index order without fast-math (no reduction whose order depends on the vector
width or the thread count), and every candidate set is certified against the fast search's error bound.
"""
from __future__ import annotations

import sys

import numba
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from threadpoolctl import threadpool_limits

import guidedmatch as gm
from guidedmatch import exact, kernels
from guidedmatch.bruteforce import DenseKnn2, knn2
from guidedmatch.collection.config import collection_matcher_config
from guidedmatch.collection.engine import match_collection
from guidedmatch.features import Features
from guidedmatch.matcher import MatcherConfig, match
from guidedmatch.prepared import prepare
from guidedmatch.testing.scenes import make_scene
from guidedmatch.testing.arc_views import arc_views

SIZE = (800, 600)


# ------------------------------------------------------------------------------------------------ references
def ref_sq(a: np.ndarray, b: np.ndarray) -> float:
    """Squared L2 in Python floats (IEEE double) in guidedmatch.exact's documented order: dimension k into running
    sum k % 4, in index order, then (s0 + s1) + (s2 + s3)."""
    s = [0.0, 0.0, 0.0, 0.0]
    for k, (x, y) in enumerate(zip(a.tolist(), b.tolist())):
        d = float(x) - float(y)
        s[k % 4] += d * d
    return (s[0] + s[1]) + (s[2] + s[3])


def ref_top2(q: np.ndarray, t: np.ndarray):
    """Exact top 2 of each row of ``q`` among ``t`` by (reference distance, index)."""
    out = []
    for row in q:
        d = [ref_sq(row, tr) for tr in t]
        o = sorted(range(len(t)), key=lambda j: (d[j], j))[:2]
        o += [-1] * (2 - len(o))
        out.append([(j, d[j] if j >= 0 else np.inf) for j in o])
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 40), st.integers(1, 33), st.integers(0, 2**31 - 1), st.sampled_from([1e-3, 1.0, 300.0]))
def test_sqdist_rows_is_the_documented_float64_sum(nq, dim, seed, scale):
    rng = np.random.default_rng(seed)
    q = (rng.standard_normal((nq, dim)) * scale).astype(np.float32)
    t = (rng.standard_normal((7, dim)) * scale).astype(np.float32)
    cand = rng.integers(-1, 7, (nq, 3))
    got = exact.sqdist_rows(q, t, cand)
    for i in range(nq):
        for c in range(3):
            j = cand[i, c]
            assert got[i, c] == (ref_sq(q[i], t[j]) if j >= 0 else np.inf)  # bit for bit
            if j >= 0:  # and the true value to float64 rounding
                assert got[i, c] == pytest.approx(float(np.sum((q[i].astype(np.float64) - t[j]) ** 2)), rel=1e-13)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(1, 12), st.just(6)), elements=st.floats(-4, 4, width=32)),
       arrays(np.float32, st.tuples(st.integers(1, 30), st.just(6)), elements=st.floats(-4, 4, width=32)))
def test_knn2_equals_the_reference_top2(q, t):
    (i1, s1, i2, s2), _ = knn2(q, t)
    for r, ((e1, d1), (e2, d2)) in enumerate(ref_top2(q, t)):
        assert (i1[r], i2[r]) == (e1, e2)
        assert s1[r] == np.float32(np.sqrt(d1)) and s2[r] == np.float32(np.sqrt(d2))


def near_ties(n_q: int = 20, n_t: int = 400, dim: int = 64, seed: int = 0):
    """Adversarial float descriptors: each query has 12 targets whose squared distances differ by less than the
    float32 GEMM's rounding error (exact order and approximate order disagree), among far ones."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(10, 20, (n_q, dim)).astype(np.float32)
    t = rng.uniform(10, 20, (n_t, dim)).astype(np.float32)
    for i in range(n_q):
        base = q[i] + np.float32(0.5)
        for k in range(12):
            v = base.copy()
            v[k % dim] = np.nextafter(v[k % dim], np.float32(np.inf)) if k % 2 else v[k % dim]
            v[(3 * k + 1) % dim] = np.nextafter(v[(3 * k + 1) % dim], np.float32(-np.inf))
            t[(i * 12 + k) * 7 % n_t] = v
    return q, t


def test_near_ties_are_exact_and_use_the_certified_fallback():
    q, t = near_ties()
    before = exact.FALLBACKS[0]
    (i1, s1, i2, s2), _ = knn2(q, t)
    assert exact.FALLBACKS[0] > before  # the certificate failed on the near-ties: whole rows recomputed
    ref = ref_top2(q, t)
    np.testing.assert_array_equal(i1, [r[0][0] for r in ref])
    np.testing.assert_array_equal(i2, [r[1][0] for r in ref])
    np.testing.assert_array_equal(s1, exact.l2([r[0][1] for r in ref]))
    # the dense search of the unguided start, chunked by 1 or 2 threads: the same, bit for bit
    for threads in (1, 2):
        with DenseKnn2(np.tile(t, (6, 1)), threads=threads) as dense:  # 2400 rows: 2 chunks with 2 threads
            d1, ds1, d2, ds2 = dense.query(q)
        (k1, ks1, k2, ks2), _ = knn2(q, np.tile(t, (6, 1)))
        np.testing.assert_array_equal(d1, k1)
        np.testing.assert_array_equal(d2, k2)
        np.testing.assert_array_equal(exact.l2(ds1), ks1)
        np.testing.assert_array_equal(exact.l2(ds2), ks2)


def test_guided_kernel_candidates_refined_equal_the_region_reference():
    """The float guided kernel's best three (vectorized sums) + the exact recompute = the exact top 2 of the region,
    near-ties included (here the region is all of image 2: no band, unbounded x-range)."""
    q, t = near_ties(n_q=15, n_t=300, seed=3)
    pts = np.random.default_rng(1).uniform(0, 100, (len(t), 2))
    cols, rows = kernels.build_strips(pts, 16.0, 0), kernels.build_strips(pts, 16.0, 1)
    nq = len(q)
    desc1 = np.concatenate([q, t])  # queries are rows 0..nq-1 of image 1
    i1, s1, i2, s2, nc, i3, s3 = kernels.guided_top2(np.arange(nq), desc1, t, np.zeros((nq, 3)), False, 1.0,
                                                     np.full(nq, -np.inf), np.full(nq, np.inf), cols, rows,
                                                     return_third=True)
    assert np.all(nc == len(t))
    top, sq = exact.exact_top(q, t, np.stack([i1, i2, i3], 1), np.stack([s1, s2, s3], 1), 2,
                              gamma=exact.sum_gamma(q.shape[1]), domain=lambda i: np.arange(len(t)))
    for r, ((e1, d1), (e2, d2)) in enumerate(ref_top2(q, t)):
        assert (top[r, 0], top[r, 1]) == (e1, e2) and (sq[r, 0], sq[r, 1]) == (d1, d2)


def test_ivf_search_is_exact_over_the_probed_cells():
    rng = np.random.default_rng(5)
    d = rng.standard_normal((3000, 32)).astype(np.float32)
    p = prepare(Features(rng.uniform(0, 100, (3000, 2)), d, (100, 100)))
    q = d[:40] + rng.normal(0, 0.3, (40, 32)).astype(np.float32)
    i1, s1, i2, s2, _ = p.search2(q)
    cent, cn = p._centroids()
    nprobe = min(int(p.index().nprobe), p.nlist)
    for r in range(len(q)):
        cells = sorted(range(p.nlist), key=lambda c: (ref_sq(q[r], cent[c]), c))[:nprobe]
        members = p._list_members(np.array(cells))
        (e1, d1), (e2, d2) = ref_top2(q[r:r + 1], d[members])[0]
        assert (i1[r], i2[r]) == (members[e1], members[e2]) and (s1[r], s2[r]) == (d1, d2)


# ------------------------------------------------------------------------------------------------ pairs
def make_views() -> dict:
    """Cameras on an arc looking at a point cloud (non-integer float descriptors: integers plus noise), plus an
    unrelated view."""
    return arc_views(3, 2600, 0, shuffle=False, unrelated=2200, fractional_unrelated=True)


def rootsift(f: Features) -> Features:
    d = np.sqrt(f.descriptors / np.maximum(f.descriptors.sum(1, keepdims=True), 1e-9)).astype(np.float32)
    return Features(f.keypoints, d, f.image_size, responses=f.responses, angles=f.angles, scales=f.scales)


@pytest.fixture(scope="module")
def pair_sets():
    scene = make_scene(SIZE, roll_deg=20.0, seed=2)
    sift = (gm.detect(scene.image1, "sift", 2500), gm.detect(scene.image2, "sift", 2500))
    orb = (gm.detect(scene.image1, "orb", 2500), gm.detect(scene.image2, "orb", 2500))
    views = make_views()
    q, t = near_ties(n_q=300, n_t=2400, dim=128, seed=7)
    rng = np.random.default_rng(9)
    adversarial = (Features(rng.uniform(0, 800, (len(q), 2)), q, SIZE), Features(rng.uniform(0, 800, (len(t), 2)), t,
                                                                                  SIZE))
    assert sift[0].descriptors.dtype == np.float32 and orb[0].descriptors.dtype == np.uint8
    return {"sift": sift, "rootsift": (rootsift(sift[0]), rootsift(sift[1])), "orb": orb,
            "views01": (views["view0.jpg"], views["view1.jpg"]), "views-other": (views["view2.jpg"], views["other.jpg"]),
            "adversarial": adversarial}, views


MODES = ("bf", "so+epi+ia", "epi")
CONFIG = MatcherConfig(auto_bf=False)  # guided at these sizes too (ORB would be brute force otherwise)


def signature(res) -> tuple:
    return (res.pairs.tobytes(), res.distances.tobytes(), res.geometry.verdict, res.geometry.num_inliers,
            res.stats.comparisons)


def run_all(sets) -> dict:
    return {(name, mode): signature(match(a, b, mode, CONFIG)) for name, (a, b) in sets.items() for mode in MODES}


def test_same_results_whatever_the_blas_and_numba_threads(pair_sets):
    sets, _ = pair_sets
    runs = {}
    old = numba.get_num_threads()
    try:
        for blas in (1, 2):
            for nb in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
                numba.set_num_threads(nb)
                with threadpool_limits(limits=blas, user_api="blas"):
                    runs[(blas, nb)] = run_all(sets)
    finally:
        numba.set_num_threads(old)
    first = next(iter(runs.values()))
    assert any(len(np.frombuffer(v[0], np.int64)) for v in first.values())  # not vacuous: there are matches
    for key, got in runs.items():
        bad = [k for k in first if got[k] != first[k]]
        assert not bad, (key, bad)


class _PerturbedIndex:
    """A faiss index whose fine distances come out perturbed (another CPU's SIMD sum) within the relative bound."""

    def __init__(self, index, rng):
        self._index, self._rng = index, rng

    def __getattr__(self, name):
        return getattr(self._index, name)

    def search_preassigned(self, q, k, Iq, Dq):
        D, I = self._index.search_preassigned(q, k, Iq, Dq)
        if np.array_equal(D[np.isfinite(D)], np.round(D[np.isfinite(D)])) and np.array_equal(q, np.round(q)):
            return D, I  # integer distances of byte-valued descriptors: exact on every CPU
        r = self._rng.uniform(-1.0, 1.0, D.shape) * (q.shape[1] / 4.0) * exact.U32
        return (D * (1.0 + r)).astype(np.float32), I


def simulate_another_cpu(monkeypatch, seed: int) -> None:
    """Every fast distance perturbed within its error bound, as a CPU with another vector width, another BLAS or
    another thread split may compute it: the GEMM products (kernels.topk_gemm_serial, behind knn2, DenseKnn2 and the
    IVF coarse step) by up to 32 float32 ulps relative (the bound allows D/2 for D >= 64), the guided kernel's float
    sums and faiss's fine distances by up to D/4 ulps relative (re-sorted: the order among near-ties may change).
    Integer distances (byte-valued descriptors below 2^24, Hamming) are exact on every CPU and stay as they are."""
    rng = np.random.default_rng(seed)
    topk, guided, index = kernels.topk_gemm_serial, kernels.guided_top2, gm.PreparedImage.index

    def topk_perturbed(dot, nn2, qn, k):
        if all(np.array_equal(x, np.round(x)) for x in (dot, nn2, qn)) and (qn.max(initial=0) + nn2.max(initial=0)
                                                                          < exact.EXACT_INT):
            return topk(dot, nn2, qn, k)  # integers below 2^24 (byte-valued descriptors): exact on every CPU
        r = rng.uniform(-1.0, 1.0, dot.shape) * 32.0 * exact.U32
        return topk(np.ascontiguousarray((dot * (1.0 + r)).astype(np.float32)), nn2, qn, k)

    def guided_perturbed(queries, desc1, desc2, *args, return_third=False, **kw):
        out = list(guided(queries, desc1, desc2, *args, return_third=True, **kw))
        if desc1.dtype.kind == "f":  # integer distances (uint8 L2, Hamming) are exact on every CPU
            i = np.stack([out[0], out[2], out[-2]], 1)
            d = np.stack([out[1], out[3], out[-1]], 1).astype(np.float64)
            d = d * (1.0 + rng.uniform(-1.0, 1.0, d.shape) * (desc1.shape[1] / 4.0) * exact.U32)
            o = np.lexsort((np.where(i >= 0, i, 1 << 40), d), axis=1)
            r = np.arange(len(d))[:, None]
            i, d = i[r, o], d[r, o].astype(np.float32)
            out[0], out[1], out[2], out[3], out[-2], out[-1] = i[:, 0], d[:, 0], i[:, 1], d[:, 1], i[:, 2], d[:, 2]
        return tuple(out) if return_third else tuple(out[:-2])

    def index_perturbed(self):
        ix = index(self)
        return None if ix is None else _PerturbedIndex(ix, rng)

    monkeypatch.setattr(kernels, "topk_gemm_serial", topk_perturbed)
    monkeypatch.setattr(kernels, "guided_top2", guided_perturbed)
    monkeypatch.setattr(gm.PreparedImage, "index", index_perturbed)


def test_same_results_on_a_simulated_other_cpu(pair_sets, monkeypatch):
    """Fast distances that differ in the last bits (another CPU, BLAS or thread split) change no result."""
    sets, _ = pair_sets
    want = run_all(sets)
    for seed in (1, 2):
        with monkeypatch.context() as m:
            simulate_another_cpu(m, seed)
            got = run_all(sets)
        bad = [k for k in want if got[k] != want[k]]
        assert not bad, (seed, bad)


def test_shared_quantizer_same_results_on_a_simulated_other_cpu(pair_sets, monkeypatch):
    """A collection's shared quantizer (image 1's cells looked up, computed once per image and certified the same
    way as the per-pair coarse step) changes nothing either."""
    from guidedmatch.collection.quantizer import train_quantizer

    _, views = pair_sets
    names = sorted(views)
    q = train_quantizer(np.concatenate([views[n].descriptors for n in names]), 60)

    def run():
        prepared = {n: prepare(views[n], quantizer=q) for n in names}
        return {(a, b): signature(match(prepared[a], prepared[b], "so+epi+ia", collection_matcher_config()))
                for a in names for b in names if a < b}

    want = run()
    assert sum(v[2] == "verified" for v in want.values()) == 3
    for seed in (1, 2):
        with monkeypatch.context() as m:
            simulate_another_cpu(m, seed)
            got = run()
        assert got == want, seed


# ------------------------------------------------------------------------------------------------ backends
class DictSource:
    """FeatureSource double: features in a dict (picklable, shipped to Dask workers by value)."""

    kind = "dict"

    def __init__(self, feats: dict):
        self.feats = feats
        self.path = None

    def names(self):
        return list(self.feats)

    def image_size(self, name):
        return self.feats[name].image_size

    def num_features(self, name):
        return len(self.feats[name])

    def load(self, name):
        return self.feats[name]

    def close(self):
        pass


class ListSink:
    def __init__(self):
        self.rows = {}

    def done_pairs(self):
        return set(self.rows)

    def write(self, name1, name2, pairs, scores, geometry):
        self.rows[frozenset((name1, name2))] = (pairs.tobytes(), scores.tobytes(), geometry.verdict,
                                                geometry.num_inliers)

    def close(self):
        pass


def direct(views, pairs):
    out = {}
    for a, b in pairs:
        r = match(views[a], views[b], "so+epi+ia", collection_matcher_config())  # the collection's settings
        out[frozenset((a, b))] = (r.pairs.tobytes(), r.distances.tobytes(), r.geometry.verdict, r.geometry.num_inliers)
    return out


def test_same_results_direct_and_in_process_threads(pair_sets):
    _, views = pair_sets
    names = list(views)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    want = direct(views, pairs)
    assert sum(v[2] == "verified" for v in want.values()) == 3  # the overlapping views; "other" never
    for threads in (1, 3):
        sink = ListSink()
        rep = match_collection(DictSource(views), pairs, sink, dict(progress=False, workers=0, threads=threads))
        assert rep.done == len(pairs) and not rep.failed
        assert sink.rows == want, threads


def test_same_results_on_a_dask_worker(pair_sets):
    pytest.importorskip("distributed")
    import cloudpickle
    from distributed import Client, LocalCluster

    from guidedmatch.collection.dask_backend import _SINGLE_THREAD_ENV

    _, views = pair_sets
    names = list(views)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    want = direct(views, pairs)
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                          env=dict(_SINGLE_THREAD_ENV), silence_logs=40) as cluster, \
                Client(cluster, set_as_default=False) as client:
            sink = ListSink()
            rep = match_collection(DictSource(views), pairs, sink, dict(progress=False), client=client)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert rep.done == len(pairs) and not rep.failed and rep.totals["backend"] == "client"
    assert sink.rows == want
