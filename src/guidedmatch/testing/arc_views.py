"""Synthetic features of a small collection, without images: cameras on an arc looking at one point cloud, each
view's keypoints the projections of the points it sees (the collection engine, streaming and determinism tests).

The cameras stand ``0.5`` apart along x (each ``0.1`` further along y and rolled ``0.05`` rad more than the one
before), looking at ``(0, 0, 7.5)``; a point is kept in a view with probability 0.85 when it projects inside the
image.
Keypoints get 0.3 px Gaussian noise, descriptors (float32, one 128-D row per 3-D point, integers 0..119) Gaussian
noise of sigma 4 clipped to 0..255 -- so the correct correspondences are known (the same 3-D point) and the views
overlap. Optionally one more view, ``"other.jpg"``, of unrelated random points and descriptors.

Camera convention of :mod:`guidedmatch.testing.twoview` (:func:`~guidedmatch.testing.twoview.look_at_rotation`,
:func:`~guidedmatch.testing.twoview.project`); pixels follow OpenCV.
"""
from __future__ import annotations

import numpy as np

from ..features import Features
from .twoview import intrinsics_matrix, look_at_rotation, project

__all__ = ["ARC_SIZE", "arc_views"]

#: image size of every view, ``(w, h)`` pixels
ARC_SIZE = (800, 600)


def arc_views(n_views: int = 4, n_points: int = 1000, seed: int = 0, *, shuffle: bool = True, unrelated: int = 0,
              fractional_unrelated: bool = False) -> dict[str, Features]:
    """``{"view0.jpg": Features, ...}``: ``n_views`` overlapping views of ``n_points`` 3-D points (module doc).

    ``shuffle``: each view's keypoints in a random order (else in the order of the 3-D points). ``unrelated``: that
    many random keypoints in one more view, ``"other.jpg"``, with descriptors of integers 0..119 -- plus a uniform
    fraction in [0, 1) each with ``fractional_unrelated`` (descriptors that are not byte-valued). Deterministic in
    ``seed``.
    """
    size = ARC_SIZE
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2.5, -2.0, 6.0], [2.5, 2.0, 9.0], (n_points, 3))
    desc = rng.integers(0, 120, (n_points, 128)).astype(np.float32)
    K = intrinsics_matrix(700.0, size)
    out = {}
    for v in range(n_views):
        c = np.array([0.5 * (v - (n_views - 1) / 2), 0.1 * v, 0.0])
        R = look_at_rotation(c, (0.0, 0.0, 7.5), roll=0.05 * v)
        x, z = project(K, R, c, X)
        ok = (z > 0) & (x[:, 0] >= 0) & (x[:, 0] < size[0]) & (x[:, 1] >= 0) & (x[:, 1] < size[1])
        keep = np.flatnonzero(ok & (rng.random(n_points) < 0.85))
        if shuffle:
            keep = keep[rng.permutation(len(keep))]
        d = desc[keep] + rng.normal(0, 4.0, (len(keep), 128)).astype(np.float32)
        out[f"view{v}.jpg"] = Features(x[keep] + rng.normal(0, 0.3, (len(keep), 2)), np.clip(d, 0, 255), size)
    if unrelated:
        n = int(unrelated)
        xy = rng.uniform(0, 1, (n, 2)) * size
        d = rng.integers(0, 120, (n, 128)).astype(np.float32)
        if fractional_unrelated:
            d = d + rng.random((n, 128)).astype(np.float32)
        out["other.jpg"] = Features(xy, d, size)
    return out
