"""The mapper's inliers selected without the lens distortion (accuracy history, twenty-second round): an oracle probe
of whether fox's distortion (k1 = 0.058, up to ~9 px at the border) is what costs its poses.

Usage::

    python tools/undistorted_inliers.py SCENE RAW_DB OUT_DB [--px 1.5] [--refit-below-deg 3] [--undistort]

RAW_DB: a database of ``guidedmatch colmap DB --inlier-px 0`` (every verified inlier at the verdict's 3 px, the
rows' F as the matcher left them). OUT_DB: a copy, whose rows are re-selected by
``ColmapSink.tighten_inliers(PX, refit_below_deg=DEG)`` -- the defaults' selection. With ``--undistort`` the copy's
keypoints are first replaced by their undistorted positions (the scene's ``distortion.txt`` and reference K, from
``GUIDEDMATCH_DATA``), the selection (and any refit F) runs on those, and the original keypoints are written back:
only which inliers each row keeps differs, the mapper sees the same keypoints. Prints the selection's report.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np


def _swap_keypoints(db_path: Path, new_xy) -> dict[int, np.ndarray]:
    """Write ``new_xy(image_id, name, keypoints)`` as the x, y of every image's keypoints in the database; returns
    the previous keypoints."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    old = {}
    try:
        for img in db.read_all_images():
            iid = int(img.image_id)
            old[iid] = np.asarray(db.read_keypoints(iid), np.float32).copy()
            kp = old[iid].copy()
            kp[:, :2] = new_xy(iid, img.name, old[iid])
            with pycolmap.DatabaseTransaction(db):
                db.update_keypoints(iid, kp)
    finally:
        db.close()
    return old


def main() -> None:
    import guidedmatch  # noqa: F401  (sets up the runtime before pycolmap)

    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.evaluation.accuracy_scenes import distortion, reference_cameras
    from guidedmatch.evaluation.consistency import undistort

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("raw_db", type=Path)
    ap.add_argument("out_db", type=Path)
    ap.add_argument("--px", type=float, default=1.5)
    ap.add_argument("--refit-below-deg", type=float, default=3.0)
    ap.add_argument("--undistort", action="store_true")
    a = ap.parse_args()
    root = Path(os.environ.get("GUIDEDMATCH_DATA", "../shared/data"))
    shutil.copyfile(a.raw_db, a.out_db)
    old = None
    if a.undistort:
        ref, dist = reference_cameras(root, a.scene), distortion(root, a.scene)
        if dist is None:
            raise SystemExit(f"{a.scene}: no distortion.txt")
        # COLMAP pixels (centre at +0.5) -> OpenCV pixels, undistorted, back
        old = _swap_keypoints(a.out_db, lambda iid, name, kp: undistort(kp[:, :2].astype(np.float64) - 0.5,
                                                                        ref[name].K, dist) + 0.5)
    with ColmapSink(a.out_db, geometry="ours") as sink:
        report = sink.tighten_inliers(a.px, refit_below_deg=a.refit_below_deg)
    if old is not None:
        _swap_keypoints(a.out_db, lambda iid, name, kp: old[iid][:, :2])
    report.pop("time_s", None)
    print(json.dumps({"scene": a.scene, "undistort": a.undistort, **report}))


if __name__ == "__main__":
    main()
