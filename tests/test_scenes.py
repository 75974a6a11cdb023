import numpy as np
import pytest

from guidedmatch.testing.scenes import make_scene


def test_ground_truth_projection_matches_the_plane_homographies(small_scene, rng):
    """project() maps through alignment.apply_homography; on 200k random image-1 points (a quarter placed next to
    the 3 px threshold) positions agree with the plain matrix product to 1e-9 px and every correct() decision is
    the one the matrix-product formula gives (the demo's "true" counts rest on these decisions)."""
    h, w = small_scene.image1.shape
    pts = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (200_000, 2))
    proj, vis = small_scene.project(pts)
    ix = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.rint(pts[:, 1]).astype(int), 0, h - 1)
    lab = small_scene.labels1[iy, ix]
    ref = np.full_like(pts, np.nan)
    for k, H in enumerate(small_scene.homographies):
        sel = lab == k
        p = np.c_[pts[sel], np.ones(sel.sum())] @ H.T
        ref[sel] = p[:, :2] / p[:, 2:3]
    np.testing.assert_array_equal(np.isnan(proj), np.isnan(ref))
    hit = ~np.isnan(ref[:, 0])
    assert hit.mean() > 0.4 and np.abs(proj[hit] - ref[hit]).max() < 1e-9
    h2, w2 = small_scene.labels2.shape
    qx = np.rint(np.where(hit, ref[:, 0], -1)).astype(int)
    qy = np.rint(np.where(hit, ref[:, 1], -1)).astype(int)
    inside = hit & (qx >= 0) & (qx < w2) & (qy >= 0) & (qy < h2)
    ref_vis = np.zeros(len(pts), bool)
    ref_vis[inside] = small_scene.labels2[qy[inside], qx[inside]] == lab[inside]
    np.testing.assert_array_equal(vis, ref_vis)
    ang = rng.uniform(0, 2 * np.pi, len(pts))
    r = rng.uniform(0, 6, len(pts))
    near = rng.random(len(pts)) < 0.25
    r[near] = 3.0 + rng.choice([-1, 1], near.sum()) * 10.0 ** rng.uniform(-9, -3, near.sum())
    q = ref + r[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    err = np.linalg.norm(ref - q, axis=1)
    np.testing.assert_array_equal(small_scene.correct(pts, q), ref_vis & (np.nan_to_num(err, nan=np.inf) < 3.0))


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
