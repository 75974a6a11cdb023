"""The rendered multi-view collection: poses, homographies and overlap agree with each other (exact ground truth)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.testing.multiview import make_multiview, write_views


@pytest.fixture(scope="module")
def mv():
    return make_multiview()


def _plane_points(scene, i, rng, n=300):
    """Pixels of view i on some plane, with their plane label."""
    lab = scene.labels[i]
    ys, xs = np.nonzero(lab >= 0)
    k = rng.choice(len(xs), size=min(n, len(xs)), replace=False)
    return np.c_[xs[k], ys[k]].astype(float), lab[ys[k], xs[k]]


def _check_epipolar(scene, i, j, rng):
    """Points moved i -> j by the per-plane homographies lie on the epipolar lines of F_ij (poses vs. renders)."""
    two = scene.two_view(i, j)
    pts, _ = _plane_points(scene, i, rng)
    proj, vis = two.project(pts)
    if vis.sum() < 10:
        return 0
    x1 = np.c_[pts[vis], np.ones(vis.sum())]
    x2 = np.c_[proj[vis], np.ones(vis.sum())]
    F = scene.fundamental(i, j)
    l2 = x1 @ F.T
    d = np.abs(np.sum(x2 * l2, 1)) / np.hypot(l2[:, 0], l2[:, 1])
    assert np.max(d) < 1e-6 * max(scene.size)
    return int(vis.sum())


def test_default_collection(mv, rng):
    n = len(mv)
    assert n >= 6 and mv.size == (640, 480)
    assert mv.isolated == (n - 1,)
    # the connected sequence: neighbours overlap strongly, the ends not at all
    for i in range(n - 2):
        assert mv.overlap[i, i + 1] > 0.3
    assert (0, n - 2) in mv.non_overlapping_pairs()
    assert all((i, n - 1) in mv.non_overlapping_pairs() for i in range(n - 1))
    for i in range(n):
        assert mv.images[i].dtype == np.uint8 and mv.images[i].std() > 20  # textured, not blank
        assert np.isclose(np.linalg.det(mv.R[i]), 1.0) and np.allclose(mv.R[i] @ mv.R[i].T, np.eye(3))
    assert sum(_check_epipolar(mv, i, i + 1, rng) for i in range(n - 2)) > 600


def test_relative_pose_composes(mv):
    R02, t02 = mv.relative_pose(0, 2)
    R01, t01 = mv.relative_pose(0, 1)
    R12, t12 = mv.relative_pose(1, 2)
    assert np.allclose(R12 @ R01, R02) and np.allclose(R12 @ t01 + t12, t02)
    X = np.array([0.3, -0.2, 8.0])  # world point -> camera 2 directly and through camera 0
    X0 = mv.R[0] @ X + mv.t[0]
    assert np.allclose(R02 @ X0 + t02, mv.R[2] @ X + mv.t[2])
    assert np.allclose(mv.center(1), -mv.R[1].T @ mv.t[1])


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 5))
def test_random_collections_consistent(seed, n):
    scene = make_multiview(n, (200, 150), seed=seed, spacing=1.5, isolated=True)
    rng = np.random.default_rng(seed)
    assert len(scene) == n + 1 and scene.isolated == (n,)
    for i in range(n - 1):
        _check_epipolar(scene, i, i + 1, rng)
        assert scene.overlapping(i, i + 1)
    assert np.allclose(np.diag(scene.overlap), 1.0)


def test_write_views(mv, tmp_path):
    import cv2

    paths = write_views(mv, tmp_path / "imgs")
    assert [p.name for p in paths] == list(mv.names)
    for p, img in zip(paths, mv.images):
        assert np.array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), img)  # PNG: lossless
    jpgs = write_views(mv, tmp_path / "jpg", ext=".jpg")
    assert all(p.suffix == ".jpg" and p.stat().st_size > 0 for p in jpgs)
