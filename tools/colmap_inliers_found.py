"""How many of COLMAP's inliers the matcher's own output contains, pair by pair, under matcher variants: which step
loses the COLMAP inliers we lack (accuracy history, twenty-third round).

    python tools/colmap_inliers_found.py CACHE/SCENE NPAIRS '{"base": {}, "epi": {"_mode": "epi"}, ...}'

NPAIRS random pairs (``random.seed(0)``) that both databases verify; every image prepared and indexed first; one
thread; each variant is matcher settings over the collection defaults (``"_mode"``: the mode, default so+epi+ia).
Prints per variant: COLMAP's inliers, how many of them the result's matches contain, the matches and inliers; for
the base variant also where the missing ones lie from the epipolar line of the pair's final F (cumulative counts).
"""
from __future__ import annotations

import collections
import json
import random
import sys
from pathlib import Path

import numpy as np

from guidedmatch import kernels  # noqa: F401 -- before faiss (OpenBLAS set-up)
from guidedmatch.collection.config import collection_matcher_config
from guidedmatch.evaluation.accuracy_analysis import _keys, read_geometries
from guidedmatch.matcher import match

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pair_phase_times import prepared_images  # noqa: E402


def sampled_pairs(folder: Path, npairs: int):
    """One thread for every kernel; ``npairs`` random pairs (``random.seed(0)``) both databases of the scene folder
    verify, as ``(name1, name2, COLMAP's inliers)``, and every image of them prepared and indexed."""
    import cv2
    import faiss
    import pycolmap

    kernels.limit_threads_here(1)
    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    col = read_geometries(folder / "colmap" / "database.db")
    ours_db = folder / "ours" / "database.db"
    ours = read_geometries(ours_db)
    db = pycolmap.Database.open(str(ours_db))
    names = {int(i.image_id): i.name for i in db.read_all_images()}
    db.close()
    random.seed(0)
    pairs = [(names[p[0]], names[p[1]], col[p]) for p in random.sample(sorted(set(col) & set(ours)), npairs)]
    return pairs, prepared_images(str(ours_db), [(a, b) for a, b, _ in pairs])


def main() -> None:
    folder, npairs, variants = Path(sys.argv[1]), int(sys.argv[2]), json.loads(sys.argv[3])
    pairs, prep = sampled_pairs(folder, npairs)
    for name, over in variants.items():
        over = dict(over)
        mode = over.pop("_mode", "so+epi+ia")
        cfg = collection_matcher_config(over or None)
        tot, far = collections.Counter(), collections.Counter()
        for a, b, cm in pairs:
            r = match(prep[a], prep[b], mode, cfg)
            m = np.asarray(r.pairs, np.int64)
            found = np.isin(_keys(cm), _keys(m))
            tot["colmap"] += len(cm)
            tot["found"] += int(found.sum())
            tot["matches"] += len(m)
            tot["inliers"] += int(r.geometry.num_inliers)
            F = r.geometry.F
            if name == "base" and F is not None and (~found).any():
                x1 = np.c_[prep[a].features.keypoints[cm[~found, 0]], np.ones((~found).sum())]
                x2 = np.c_[prep[b].features.keypoints[cm[~found, 1]], np.ones((~found).sum())]
                line = x1 @ np.asarray(F).T
                d = np.abs((line * x2).sum(1)) / np.hypot(line[:, 0], line[:, 1])
                for t in (1.5, 3.0, 5.0, 8.0):
                    far[f"<= {t} px"] += int((d <= t).sum())
                far["all"] += len(d)
        print(name, dict(tot), flush=True)
        if far:
            print("  missing, distance to the final F's epipolar line:", dict(far), flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main()
