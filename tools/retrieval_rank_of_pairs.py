"""tools/retrieval_rank_of_pairs.py FEATURES_DB MATCHED_DB: how many verified pairs of MATCHED_DB lie outside the top K of the
collection's own bag-of-words ranking (guidedmatch.collection.retrieval, RetrievalConfig defaults: CSLS), K = 5 ... 40.
A pair's rank is the better of its two images' rankings of each other."""
import sqlite3
import sys

import numpy as np

from guidedmatch.collection import retrieval as R
from guidedmatch.collection.sources import ColmapSource
import pycolmap  # after guidedmatch (zlib)

feat, matched = sys.argv[1], sys.argv[2]
src = ColmapSource(feat)
names = src.names()
n = len(names)
cfg = R.config_from(R.RetrievalConfig, {"progress": False})
coarse, fine, bow = R._bag(src, names, cfg, None, {})
r = R.hub_scores(bow, cfg.hub_k) if cfg.hub_k > 0 else None
order = R._top(bow, bow.T.tocsc(), np.arange(n), n - 1, r)
rank = np.zeros((n, n), int)
for i in range(n):
    rank[i, order[i]] = np.arange(1, n)
prank = np.minimum(rank, rank.T)
con = sqlite3.connect(matched)
id2name = dict(con.execute("SELECT image_id, name FROM images"))
index = {nm: i for i, nm in enumerate(names)}
stat = []
for pid, rows in con.execute("SELECT pair_id, rows FROM two_view_geometries"):
    a, b = pycolmap.pair_id_to_image_pair(int(pid))
    stat.append((prank[index[id2name[a]], index[id2name[b]]], rows))
stat = np.array(stat)
v = stat[:, 1] > 0
print(f"pairs {len(stat)}, verified {v.sum()}")
for k in (5, 10, 15, 20, 25, 30, 40):
    inside = stat[:, 0] <= k
    out = ~inside & v
    print(f"K={k}: shortlisted {inside.sum()}, verified inside {np.sum(inside & v)}, outside {out.sum()} "
          f"(median inliers {np.median(stat[out, 1]) if out.any() else 0:.0f}, < 64 inliers: {np.sum(out & (stat[:, 1] < 64))})")
