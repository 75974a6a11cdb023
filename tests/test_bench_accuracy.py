"""The accuracy benchmark's math and bookkeeping on synthetic cameras with known geometry (no data needed)."""
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from guidedmatch.errors import InputError
from guidedmatch.evaluation import accuracy_analysis as aa
from guidedmatch.evaluation import bench_accuracy as ba
from guidedmatch.evaluation.poses import (CameraPose, aligned_centre_errors, error_by_sequence_distance,
                                          evaluate_poses, read_cameras_txt, similarity_align)

K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])


def ring(n=10, seed=0):
    """``n`` cameras on a circle looking at the origin (a capture sequence in name order)."""
    rng = np.random.default_rng(seed)
    cams = {}
    for k in range(n):
        a = 2 * math.pi * k / n
        C = np.array([4 * math.cos(a), 4 * math.sin(a), 0.3 * rng.normal()])
        z = -C / np.linalg.norm(C)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        cams[f"{k:03d}.jpg"] = CameraPose(R, -R @ C, K, (640, 480))
    return cams


def transform(cams, s, R, t):
    """The same cameras in a world moved by ``X' = s R X + t`` (cameras scaled with it)."""
    out = {}
    for n, c in cams.items():
        Rc = c.R @ R.T
        out[n] = CameraPose(Rc, s * c.t - Rc @ t, c.K, c.size)
    return out


similarities = st.tuples(st.floats(0.05, 20.0), st.lists(st.floats(-3, 3), min_size=3, max_size=3),
                         st.lists(st.floats(-100, 100), min_size=3, max_size=3))


@settings(max_examples=25, deadline=None)
@given(similarities)
def test_similarity_align_recovers_a_known_similarity(sim):
    s, rv, t = sim
    R = Rotation.from_rotvec(rv).as_matrix()
    X = np.random.default_rng(1).normal(size=(12, 3))
    s2, R2, t2 = similarity_align(X, s * X @ R.T + t)
    assert s2 == pytest.approx(s, rel=1e-8)
    np.testing.assert_allclose(R2, R, atol=1e-8)
    np.testing.assert_allclose(t2, t, atol=1e-6 * max(1.0, s))


def test_similarity_align_never_returns_a_reflection():
    X = np.random.default_rng(2).normal(size=(10, 3))
    _, R, _ = similarity_align(X, X * [1, 1, -1])   # a mirror image: the best rotation, not the mirror
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_similarity_align_rejects_degenerate_input():
    with pytest.raises(InputError):
        similarity_align(np.zeros((5, 3)), np.ones((5, 3)))
    with pytest.raises(InputError):
        similarity_align(np.zeros((2, 3)), np.zeros((2, 3)))


@settings(max_examples=15, deadline=None)
@given(similarities)
def test_relative_pose_errors_and_aligned_centres_ignore_the_gauge(sim):
    s, rv, t = sim
    gt = ring()
    est = transform(gt, s, Rotation.from_rotvec(rv).as_matrix(), np.array(t))
    ev = evaluate_poses(est, gt)
    assert ev.median_error_deg < 1e-4 and ev.auc["1"] > 0.9999
    al = aligned_centre_errors(est, gt)
    assert al["max_rel"] < 1e-6 and al["scale"] == pytest.approx(1 / s, rel=1e-6)


def test_errors_see_a_perturbed_camera():
    gt = ring()
    est = dict(gt)
    c = gt["003.jpg"]
    dR = Rotation.from_rotvec([0, math.radians(2.0), 0]).as_matrix()
    est["003.jpg"] = CameraPose(dR @ c.R, dR @ c.t, c.K, c.size)   # rotated about its own centre by 2 deg
    ev = evaluate_poses(est, gt)
    bad = [r for r in ev.per_pair if "003.jpg" in (r["name1"], r["name2"])]
    assert all(r["rotation_deg"] == pytest.approx(2.0, abs=1e-6) for r in bad)
    assert all(r["error_deg"] < 1e-6 for r in ev.per_pair if r not in bad)
    al = aligned_centre_errors(est, gt)   # same centres: nothing to see in the positions
    assert al["max_rel"] < 1e-9


def test_error_by_sequence_distance_bins_match_a_loop():
    names = [f"{k}" for k in range(10)]
    rows = [dict(name1=a, name2=b, error_deg=float(abs(int(a) - int(b))))
            for a, b in itertools.combinations(names, 2)]
    groups = error_by_sequence_distance(rows, names, bins=(1, 3, 6))
    for g in groups:
        d = [abs(int(r["name1"]) - int(r["name2"])) for r in rows]
        sel = [r["error_deg"] for r, k in zip(rows, d) if g["lo"] <= k < g["hi"]]
        assert g["pairs"] == len(sel) and g["median_error_deg"] == float(np.median(sel))
    assert [g["lo"] for g in groups] == [1, 3, 6] and sum(g["pairs"] for g in groups) == 45


def test_read_cameras_txt_projects_like_the_format_says(tmp_path):
    cams = ring(4)
    lines = []
    for n, c in cams.items():
        lines.append(" ".join([n, *(f"{v:.17g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2], *c.R.ravel(), *c.t)),
                               "640", "480"]))
    (tmp_path / "cameras.txt").write_text("\n".join(lines) + "\n")
    back = read_cameras_txt(tmp_path / "cameras.txt")
    for n, c in cams.items():
        np.testing.assert_allclose(back[n].R, c.R, atol=1e-12)
        np.testing.assert_allclose(back[n].t, c.t, atol=1e-12)
        np.testing.assert_allclose(back[n].K, K)
    (tmp_path / "bad.txt").write_text("a.jpg 1 2 3\n")
    with pytest.raises(InputError):
        read_cameras_txt(tmp_path / "bad.txt")


def _project(c, X):
    x = (X @ c.R.T + c.t) @ c.K.T
    return x[:, :2] / x[:, 2:]


def test_epipolar_distances_zero_for_true_matches_and_the_offset_for_moved_ones():
    cams = ring(6)
    a, b = cams["000.jpg"], cams["001.jpg"]
    X = np.random.default_rng(3).uniform(-1, 1, size=(50, 3))
    x1, x2 = _project(a, X), _project(b, X)
    assert ba.epipolar_distances(x1, x2, a, b).max() < 1e-6
    # move each x2 by 3 px perpendicular to its epipolar line: the image-2 distance is exactly 3 px
    from guidedmatch.evaluation.poses import relative_pose
    R, t = relative_pose(a, b)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(b.K).T @ tx @ R @ np.linalg.inv(a.K)
    lines = np.c_[x1, np.ones(len(x1))] @ F.T
    nrm = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    d = ba.epipolar_distances(x1, x2 + 3 * nrm, a, b)
    assert d.min() >= 3 - 1e-6   # the max of the two sides: image 2's is 3 px, image 1's whatever it is
    l1 = np.c_[x2 + 3 * nrm, np.ones(len(x2))] @ F
    d1 = np.abs(np.sum(np.c_[x1, np.ones(len(x1))] * l1, 1)) / np.linalg.norm(l1[:, :2], axis=1)
    np.testing.assert_allclose(d, np.maximum(d1, 3.0), atol=1e-6)


def test_aggregate_takes_the_median_of_each_column_over_seeds():
    runs = [dict(registered=r, median_error_deg=e, auc={"1": a1, "2": a1 + 0.1, "5": a1 + 0.2}, mapping_s=m)
            for r, e, a1, m in [(25, 0.5, 0.4, 10.0), (24, 0.7, 0.3, 30.0), (25, 0.6, 0.35, 20.0)]]
    agg = ba.aggregate(runs)
    assert agg["registered"] == 25 and agg["median_error_deg"] == 0.6 and agg["auc"]["1"] == 0.35
    assert agg["auc1_range"] == [0.3, 0.4] and agg["mapping_s"] == 20.0


def test_pooled_drift_pairs_errors_with_their_names():
    names = [f"{k}" for k in range(5)]
    pairs = list(itertools.combinations(names, 2))
    run = {"errors": [float(abs(int(a) - int(b))) if abs(int(a) - int(b)) < 4 else None for a, b in pairs]}
    groups = ba.pooled_drift([run, run], names)
    assert groups[0]["lo"] == 1 and groups[0]["pairs"] == 8 and groups[0]["median_error_deg"] == 1.0
    assert groups[-1]["lo"] == 4 and groups[-1]["median_error_deg"] == math.inf   # None = not registered


def test_intersection_and_free_union_of_inlier_sets():
    rng = np.random.default_rng(4)
    a = np.unique(rng.integers(0, 50, size=(80, 2)), axis=0)
    b = np.unique(rng.integers(0, 50, size=(80, 2)), axis=0)
    both = aa.intersect_inliers(a, b)
    assert {tuple(r) for r in both} == {tuple(r) for r in a} & {tuple(r) for r in b}
    u = aa.union_free(a, b)
    assert len(u) >= len(a) and (u[: len(a)] == a).all()
    extra = u[len(a):]
    assert not np.isin(extra[:, 0], a[:, 0]).any() and not np.isin(extra[:, 1], a[:, 1]).any()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 12), st.integers(2, 30), st.sampled_from([None, 0.8, 0.6]))
def test_global_ratio_test_matches_a_loop(seed, nq, nt, ratio):
    # byte-valued descriptors (SIFT): the GEMM form is exact, so it must agree with a plain loop, ties included
    rng = np.random.default_rng(seed)
    t = rng.integers(0, 4, size=(nt, 8)).astype(np.float32)   # few values: ties are common
    q = rng.integers(0, 4, size=(nq, 8)).astype(np.float32)
    partner = rng.integers(0, nt, size=nq)
    got = aa.global_test(q, t, partner, ratio)
    for k in range(nq):
        d = [math.dist(q[k], t[j]) for j in range(nt)]
        mine = d[partner[k]]
        other = min(d[j] for j in range(nt) if j != partner[k])
        want = mine <= other and (ratio is None or mine < ratio * other)
        assert got[k] == want


def test_verdict_inliers_read_from_the_line_guidedmatch_colmap_prints(tmp_path):
    """The verified inliers before the mapper's selection come from the very line ``guidedmatch colmap`` prints
    (describe_tightening); a run that printed none tightened nothing; ours+cap reads ours'; COLMAP's are its own."""
    from guidedmatch.evaluation.bench_accuracy import verdict_inliers
    from guidedmatch.sfm.stages import describe_tightening

    rec = {"max_error_px": 1.5, "min_inliers": 15, "refit_below_deg": 3.0, "pairs": 28, "pairs_tightened": 27,
           "pairs_refit": 2, "inliers_before": 64_321, "inliers_after": 60_665, "time_s": 0.4}
    for m in ("ours", "ours@refit_below_deg=0"):
        (tmp_path / m).mkdir()
    (tmp_path / "ours" / "match.log").write_text(f"matched ...\nmapper     : {describe_tightening(rec)}\nnext ...\n")
    (tmp_path / "ours@refit_below_deg=0" / "match.log").write_text("matched ...\n")
    assert verdict_inliers("ours", tmp_path, 60_665) == 64_321
    assert verdict_inliers("ours+cap", tmp_path, 23_000) == 64_321
    assert verdict_inliers("ours@refit_below_deg=0", tmp_path, 5) == 5
    assert verdict_inliers("colmap", tmp_path, 44_420) == 44_420
    assert verdict_inliers("ours@inlier_px=0", tmp_path, 7) is None     # no log
