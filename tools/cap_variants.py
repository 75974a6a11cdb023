"""tools/cap_variants.py SRC_DB OUT_DB K MODE: copy SRC_DB and keep at most K inliers per two-view geometry, spread over
image 1 (geometry.spread_matches), ranked by MODE: dist (descriptor distance: guidedmatch sfm's cap), track (keypoints
in more other verified pairs first, then distance), conf / conf1 (inliers a third view confirms first, counts capped
at 3 / 1, then distance). Used on Herz-Jesus-P8's OpenCV-SIFT database (benchmarks/results/sfm/history.md)."""
import sys, shutil, numpy as np
from collections import defaultdict
from guidedmatch.evaluation.accuracy_analysis import read_geometries, rewrite_geometries
from guidedmatch.evaluation.bench_accuracy import copy_database
from guidedmatch.geometry import spread_matches
from guidedmatch.collection.colmap_source import _descriptor_rows
from guidedmatch.collection.rescue import _partner
from pathlib import Path
import pycolmap   # after guidedmatch (zlib)
src, out, K, mode = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
copy_database(src, out)
G = read_geometries(out)
db = pycolmap.Database.open(str(out))
kp, desc, size = {}, {}, {}
for img in db.read_all_images():
    i = img.image_id
    kp[i] = np.asarray(db.read_keypoints(i))[:, :2]
    d = db.read_descriptors(i); sh = np.shape(d.data)
    desc[i] = _descriptor_rows(d, int(sh[1]))[1].astype(np.float32)
    cam = db.read_camera(img.camera_id); size[i] = (cam.width, cam.height)
db.close()
nkp = {i: len(kp[i]) for i in kp}
deg = {i: np.zeros(nkp[i], np.int32) for i in kp}
for (a, b), m in G.items():
    np.add.at(deg[a], m[:, 0], 1); np.add.at(deg[b], m[:, 1], 1)
nb = defaultdict(set)
for a, b in G: nb[a].add(b); nb[b].add(a)
new = {}
ncap = 0
for (a, b), m in G.items():
    if len(m) <= K: new[(a, b)] = m; continue
    dist = np.linalg.norm(desc[a][m[:, 0]] - desc[b][m[:, 1]], axis=1)
    if mode == "dist":
        s = dist
    elif mode == "track":
        sup = np.minimum(deg[a][m[:, 0]], deg[b][m[:, 1]]) - 1
        s = -np.minimum(sup, 3) * 1e4 + dist
    elif mode in ("conf", "conf1"):
        conf = np.zeros(len(m), np.int32)
        for c in (nb[a] & nb[b]) - {a, b}:
            pa = _partner(G[(min(a, c), max(a, c))], nkp[a], 0 if a < c else 1)
            pb = _partner(G[(min(b, c), max(b, c))], nkp[b], 0 if b < c else 1)
            ka, kb = pa[m[:, 0]], pb[m[:, 1]]
            conf += (ka >= 0) & (ka == kb)
        cc = np.minimum(conf, 1 if mode == "conf1" else 3)
        s = -cc * 1e4 + dist
    keep = np.sort(spread_matches(kp[a][m[:, 0]], size[a], s, K, 16))
    new[(a, b)] = m[keep]; ncap += 1
print(rewrite_geometries(out, new), "capped", ncap)
