"""Tests of guidedmatch.alignment (Teng & Dong §III-E) on synthetic scenes with known K, R, t."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from guidedmatch.alignment import (
    APPROACHES,
    AlignmentResult,
    FocalResult,
    PoseResult,
    align_from_fundamental,
    alignment_homographies,
    apply_homography,
    bougnoux_focals,
    euler_xyz,
    euler_zyx,
    intrinsics,
    relative_pose,
    twist_angle,
    warp_to_canvas,
)
from guidedmatch.epipolar import estimate_fundamental
from guidedmatch.evaluation.alignment_sim import khat, run_alignment_experiment
from guidedmatch.results import Failure
from guidedmatch.testing.twoview import (
    forward_pair,
    general_pair,
    make_scene,
    roll_pair,
    rot_x,
    rot_y,
    rot_z,
    rotation_about,
    sphere_pair,
)

HSET = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SIZE = (640, 480)


def _rot_err_deg(A, B):
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def _axes_gap(s):
    """Distance between the two optical axes relative to the baseline (0 = intersecting axes)."""
    d2 = s.R[2, :]
    n = np.cross([0, 0, 1.0], d2)
    if np.linalg.norm(n) < 1e-9:
        return 1.0
    return abs(s.t @ n) / np.linalg.norm(n) / np.linalg.norm(s.t)


def _random_rotation(rng):
    v = rng.normal(size=3)
    return rotation_about(v, rng.uniform(0, np.pi))


# ----------------------------------------------------------------------------------- intrinsics
def test_intrinsics_principal_point_is_pixel_grid_centre():
    K = intrinsics(900.0, (640, 480))
    assert np.allclose(K, [[900, 0, 319.5], [0, 900, 239.5], [0, 0, 1]])


# -------------------------------------------------------------------------------------- focal
@HSET
@given(seed=st.integers(0, 10_000), f1=st.floats(500, 2500), f2=st.floats(500, 2500))
def test_bougnoux_exact_with_true_F(seed, f1, f2):
    s = general_pair(seed, f1=f1, f2=f2, max_angle_deg=35)
    assume(_axes_gap(s) > 0.1)
    fr = bougnoux_focals(s.F, SIZE, SIZE)
    assert isinstance(fr, FocalResult)
    assert fr.raw_f1 == pytest.approx(f1, rel=1e-6) and fr.raw_f2 == pytest.approx(f2, rel=1e-6)
    assert fr.reason1 == fr.reason2 == "ok" and not fr.fallback1 and not fr.fallback2
    assert fr.f1 == fr.raw_f1 and fr.f2 == fr.raw_f2


@HSET
@given(seed=st.integers(0, 10_000), f1=st.floats(600, 2000), f2=st.floats(600, 2000))
def test_bougnoux_within_few_percent_from_estimated_F(seed, f1, f2):
    s = general_pair(seed, f1=f1, f2=f2, max_angle_deg=35, noise=0.0)
    assume(_axes_gap(s) > 0.3)
    r = estimate_fundamental(s.x1, s.x2)
    fr = bougnoux_focals(r.F, SIZE, SIZE)
    assert not fr.fallback1 and not fr.fallback2, fr
    assert fr.f1 == pytest.approx(f1, rel=0.03) and fr.f2 == pytest.approx(f2, rel=0.03)


def test_bougnoux_fallbacks_on_degenerate_scenes():
    wh = SIZE[0] + SIZE[1]
    # pure translation along the optical axis: epipoles at the principal points
    s = forward_pair(0)
    fr = bougnoux_focals(s.F, SIZE, SIZE)
    assert fr.fallback1 and fr.fallback2 and fr.f1 == fr.f2 == wh
    assert fr.reason1 == "epipole at principal point" and np.isnan(fr.raw_f1)
    # ... also from a noisy estimated F (epipole near the principal point: unusable value)
    s = forward_pair(1, noise=0.5)
    fr = bougnoux_focals(estimate_fundamental(s.x1n, s.x2n).F, SIZE, SIZE)
    assert fr.fallback1 and fr.fallback2 and fr.f1 == fr.f2 == wh
    # identical images (noisy): no epipolar geometry, Bougnoux has no valid value
    s = general_pair(2)
    x2 = s.x1 + np.random.default_rng(0).normal(0, 0.5, s.x1.shape)
    fr = bougnoux_focals(estimate_fundamental(s.x1, x2).F, SIZE, SIZE)
    assert fr.fallback1 and fr.fallback2 and fr.f1 == fr.f2 == wh and fr.reason1 != "ok"
    # intersecting optical axes (the paper's simulation geometry): 0/0
    s = sphere_pair(3, noise=0.0)
    fr = bougnoux_focals(s.F, SIZE, SIZE)
    assert fr.fallback1 and fr.fallback2
    # a valid value outside Fusiello's range [(w+h)/3, 3(w+h)] is reported but not used
    s = general_pair(4, f1=250.0, f2=250.0)
    assert _axes_gap(s) > 0.1
    fr = bougnoux_focals(s.F, SIZE, SIZE)
    assert fr.raw_f1 == pytest.approx(250.0, rel=1e-6) and fr.f1 == wh and fr.fallback1
    assert fr.reason1 == "outside [(w+h)/3, 3(w+h)]"


# --------------------------------------------------------------------------------------- pose
@HSET
@given(seed=st.integers(0, 10_000), angle=st.floats(0.0, 45.0))
def test_relative_pose_exact_and_paper_convention(seed, angle):
    s = general_pair(seed, max_angle_deg=angle)
    p = relative_pose(s.F, s.K1, s.K2, s.x1, s.x2)
    assert isinstance(p, PoseResult)
    assert _rot_err_deg(p.R, s.R) < 1e-5
    assert np.allclose(p.t, s.t / np.linalg.norm(s.t), atol=1e-6)
    assert p.num_in_front == p.num_points == len(s.x1)
    # m2 ~ K2 [R | -R t] M reproduces x2 (up to the scale of t)
    scale = np.linalg.norm(s.t)
    m2 = (s.X - p.t * scale) @ p.R.T @ s.K2.T
    assert np.allclose(m2[:, :2] / m2[:, 2:], s.x2, atol=1e-6)
    assert np.allclose(np.linalg.svd(p.E, compute_uv=False), [1, 1, 0], atol=1e-8)


@HSET
@given(seed=st.integers(0, 10_000), angle=st.floats(5.0, 40.0))
def test_relative_pose_within_1deg_at_half_pixel_noise(seed, angle):
    s = general_pair(seed, n_points=300, max_angle_deg=angle, baseline=1.5, noise=0.5)
    r = estimate_fundamental(s.x1n, s.x2n)
    p = relative_pose(r.F, s.K1, s.K2, s.x1n[r.inliers], s.x2n[r.inliers])
    assert p
    assert _rot_err_deg(p.R, s.R) < 1.0


def test_relative_pose_bad_input():
    s = general_pair(0)
    assert isinstance(relative_pose(s.F, s.K1, s.K2, s.x1[:0], s.x2[:0]), Failure)
    x1 = s.x1.copy()
    x1[3] = np.nan
    assert isinstance(relative_pose(s.F, s.K1, s.K2, x1, s.x2), Failure)
    assert isinstance(relative_pose(np.diag([1.0, 0, 0]), s.K1, s.K2, s.x1, s.x2), Failure)
    assert isinstance(relative_pose(s.F * np.nan, s.K1, s.K2, s.x1, s.x2), Failure)


# ------------------------------------------------------------------------------ euler / twist
@HSET
@given(seed=st.integers(0, 10_000))
def test_euler_decompositions_reconstruct(seed):
    R = _random_rotation(np.random.default_rng(seed))
    z, y, x = euler_zyx(R)
    assert np.allclose(rot_z(z) @ rot_y(y) @ rot_x(x), R, atol=1e-9)
    x, y, z = euler_xyz(R)
    assert np.allclose(rot_x(x) @ rot_y(y) @ rot_z(z), R, atol=1e-9)


# ------------------------------------------------------------------------------- homographies
@pytest.mark.parametrize("approach", [a for a in APPROACHES if a != "d"])  # d needs a baseline
@pytest.mark.parametrize("roll", [-170.0, -35.0, 0.0, 12.5, 90.0, 179.0])
def test_every_approach_removes_a_pure_roll_exactly(approach, roll):
    """Camera 2 = camera 1 rolled about its optical axis (t = 0): H2 x2 == x1, order restored exactly."""
    s = roll_pair(0, roll_deg=roll)
    H1, H2, roll_deg = alignment_homographies(s.R, s.K1, s.K2, approach)
    assert np.allclose(H1, np.eye(3))
    a2 = apply_homography(H2, s.x2)
    assert np.abs(a2 - s.x1).max() < 1e-8
    assert khat(s.x1[:, 0], a2[:, 0]) == 0.0
    assert roll_deg == pytest.approx(roll, abs=1e-9)


@pytest.mark.parametrize("roll", [-150.0, -40.0, 25.0, 120.0])
def test_Hc_end_to_end_removes_roll_with_baseline(roll):
    """Roll + sideways baseline, noiseless, F estimated from the points, true K: the H_c-aligned image 2
    equals the unrolled view from the same centre (so the x-order is that of the unrolled pair)."""
    base = (0.8, 0.1, 0.05)
    s = roll_pair(1, roll_deg=roll, baseline=base)
    ref = roll_pair(1, roll_deg=0.0, baseline=base)
    r = estimate_fundamental(s.x1, s.x2)
    res = align_from_fundamental(r.F, s.x1, s.x2, SIZE, SIZE, "c", K1=s.K1, K2=s.K2)
    assert isinstance(res, AlignmentResult) and res
    a2 = apply_homography(res.H2, s.x2)
    assert np.abs(a2 - ref.x2).max() < 0.05  # float32 USAC
    assert res.roll_deg == pytest.approx(roll, abs=0.01)
    assert khat(s.x1[:, 0], a2[:, 0]) <= khat(s.x1[:, 0], ref.x2[:, 0]) + 0.002
    assert khat(s.x1[:, 0], a2[:, 0]) < khat(s.x1[:, 0], s.x2[:, 0])


@HSET
@given(seed=st.integers(0, 10_000))
def test_literal_Hc_versus_intended(seed):
    """What R_u R^T does (module docstring): the literal "c" points the aligned camera along R e3
    (third COLUMN of R) -- the mirror of camera 2's true direction R^T e3 about camera 1's axis -- while
    "c_inplane" keeps camera 2's direction and is a pure rotation about the optical axis."""
    rng = np.random.default_rng(seed)
    R = _random_rotation(rng)
    assume(R[2, 2] > -0.99)
    K = intrinsics(800.0, SIZE)
    Ki = np.linalg.inv(K)
    _, Hc, _ = alignment_homographies(R, K, K, "c")
    _, Hi, roll_i = alignment_homographies(R, K, K, "c_inplane")
    Qc = Ki @ Hc @ K
    Qi = Ki @ Hi @ K
    for Q in (Qc, Qi):
        assert np.allclose(Q @ Q.T, np.eye(3), atol=1e-9) and np.linalg.det(Q) == pytest.approx(1.0)
    e3 = np.array([0, 0, 1.0])
    # aligned camera orientation (world -> camera) = Q R; its viewing direction = (Q R)^T e3
    assert np.allclose((Qc @ R).T @ e3, R[:, 2], atol=1e-9)  # literal: third column
    assert np.allclose((Qi @ R).T @ e3, R[2, :], atol=1e-9)  # intended: camera 2's own direction
    assert np.allclose(Qi @ e3, e3, atol=1e-9)  # pure twist about the optical axis
    assert roll_i == pytest.approx(-np.degrees(twist_angle(Qi)))
    # the literal R_u (= Qc R, the aligned camera's orientation) maps r3 = R e3 to e3
    assert np.allclose(Qc @ R @ R[:, 2], e3, atol=1e-9)
    # the literal one tilts camera 2 by angle(R^T e3, R e3) (~ 2 theta for small angles)
    tilt = np.degrees(np.arccos(np.clip(Qc[2, 2], -1, 1)))
    expect = np.degrees(np.arccos(np.clip(R[2, :] @ R[:, 2], -1, 1)))
    assert tilt == pytest.approx(expect, abs=1e-6)


def test_literal_Hc_on_pure_pan_is_a_double_tilt():
    """No roll, camera 2 panned by 10 deg: "c_inplane" leaves image 2 alone, the literal "c" rotates the
    camera by 20 deg (to the mirrored direction)."""
    R = rot_y(np.radians(10.0))
    K = intrinsics(800.0, SIZE)
    _, Hc, roll_c = alignment_homographies(R, K, K, "c")
    _, Hi, roll_i = alignment_homographies(R, K, K, "c_inplane")
    assert np.allclose(Hi, np.eye(3), atol=1e-12) and roll_i == pytest.approx(0.0, abs=1e-12)
    Qc = np.linalg.inv(K) @ Hc @ K
    assert np.allclose(Qc, rot_y(np.radians(-20.0)), atol=1e-12) and roll_c == pytest.approx(0.0, abs=1e-9)


@HSET
@given(seed=st.integers(0, 10_000), approach=st.sampled_from(APPROACHES), bougnoux=st.booleans())
def test_alignment_homographies_are_proper(seed, approach, bougnoux):
    s = sphere_pair(seed, noise=1.0) if seed % 2 else general_pair(seed, noise=1.0)
    r = estimate_fundamental(s.x1n, s.x2n)
    kw = {} if bougnoux else {"K1": s.K1, "K2": s.K2}
    res = align_from_fundamental(r.F, s.x1n[r.inliers], s.x2n[r.inliers], SIZE, SIZE, approach, **kw)
    assert isinstance(res, AlignmentResult)
    T = np.array([[2 / SIZE[0], 0, -1], [0, 2 / SIZE[1], -1], [0, 0, 1.0]])  # pixels -> [-1, 1]
    for H in (res.H1, res.H2):
        assert H.shape == (3, 3) and np.isfinite(H).all()
        Hn = T @ H @ np.linalg.inv(T)
        assert abs(np.linalg.det(Hn / np.linalg.norm(Hn))) > 1e-6
    if approach != "d":
        assert np.array_equal(res.H1, np.eye(3))
    assert res.approach == approach and np.isfinite(res.roll_deg)
    assert np.allclose(res.R @ res.R.T, np.eye(3), atol=1e-9)


def test_approach_d_rectifies():
    """Wu et al. two-sided SVD rectification: with the true K, corresponding points share the same y."""
    s = sphere_pair(5, noise=0.0)
    res = align_from_fundamental(s.F, s.x1, s.x2, SIZE, SIZE, "d", K1=s.K1, K2=s.K2)
    a1 = apply_homography(res.H1, s.x1)
    a2 = apply_homography(res.H2, s.x2)
    assert np.abs(a1[:, 1] - a2[:, 1]).max() < 1e-6
    assert np.median(a1[:, 0] - a2[:, 0]) > 0  # camera 2 at +x: positive disparity


@HSET
@given(seed=st.integers(0, 10_000), roll=st.floats(20.0, 160.0), sign=st.sampled_from([-1, 1]))
def test_Hc_reduces_khat_on_rolled_scenes(seed, roll, sign):
    s = general_pair(seed, n_points=200, max_angle_deg=10, noise=0.5, roll_deg=sign * roll)
    r = estimate_fundamental(s.x1n, s.x2n)
    res = align_from_fundamental(r.F, s.x1n[r.inliers], s.x2n[r.inliers], SIZE, SIZE)  # "c", Bougnoux
    assert res
    a2 = apply_homography(res.H2, s.x2n)
    before = khat(s.x1n[:, 0], s.x2n[:, 0])
    after = khat(s.x1n[:, 0], a2[:, 0])
    assert after < before
    assert after < 0.2


# ----------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "case, words",
    [
        ("few", "fewer than 8"),
        ("collinear", "collinear"),
        ("rank1", "rank < 2"),
        ("nanF", "finite"),
        ("nanpts", "non-finite"),
        ("approach", "unknown approach"),
    ],
)
def test_align_bad_input_gives_failure(case, words):
    s = general_pair(0)
    F, x1, x2, ap = s.F, s.x1, s.x2, "c"
    if case == "few":
        x1, x2 = x1[:5], x2[:5]
    elif case == "collinear":
        x1 = np.c_[np.arange(len(x1), dtype=float), np.arange(len(x1), dtype=float)]
    elif case == "rank1":
        F = np.outer([1.0, 2, 3], [3.0, 1, 2])
    elif case == "nanF":
        F = F.copy()
        F[0, 0] = np.nan
    elif case == "nanpts":
        x2 = x2.copy()
        x2[7, 1] = np.nan
    elif case == "approach":
        ap = "z"
    res = align_from_fundamental(F, x1, x2, SIZE, SIZE, ap)
    assert isinstance(res, Failure) and not res and words in res.reason


# ------------------------------------------------------------------------------ apply / warp
@HSET
@given(seed=st.integers(0, 10_000))
def test_apply_homography_matches_loop(seed):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(3, 3))
    pts = rng.uniform(-100, 100, (20, 2))
    ref = []
    for p in pts:
        q = H @ np.array([p[0], p[1], 1.0])
        ref.append(q[:2] / q[2])
    assert np.allclose(apply_homography(H, pts), ref)


def test_apply_homography_nan_at_infinity():
    H = np.array([[1.0, 0, 0], [0, 1, 0], [1, 0, 0]])  # w = x
    out = apply_homography(H, np.array([[0.0, 5.0], [2.0, 4.0]]))
    assert np.isnan(out[0]).all() and np.allclose(out[1], [1.0, 2.0])
    assert apply_homography(np.eye(3), np.zeros((0, 2))).shape == (0, 2)


def test_warp_to_canvas_holds_whole_image():
    img = np.zeros((48, 64), np.uint8)
    img[10, 20] = 255
    img[1:-1, 1:-1] = np.maximum(img[1:-1, 1:-1], 10)
    K = intrinsics(80.0, (64, 48))
    H = K @ rot_z(np.radians(30.0)) @ rot_x(np.radians(5.0)) @ np.linalg.inv(K)
    warped, Hc = warp_to_canvas(img, H)
    corners = np.array([[0, 0], [63, 0], [63, 47], [0, 47]], float)
    wc = apply_homography(Hc, corners)
    assert (wc >= -0.5).all() and (wc[:, 0] <= warped.shape[1] - 0.5).all() and (wc[:, 1] <= warped.shape[0] - 0.5).all()
    x, y = np.rint(apply_homography(Hc, np.array([[20.0, 10.0]]))[0]).astype(int)
    assert warped[y - 1:y + 2, x - 1:x + 2].max() > 50
    T = Hc @ np.linalg.inv(H)  # the canvas offset is a pure translation
    assert np.allclose(T[:2, :2], np.eye(2), atol=1e-9) and np.allclose(T[2], [0, 0, 1], atol=1e-9)
    assert (warped > 0).sum() == pytest.approx((img > 0).sum() * abs(np.linalg.det(H[:2, :2])), rel=0.35)


# --------------------------------------------------------------------------------- experiment
def test_alignment_experiment_small(tmp_path):
    out = run_alignment_experiment(n_pairs=40, out_dir=tmp_path, seed=1, progress=False, workers=1)
    for key in ("csv", "png", "table_md", "json"):
        assert (tmp_path / out["files"][key].split("/")[-1]).exists()
    assert "| angle (deg) |" in out["table_md"] and out["n_pairs"] == 40
    lines = (tmp_path / "alignment_samples.csv").read_text().strip().splitlines()
    assert len(lines) == 41 and "ratio_c" in lines[0] and "ratio_c_trueK" in lines[0]
    # deterministic for a seed, independent of the number of workers
    again = run_alignment_experiment(n_pairs=40, out_dir=tmp_path / "b", seed=1, progress=False, workers=2)
    assert again["table"] == out["table"]


def test_make_scene_geometry():
    s = make_scene(np.array([[0.0, 0, 5], [1, 1, 6], [-1, 0.5, 4]]), intrinsics(500, SIZE), intrinsics(500, SIZE),
                   np.eye(3), np.array([1.0, 0, 0]), SIZE, SIZE)
    assert np.allclose(s.x1[0], [319.5, 239.5]) and np.allclose(s.x2[0], [319.5 - 100, 239.5])


@HSET
@given(seed=st.integers(0, 10_000), n=st.integers(2, 300))
def test_khat_matches_scipy_reference(seed, n):
    from guidedmatch.evaluation.alignment_sim import _khat_scipy

    rng = np.random.default_rng(seed)
    x1 = rng.normal(size=n)
    x2 = x1 + rng.normal(0, rng.uniform(0.01, 3), n)
    assert khat(x1, x2) == pytest.approx(_khat_scipy(x1, x2), abs=1e-12)
    # slow O(N^2) definition
    d = np.sign(x1[:, None] - x1[None, :]) * np.sign(x2[:, None] - x2[None, :])
    assert khat(x1, x2) == pytest.approx((d < 0).sum() / (n * (n - 1)), abs=1e-12)


# ------------------------------------------------------------------------- validation (check_alignment)
from guidedmatch.alignment import check_alignment, safe_alignment  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402


def _local_scale_fd(H, pts, eps=1e-3):
    """Slow reference: sqrt|det J| and sign(det J) from central differences of apply_homography, per point."""
    out, sign = [], []
    for p in pts:
        J = np.empty((2, 2))
        for k in range(2):
            d = np.zeros(2)
            d[k] = eps
            J[:, k] = (apply_homography(H, (p + d)[None])[0] - apply_homography(H, (p - d)[None])[0]) / (2 * eps)
        det = np.linalg.det(J)
        out.append(np.sqrt(abs(det)))
        sign.append(np.sign(det))
    return np.array(out), np.array(sign)


def test_check_alignment_accepts_rotations_about_the_centre():
    pts = np.random.default_rng(0).uniform(0, 639, (100, 2))
    K = intrinsics(800.0, SIZE)
    for a in (0.0, 30.0, 179.0, -120.0):
        H = K @ rot_z(np.radians(a)) @ np.linalg.inv(K)
        chk = check_alignment(H, pts, SIZE)
        assert chk and chk.reason == "ok"
        assert chk.scale_range == pytest.approx((1.0, 1.0), abs=1e-9) and chk.horizon_px == np.inf


@pytest.mark.parametrize("H, words", [
    (np.diag([-1.0, 1.0, 1.0]), "orientation not kept"),                      # mirror
    (np.array([[1.0, 0, 0], [0, 1, 0], [-1 / 300.0, 0, 1]]), "orientation"),  # line x = 300 at infinity crosses
    (np.diag([10.0, 10.0, 1.0]), "local scale out of range"),                 # 10x zoom
    (np.diag([0.1, 0.1, 1.0]), "local scale out of range"),
    (np.array([[2.0, 0, 0], [0, 2, 0], [0.004, 0, 1]]), "near the line at infinity"),  # scale ok, horizon 250 px
    (np.full((3, 3), np.nan), "finite"),
    (np.zeros((3, 3)), "finite"),  # normalising a zero matrix gives NaN
    (np.array([[1.0, 2, 0], [2, 4, 0], [0, 0, 1]]), "singular"),
])
def test_check_alignment_rejects_degenerate(H, words):
    pts = np.random.default_rng(1).uniform(0, 639, (100, 2)) * [1, 0.75]
    with np.errstate(all="ignore"):
        chk = check_alignment(H, pts, SIZE)
    assert not chk and words in chk.reason, chk.reason


@HSET
@given(H=hnp.arrays(np.float64, (3, 3), elements=st.floats(-2, 2)),
       pts=hnp.arrays(np.float64, (20, 2), elements=st.floats(0, 479)))
def test_check_alignment_against_finite_differences(H, pts):
    """scale_range and the orientation test agree with a numerical Jacobian at every keypoint."""
    H = H + np.diag([300.0, 300.0, 1.0])  # mostly well-conditioned, perspective terms up to 2 / 300 px
    H[2, :2] /= 300.0
    with np.errstate(all="ignore"):
        chk = check_alignment(H, pts, SIZE, scale_bounds=(1e-9, 1e9), horizon_diagonals=0.0)
        w = pts @ H[2, :2] + H[2, 2]
    assume(np.all(np.abs(w) > 1e-2))
    s, sign = _local_scale_fd(H, pts)
    assume(np.all(s > 1e-6))
    assert (bool(chk) or "singular" in chk.reason) == (np.all(sign > 0) and "singular" not in chk.reason)
    if chk:
        assert chk.scale_range == pytest.approx((s.min(), s.max()), rel=1e-4)


def test_safe_alignment_double_turn_falls_back_to_inplane():
    """The printed approach (c) turns camera 2 by up to 2 theta: at a 78 deg viewing angle the keypoints end up
    behind the turned camera (mirrored frame); the chain falls back to the in-plane twist and says why."""
    s = sphere_pair(3, noise=0.0)
    for kw in ({"K1": s.K1, "K2": s.K2}, {}):  # true intrinsics, and Bougnoux (degenerate here: f = w + h)
        al = safe_alignment(s.F, s.x1, s.x2, SIZE, SIZE, "c", s.x2, **kw)
        assert al.requested == "c" and al.approach == "c_inplane" and al.fell_back
        assert al.fallbacks[0][0] == "c" and "orientation not kept" in al.fallbacks[0][1]
        assert al.check and al.check.scale_range == pytest.approx((1.0, 1.0), abs=1e-9)
        assert not check_alignment(alignment_homographies(al.result.R, al.result.K1, al.result.K2, "c")[1], s.x2, SIZE)


@HSET
@given(seed=st.integers(0, 10_000), approach=st.sampled_from(APPROACHES), bougnoux=st.booleans())
def test_safe_alignment_result_always_passes_its_check(seed, approach, bougnoux):
    s = sphere_pair(seed, noise=1.0) if seed % 2 else general_pair(seed, noise=1.0)
    kw = {} if bougnoux else {"K1": s.K1, "K2": s.K2}
    al = safe_alignment(s.F, s.x1n, s.x2n, SIZE, SIZE, approach, s.x2n, s.x1n, **kw)
    assert al.approach in (approach, "c_inplane", "none")
    assert check_alignment(al.H2, s.x2n, SIZE)
    chain = list(dict.fromkeys([approach, "c_inplane", "none"]))  # the order links are tried in
    assert [a for a, _ in al.fallbacks] == chain[:chain.index(al.approach)]  # every link before the used one
    if al.approach == "c_inplane":  # in-plane rotation about the principal point: never rejected
        assert al.check.scale_range == pytest.approx((1.0, 1.0), abs=1e-9)


def test_safe_alignment_none_when_every_link_fails():
    s = general_pair(0)
    al = safe_alignment(np.full((3, 3), np.nan), s.x1, s.x2, SIZE, SIZE, "c", s.x2)
    assert al.approach == "none" and np.array_equal(al.H2, np.eye(3)) and al.result is None
    assert [a for a, _ in al.fallbacks] == ["c", "c_inplane"]
