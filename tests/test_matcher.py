import numpy as np
import pytest

from guidedmatch.bruteforce import match_bruteforce
from guidedmatch.features import Features, detect
from guidedmatch.matcher import MODES, MatcherConfig, match

FAST = MatcherConfig(update_every=60, num_updates=2)  # small scene: fewer correspondences per update


@pytest.fixture(scope="module")
def scene_and_features():
    from guidedmatch.testing.scenes import make_scene

    s = make_scene((800, 600), roll_deg=30.0, seed=5)
    return s, detect(s.image1), detect(s.image2)


def _true(scene, f1, f2, res):
    return scene.correct(f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]])


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_returns_valid_indices(scene_and_features, mode):
    s, f1, f2 = scene_and_features
    r = match(f1, f2, mode, FAST)
    assert r.pairs.dtype == np.int64 and r.pairs.shape == (len(r), 2) and len(r) > 50
    assert r.pairs[:, 0].min() >= 0 and r.pairs[:, 0].max() < len(f1)
    assert r.pairs[:, 1].min() >= 0 and r.pairs[:, 1].max() < len(f2)
    assert len(np.unique(r.pairs[:, 0])) == len(r)  # each image-1 feature matched at most once
    for k, v in r.flags.items():
        assert len(v) == len(r), k
    assert r.stats.comparisons <= len(f1) * len(f2)
    if mode != "bf":
        assert r.stats.num_model_updates == 2
        assert r.stats.comparisons == sum(r.stats.phase_comparisons)
        # every image-1 feature is drawn exactly once (those outside the overlap window count as drawn)
        assert sum(r.stats.phase_queries) == len(f1)


def test_bf_mode_equals_bruteforce_module(scene_and_features):
    _, f1, f2 = scene_and_features
    a = match(f1, f2, "bf")
    b = match_bruteforce(f1, f2)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    np.testing.assert_array_equal(a.distances, b.distances)


def test_final_pass_pairs_lie_in_reference_candidate_sets_and_counts_are_exact(scene_and_features):
    s, f1, f2 = scene_and_features
    cfg = FAST.replace(recheck=False)
    r, models = match(f1, f2, "so+epi+ia", cfg, return_models=True)
    assert models is not None and models.so is not None and models.F is not None
    final = models.final_queries
    # comparisons of the final pass == sum of independently recomputed candidate-set sizes
    ref_sizes = np.array([len(models.candidates(q)) for q in final])
    last_phase = r.stats.num_model_updates
    assert r.stats.phase_comparisons[last_phase] == ref_sizes.sum()
    assert r.stats.phase_comparisons[0] == r.stats.phase_queries[0] * len(f2)  # unguided start = BF
    # every final-pass match lies in its reference candidate set and is its nearest descriptor there
    fin = r.flags["phase"] == last_phase
    rng = np.random.default_rng(0)
    for k in rng.choice(np.flatnonzero(fin), size=min(150, fin.sum()), replace=False):
        i, j = r.pairs[k]
        cand = models.candidates(i)
        assert j in cand
        dist = np.linalg.norm(f2.descriptors[cand] - f1.descriptors[i], axis=1)
        assert np.isclose(dist.min(), r.distances[k], rtol=1e-4)


def test_guided_cost_is_a_small_fraction_of_bruteforce(scene_and_features):
    _, f1, f2 = scene_and_features
    r = match(f1, f2, "so+epi+ia", FAST)
    assert r.stats.comparison_ratio < 0.25


def test_alignment_helps_on_rolled_scene(scene_and_features):
    s, f1, f2 = scene_and_features
    ia = _true(s, f1, f2, match(f1, f2, "so+epi+ia", FAST)).sum()
    no = _true(s, f1, f2, match(f1, f2, "so+epi", FAST)).sum()
    assert ia >= no


def test_binary_descriptors(scene_and_features):
    s, _, _ = scene_and_features
    f1, f2 = detect(s.image1, "orb", 3000), detect(s.image2, "orb", 3000)
    r = match(f1, f2, "so+epi+ia", FAST)
    assert r.stats.metric == "hamming" and len(r) > 20
    assert _true(s, f1, f2, r).mean() > 0.5


def test_unusable_so_model_falls_back_and_reports(scene_and_features, monkeypatch):
    import guidedmatch.spatial_order as so

    _, f1, f2 = scene_and_features
    real = so.fit_spatial_order

    def broken(*a, **k):
        m = real(*a, **k)
        import dataclasses

        return dataclasses.replace(m, usable=False, reason="forced for the test")

    monkeypatch.setattr(so, "fit_spatial_order", broken)
    r = match(f1, f2, "so+epi", FAST)
    whats = [f.what for f in r.stats.fallbacks]
    assert "spatial_order" in whats and "forced for the test" in r.stats.fallbacks[0].reason
    assert len(r) > 50  # still matched (epipolar band only)


def test_too_few_correspondences_reports_missing_updates(scene_and_features):
    _, f1, f2 = scene_and_features
    r = match(f1, f2, "so+epi+ia", MatcherConfig(update_every=100000, one_to_one=False))
    assert r.stats.num_model_updates == 0
    assert any(f.what == "updates" for f in r.stats.fallbacks)
    b = match(f1, f2, "bf")
    assert len(r) == len(b)  # no model: every feature was matched against all of image 2


def _feats(n, seed=0, size=(100, 100)):
    rng = np.random.default_rng(seed)
    return Features.from_arrays(rng.uniform(0, 99, (n, 2)), rng.integers(0, 50, (n, 16)).astype(np.float32), size)


@pytest.mark.parametrize("n1,n2", [(0, 0), (0, 10), (10, 0), (1, 1), (1, 50), (3, 2)])
@pytest.mark.parametrize("mode", MODES)
def test_empty_and_tiny_inputs_return_cleanly(n1, n2, mode):
    r = match(_feats(n1, 1), _feats(n2, 2), mode)
    assert r.pairs.shape == (len(r), 2) and len(r) <= min(n1, n2)
    # too few features for any model: every mode degrades to brute force and says so
    assert r.stats.comparisons == n1 * n2
    if mode != "bf" and n1 and n2:
        assert any(f.what == "updates" for f in r.stats.fallbacks)


def test_identical_images(scene_and_features):
    _, f1, _ = scene_and_features
    r = match(f1, f1, "so+epi+ia", FAST)
    assert len(r) > 0.5 * len(f1)
    same = r.pairs[:, 0] == r.pairs[:, 1]
    assert same.mean() > 0.95
    # identical views: no relative pose puts the points in front of both cameras, so the alignment fails; that is
    # reported and the run matches in original coordinates (no H2)
    assert [f.what for f in r.stats.fallbacks].count("alignment") == r.stats.num_model_updates == 2
    assert r.stats.alignment_H2 is None and all(u.H2 is None for u in r.stats.updates)


def test_descriptor_mismatch_raises(scene_and_features):
    _, f1, _ = scene_and_features
    bad = Features.from_arrays(f1.keypoints[:10], np.zeros((10, 64), np.float32), f1.image_size)
    with pytest.raises(ValueError, match="lengths differ"):
        match(f1, bad)


def test_invalid_config():
    with pytest.raises(ValueError):
        MatcherConfig(alignment="z")
    with pytest.raises(ValueError):
        MatcherConfig(ratio=1.5)
    with pytest.raises(ValueError, match="unknown mode"):
        match(_feats(5), _feats(5), "fast")


def test_byte_exact_kernel_equals_float_kernel(scene_and_features, monkeypatch):
    """SIFT descriptors are integers 0..255: the uint8/int32 kernel must give the same matches as float32."""
    import guidedmatch.kernels as K

    _, f1, f2 = scene_and_features
    a = match(f1, f2, "so+epi+ia", FAST)
    assert a.stats.byte_exact_kernel
    monkeypatch.setattr(K, "as_exact_uint8", lambda d: None)
    b = match(f1, f2, "so+epi+ia", FAST)
    assert not b.stats.byte_exact_kernel
    np.testing.assert_array_equal(a.pairs, b.pairs)
    np.testing.assert_allclose(a.distances, b.distances, rtol=1e-6)
    assert a.stats.comparisons == b.stats.comparisons


@pytest.fixture
def narrow_window(monkeypatch):
    """Spatial-order models fitted on the matches of the middle half of image 1 only: ω* is narrower than the
    x-extent of the F inliers, so the band-only rescue has work to do."""
    import guidedmatch.spatial_order as so

    real = so.fit_spatial_order

    def narrowed(x1, x2, config, *, y1=None, y2=None, likely_correct=None):
        if y1 is None:  # the per-match probabilities of the final set: unchanged
            return real(x1, x2, config)
        lo, hi = np.percentile(x1, [25, 75])
        m = (x1 > lo) & (x1 < hi)
        return real(x1[m], x2[m], config, y1=y1[m], y2=y2[m],
                    likely_correct=None if likely_correct is None else likely_correct[m])

    monkeypatch.setattr(so, "fit_spatial_order", narrowed)


def test_band_only_rescue_matches_outside_the_window_only_in_the_band(scene_and_features, narrow_window):
    """outside_window="band": final-pass features outside the SO window ω* but inside the x-extent of the F inliers
    are matched in the epipolar band only (checked here with an independent line computation); "drop" never
    matches a feature outside ω*."""
    from guidedmatch.spatial_order import admissible_x_ranges

    _, f1, f2 = scene_and_features
    r, models = match(f1, f2, "so+epi+ia", FAST.replace(recheck=False), return_models=True)
    last = r.stats.num_model_updates
    fin = r.flags["phase"] == last
    i, j = r.pairs[fin, 0], r.pairs[fin, 1]
    x1a = models.pts1a[i]
    inside, _, _, _ = admissible_x_ranges(models.so, x1a[:, 0])
    out = ~inside
    assert out.sum() >= 50  # the rescue is exercised
    lo, hi = models.inlier_x1_range
    assert np.all((x1a[out, 0] >= lo) & (x1a[out, 0] <= hi))
    for k in np.flatnonzero(out):
        line = models.F_aligned @ np.array([x1a[k, 0], x1a[k, 1], 1.0])
        x2 = models.pts2a[j[k]]
        assert abs(line[0] * x2[0] + line[1] * x2[1] + line[2]) / np.hypot(line[0], line[1]) <= models.band_px + 1e-9
    # the rescued final-pass queries are counted in band_only_outside_window (with those of the guided batches)
    fq = models.final_queries
    ok_fq, _, _, _ = admissible_x_ranges(models.so, models.pts1a[fq, 0])
    resc = ~ok_fq & (models.pts1a[fq, 0] >= lo) & (models.pts1a[fq, 0] <= hi)
    assert resc.sum() <= r.stats.band_only_outside_window <= len(f1) - r.stats.phase_queries[0]
    drop, dm = match(f1, f2, "so+epi+ia", FAST.replace(recheck=False, outside_window="drop"), return_models=True)
    assert drop.stats.band_only_outside_window == 0
    dfin = drop.flags["phase"] == drop.stats.num_model_updates
    inside_d, _, _, _ = admissible_x_ranges(dm.so, dm.pts1a[drop.pairs[dfin, 0], 0])
    assert inside_d.all()
