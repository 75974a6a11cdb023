import numpy as np
import pytest

from guidedmatch.datasets import (EpipolarGT, HomographyGT, data_root, oxford_pairs, strecha_pairs,
                                  synthesize_pair, synthetic_pairs)

ROOT = data_root()
needs_data = pytest.mark.skipif(ROOT is None, reason="evaluation data not found (set GUIDEDMATCH_DATA)")


def test_data_root_override_and_env(tmp_path, monkeypatch):
    monkeypatch.setenv("GUIDEDMATCH_DATA", str(tmp_path))
    assert data_root() == tmp_path
    assert data_root(tmp_path / "x") in (None, tmp_path / "x")  # a missing override is never silently replaced
    with pytest.raises(FileNotFoundError, match="GUIDEDMATCH_DATA"):
        oxford_pairs(tmp_path / "missing")


def test_homography_gt_threshold(rng):
    H = np.array([[0.9, 0.1, 20], [-0.1, 0.9, 5], [1e-5, 0, 1]])
    gt = HomographyGT(H, (640, 480), (640, 480))
    p1 = rng.uniform(50, 400, (200, 2))
    p2 = gt.project(p1)
    assert gt.correct(p1, p2).all()
    assert gt.correct(p1, p2 + [0, 2.9]).all()
    assert not gt.correct(p1, p2 + [0, 3.1]).any()
    assert not gt.correct([[-10.0, 5.0]], gt.project([[-10.0, 5.0]])).any()  # outside image 1


def test_epipolar_gt_from_pose_agrees_with_scene(small_scene, rng):
    gt = EpipolarGT.from_pose(small_scene.K1, small_scene.K2, small_scene.R, small_scene.t)
    h, w = small_scene.image1.shape
    p1 = rng.uniform([0, 0], [w - 1, h - 1], (500, 2))
    p2, vis = small_scene.project(p1)
    assert gt.error(p1[vis], p2[vis]).max() < 1e-6
    assert gt.correct(p1[vis], p2[vis]).all()
    # move each image-2 point 10 px off its epipolar line (along the line normal): no longer correct
    lines = np.c_[p1[vis], np.ones(vis.sum())] @ gt.F.T
    normal = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    assert not gt.correct(p1[vis], p2[vis] + 10 * normal).any()


@pytest.mark.parametrize("set_id", [1, 2, 3])
def test_synthetic_homography_maps_image1_pixels_onto_image2(set_id, small_scene):
    """Warp a rendered image and check GT on SIFT matches: most ratio-test matches must be within 3 px."""
    from guidedmatch.bruteforce import match_bruteforce
    from guidedmatch.features import detect

    img1 = small_scene.image1
    img2, H, info = synthesize_pair(np.dstack([img1] * 3), set_id, rng=set_id)
    gt = HomographyGT(H, info["size1"], info["size2"])
    f1, f2 = detect(img1), detect(img2)
    r = match_bruteforce(f1, f2)
    ok = gt.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    err = gt.error(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    assert len(r) > 50 and ok.mean() > 0.8
    assert np.median(err[ok]) < 1.0  # sub-pixel: the homography is exact, not just roughly right


@pytest.mark.data
@needs_data
def test_oxford_and_strecha_pairs_load_with_consistent_gt():
    from guidedmatch.bruteforce import match_bruteforce
    from guidedmatch.features import detect

    ox = oxford_pairs(ROOT)
    assert len(ox) == 12 and ox[0].name == "oxford/bikes/1-2"
    p = ox[0]
    i1, i2 = p.load()
    f1, f2 = detect(i1, max_features=2000), detect(i2, max_features=2000)
    r = match_bruteforce(f1, f2)
    assert p.gt.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]]).mean() > 0.7
    st = strecha_pairs(ROOT, with_sizes=False)
    assert len(st) == 18
    F = st[0].gt.F
    assert abs(np.linalg.det(F)) < 1e-8 and np.isclose(np.linalg.norm(F), 1.0)


@pytest.mark.data
@needs_data
def test_synthetic_pairs_are_deterministic_and_lazy():
    a = next(iter(synthetic_pairs(ROOT, 2, n_pairs=1, seed=3, max_side=500)))
    b = next(iter(synthetic_pairs(ROOT, 2, n_pairs=1, seed=3, max_side=500)))
    np.testing.assert_array_equal(a.gt.H, b.gt.H)
    i1, i2 = a.load()
    j1, j2 = b.load()
    np.testing.assert_array_equal(i2, j2)
    assert max(i1.shape[:2]) <= 500
