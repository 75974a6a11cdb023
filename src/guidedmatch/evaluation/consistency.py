"""Which verified inlier matches of a COLMAP database agree with a reconstruction built from it.

Two judges. The model: a fundamental matrix cannot see a wrong match that lies on the right epipolar line (a repeated window, a feature
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

The reference cameras (:func:`pair_table`): where poses independent of the matches exist, an inlier farther than
:data:`EPI_WRONG_PX` (4 px) from the reference epipolar line in either image is wrong. This sees neither a wrong
match along the line nor one within 4 px of it, and it is only as good as the reference (distorted images are
undistorted first).
"""
from __future__ import annotations

import itertools
import os
from typing import Any, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .poses import CameraPose

__all__ = ["ModelJudge", "inlier_consistency", "label_errors", "epipolar_distances", "undistort", "pair_table",
           "EPI_WRONG_PX"]

#: an inlier farther than this (px) from a reference epipolar line is wrong (:func:`pair_table`)
EPI_WRONG_PX = 4.0


def label_errors(errors: np.ndarray, ok_px: float = 3.0, wrong_px: float = 10.0) -> dict:
    """Counts of ``errors`` (pixels; NaN = not labelled) within ``ok_px``, beyond ``wrong_px`` and in between.

    >>> label_errors(np.array([0.5, 2.0, 5.0, 40.0, np.nan]))
    {'labelled': 4, 'consistent': 2, 'uncertain': 1, 'wrong': 1}
    """
    e = np.asarray(errors, float)
    lab = np.isfinite(e)
    return {"labelled": int(lab.sum()), "consistent": int((lab & (e <= ok_px)).sum()),
            "uncertain": int((lab & (e > ok_px) & (e <= wrong_px)).sum()), "wrong": int((lab & (e > wrong_px)).sum())}


class ModelJudge:
    """A reconstruction as a judge of matches between its images: per registered image (by name) the 3-D point id
    of each keypoint and the projection into that image (COLMAP's ``cam_from_world``, points behind the camera
    project to NaN)."""

    def __init__(self, reconstruction: Any):
        import pycolmap

        rec = reconstruction if isinstance(reconstruction, pycolmap.Reconstruction) else \
            pycolmap.Reconstruction(str(reconstruction))
        self._images = {img.name: img for img in rec.images.values() if img.has_pose}
        self._cameras = rec.cameras
        self._xyz = {pid: np.asarray(p.xyz) for pid, p in rec.points3D.items()}
        self._point_ids: dict[str, np.ndarray] = {}

    def has(self, name: str) -> bool:
        """``name`` is a registered image of the model."""
        return name in self._images

    def xyz(self, point_id: int) -> np.ndarray:
        """``(3,)`` world position of the model's 3-D point ``point_id``."""
        return self._xyz[int(point_id)]

    def point_ids(self, name: str) -> np.ndarray:
        """``(K,) int64`` 3-D point id of each keypoint of ``name`` (-1: none)."""
        ids = self._point_ids.get(name)
        if ids is None:
            ids = self._point_ids[name] = np.array([p.point3D_id if p.has_point3D() else -1
                                                    for p in self._images[name].points2D], np.int64)
        return ids

    def project(self, name: str, X: np.ndarray) -> np.ndarray:
        """``(P, 2)`` pixels of world points ``X (P, 3)`` in image ``name``; NaN behind the camera."""
        img = self._images[name]
        pose = img.cam_from_world() if callable(getattr(img, "cam_from_world", None)) else img.cam_from_world
        xc = X @ pose.rotation.matrix().T + np.asarray(pose.translation)
        uv = np.full((len(X), 2), np.nan)
        front = xc[:, 2] > 1e-9
        if front.any():
            uv[front] = np.asarray(self._cameras[img.camera_id].img_from_cam(xc[front]), float).reshape(-1, 2)
        return uv

    def errors(self, name1: str, name2: str, matches: np.ndarray, kp1: np.ndarray, kp2: np.ndarray) -> np.ndarray:
        """``(M,)`` pixels between each match's keypoint and where the model puts it: the 3-D point of the image-1
        keypoint projected into image 2 (or, when it has none, that of the image-2 keypoint into image 1); NaN when
        neither keypoint has a 3-D point. ``kp1``, ``kp2``: the images' keypoints ``(K, >=2)``, the model's own."""
        p1, p2 = self.point_ids(name1), self.point_ids(name2)
        if len(p1) != len(kp1) or len(p2) != len(kp2):
            raise ValueError(f"the model's keypoints of {name1} / {name2} are not the given ones (map these "
                             "features, then check them against that model)")
        m = np.asarray(matches, np.int64).reshape(-1, 2)
        e = np.full(len(m), np.nan)
        a, b = p1[m[:, 0]], p2[m[:, 1]]
        use_a = a >= 0
        if use_a.any():  # the image-1 keypoint's 3-D point seen from image 2
            X = np.array([self._xyz[int(p)] for p in a[use_a]])
            e[use_a] = np.linalg.norm(self.project(name2, X) - kp2[m[use_a, 1], :2], axis=1)
        use_b = ~use_a & (b >= 0)
        if use_b.any():  # else the image-2 keypoint's seen from image 1
            X = np.array([self._xyz[int(p)] for p in b[use_b]])
            e[use_b] = np.linalg.norm(self.project(name1, X) - kp1[m[use_b, 0], :2], axis=1)
        return e


def inlier_consistency(database: str | os.PathLike, reconstruction: Any, ok_px: float = 3.0,
                       wrong_px: float = 10.0) -> dict:
    """Label the two-view-geometry inliers of ``database`` with ``reconstruction`` (a ``pycolmap.Reconstruction``
    or its folder) built from the same features (same image names and keypoints).

    Returns ``{"inliers", "labelled", "consistent", "uncertain", "wrong", "wrong_rate", "est_correct",
    "ok_px", "wrong_px"}`` (``wrong_rate`` = wrong / labelled; ``est_correct`` = inliers x consistent / labelled).
    """
    import pycolmap

    judge = ModelJudge(reconstruction)
    db = pycolmap.Database.open(str(database))
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        keypoints = {i: np.asarray(db.read_keypoints(i)) for i, n in names.items() if judge.has(n)}
        inliers = 0
        errors = []
        for a, b in itertools.combinations(sorted(names), 2):
            if not db.exists_two_view_geometry(a, b):
                continue
            m = np.asarray(db.read_two_view_geometry(a, b).inlier_matches, np.int64).reshape(-1, 2)
            inliers += len(m)
            if len(m) and a in keypoints and b in keypoints:
                errors.append(judge.errors(names[a], names[b], m, keypoints[a], keypoints[b]))
    finally:
        db.close()
    counts = label_errors(np.concatenate(errors) if errors else np.zeros(0), ok_px, wrong_px)
    lab = counts["labelled"]
    return dict(inliers=int(inliers), **counts, wrong_rate=counts["wrong"] / lab if lab else float("nan"),
                est_correct=inliers * counts["consistent"] / lab if lab else float("nan"), ok_px=ok_px,
                wrong_px=wrong_px)


# --------------------------------------------------------------------------- judge: reference cameras
def epipolar_distances(kp1: np.ndarray, kp2: np.ndarray, cam1: CameraPose, cam2: CameraPose) -> np.ndarray:
    """``(M,)`` max of the two point-to-epipolar-line distances (px) of matched pixel positions ``kp1``, ``kp2``
    ``(M, 2)`` under the reference cameras (pinhole; undistort first).

    >>> from guidedmatch.evaluation.poses import CameraPose
    >>> K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    >>> a, b = CameraPose(np.eye(3), np.zeros(3), K), CameraPose(np.eye(3), np.array([-1.0, 0, 0]), K)
    >>> epipolar_distances(np.array([[50.0, 50], [50, 50]]), np.array([[10.0, 50], [10, 53]]), a, b).round(6).tolist()
    [0.0, 3.0]
    """
    from .poses import relative_pose

    R, t = relative_pose(cam1, cam2)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(cam2.K).T @ tx @ R @ np.linalg.inv(cam1.K)
    x1 = np.c_[kp1[:, :2], np.ones(len(kp1))]
    x2 = np.c_[kp2[:, :2], np.ones(len(kp2))]
    l2 = x1 @ F.T   # lines in image 2
    l1 = x2 @ F     # lines in image 1
    num = np.abs(np.sum(x2 * l2, axis=1))
    d2 = num / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-12)
    d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
    return np.maximum(d1, d2)


def undistort(kp: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixel positions without the lens distortion ``dist`` (OpenCV ``k1 k2 p1 p2``), same ``K``."""
    if dist is None or len(kp) == 0:
        return kp[:, :2]
    import cv2

    return cv2.undistortPoints(np.ascontiguousarray(kp[:, :2], np.float64).reshape(-1, 1, 2), K, dist,
                               P=K).reshape(-1, 2)


def pair_table(db_path: os.PathLike, ref: dict[str, CameraPose], dist: np.ndarray | None, px: float = EPI_WRONG_PX
               ) -> list[dict]:
    """Per verified pair of a database: ``name1, name2, inliers, epi_ok`` (inliers within ``px`` of the reference
    epipolar lines) and ``angle_deg`` (relative rotation of the reference cameras)."""
    import pycolmap

    from .poses import relative_pose, rotation_error_deg

    db = pycolmap.Database.open(str(db_path))
    rows = []
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        kps: dict[int, np.ndarray] = {}

        def kp(i):
            if i not in kps:
                kps[i] = undistort(np.asarray(db.read_keypoints(i), np.float64), ref[names[i]].K, dist)
            return kps[i]

        pids, counts = db.read_two_view_geometry_num_inliers()
        for pid, n in zip(pids, counts):
            if int(n) == 0:
                continue
            i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
            a, b = names[i1], names[i2]
            if a not in ref or b not in ref:
                continue
            m = np.asarray(db.read_two_view_geometry(i1, i2).inlier_matches, np.int64).reshape(-1, 2)
            d = epipolar_distances(kp(i1)[m[:, 0]], kp(i2)[m[:, 1]], ref[a], ref[b])
            R, _ = relative_pose(ref[a], ref[b])
            rows.append({"name1": min(a, b), "name2": max(a, b), "inliers": len(m), "epi_ok": int((d <= px).sum()),
                         "angle_deg": rotation_error_deg(R, np.eye(3))})
    finally:
        db.close()
    return rows
