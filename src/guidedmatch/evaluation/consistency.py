"""Which verified inlier matches of a COLMAP database agree with a reconstruction built from it.

A fundamental matrix cannot see a wrong match that lies on the right epipolar line (a repeated window, a feature
of the same row of a facade): it passes the two-view check and is counted as a "verified inlier". A third view
can see it. After mapping, every registered image has a pose and many keypoints a 3-D point, so each inlier
``(i in image A, j in image B)`` of a two-view geometry can be checked: the 3-D point of ``i`` (or, when ``i`` has
none, that of ``j``) is projected into the other image and compared with the matched keypoint. A correct match
lands within a pixel or two (the model's reprojection error); a wrong one lands far away along the line.

* **consistent**: within ``ok_px`` (3 px); **wrong**: farther than ``wrong_px`` (10 px); in between: uncertain;
* inliers with no 3-D point on either side, or in a pair with an unregistered image, are not labelled;
* ``est_correct`` = inliers x consistent / labelled: the verified inliers one can expect to be right.

The judge can be the method's own model or any model mapped from the same features (same image names and
keypoint indices). ``guidedmatch bench sfm`` judges every row with the model of COLMAP's exhaustive matches
(:func:`guidedmatch.evaluation.bench_sfm.judge_with_colmap_model`): a method's own wrong matches also made some of
its own tracks, which then flag right matches (Herz-Jesus-P8 at 8192, guidedmatch so+epi+ia: 4.1 % wrong by its
own model, 2.5 % by COLMAP's). By COLMAP's model, at 8192 / ~68k features: COLMAP exhaustive 0.13 % / 0.08 %,
COLMAP guided matching 1.6 % (8192), guidedmatch so+epi+ia 2.5 % / 1.6 %.
"""
from __future__ import annotations

import itertools
import os
from typing import Any

import numpy as np

__all__ = ["inlier_consistency", "label_errors"]


def label_errors(errors: np.ndarray, ok_px: float = 3.0, wrong_px: float = 10.0) -> dict:
    """Counts of ``errors`` (pixels; NaN = not labelled) within ``ok_px``, beyond ``wrong_px`` and in between.

    >>> label_errors(np.array([0.5, 2.0, 5.0, 40.0, np.nan]))
    {'labelled': 4, 'consistent': 2, 'uncertain': 1, 'wrong': 1}
    """
    e = np.asarray(errors, float)
    lab = np.isfinite(e)
    return {"labelled": int(lab.sum()), "consistent": int((lab & (e <= ok_px)).sum()),
            "uncertain": int((lab & (e > ok_px) & (e <= wrong_px)).sum()), "wrong": int((lab & (e > wrong_px)).sum())}


def _projector(image: Any, camera: Any):
    pose = image.cam_from_world() if callable(getattr(image, "cam_from_world", None)) else image.cam_from_world
    R, t = pose.rotation.matrix(), np.asarray(pose.translation)

    def project(X: np.ndarray) -> np.ndarray:
        xc = X @ R.T + t
        uv = np.full((len(X), 2), np.nan)
        front = xc[:, 2] > 1e-9
        if front.any():
            uv[front] = np.asarray(camera.img_from_cam(xc[front]), float).reshape(-1, 2)
        return uv

    return project


def inlier_consistency(database: str | os.PathLike, reconstruction: Any, ok_px: float = 3.0,
                       wrong_px: float = 10.0) -> dict:
    """Label the two-view-geometry inliers of ``database`` with ``reconstruction`` (a ``pycolmap.Reconstruction``
    or its folder) built from the same database (same image names and keypoints).

    Returns ``{"inliers", "labelled", "consistent", "uncertain", "wrong", "wrong_rate", "est_correct",
    "ok_px", "wrong_px"}`` (``wrong_rate`` = wrong / labelled; ``est_correct`` = inliers x consistent / labelled).
    """
    import pycolmap

    rec = reconstruction if isinstance(reconstruction, pycolmap.Reconstruction) else \
        pycolmap.Reconstruction(str(reconstruction))
    by_name = {img.name: img for img in rec.images.values() if img.has_pose}
    xyz = {pid: np.asarray(p.xyz) for pid, p in rec.points3D.items()}
    db = pycolmap.Database.open(str(database))
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        point_ids, keypoints, projectors = {}, {}, {}
        for image_id, name in names.items():
            img = by_name.get(name)
            if img is None:
                continue
            point_ids[image_id] = np.array([p.point3D_id if p.has_point3D() else -1 for p in img.points2D], np.int64)
            keypoints[image_id] = np.asarray(db.read_keypoints(image_id))[:, :2]
            projectors[image_id] = _projector(img, rec.cameras[img.camera_id])
        inliers = 0
        errors = []
        for a, b in itertools.combinations(sorted(names), 2):
            if not db.exists_two_view_geometry(a, b):
                continue
            m = np.asarray(db.read_two_view_geometry(a, b).inlier_matches, np.int64).reshape(-1, 2)
            inliers += len(m)
            if len(m) == 0 or a not in projectors or b not in projectors:
                continue
            if len(point_ids[a]) != len(keypoints[a]) or len(point_ids[b]) != len(keypoints[b]):
                raise ValueError(f"{database}: the reconstruction's keypoints of {names[a]} / {names[b]} are not the "
                                 "database's (map this database, then check it against that model)")
            e = np.full(len(m), np.nan)
            pa, pb = point_ids[a][m[:, 0]], point_ids[b][m[:, 1]]
            use_a = pa >= 0
            if use_a.any():  # i's 3-D point seen from B
                X = np.array([xyz[int(p)] for p in pa[use_a]])
                e[use_a] = np.linalg.norm(projectors[b](X) - keypoints[b][m[use_a, 1]], axis=1)
            use_b = ~use_a & (pb >= 0)
            if use_b.any():  # else j's 3-D point seen from A
                X = np.array([xyz[int(p)] for p in pb[use_b]])
                e[use_b] = np.linalg.norm(projectors[a](X) - keypoints[a][m[use_b, 0]], axis=1)
            errors.append(e)
    finally:
        db.close()
    counts = label_errors(np.concatenate(errors) if errors else np.zeros(0), ok_px, wrong_px)
    lab = counts["labelled"]
    return dict(inliers=int(inliers), **counts, wrong_rate=counts["wrong"] / lab if lab else float("nan"),
                est_correct=inliers * counts["consistent"] / lab if lab else float("nan"), ok_px=ok_px,
                wrong_px=wrong_px)
