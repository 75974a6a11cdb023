import numpy as np
import pytest

from guidedmatch.testing.scenes import make_scene


def test_projected_points_satisfy_epipolar_constraint(small_scene, rng):
    h, w = small_scene.image1.shape
    pts = rng.uniform([0, 0], [w - 1, h - 1], (2000, 2))
    proj, vis = small_scene.project(pts)
    assert vis.mean() > 0.4
    x1 = np.c_[pts[vis], np.ones(vis.sum())]
    x2 = np.c_[proj[vis], np.ones(vis.sum())]
    lines = x1 @ small_scene.F.T
    dist = np.abs(np.sum(lines * x2, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert dist.max() < 1e-6  # pixels


def test_ground_truth_marks_true_correct_and_perturbed_wrong(small_scene, rng):
    h, w = small_scene.image1.shape
    pts = rng.uniform([0, 0], [w - 1, h - 1], (1000, 2))
    proj, vis = small_scene.project(pts)
    p, q = pts[vis], proj[vis]
    assert small_scene.correct(p, q).all()
    assert small_scene.correct(p, q + [2.0, 0.0]).all()          # within 3 px
    assert not small_scene.correct(p, q + [3.5, 0.0]).any()      # beyond 3 px
    assert not small_scene.correct(p, q[::-1]).all()


def _measured_roll_deg(R, t, K):
    """Roll of a camera about its optical axis, measured from its pose: the image direction of the world's y axis
    (down) at the principal point, as an angle from the image's y axis."""
    c = -R.T @ t
    X = c + 7.0 * R[2]  # a point on the optical axis

    def proj(P):
        p = K @ (R @ P + t)
        return p[:2] / p[2]

    v = proj(X + 0.01 * np.array([0.0, 1.0, 0.0])) - proj(X)
    return float(np.degrees(np.arctan2(-v[0], v[1])))


@pytest.mark.parametrize("roll", [-20.0, 0.0, 35.0])
def test_scene_has_requested_roll_and_is_deterministic(roll):
    a = make_scene((160, 120), roll_deg=roll, seed=7)
    b = make_scene((160, 120), roll_deg=roll, seed=7)
    np.testing.assert_array_equal(a.image2, b.image2)
    np.testing.assert_allclose(a.R @ a.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(a.R), 1.0, atol=1e-12)
    # the roll of camera 2 measured from its rendered pose (camera 1 is upright)
    assert abs(_measured_roll_deg(a.R, a.t, a.K2) - roll) < 1e-9
    assert abs(_measured_roll_deg(np.eye(3), np.zeros(3), a.K1)) < 1e-9
    assert np.linalg.matrix_rank(a.F) == 2


def test_detected_bf_matches_are_mostly_correct(small_scene, small_scene_features):
    from guidedmatch.bruteforce import match_bruteforce

    f1, f2 = small_scene_features
    assert len(f1) > 300 and len(f2) > 300
    r = match_bruteforce(f1, f2)
    ok = small_scene.correct(f1.keypoints[r.pairs[:, 0]], f2.keypoints[r.pairs[:, 1]])
    assert ok.mean() > 0.7
