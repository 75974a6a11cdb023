"""Verified pairs and inliers of matched databases by the distance of their two images along the capture (name
order): which methods give the mapper short-range and which long-range constraints (the accuracy history's
fifteenth round, fox).

    python tools/inliers_by_capture_distance.py SCENE_CACHE METHOD[,METHOD...]

SCENE_CACHE is a scene folder of ``guidedmatch bench accuracy --cache`` (``colmap/database.db``,
``ours/database.db``, ``ours_cap/database.db``, ...).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pycolmap

from guidedmatch.evaluation.accuracy_analysis import read_geometries

BINS = (1, 2, 4, 8, 16, 32, 64, 128)


def main(cache: Path, methods: list[str]) -> None:
    db = pycolmap.Database.open(str(cache / "colmap" / "database.db"))
    names = {img.image_id: img.name for img in db.read_all_images()}
    db.close()
    pos = {n: k for k, n in enumerate(sorted(names.values()))}
    print("method | " + " | ".join(f"{BINS[k]}-{BINS[k + 1] - 1} apart: pairs, inliers" for k in range(len(BINS) - 1)))
    for m in methods:
        geoms = read_geometries(cache / m.replace("+", "_") / "database.db")
        inl, pairs = np.zeros(len(BINS) - 1, np.int64), np.zeros(len(BINS) - 1, np.int64)
        for (a, b), x in geoms.items():
            k = int(np.searchsorted(BINS, abs(pos[names[a]] - pos[names[b]]), side="right")) - 1
            if 0 <= k < len(pairs):
                inl[k] += len(x)
                pairs[k] += 1
        print(f"{m} | " + " | ".join(f"{p}, {i:,}" for p, i in zip(pairs, inl)))


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2].split(","))
