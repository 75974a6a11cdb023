"""Oracle probe on fox (accuracy history, twenty-second round): re-select the mapper's inliers of every F row from
the pair's raw matches, with F refit on the row's current inliers, in raw ('control') or undistorted ('oracle': the
scene's ``distortion.txt`` and reference K under ``GUIDEDMATCH_DATA``) pixel coordinates, within PX px (Sampson), at
least 15 closest. Planar rows and rows with <= 15 inliers untouched.

    python tools/raw_match_reselect.py DATABASE control|oracle PX [SCENE]     # SCENE default fox
"""
import json
import os
import sys
from pathlib import Path

import cv2
import numpy as np

import guidedmatch  # noqa: F401  (sets up the runtime before pycolmap)
import pycolmap
from guidedmatch.epipolar import sampson_distance
from guidedmatch.evaluation.accuracy_scenes import distortion, reference_cameras
from guidedmatch.evaluation.consistency import undistort
from guidedmatch.geometry import closest_inliers

db_path, mode, px = sys.argv[1], sys.argv[2], float(sys.argv[3])
scene = sys.argv[4] if len(sys.argv) > 4 else "fox"
root = Path(os.environ.get("GUIDEDMATCH_DATA", "../shared/data"))
ref, dist = (reference_cameras(root, scene), distortion(root, scene)) if mode == "oracle" else ({}, None)

db = pycolmap.Database.open(db_path)
names = {int(img.image_id): img.name for img in db.read_all_images()}
kps = {}


def pts(iid):
    if iid not in kps:
        x = np.asarray(db.read_keypoints(iid))[:, :2].astype(np.float64)   # COLMAP pixels (centre at .5)
        if mode == "oracle":
            x = undistort(x - 0.5, ref[names[iid]].K, dist) + 0.5
        kps[iid] = x
    return kps[iid]


pids, counts = (np.asarray(a) for a in db.read_two_view_geometry_num_inliers())
rep = {"rows": 0, "rewritten": 0, "before": int(counts.sum()), "after": 0, "med_err_in": []}
for pid, c in zip(pids, counts):
    if c <= 15:
        rep["after"] += int(c)
        continue
    i1, i2 = (int(i) for i in pycolmap.pair_id_to_image_pair(int(pid)))
    g = db.read_two_view_geometry(i1, i2)
    if int(g.config) in (4, 5, 6) or g.F is None or not np.any(g.F):
        rep["after"] += int(c)
        continue
    rep["rows"] += 1
    m_in = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
    m_all = np.asarray(db.read_matches(i1, i2), dtype=np.int64).reshape(-1, 2)
    p1, p2 = pts(i1), pts(i2)
    try:
        F, mask = cv2.findFundamentalMat(p1[m_in[:, 0]], p2[m_in[:, 1]], cv2.USAC_MAGSAC, 1.0, 0.9999, 10000)
    except cv2.error:
        F = None
    if F is None or F.shape != (3, 3):
        rep["after"] += int(c)
        continue
    e_in = sampson_distance(F, p1[m_in[:, 0]], p2[m_in[:, 1]])
    rep["med_err_in"].append(float(np.median(e_in)))
    err = sampson_distance(F, p1[m_all[:, 0]], p2[m_all[:, 1]])
    idx = closest_inliers(err, px, 15)
    g.inlier_matches = np.ascontiguousarray(m_all[idx], dtype=np.uint32).reshape(-1, 2)
    with pycolmap.DatabaseTransaction(db):
        db.update_two_view_geometry(i1, i2, g)
    rep["rewritten"] += 1
    rep["after"] += len(idx)
rep["med_err_in"] = float(np.median(rep["med_err_in"]))
db.close()
print(json.dumps(rep))
