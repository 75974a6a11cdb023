"""Relative-pose evaluation (evaluation/poses.py): gauge invariance, known perturbations, failures, AUC, Strecha I/O."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from guidedmatch.datasets import data_root
from guidedmatch.errors import InputError
from guidedmatch.testing.data import needs_data
from guidedmatch.evaluation.poses import (CameraPose, evaluate_poses, pose_auc, read_strecha_camera,
                                          read_strecha_cameras, rotation_error_deg)


def _ring(n=6, seed=0):
    """``n`` cameras on an arc looking at the origin, random small tilts."""
    rng = np.random.default_rng(seed)
    cams = {}
    for i in range(n):
        a = 0.4 * i
        C = np.array([5 * math.sin(a), rng.normal(0, 0.3), -5 * math.cos(a)])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix() @ np.stack([x, y, z])
        cams[f"{i:04d}.png"] = CameraPose(R, -R @ C)
    return cams


def _similarity(cams, s, Q, d):
    """The same cameras in a world frame X' = s Q X + d."""
    return {n: CameraPose(c.R @ Q.T, s * c.t - c.R @ Q.T @ d) for n, c in cams.items()}


finite = st.floats(-10, 10, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(rotvec=arrays(np.float64, 3, elements=st.floats(-3, 3)), d=arrays(np.float64, 3, elements=finite),
       s=st.floats(0.01, 100))
def test_gauge_invariance(rotvec, d, s):
    gt = _ring()
    est = _similarity(gt, s, Rotation.from_rotvec(rotvec).as_matrix(), d)
    ev = evaluate_poses(est, gt)
    assert ev.num_registered == 6 and len(ev.per_pair) == 15
    assert max(r["error_deg"] for r in ev.per_pair) < 1e-4
    assert ev.auc["1"] > 0.9999


@settings(max_examples=30, deadline=None)
@given(axis=arrays(np.float64, 3, elements=st.floats(-1, 1)).filter(lambda a: np.linalg.norm(a) > 0.1),
       angle=st.floats(0.01, 20))
def test_rotation_about_centre_gives_its_angle(axis, angle):
    """Turning camera 3 about its own centre by ``angle`` = a pose error of exactly ``angle`` on its pairs."""
    gt = _ring()
    D = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix()
    est = dict(gt)
    c = gt["0003.png"]
    est["0003.png"] = CameraPose(D @ c.R, D @ c.t)   # same centre
    ev = evaluate_poses(est, gt)
    for r in ev.per_pair:
        if "0003.png" in (r["name1"], r["name2"]):
            assert r["rotation_deg"] == pytest.approx(angle, abs=1e-6)
            assert r["translation_deg"] <= angle + 1e-6
            assert r["error_deg"] == pytest.approx(angle, abs=1e-6)
        else:
            assert r["error_deg"] < 1e-6


def test_moved_centre_against_centre_directions():
    """Translation error = angle between centre differences (slow reference written with centres only)."""
    gt = _ring()
    est = dict(gt)
    c = gt["0002.png"]
    C_new = c.center + np.array([0.3, -0.2, 0.1])
    est["0002.png"] = CameraPose(c.R, -c.R @ C_new)
    ev = evaluate_poses(est, gt)
    for r in ev.per_pair:
        a, b = r["name1"], r["name2"]
        if "0002.png" not in (a, b):
            assert r["error_deg"] < 1e-6
            continue
        o = b if a == "0002.png" else a
        v_gt = gt[o].center - c.center
        v_est = gt[o].center - C_new
        ref = math.degrees(math.acos(np.dot(v_gt, v_est) / np.linalg.norm(v_gt) / np.linalg.norm(v_est)))
        assert r["rotation_deg"] < 1e-6
        assert r["translation_deg"] == pytest.approx(ref, abs=1e-6)


def test_flipped_translation_is_180_not_0():
    gt = _ring(3)
    est = {n: CameraPose(c.R, -c.t) for n, c in gt.items()}     # centres mirrored through the origin
    ev = evaluate_poses(est, gt)
    assert all(r["translation_deg"] > 90 for r in ev.per_pair)


def test_unregistered_are_failures():
    gt = _ring(5)
    est = {n: c for n, c in gt.items() if n not in ("0001.png", "0004.png")}
    est["unknown.png"] = gt["0000.png"]       # names outside the GT are ignored
    ev = evaluate_poses(est, gt)
    assert ev.num_registered == 3 and ev.unregistered == ["0001.png", "0004.png"]
    fails = [r for r in ev.per_pair if math.isinf(r["error_deg"])]
    assert len(fails) == 10 - 3                # only the 3 pairs among registered images are scored
    assert ev.auc["5"] == pytest.approx(3 / 10)
    assert math.isinf(ev.median_error_deg)
    d = ev.to_dict()
    assert d["num_pairs"] == 10 and len(d["per_pair"]) == 10


@settings(max_examples=60, deadline=None)
@given(errors=st.lists(st.one_of(st.floats(0, 20), st.just(math.inf)), min_size=1, max_size=30),
       T=st.floats(0.1, 10))
def test_auc_against_numeric_integral(errors, T):
    """AUC = (1/T) * integral_0^T recall(e) de, checked by a fine Riemann sum of the step recall."""
    grid = (np.arange(200_000) + 0.5) * (T / 200_000)
    e = np.array(errors)
    recall = (e[None, :] <= grid[:, None]).mean(axis=1) if len(grid) * len(e) < 7e6 else None
    if recall is None:
        recall = np.array([(e <= g).mean() for g in grid])
    assert pose_auc(errors, [T])[0] == pytest.approx(recall.mean(), abs=2e-4)


def test_rotation_error_symmetry_and_range():
    rng = np.random.default_rng(1)
    for _ in range(20):
        A, B = Rotation.random(2, random_state=rng).as_matrix()
        e = rotation_error_deg(A, B)
        assert 0 <= e <= 180 and e == pytest.approx(rotation_error_deg(B, A), abs=1e-9)
        ref = np.degrees(np.linalg.norm(Rotation.from_matrix(A.T @ B).as_rotvec()))
        assert e == pytest.approx(ref, abs=1e-5)


def test_bad_inputs():
    with pytest.raises(InputError):
        CameraPose(np.eye(3) * 2, np.zeros(3))
    with pytest.raises(InputError):
        CameraPose(np.eye(3), np.array([0, np.nan, 0]))
    with pytest.raises(InputError):
        evaluate_poses({}, {"a": CameraPose(np.eye(3), np.zeros(3))})


def test_bad_camera_file(tmp_path):
    p = tmp_path / "x.jpg.camera"
    p.write_text("1 2 3\n")
    with pytest.raises(InputError):
        read_strecha_camera(p)
    with pytest.raises(InputError):
        read_strecha_cameras(tmp_path / "nothing")


@needs_data("pose_pairs/strecha/strecha_pairs_with_gt.txt", "pose_pairs/strecha/Herz-Jesus-P8/gt_dense_cameras/*.camera")
def test_strecha_cameras_agree_with_the_pairs_file():
    """The .camera convention (R camera-to-world, centre) reproduces the independent SuperGlue-style pairs file."""
    from guidedmatch.evaluation.poses import relative_pose

    base = data_root() / "pose_pairs" / "strecha"
    cams = read_strecha_cameras(base / "Herz-Jesus-P8" / "gt_dense_cameras")
    assert len(cams) == 8 and cams["0000.jpg"].size == (3072, 2048)
    n = 0
    for line in (base / "strecha_pairs_with_gt.txt").read_text().splitlines():
        tok = line.split()
        if not tok:
            continue
        a, b = tok[0].split("/")[-1], tok[1].split("/")[-1]
        T = np.array(tok[22:38], float).reshape(4, 4)
        R, t = relative_pose(cams[a], cams[b])
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-6)
        np.testing.assert_allclose(t, T[:3, 3], atol=1e-5)
        np.testing.assert_allclose(cams[a].K, np.array(tok[4:13], float).reshape(3, 3))
        n += 1
    assert n == 18


def _reconstruction(cams, size=(640, 480), f=500.0):
    """A pycolmap.Reconstruction holding ``cams`` as registered images (no points)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", f, *size))
    for i, (name, c) in enumerate(sorted(cams.items()), 1):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i), pose)
    return rec


def test_reconstruction_poses_and_its_gauge():
    """poses_from_reconstruction reads cam_from_world; a similarity transform of the model changes no error."""
    import pycolmap

    from guidedmatch.evaluation.poses import poses_from_reconstruction

    gt = _ring()
    rec = _reconstruction(gt)
    got = poses_from_reconstruction(rec)
    for n, c in gt.items():
        np.testing.assert_allclose(got[n].R, c.R, atol=1e-9)
        np.testing.assert_allclose(got[n].t, c.t, atol=1e-9)
        assert got[n].K[0, 0] == 500.0 and got[n].size == (640, 480)
    rec.transform(pycolmap.Sim3d(3.7, pycolmap.Rotation3d(Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix()),
                                 np.array([5.0, -2.0, 1.0])))
    moved = poses_from_reconstruction(rec)
    assert np.abs(moved["0001.png"].t - gt["0001.png"].t).max() > 0.1      # the transform did move the model
    ev = evaluate_poses(rec, gt)
    assert max(r["error_deg"] for r in ev.per_pair) < 1e-6


def test_rendered_collection_ground_truth():
    """The rendered multi-view collection's cameras (known poses) evaluated against themselves through a pycolmap
    model with one camera deregistered: 0 error on the pairs of registered views, the rest failures."""
    mv = pytest.importorskip("guidedmatch.testing.multiview")
    scene = mv.make_multiview(n_views=5, size=(320, 240), seed=1, isolated=False)
    gt = {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)}
    rec = _reconstruction({n: c for n, c in gt.items() if n != scene.names[2]}, size=(320, 240))
    ev = evaluate_poses(rec, gt)
    assert ev.unregistered == [scene.names[2]] and ev.num_registered == 4
    finite = [r["error_deg"] for r in ev.per_pair if math.isfinite(r["error_deg"])]
    assert len(finite) == 6 and max(finite) < 1e-6
    assert ev.auc["1"] == pytest.approx(6 / 10, abs=1e-6)
