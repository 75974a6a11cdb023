"""Tests of guidedmatch.spatial_order against O(N^2) references and synthetic permutations (Talker §6.1)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.spatial_order import (
    SpatialOrderConfig,
    SpatialOrderModel,
    admissible_x_ranges,
    bad_inversion_range,
    estimate_n_good,
    fit_spatial_order,
    gap_inversion_table,
    gap_probability_table,
    inversions_per_match,
    kendall_distance,
    match_probabilities,
    match_ranks,
    normalized_kendall_distance,
    permutation_from_coordinates,
    probability_correct,
    search_overlap,
)
from guidedmatch.testing.permutations import generate_permutation

SETTINGS = settings(max_examples=150, deadline=None)


# ---------------------------------------------------------------- O(N^2) references


def ref_kendall(a) -> int:
    a = list(a)
    return sum(1 for i in range(len(a)) for j in range(i + 1, len(a)) if a[i] > a[j])


def ref_inversions(a):
    n = len(a)
    hl = [sum(1 for j in range(i) if a[j] > a[i]) for i in range(n)]
    hr = [sum(1 for j in range(i + 1, n) if a[j] < a[i]) for i in range(n)]
    return np.array(hl, dtype=np.int64), np.array(hr, dtype=np.int64)


def ref_ranks(x, y=None):
    keys = [(x[m], 0.0 if y is None else y[m], m) for m in range(len(x))]
    order = sorted(range(len(x)), key=lambda m: keys[m])
    r = np.empty(len(x), dtype=np.int64)
    r[order] = np.arange(len(x))
    return r


# ---------------------------------------------------------------- ranks and Kendall distance


@SETTINGS
@given(st.lists(st.integers(-5, 5), min_size=0, max_size=60))
def test_kendall_distance_matches_reference_with_ties(a):
    assert kendall_distance(np.array(a, dtype=np.int64)) == ref_kendall(a)


@pytest.mark.parametrize("a", [[], [3], [1, 2], [2, 1], [1, 1]])
def test_kendall_distance_tiny(a):
    assert kendall_distance(np.array(a)) == ref_kendall(a)


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.integers(0, 3), st.integers(0, 3)),
                min_size=0, max_size=40),
       st.booleans())
def test_normalized_kendall_ties_broken_by_y_then_index(rows, use_y):
    arr = np.array(rows, dtype=np.float64).reshape(-1, 4)
    x1, x2, y1, y2 = arr.T
    yy1, yy2 = (y1, y2) if use_y else (None, None)
    r1, r2 = ref_ranks(x1, yy1), ref_ranks(x2, yy2)
    np.testing.assert_array_equal(match_ranks(x1, yy1), r1)
    sigma = np.empty(len(r1), dtype=np.int64)
    sigma[r1] = r2
    np.testing.assert_array_equal(permutation_from_coordinates(x1, x2, yy1, yy2)[0], sigma)
    k_hat = normalized_kendall_distance(x1, x2, yy1, yy2)
    n = len(x1)
    if n < 2:
        assert math.isnan(k_hat)
    else:
        assert k_hat == pytest.approx(2.0 * ref_kendall(sigma) / (n * (n - 1)))


@SETTINGS
@given(st.lists(st.integers(-4, 4), min_size=0, max_size=50))
def test_inversions_per_match_matches_reference(a):
    hl, hr = inversions_per_match(np.array(a, dtype=np.int64))
    rl, rr = ref_inversions(a)
    np.testing.assert_array_equal(hl, rl)
    np.testing.assert_array_equal(hr, rr)


def test_inversions_identity_for_permutations():
    sigma = np.random.default_rng(3).permutation(500)
    hl, hr = inversions_per_match(sigma)
    np.testing.assert_array_equal(hr - hl, sigma - np.arange(500))  # H^r - H^l = sigma(i) - i
    assert hl.sum() == kendall_distance(sigma) == hr.sum()


# ---------------------------------------------------------------- N_G (Talker Eq. 8)


def test_estimate_n_good_root_and_limits():
    for n in (2, 10, 600):
        assert estimate_n_good(0.0, n) == n
        assert estimate_n_good(0.5, n) == 0.0
        assert estimate_n_good(0.7, n) == 0.0
        ks = np.linspace(0.0, 0.5, 51)
        ng = estimate_n_good(ks, n)
        assert np.all(np.diff(ng) <= 1e-9) and np.all((ng >= 0) & (ng <= n))
        res = ng**2 / 6.0 - (0.5 - n / 3.0) * ng - n * (n - 1) * (0.5 - ks)
        np.testing.assert_allclose(res[1:-1], 0.0, atol=1e-6 * n * n)
    assert math.isnan(estimate_n_good(float("nan"), 5))


# ---------------------------------------------------------------- gap table (Teng & Dong §III-C)


def brute_gap_inversions(sigma):
    """H_k = sum_j eta(i_h, j) with i_h = h - 0.5, sigma(i_h) = k - 0.5 (0-based ranks), by definition (Eq. 1)."""
    n = len(sigma)
    out = np.zeros((n + 1, n + 1), dtype=np.int64)
    for h in range(n + 1):
        for k in range(n + 1):
            ih, jk = h - 0.5, k - 0.5
            out[h, k] = sum(1 for j in range(n) if (j < ih and sigma[j] > jk) or (j > ih and sigma[j] < jk))
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 12).flatmap(lambda n: st.permutations(list(range(n)))))
def test_gap_inversion_table_matches_brute_force(perm):
    sigma = np.array(perm, dtype=np.int64)
    hl, hr = gap_inversion_table(sigma)
    np.testing.assert_array_equal(hl + hr, brute_gap_inversions(sigma))
    n = len(sigma)
    c = np.array([[sum(1 for m in range(h) if sigma[m] < k) for k in range(n + 1)] for h in range(n + 1)])
    np.testing.assert_array_equal(hl, np.arange(n + 1)[:, None] - c)
    np.testing.assert_array_equal(hr, np.arange(n + 1)[None, :] - c)


@pytest.mark.parametrize("n,n_good,seed,var_floor,swaps", [(30, 20, 0, 1.0, 0), (120, 60, 1, 1.0, 0), (150, 140, 2, 1.0, 0),
                                                           (500, 150, 3, 1.0, 0), (600, 420, 4, 1.0, 40),
                                                           (300, 200, 5, 25.0, 10), (250, 150, 6, 0.1, 0)])
def test_fused_gap_kernel_equals_dense_threshold(n, n_good, seed, var_floor, swaps):
    # the fused kernel skips cells it can prove out (Lipschitz bound along a row); the dense reference evaluates all.
    # With swaps, the order noise measured on the correct matches (likely_correct) shifts and widens H | G.
    sp = generate_permutation(n, n_good, overlap=(1.0, 1.0), seed=seed, n_swaps=swaps)
    cfg = SpatialOrderConfig(overlap="none", var_floor=var_floor)
    model = fit_spatial_order(sp.x1, sp.x2, cfg, likely_correct=sp.is_good if swaps else None)
    assert model.order_noise[0] > 0 or not swaps
    assert model.usable and model.n_window == n
    p = gap_probability_table(model.sigma_window, model.n_good, cfg, model.order_noise)
    dense = p >= cfg.threshold
    mask = np.zeros_like(dense)
    for h in range(n + 1):
        for a, b in model.gap_runs[model.gap_runs_ptr[h]:model.gap_runs_ptr[h + 1]]:
            mask[h, a:b + 1] = True
    near = np.abs(p - cfg.threshold) < 1e-9 * cfg.threshold
    assert np.array_equal(mask | near, dense | near)
    np.testing.assert_array_equal(model.gap_count, dense.sum(1))
    rows = dense.any(1)
    np.testing.assert_array_equal(model.gap_lo[rows], dense[rows].argmax(1))
    np.testing.assert_array_equal(model.gap_hi[rows], n - dense[rows][:, ::-1].argmax(1))
    assert np.all(model.gap_lo[~rows] > model.gap_hi[~rows])
    np.testing.assert_array_equal(model.gap_contiguous, model.gap_count == np.maximum(model.gap_hi - model.gap_lo + 1, 0))


# ---------------------------------------------------------------- probabilities


def test_exact_and_gaussian_probabilities_agree_in_gaussian_regime():
    """Measured (N=200, N_G=120, full overlap, 3 seeds): max |dP| ~0.06, mean ~0.004 for x in [0.2, 0.8]."""
    diffs = []
    for seed in range(3):
        sp = generate_permutation(200, 120, overlap=(1.0, 1.0), seed=seed)
        sigma = sp.sigma
        n = len(sigma)
        hl, hr = inversions_per_match(sigma)
        idx = np.arange(n)
        args = (idx, sigma, hl + hr, n - 1, 120.0, n)
        pe = probability_correct(*args, method="exact")
        pg = probability_correct(*args, method="gaussian")
        x = idx / n
        valid = (x >= 0.2) & (x <= 0.8)  # N_B x (1 - x) >= 12: hypergeometrics close to Gaussian
        diffs.append(np.abs(pe - pg)[valid])
    d = np.concatenate(diffs)
    assert d.max() <= 0.10
    assert d.mean() <= 0.01


def test_bad_inversion_range_calibration():
    """P(H|B) bounds vs simulation: incorrect matches' H fall inside [H_lo, H_hi] and are roughly uniform there."""
    inside, u = [], []
    for seed in range(5):
        sp = generate_permutation(600, 300, overlap=(1.0, 1.0), seed=seed)
        good = np.zeros(600, dtype=bool)
        good[match_ranks(sp.x1)] = sp.is_good
        hl, hr = inversions_per_match(sp.sigma)
        i = np.nonzero(~good)[0]
        lo, hi = bad_inversion_range(i, 599, 300)
        h = (hl + hr)[i]
        inside.append(np.mean((h >= lo) & (h <= hi)))
        u.append((h - lo) / (hi - lo))
    assert np.mean(inside) >= 0.97
    frac = np.histogram(np.concatenate(u), bins=np.linspace(0, 1, 6))[0] / sum(len(v) for v in u)
    assert np.all((frac > 0.10) & (frac < 0.30)), frac


# ---------------------------------------------------------------- overlap search


@pytest.mark.parametrize("method", ["k1d", "k2d"])
def test_overlap_search_recovers_windows(method):
    ious = []
    for seed in range(4):
        sp = generate_permutation(300, 150, seed=seed)
        w = search_overlap(sp.sigma, 0.1, method)
        for (a, b), (c, d) in (((w[0], w[1]), sp.window1), ((w[2], w[3]), sp.window2)):
            ious.append(max(0, min(b, d) - max(a, c)) / (max(b, d) - min(a, c)))
    assert np.mean(ious) >= 0.85


def test_overlap_none_is_full():
    assert search_overlap(np.arange(10)[::-1], 0.1, "none") == (0, 10, 0, 10)


# ---------------------------------------------------------------- synthetic accuracy (Talker §6.1)


def _accuracy(n, seeds, frac=0.5, n_swaps=0):
    err, pg, pb, cov, adm = [], [], [], [], []
    for seed in seeds:
        sp = generate_permutation(n, int(frac * n), n_holdout=max(20, n // 20), n_swaps=n_swaps, seed=seed)
        m = fit_spatial_order(sp.x1, sp.x2)
        assert m.usable, m.reason
        err.append(abs(m.n_good - sp.n_good) / n)
        p = match_probabilities(sp.x1, sp.x2, m)
        pg.append(p[sp.is_good].mean())
        pb.append(p[~sp.is_good].mean())
        keep, lo, hi, _ = admissible_x_ranges(m, sp.holdout_x1)
        cov.append(np.mean(keep & (sp.holdout_x2 >= lo) & (sp.holdout_x2 <= hi)))
        h = np.searchsorted(m.x1_sorted, sp.holdout_x1, side="left")
        adm.append(np.mean(m.gap_count[h] / (m.n_window + 1)))
    return tuple(float(np.mean(v)) for v in (err, pg, pb, cov, adm))


@pytest.mark.parametrize("n,seeds", [(200, range(10)), (600, range(6)), (2000, range(3))])
def test_synthetic_accuracy(n, seeds):
    err, pg, pb, cov, adm = _accuracy(n, seeds)
    print(f"\nN={n}: |N_G err|/N={err:.3f} P(good)={pg:.3f} P(bad)={pb:.3f} coverage={cov:.3f} admitted={adm:.3f}")
    assert err <= 0.05  # Talker reports 3-10 %
    assert pg >= 0.75 and pb <= 0.10
    assert cov >= 0.95
    assert adm <= 0.25


def test_synthetic_accuracy_with_order_noise():
    err, pg, pb, cov, adm = _accuracy(600, range(3), frac=0.6, n_swaps=60)
    assert err <= 0.06 and pg >= 0.7 and pb <= 0.1 and cov >= 0.9


# ---------------------------------------------------------------- model object, lookup, bad input


def test_lookup_semantics():
    sp = generate_permutation(400, 300, n_holdout=50, seed=7)
    m = fit_spatial_order(sp.x1, sp.x2)
    assert isinstance(m, SpatialOrderModel) and m.usable and m.reason == ""
    assert np.all(np.diff(m.x1_sorted) >= 0) and np.all(np.diff(m.x2_sorted) >= 0)
    assert len(m.gap_lo) == len(m.gap_hi) == m.n_window + 1
    xq = np.concatenate([sp.holdout_x1, [m.window1_x[0] - 1.0, m.window1_x[1] + 1.0, np.nan]])
    keep, lo, hi, cont = admissible_x_ranges(m, xq)
    assert not keep[-3:].any() and np.isnan(lo[-3:]).all()
    h = np.searchsorted(m.x1_sorted, xq[:-3], side="left")
    k_lo, k_hi = m.gap_lo[h], m.gap_hi[h]
    ext = np.concatenate([[-np.inf], m.x2_sorted, [np.inf]])
    ok = keep[:-3]
    np.testing.assert_array_equal(lo[:-3][ok], ext[k_lo[ok]])
    np.testing.assert_array_equal(hi[:-3][ok], ext[k_hi[ok] + 1])
    assert np.all(lo[:-3][ok] < hi[:-3][ok])
    np.testing.assert_array_equal(cont[:-3], m.gap_contiguous[h])


def test_match_order_invariance():
    sp = generate_permutation(300, 200, seed=11)
    m = fit_spatial_order(sp.x1, sp.x2)
    perm = np.random.default_rng(0).permutation(300)
    m2 = fit_spatial_order(sp.x1[perm], sp.x2[perm])
    np.testing.assert_array_equal(m.sigma, m2.sigma)
    np.testing.assert_allclose(m.probabilities[perm], m2.probabilities)
    assert m.n_good == m2.n_good and m.omega == m2.omega


@pytest.mark.parametrize(
    "x1,x2,word",
    [
        ([], [], "fewer than 2"),
        ([1.0], [2.0], "fewer than 2"),
        ([3.0, 3.0, 3.0], [1.0, 2.0, 3.0], "all x equal"),
        ([1.0, np.nan, 3.0], [1.0, 2.0, 3.0], "non-finite"),
        ([1.0, 2.0], [1.0, 2.0, 3.0], "length"),
    ],
)
def test_bad_input_flagged_unusable(x1, x2, word):
    m = fit_spatial_order(x1, x2)
    assert not m.usable and word in m.reason
    keep, lo, hi, cont = admissible_x_ranges(m, np.array([0.0, 5.0]))
    assert keep.all() and np.all(lo == -np.inf) and np.all(hi == np.inf) and cont.all()


def test_random_permutation_unusable_and_probabilities_zero():
    rng = np.random.default_rng(5)
    unusable = 0
    for _ in range(20):
        x1, x2 = rng.uniform(0, 640, 200), rng.uniform(0, 640, 200)
        m = fit_spatial_order(x1, x2)
        unusable += not m.usable
        if not m.usable:
            assert "order structure" in m.reason
            assert np.all(match_probabilities(x1, x2, m) == 0)
    assert unusable >= 19
    m = fit_spatial_order([1.0, 2.0, 3.0], [3.0, 2.0, 1.0])  # K_hat = 1 > 1/2
    assert not m.usable and "K_hat=1.000" in m.reason


def test_small_all_correct_is_usable_and_y_breaks_ties():
    x = np.arange(12.0)
    m = fit_spatial_order(x, 2 * x + 5)
    assert m.usable and m.n_good == 12 and m.k_hat == 0.0
    # duplicated x resolved by y: order preserved when y agrees, reversed order when y disagrees
    x1 = np.array([0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5], float)
    y = np.arange(12.0)
    assert normalized_kendall_distance(x1, x1, y, y) == 0.0
    assert normalized_kendall_distance(x1, x1, y, -y) > 0.0


def test_generator_ground_truth_consistent():
    sp = generate_permutation(500, 200, n_holdout=30, n_swaps=10, seed=2)
    assert sorted(sp.sigma) == list(range(500)) and sp.is_good.sum() == sp.n_good == 200
    np.testing.assert_array_equal(sp.holdout_gap1, np.searchsorted(np.sort(sp.x1), sp.holdout_x1))
    np.testing.assert_array_equal(sp.holdout_gap2, np.searchsorted(np.sort(sp.x2), sp.holdout_x2))
    r1, r2 = match_ranks(sp.x1)[sp.is_good], match_ranks(sp.x2)[sp.is_good]
    assert (r1.min(), r1.max() + 1) == sp.window1 and (r2.min(), r2.max() + 1) == sp.window2
    a = generate_permutation(100, 50, seed=9)
    b = generate_permutation(100, 50, rng=np.random.default_rng(9))
    np.testing.assert_array_equal(a.sigma, b.sigma)


def test_k2d_and_exact_configs_fit():
    sp = generate_permutation(120, 80, seed=4)
    mg = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(overlap="k2d"))
    me = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(overlap="k2d", probability="exact"))
    assert mg.usable and me.usable and mg.omega == me.omega
    inside = mg.in_window
    assert np.mean(np.abs(mg.probabilities - me.probabilities)[inside]) < 0.05
    assert np.all(me.probabilities[~inside] == 0)
    mn = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(overlap="none"))
    assert mn.omega == (0, 120, 0, 120) and mn.n_window == 120


def test_order_noise_widens_the_search_range_and_is_measured_on_likely_correct_matches():
    """With local swaps among correct matches (A1 broken) the order-noise term must admit more gaps, and the
    noise measured on a given correct mask must equal the inversions among exactly those matches."""
    sp = generate_permutation(600, 400, overlap=(1.0, 1.0), n_swaps=150, swap_radius=6, seed=4)
    off = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(overlap="none", order_noise=False))
    on = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(overlap="none"), likely_correct=sp.is_good)
    assert off.order_noise == (0.0, 0.0) and on.order_noise[0] > 0
    assert on.gap_count.sum() > off.gap_count.sum()
    # reference: O(N^2) inversions among the true correct matches only
    g = np.flatnonzero(sp.is_good)
    x1, x2 = sp.x1[g], sp.x2[g]
    inv = ((x1[:, None] < x1[None, :]) & (x2[:, None] > x2[None, :])) | ((x1[:, None] > x1[None, :]) & (x2[:, None] < x2[None, :]))
    hg = inv.sum(1)
    np.testing.assert_allclose(on.order_noise, (hg.mean(), hg.var()), rtol=1e-9)


def test_model_without_gap_table_has_same_probabilities_and_refuses_lookups():
    sp = generate_permutation(300, 200, seed=8)
    full = fit_spatial_order(sp.x1, sp.x2)
    lite = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(gap_table=False))
    np.testing.assert_array_equal(full.probabilities, lite.probabilities)
    np.testing.assert_array_equal(match_probabilities(sp.x1, sp.x2), full.probabilities)
    with pytest.raises(ValueError, match="gap_table=False"):
        admissible_x_ranges(lite, sp.x1[:5])


# ---------------------------------------------------------------- config semantics and validation


def test_exact_probability_changes_only_the_reported_probabilities():
    """config.probability is the model of the per-match probabilities; window, order noise and gap table are the
    Gaussian model's whatever it says (no likely_correct mask: the order noise comes from the model's own P)."""
    sp = generate_permutation(150, 100, n_swaps=20, seed=3)
    g = fit_spatial_order(sp.x1, sp.x2)
    e = fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(probability="exact"))
    assert g.usable and e.usable and g.omega == e.omega and g.order_noise == e.order_noise
    for name in ("gap_lo", "gap_hi", "gap_count", "gap_runs_ptr", "gap_runs", "sigma_window"):
        np.testing.assert_array_equal(getattr(g, name), getattr(e, name))
    assert not np.array_equal(g.probabilities, e.probabilities)
    hl, hr = inversions_per_match(e.sigma_window)
    ref = probability_correct(np.arange(e.n_window), e.sigma_window, hl + hr, e.n_window - 1, e.n_good,
                              e.n_window, method="exact")
    np.testing.assert_array_equal(np.sort(e.probabilities[e.in_window]), np.sort(ref))


@pytest.mark.parametrize("field,value", [
    ("threshold", 0.0), ("threshold", 1.0), ("threshold", float("nan")), ("threshold", -0.1),
    ("grid_fraction", 0.0), ("grid_fraction", 1.5), ("grid_fraction", float("inf")),
    ("overlap", "k3d"), ("probability", "Exact"), ("num_beta", 0), ("num_beta", 2.5), ("num_beta", True),
    ("refine", 1), ("trim_rounds", -1), ("var_floor", 0.0), ("var_floor", float("nan")), ("gap_table", "yes"),
    ("order_noise", None), ("min_z", -1.0), ("min_z", float("inf")),
])
def test_config_rejects_bad_values_at_construction(field, value):
    from guidedmatch.errors import ConfigError

    with pytest.raises(ConfigError, match=f"SpatialOrderConfig.{field} must be"):
        SpatialOrderConfig(**{field: value})


def test_config_from_dict_and_unknown_names():
    from guidedmatch.errors import ConfigError

    x = np.arange(20.0)
    m = fit_spatial_order(x, x, {"overlap": "none", "threshold": 0.05})
    assert m.usable and m.config == SpatialOrderConfig(overlap="none", threshold=0.05)
    with pytest.raises(ConfigError, match="unknown SpatialOrderConfig option.*thresh.*valid: threshold"):
        fit_spatial_order(x, x, {"thresh": 0.05})
    assert SpatialOrderConfig(num_beta=np.int64(3)).num_beta == 3  # numpy integers are integers


def test_numba_cache_is_used_by_a_second_process():
    """cache=True survives the split into a subpackage: after one process has run a fit (compiling or loading),
    a fresh process loads every dispatcher it calls from the on-disk cache and compiles nothing."""
    import os
    import subprocess
    import sys

    code = ("from guidedmatch.spatial_order import fit_spatial_order, SpatialOrderConfig\n"
            "from guidedmatch.testing.permutations import generate_permutation\n"
            "sp = generate_permutation(200, 120, seed=0)\n"
            "assert fit_spatial_order(sp.x1, sp.x2).usable\n"
            "assert fit_spatial_order(sp.x1, sp.x2, SpatialOrderConfig(probability='exact')).usable\n")
    env = {**os.environ, "NUMBA_DEBUG_CACHE": "1"}
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
    second = runs[1].stdout + runs[1].stderr
    loaded = {line.split("_kernels.")[1].split("-")[0] for line in second.splitlines()
              if "data loaded" in line and "spatial_order" in line and "_kernels." in line}
    assert loaded == {"_inversions_dense", "_sweep_kendall", "_refine_window_nb", "_exact_lik_good", "_gap_kernel",
                      "_window_fit_gaussian"}
    assert "data saved" not in second and "index saved" not in second


@settings(max_examples=150, deadline=None)
@given(n=st.integers(0, 300), shuffled=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1),
       bounds=st.tuples(*(st.floats(0.0, 1.0) for _ in range(4))), num_beta=st.integers(1, 9),
       var_floor=st.sampled_from([0.25, 1.0, 3.5]))
def test_window_fit_kernel_equals_the_numpy_computation(n, shuffled, seed, bounds, num_beta, var_floor):
    """The nogil window fit (Gaussian model) against its NumPy formulation: the same matches, ranks, inversions and
    K_hat exactly, N_G and every probability to rounding (the sums run in another order; with a var_floor far
    below 1 the Gaussian is so narrow that those last-bit differences grow to ~1e-10 in P, hence the range)."""
    from guidedmatch.spatial_order import model as M
    from guidedmatch.spatial_order.window import Window

    rng = np.random.default_rng(seed)
    sigma = np.arange(n)
    moved = rng.choice(n, size=int(shuffled * n), replace=False) if n else np.zeros(0, np.int64)
    sigma[moved] = rng.permutation(sigma[moved])
    a, b = sorted(int(v * n) for v in bounds[:2])
    c, d = sorted(int(v * n) for v in bounds[2:])
    cfg = SpatialOrderConfig(num_beta=num_beta, var_floor=var_floor)
    got = M._window_fit(sigma, Window(a, b, c, d), cfg, "gaussian")
    ref = M._window_fit_numpy(sigma, Window(a, b, c, d), cfg, "gaussian")
    if ref is None:
        assert got is None
        return
    for x, y in zip(got[:5], ref[:5]):
        np.testing.assert_array_equal(x, y)
    assert got.k_hat == ref.k_hat
    assert got.n_good == pytest.approx(ref.n_good, rel=1e-12, abs=1e-12)
    # the kernel and NumPy sum the per-interval terms in different orders: float64 rounding, a few 1e-11 relative
    # at most seen (n=137, seed=1, num_beta=8: 3.2e-11); 1e-9 still fails any real difference in the model
    np.testing.assert_allclose(got.prob, ref.prob, rtol=1e-9, atol=1e-13)
