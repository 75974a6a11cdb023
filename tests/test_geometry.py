"""Tests of the two-view verdict (guidedmatch.geometry): synthetic correspondences with known geometry, the null
case (correspondences sharing no geometry), repeated-texture clusters, and rendered scenes."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from guidedmatch.geometry import VERDICTS, TwoViewGeometry, VerdictConfig, random_inlier_bound, two_view_geometry
from guidedmatch.testing.twoview import general_pair

SIZE = (640, 480)


def test_random_inlier_bound_formula():
    assert random_inlier_bound(7, 0.5, 7, 5.0) == pytest.approx(7 + 5.0)
    assert random_inlier_bound(107, 0.01, 7, 5.0) == pytest.approx(7 + 1.0 + 5.0 * np.sqrt(2.0))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.sampled_from([20, 60, 200, 600]))
def test_no_geometry_is_never_verified(seed, m):
    """Correspondences drawn independently in both images (the null case): never 'verified'."""
    rng = np.random.default_rng(seed)
    x1 = rng.uniform(0, 1, (m, 2)) * SIZE
    x2 = rng.uniform(0, 1, (m, 2)) * SIZE
    g = two_view_geometry(x1, x2, SIZE, SIZE)
    assert g.verdict == "no-overlap" and not g and g.model == "none" and g.num_inliers == 0
    assert g.evidence["num_evidence"] == m and g.reason


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), outliers=st.floats(0.0, 0.8))
def test_general_scene_is_verified_F(seed, outliers):
    s = general_pair(seed, n_points=300, noise=0.5)
    x1, x2 = s.x1n.copy(), s.x2n.copy()
    rng = np.random.default_rng(seed)
    bad = rng.random(len(x1)) < outliers
    x2[bad] = rng.uniform(0, 1, (bad.sum(), 2)) * SIZE
    g = two_view_geometry(x1, x2, SIZE, SIZE)
    assert g and g.verdict == "verified" and g.model == "F"
    assert g.inliers.shape == (len(x1),) and g.num_inliers == int(g.inliers.sum())
    # the inlier mask is right on nearly every correspondence (a random point can fall into a band by chance)
    assert np.mean(g.inliers[~bad]) > 0.95
    assert not bad.any() or np.mean(g.inliers[bad]) < 0.15


def test_repeated_texture_cluster_is_not_evidence():
    """Many image-1 features matched to one image-2 point fit any F with its epipole there; they count once."""
    rng = np.random.default_rng(0)
    x1 = rng.uniform(0, 1, (80, 2)) * SIZE
    x2 = rng.uniform(0, 1, (80, 2)) * SIZE
    x2[:30] = [300.0, 200.0]  # 30 features of image 1 all matched to the same image-2 point
    g = two_view_geometry(x1, x2, SIZE, SIZE)
    assert g.verdict == "no-overlap"
    assert g.evidence["F_inliers_raw"] >= 30 > g.evidence["F_inliers"]


def test_planar_scene_is_H_and_report_on():
    rng = np.random.default_rng(1)
    x1 = rng.uniform(0, 1, (150, 2)) * SIZE
    H = np.array([[0.9, 0.1, 30.0], [-0.05, 1.1, 10.0], [1e-4, 0.0, 1.0]])
    p = np.c_[x1, np.ones(150)] @ H.T
    x2 = p[:, :2] / p[:, 2:] + rng.normal(0, 0.3, (150, 2))
    g = two_view_geometry(x1, x2, SIZE, SIZE)
    assert g.verdict == "verified" and g.model == "H" and g.colmap_config == 6
    # report over other correspondences: half true, half shifted by 20 px
    y1 = x1[:40]
    y2 = x2[:40].copy()
    y2[20:] += 20.0
    r = two_view_geometry(x1, x2, SIZE, SIZE, report_on=(y1, y2))
    assert r.num_matches == 40 and r.inliers[:20].all() and not r.inliers[20:].any()


@pytest.mark.parametrize("m", [0, 3])
def test_too_few(m):
    g = two_view_geometry(np.zeros((m, 2)), np.zeros((m, 2)), SIZE, SIZE)
    assert g.verdict == "too-few-matches" and g.model == "none" and g.verdict in VERDICTS


def test_degenerate_inputs_do_not_raise():
    x = np.tile([[10.0, 20.0]], (50, 1))
    g = two_view_geometry(x, x, SIZE, SIZE)  # all identical points
    assert isinstance(g, TwoViewGeometry) and g.verdict in VERDICTS and not g
    x1 = np.c_[np.linspace(0, 600, 50), np.linspace(0, 400, 50)]  # collinear
    assert two_view_geometry(x1, x1 + 5.0, SIZE, SIZE).verdict in VERDICTS  # must not raise
    with pytest.raises(ValueError):
        two_view_geometry(np.zeros((5, 2)), np.zeros((4, 2)), SIZE, SIZE)


@pytest.mark.parametrize("kw", [dict(threshold_px=0), dict(chance_factor=-1.0), dict(min_inliers=-1),
                                dict(sigmas=float("nan"))])
def test_config_validation(kw):
    with pytest.raises(ValueError):
        VerdictConfig(**kw)


# ------------------------------------------------------------------------------------- rendered scenes
@pytest.fixture(scope="module")
def rendered():
    from guidedmatch.features import detect
    from guidedmatch.testing.scenes import make_scene

    a = make_scene((640, 480), roll_deg=25.0, seed=3)
    b = make_scene((640, 480), roll_deg=10.0, seed=8)
    rot = make_scene((640, 480), roll_deg=20.0, seed=5, baseline=0.0)  # pure rotation: a homography
    return {k: (detect(s.image1), detect(s.image2), s) for k, s in (("a", a), ("b", b), ("rot", rot))}


def _bf_geometry(f1, f2):
    from guidedmatch.bruteforce import match_bruteforce

    r = match_bruteforce(f1.descriptors, f2.descriptors, ratio=0.8)
    return two_view_geometry(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]], f1.image_size, f2.image_size), r


def test_rendered_overlapping_scene_verified(rendered):
    f1, f2, s = rendered["a"]
    g, r = _bf_geometry(f1, f2)
    assert g.verdict == "verified" and g.model == "F"
    ok = s.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    assert np.mean(ok[g.inliers]) > 0.9  # the inliers are true correspondences


def test_rendered_unrelated_scenes_no_overlap(rendered):
    f1 = rendered["a"][0]
    f2 = rendered["b"][1]  # another scene (different textures and cameras)
    g, _ = _bf_geometry(f1, f2)
    assert g.verdict == "no-overlap" and g.num_inliers == 0


def test_rendered_pure_rotation_is_H(rendered):
    f1, f2, _ = rendered["rot"]
    g, _ = _bf_geometry(f1, f2)
    assert g.verdict == "verified" and g.model == "H"


def test_report_geometry_keeps_the_decision():
    from guidedmatch.geometry import report_geometry

    s = general_pair(3, n_points=200, noise=0.3)
    d = two_view_geometry(s.x1n, s.x2n, SIZE, SIZE)
    assert d.model == "F"
    y1, y2 = s.x1n[:50].copy(), s.x2n[:50].copy()
    y2[25:] += 40.0  # far off their epipolar lines (generically)
    r = report_geometry(d, y1, y2, F=s.F)
    assert r.verdict == "verified" and r.model == "F" and r.num_matches == 50 and np.array_equal(r.F, s.F)
    assert r.inliers[:25].all() and r.inliers[25:].mean() < 0.2 and r.evidence["num_reported"] == 50
    rng = np.random.default_rng(0)
    null = two_view_geometry(rng.uniform(0, 1, (100, 2)) * SIZE, rng.uniform(0, 1, (100, 2)) * SIZE, SIZE, SIZE)
    r = report_geometry(null, y1, y2)
    assert r.verdict == "no-overlap" and not r.inliers.any() and r.num_matches == 50


def test_F_prior_is_kept_only_when_it_explains_more():
    s = general_pair(5, n_points=300, noise=0.3)
    rng = np.random.default_rng(5)
    x1, x2 = s.x1n.copy(), s.x2n.copy()
    bad = rng.random(len(x1)) < 0.6
    x2[bad] = rng.uniform(0, 1, (bad.sum(), 2)) * SIZE
    short = VerdictConfig(max_iters=1)  # one RANSAC sample: almost surely misses the model
    g0 = two_view_geometry(x1, x2, SIZE, SIZE, short)
    g = two_view_geometry(x1, x2, SIZE, SIZE, short, F_prior=s.F)
    assert g.verdict == "verified" and g.evidence.get("F_from_prior") and np.array_equal(g.F, s.F)
    assert g.evidence["F_inliers"] >= g0.evidence["F_inliers"] and g.inliers[~bad].mean() > 0.95
    # a prior that explains nothing changes nothing
    wrong = np.linalg.svd(rng.normal(size=(3, 3)))[0] @ np.diag([1.0, 0.5, 0.0])
    h = two_view_geometry(x1, x2, SIZE, SIZE, VerdictConfig(), F_prior=wrong)
    ref = two_view_geometry(x1, x2, SIZE, SIZE, VerdictConfig())
    assert "F_from_prior" not in h.evidence and h.evidence["F_inliers"] == ref.evidence["F_inliers"]
