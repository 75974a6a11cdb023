import sys

import numpy as np
import pytest

from guidedmatch.evaluation import peers as P
from guidedmatch.features import Features


def _naive_2nn_ratio(d1, d2, ratio=0.8):
    """Obviously-correct reference: full distance matrix, sort, Lowe ratio (d2 = inf with one candidate)."""
    if d1.dtype == np.uint8:
        x = np.unpackbits(d1[:, None, :] ^ d2[None, :, :], axis=2).sum(axis=2).astype(np.float64)
    else:
        x = np.sqrt(((d1[:, None, :].astype(np.float64) - d2[None, :, :]) ** 2).sum(axis=2))
    order = np.argsort(x, axis=1, kind="stable")
    i = np.arange(len(d1))
    best = x[i, order[:, 0]]
    second = x[i, order[:, 1]] if d2.shape[0] > 1 else np.full(len(d1), np.inf)
    keep = best < ratio * second
    return {(int(a), int(order[a, 0])) for a in i[keep]}, dict(zip(i[keep].tolist(), best[keep].tolist()))


def _float(rng, n, dim=32):
    return rng.normal(size=(n, dim)).astype(np.float32)


def _binary(rng, n, nbytes=32):
    return rng.integers(0, 256, (n, nbytes), dtype=np.uint8)


def _close_pairs(rng, make, n1=150, n2=200):
    """Half of image-1 descriptors are noisy copies of image-2 ones, so the ratio test keeps some."""
    d2 = make(rng, n2)
    d1 = make(rng, n1)
    src = rng.choice(n2, n1 // 2, replace=False)
    if d1.dtype == np.uint8:
        flip = rng.integers(0, 256, (n1 // 2, d1.shape[1]), dtype=np.uint8) & rng.integers(0, 256, (n1 // 2, d1.shape[1]), dtype=np.uint8) & 0x11
        d1[: n1 // 2] = d2[src] ^ flip
    else:
        d1[: n1 // 2] = d2[src] + 0.2 * rng.normal(size=(n1 // 2, d1.shape[1])).astype(np.float32)
    return d1, d2


@pytest.mark.parametrize("make", [_float, _binary], ids=["float", "binary"])
@pytest.mark.parametrize("fn", [P.match_opencv_bf, P.match_faiss], ids=["opencv_bf", "faiss"])
def test_exact_peers_equal_naive_2nn(fn, make, rng):
    if fn is P.match_faiss and not P.faiss_available():
        pytest.skip("faiss not installed (bench extra)")
    d1, d2 = _close_pairs(rng, make)
    ref, ref_d = _naive_2nn_ratio(d1, d2)
    r = fn(d1, d2)
    got = {tuple(map(int, p)) for p in r.pairs}
    assert got == ref and len(ref) > 30
    np.testing.assert_allclose(r.distances, [ref_d[i] for i in r.pairs[:, 0]], rtol=1e-4, atol=1e-3)
    assert r.stats.comparisons == len(d1) * len(d2)
    assert r.stats.time_s >= 0 and r.stats.method in ("opencv_bf", "faiss_flat")
    assert r.pairs.dtype == np.int64 and r.distances.dtype == np.float32


@pytest.mark.parametrize("make", [_float, _binary], ids=["float", "binary"])
def test_flann_approximately_equals_naive_2nn(make, rng):
    d1, d2 = _close_pairs(rng, make)
    ref, _ = _naive_2nn_ratio(d1, d2)
    r = P.match_opencv_flann(d1, d2)
    got = {tuple(map(int, p)) for p in r.pairs}
    assert len(got & ref) >= 0.8 * len(ref)
    assert r.stats.comparisons is None and "unknown" in r.stats.details["comparisons_note"]
    assert r.stats.details["index"] == ("lsh" if make is _binary else "kdtree")


def test_peers_accept_features_and_edge_cases(rng):
    d1, d2 = _close_pairs(rng, _float, 40, 60)
    f1 = Features.from_arrays(rng.uniform(0, 100, (40, 2)), d1, (100, 100))
    f2 = Features.from_arrays(rng.uniform(0, 100, (60, 2)), d2, (100, 100))
    a = P.match_opencv_bf(f1, f2)
    b = P.match_opencv_bf(d1, d2)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    # a single image-2 descriptor: no second neighbour, d2 = inf, the match is kept
    fns = (P.match_opencv_bf, P.match_opencv_flann) + ((P.match_faiss,) if P.faiss_available() else ())
    for fn in fns:
        r = fn(d1[:3], d2[:1])
        assert len(r) == 3 and (r.pairs[:, 1] == 0).all()
        e = fn(d1[:0], d2)
        assert len(e) == 0 and e.pairs.shape == (0, 2)
    with pytest.raises(ValueError):
        P.match_opencv_bf(d1, _binary(rng, 5))


def test_faiss_missing_gives_clear_import_error(monkeypatch, rng):
    monkeypatch.setitem(sys.modules, "faiss", None)  # makes `import faiss` raise ImportError
    assert not P.faiss_available()
    assert "faiss_flat" not in P.available_peers()
    with pytest.raises(ImportError, match=r"bench"):
        P.match_faiss(_float(rng, 5), _float(rng, 5))


def test_gms_filters_1nn_matches_on_a_real_scene(small_scene, small_scene_features):
    from guidedmatch.datasets import EpipolarGT

    f1, f2 = small_scene_features
    s = small_scene
    gt = EpipolarGT.from_pose(s.K1, s.K2, s.R, s.t)
    r = P.match_gms(f1, f2, with_rotation=True, with_scale=False)
    assert r.stats.comparisons == len(f1) * len(f2) and r.stats.details["with_rotation"] is True
    assert 0 < len(r) <= r.stats.details["num_nn_matches"] == len(f1)
    ok = gt.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    nn = P.match_opencv_bf(f1, f2, ratio=None)
    ok_nn = gt.correct(f1.keypoints[nn.pairs[:, 0]], f2.keypoints[nn.pairs[:, 1]])
    assert ok.mean() > ok_nn.mean() and ok.mean() > 0.8  # GMS keeps mostly correct 1-NN matches
    # GMS output is a subset of the 1-NN matches
    assert {tuple(p) for p in r.pairs.tolist()} <= {tuple(p) for p in nn.pairs.tolist()}
    with pytest.raises(TypeError):
        P.match_gms(f1.descriptors, f2.descriptors)
