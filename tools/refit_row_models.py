"""Refit each F row's fundamental matrix on its own verified inliers, then keep the inliers within PX of the refit
(at least 15 per pair) -- the "stored F refit" experiment of the accuracy history's fifteenth round (not kept).

With one model fit per pair (``num_updates=1``) the F a row carries is the early fit; this asks whether tightening
around a refit F gives the mapper better inliers. Run it on a ``guidedmatch colmap DB --inlier-px 0`` database (every
verified inlier); planar rows (configuration 4-6) are tightened around their stored model as ``--inlier-px`` does.
With MAX_DEG, only the F rows whose median triangulation angle is below MAX_DEG are refit (small baselines, where the
early F is least determined; the angle from E = K2^T F K1 with the database's camera guesses, ``cv2.recoverPose`` and
the inliers triangulated), the others tightened around their stored F.

    python tools/refit_row_models.py UNTIGHTENED.db OUT.db [PX=1.5 [MAX_DEG]]

The MAX_DEG variant is now the sink's own tightening (``guidedmatch colmap --refit-below-deg 3``, the default;
``ColmapSink.tighten_inliers``), with the pose of E chosen without ``cv2.recoverPose``'s 50-baseline limit, a seeded
MAGSAC++ and only rows with some inlier beyond PX looked at (idempotent); on the fifteenth round's fox database it
keeps 763,141 inliers where this tool kept 763,966 (1,907 of 2,002 rows equal). This tool stays as the record of
that round's prototype.

OUT.db is a copy of UNTIGHTENED.db with the rows rewritten; prints the residuals before / after and the counts.
"""
from __future__ import annotations

import shutil
import sys
import time

import cv2
import numpy as np
import pycolmap

from guidedmatch.collection.sinks import _model_error
from guidedmatch.epipolar import sampson_distance
from guidedmatch.geometry import closest_inliers


def triangulation_angle_deg(F, x1, x2, K1, K2) -> float:
    """Median angle (degrees) between the two viewing rays of the inliers ``x1 <-> x2`` under the pose of
    ``E = K2^T F K1`` (``cv2.recoverPose``); NaN when the pose cannot be recovered."""
    n1 = cv2.undistortPoints(x1.reshape(-1, 1, 2), K1, None).reshape(-1, 2)
    n2 = cv2.undistortPoints(x2.reshape(-1, 1, 2), K2, None).reshape(-1, 2)
    try:
        _, R, t, _ = cv2.recoverPose(K2.T @ F @ K1, n1, n2, np.eye(3))
    except cv2.error:
        return float("nan")
    X = cv2.triangulatePoints(np.c_[np.eye(3), np.zeros(3)], np.c_[R, t], n1.T, n2.T)
    X = (X[:3] / X[3]).T
    r2 = X + (R.T @ t.ravel())   # ray from the second centre, -R^T t
    cos = np.sum(X * r2, 1) / (np.linalg.norm(X, axis=1) * np.linalg.norm(r2, axis=1) + 1e-12)
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))


def main(src: str, out: str, px: float = 1.5, max_deg: float | None = None) -> None:
    for suffix in ("", "-wal", "-shm"):
        try:
            shutil.copyfile(src + suffix, out + suffix)
        except FileNotFoundError:
            pass
    db = pycolmap.Database.open(out)
    images = {img.image_id: img for img in db.read_all_images()}
    cams = {c.camera_id: c for c in db.read_all_cameras()}
    kp = {i: np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64) for i in images}

    def K(i):
        f, cx, cy = np.asarray(cams[images[i].camera_id].params)[:3]
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])

    old_all, new_all, refit_rows, before, after = [], [], 0, 0, 0
    t0 = time.time()
    for pid, g in zip(*db.read_two_view_geometries()):
        m = np.asarray(g.inlier_matches)
        if len(m) < 15:
            continue
        i1, i2 = pycolmap.pair_id_to_image_pair(pid)
        x1, x2 = kp[i1][m[:, 0]], kp[i2][m[:, 1]]
        e_old = _model_error(g, x1, x2)
        if e_old is None:
            continue
        before += len(m)
        e_new, F_new = e_old, None
        if (int(g.config) not in (4, 5, 6) and g.F is not None and np.any(g.F) and len(m) >= 16
                and (max_deg is None or triangulation_angle_deg(np.asarray(g.F), x1, x2, K(i1), K(i2)) < max_deg)):
            try:
                F, _ = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 1.0, 0.9999, 10000)
            except cv2.error:
                F = None
            if F is not None and F.shape == (3, 3):
                e = sampson_distance(F, x1, x2)
                if np.median(e) <= np.median(e_old):   # the refit only where it fits these inliers better
                    e_new, F_new = e, F
            refit_rows += 1
        old_all.append(e_old)
        new_all.append(e_new)
        keep = closest_inliers(e_new, px, 15)
        after += len(keep)
        if F_new is not None or len(keep) < len(m):
            if F_new is not None:
                g.F = F_new
            g.inlier_matches = np.ascontiguousarray(m[keep], dtype=np.uint32)
            db.update_two_view_geometry(i1, i2, g)
    db.close()
    a, b = np.concatenate(old_all), np.concatenate(new_all)
    print(f"{refit_rows} F rows selected for a refit (kept where it fits better) in {time.time() - t0:.1f} s; median error stored F {np.median(a):.3f} -> "
          f"refit {np.median(b):.3f} px; within 1.5 px {np.mean(a <= 1.5):.3f} -> {np.mean(b <= 1.5):.3f}; "
          f"inliers {before} -> kept {after} at {px} px")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]) if len(sys.argv) > 3 else 1.5,
         float(sys.argv[4]) if len(sys.argv) > 4 else None)
