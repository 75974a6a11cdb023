"""Fuzz tests of ``match``: random and degenerate feature sets never raise, and results are consistent.

Degenerate layouts: all points collinear, all identical, two tight clusters, tiny images, huge coordinates; the
descriptors of image 2 are a noisy permutation of image 1's (so the ratio test passes and models get fitted on the
degenerate geometry) or unrelated. Every mode, float (L2) and binary (Hamming) descriptors.
"""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from guidedmatch.features import Features
from guidedmatch.matcher import MODES, MatcherConfig, match

LAYOUTS = ("random", "collinear", "identical", "two_clusters", "tiny", "huge")


def _points(layout, n, rng):
    if layout == "random":
        return rng.uniform(0, 640, (n, 2)), (640, 480)
    if layout == "collinear":
        t = rng.uniform(0, 600, n)
        return np.c_[t, 0.5 * t + 10], (640, 480)
    if layout == "identical":
        return np.tile([[123.0, 45.0]], (n, 1)), (640, 480)
    if layout == "two_clusters":
        c = rng.integers(0, 2, n)[:, None]
        return np.where(c, [[50.0, 60.0]], [[500.0, 400.0]]) + rng.normal(0, 0.5, (n, 2)), (640, 480)
    if layout == "tiny":
        return rng.uniform(0, 3, (n, 2)), (3, 2)
    return rng.uniform(-1e9, 1e9, (n, 2)), (100000, 100000)  # huge coordinates


@st.composite
def feature_pairs(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    n1 = draw(st.integers(0, 260))
    n2 = draw(st.integers(0, 260))
    lay1, lay2 = draw(st.sampled_from(LAYOUTS)), draw(st.sampled_from(LAYOUTS))
    binary = draw(st.booleans())
    related = draw(st.booleans()) and n1 > 0
    k1, s1 = _points(lay1, n1, rng)
    k2, s2 = _points(lay2, n2, rng)
    if binary:
        d1 = rng.integers(0, 256, (n1, 32), dtype=np.uint8)
        d2 = rng.integers(0, 256, (n2, 32), dtype=np.uint8)
        if related:
            src = rng.integers(0, n1, n2)
            flip = rng.random((n2, 32)) < 0.02
            d2 = d1[src] ^ (flip * rng.integers(1, 256, (n2, 32))).astype(np.uint8)
        kind = "orb"
    else:
        byte = draw(st.booleans())  # byte-valued (SIFT-like) or L2-normalised floats
        d1 = rng.integers(0, 256, (n1, 64)).astype(np.float32) if byte else rng.normal(size=(n1, 64)).astype(np.float32)
        d2 = rng.integers(0, 256, (n2, 64)).astype(np.float32) if byte else rng.normal(size=(n2, 64)).astype(np.float32)
        if related:
            d2 = d1[rng.integers(0, n1, n2)] + rng.normal(0, 2.0 if byte else 0.01, (n2, 64)).astype(np.float32)
            if byte:
                d2 = np.clip(np.round(d2), 0, 255).astype(np.float32)
        if not byte:
            d1 /= np.linalg.norm(d1, axis=1, keepdims=True) + 1e-12
            d2 /= np.linalg.norm(d2, axis=1, keepdims=True) + 1e-12
        kind = "user"
    resp1 = rng.random(n1).astype(np.float32) if draw(st.booleans()) else None
    f1 = Features(k1, d1, s1, kind, responses=resp1)
    f2 = Features(k2, d2, s2, kind)
    mode = draw(st.sampled_from(MODES))
    cfg = MatcherConfig(update_every=draw(st.integers(8, 60)), num_updates=draw(st.integers(0, 3)),
                        batch_size=draw(st.sampled_from([8, 64])), min_model_matches=draw(st.sampled_from([8, 16])),
                        outside_window=draw(st.sampled_from(["drop", "band", "band_all"])))
    return f1, f2, mode, cfg, (lay1, lay2, binary, related)


def _true_distances(f1, f2, pairs):
    a, b = f1.descriptors[pairs[:, 0]], f2.descriptors[pairs[:, 1]]
    if f1.binary:
        return np.unpackbits(a ^ b, axis=1).sum(axis=1).astype(np.float64)
    return np.sqrt(((a.astype(np.float64) - b) ** 2).sum(axis=1))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(feature_pairs())
def test_match_never_raises_and_results_are_consistent(case):
    f1, f2, mode, cfg, _info = case
    res = match(f1, f2, mode=mode, config=cfg)
    n1, n2 = len(f1), len(f2)
    p, d = res.pairs, res.distances
    assert p.dtype == np.int64 and p.ndim == 2 and p.shape[1] == 2 and d.dtype == np.float32 and d.shape == (len(p),)
    assert np.all((p[:, 0] >= 0) & (p[:, 0] < n1) & (p[:, 1] >= 0) & (p[:, 1] < n2))
    assert len(np.unique(p[:, 0])) == len(p)  # each image-1 feature matched at most once
    if mode != "bf" and cfg.one_to_one is not False:
        assert len(np.unique(p[:, 1])) == len(p)
    assert np.all(np.isfinite(d)) and np.all(d >= 0)
    np.testing.assert_allclose(d, _true_distances(f1, f2, p), rtol=1e-3, atol=1e-3)
    s = res.stats
    assert tuple(s.num_features) == (n1, n2) and s.time_s >= 0
    assert 0 <= s.comparisons <= n1 * n2 and int(s.comparisons) == s.comparisons
    if mode == "bf":
        assert s.comparisons == n1 * n2
    else:
        assert s.comparisons == sum(s.phase_comparisons)
        assert sum(s.phase_queries) == s.queries_matched_against + s.dropped_outside_overlap <= n1
        assert s.num_model_updates <= cfg.num_updates
    for k, v in res.flags.items():
        assert len(v) == len(p), k
    if cfg.ratio is not None and len(p):
        assert np.all(d <= np.finfo(np.float32).max)
