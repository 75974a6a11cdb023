"""Drop a random FRAC of every verified row's inliers (rows > 15 inliers; at least 15 kept) of a COLMAP database,
seeded: how much the pose moves for a small change of the mapper's input (accuracy history, twenty-second round).

    python tools/drop_inliers.py DATABASE FRAC SEED
"""
import sys
import numpy as np
import pycolmap
db_path, frac, seed = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(seed)
db = pycolmap.Database.open(db_path)
pids, counts = (np.asarray(a) for a in db.read_two_view_geometry_num_inliers())
before = after = 0
for pid, c in sorted(zip(pids.tolist(), counts.tolist())):
    before += c
    if c <= 15:
        after += c
        continue
    i1, i2 = (int(i) for i in pycolmap.pair_id_to_image_pair(int(pid)))
    g = db.read_two_view_geometry(i1, i2)
    m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
    keep = rng.random(len(m)) >= frac
    if keep.sum() < 15:
        keep[np.argsort(rng.random(len(m)))[:15]] = True
    g.inlier_matches = np.ascontiguousarray(m[keep], dtype=np.uint32)
    with pycolmap.DatabaseTransaction(db):
        db.update_two_view_geometry(i1, i2, g)
    after += int(keep.sum())
db.close()
print(before, after)
