"""How far the verified inliers of a COLMAP database lie from their own pair's model: the fraction within 0.5, 1,
1.5, 2, 3 and 4 px (Sampson distance to the row's F; transfer error of H for a planar row), over every inlier of
every verified pair -- what ``--inlier-px`` would keep at each threshold (before its floor of 15 per pair).

    python tools/inlier_residuals.py DATABASE.db [DATABASE2.db ...]
"""
from __future__ import annotations

import sys

import numpy as np
import pycolmap

from guidedmatch.epipolar import sampson_distance
from guidedmatch.geometry import transfer_error

EDGES = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0)


def residuals(path: str) -> np.ndarray:
    db = pycolmap.Database.open(path)
    try:
        kp = {}
        out = []
        for pid, n in zip(*db.read_two_view_geometry_num_inliers()):
            if n == 0:
                continue
            i1, i2 = (int(i) for i in pycolmap.pair_id_to_image_pair(int(pid)))
            g = db.read_two_view_geometry(i1, i2)
            for i in (i1, i2):
                if i not in kp:
                    kp[i] = np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64)
            m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            x1, x2 = kp[i1][m[:, 0]], kp[i2][m[:, 1]]
            if int(g.config) in (4, 5, 6) and g.H is not None and np.any(g.H):
                out.append(transfer_error(np.asarray(g.H), x1, x2))
            elif g.F is not None and np.any(g.F):
                out.append(sampson_distance(np.asarray(g.F), x1, x2))
        return np.concatenate(out) if out else np.zeros(0)
    finally:
        db.close()


def main(paths: list[str]) -> int:
    print("| database | inliers | " + " | ".join(f"<= {e:g} px" for e in EDGES) + " | median px |")
    print("|---|---|" + "---|" * len(EDGES) + "---|")
    for p in paths:
        r = residuals(p)
        cells = " | ".join(f"{np.mean(r <= e):.1%}" for e in EDGES) if len(r) else " | ".join("-" for _ in EDGES)
        print(f"| {p} | {len(r):,} | {cells} | {np.median(r) if len(r) else float('nan'):.2f} |")
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1:]))
