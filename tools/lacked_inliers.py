"""What our database lacks of COLMAP's inliers and what it adds, on the same keypoints, and variant databases that
restore or remove each part (accuracy history, twenty-third round).

    python tools/lacked_inliers.py breakdown CACHE/SCENE
    python tools/lacked_inliers.py variants CACHE/SCENE OUT_DIR [NAME,NAME,...]

CACHE/SCENE: a scene folder of ``guidedmatch bench accuracy``'s cache (``colmap/database.db`` and
``ours/database.db``, the same features). ``breakdown`` prints, by distance along the capture (file-name numbers),
how COLMAP's inliers fare in ours: shared, in our ``matches`` but not selected for the mapper, the keypoint matched
to another partner, not matched at all, or in a pair we rejected; and splits the inliers we add (on keypoints COLMAP
left free) by the exact ratio test against all of image 2 (:func:`guidedmatch.evaluation.accuracy_analysis.
global_test`): distinct (the partner is the nearest neighbour at < 0.8 of the next), the nearest neighbour but
ambiguous, another descriptor nearer. ``variants`` writes databases to map as ``ours`` (``guidedmatch bench
accuracy`` on a copy of the cache, see the history):

* ``colmap_added_distinct.db`` / ``colmap_added_ambiguous.db``: COLMAP's inliers plus our distinct / other additions;
* ``ours_d4.db``: our mapper's inliers plus our matches within 4 px (Sampson, the row's model) that are distinct;
* ``ours_distinct4.db``: only our matches within 4 px that are distinct (a row left with < 15 keeps its inliers);
* ``ours_lacked_unmatched.db`` / ``ours_lacked_selection.db`` (oracles): ours plus COLMAP's inliers on keypoints we
  did not match at all / plus those in our matches that the 1.5 px selection left out.
"""
from __future__ import annotations

import collections
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap

from guidedmatch.collection.sinks import _model_error
from guidedmatch.evaluation.accuracy_analysis import (_keys, global_distances, global_test, ratio_test, read_geometries,
                                                      rewrite_geometries, union_free)

BANDS = ((1, 1, "1"), (2, 4, "2-4"), (5, 16, "5-16"), (17, 10**9, "17+"))


class Scene:
    def __init__(self, folder: Path):
        self.colmap = read_geometries(folder / "colmap" / "database.db")
        self.ours_path = folder / "ours" / "database.db"
        self.ours = read_geometries(self.ours_path)
        self.db = pycolmap.Database.open(str(self.ours_path))
        self.names = {int(i.image_id): i.name for i in self.db.read_all_images()}
        self._desc: dict[int, np.ndarray] = {}
        self._kp: dict[int, np.ndarray] = {}

    def band(self, i1: int, i2: int) -> str:
        num = [int(re.sub(r"\D", "", self.names[i]) or 0) for i in (i1, i2)]
        d = abs(num[0] - num[1])
        return next(name for lo, hi, name in BANDS if lo <= d <= hi) if d else "0"

    def desc(self, i: int) -> np.ndarray:
        if i not in self._desc:
            self._desc[i] = np.asarray(self.db.read_descriptors(i).data, np.float32)
        return self._desc[i]

    def kp(self, i: int) -> np.ndarray:
        if i not in self._kp:
            self._kp[i] = np.asarray(self.db.read_keypoints(i))[:, :2].astype(np.float64)
        return self._kp[i]

    def matches(self, i1: int, i2: int) -> np.ndarray:
        if not self.db.exists_matches(i1, i2):
            return np.zeros((0, 2), np.int64)
        return np.asarray(self.db.read_matches(i1, i2), np.int64).reshape(-1, 2)


def breakdown(folder: Path) -> None:
    s = Scene(folder)
    lack = collections.defaultdict(collections.Counter)
    for p, cm in s.colmap.items():
        row = lack[s.band(*p)]
        row["colmap"] += len(cm)
        if p not in s.ours:
            row["pair rejected"] += len(cm)
            continue
        ot, om = s.ours[p], s.matches(*p)
        kt, km = _keys(ot), _keys(om)
        ck = _keys(cm)
        shared, in_matches = np.isin(ck, kt), np.isin(ck, km)
        other = np.isin(cm[:, 0], om[:, 0]) | np.isin(cm[:, 1], om[:, 1])
        row["shared"] += int(shared.sum())
        row["in our matches, not selected"] += int((~shared & in_matches).sum())
        row["keypoint matched to another"] += int((~in_matches & other).sum())
        row["not matched"] += int((~in_matches & ~other).sum())
    print("COLMAP's inliers in ours, by capture distance:")
    for b in ("1", "2-4", "5-16", "17+", "0"):
        if b in lack:
            print(f"  {b:>5}: {dict(lack[b])}")
    add = collections.Counter()
    for p, m in s.ours.items():
        base = s.colmap.get(p, np.zeros((0, 2), np.int64))
        added = union_free(base, m)[len(base):]
        if len(added) == 0:
            continue
        d = global_distances(s.desc(p[0])[added[:, 0]], s.desc(p[1]), added[:, 1])
        nn, distinct = ratio_test(*d, None), ratio_test(*d, 0.8)
        add["added"] += len(added)
        add["distinct"] += int(distinct.sum())
        add["nearest but ambiguous"] += int((nn & ~distinct).sum())
        add["another descriptor nearer"] += int((~nn).sum())
    print("inliers we add on keypoints COLMAP left free:", dict(add))


def variants(folder: Path, out: Path) -> None:
    s = Scene(folder)
    out.mkdir(parents=True, exist_ok=True)
    parts = {k: {} for k in ("colmap_added_distinct", "colmap_added_ambiguous", "ours_d4", "ours_distinct4",
                             "ours_lacked_unmatched", "ours_lacked_selection")}
    for p, m in s.ours.items():
        i1, i2 = p
        base = s.colmap.get(p, np.zeros((0, 2), np.int64))
        added = union_free(base, m)[len(base):]
        ok = global_test(s.desc(i1)[added[:, 0]], s.desc(i2), added[:, 1], 0.8)
        parts["colmap_added_distinct"][p] = np.concatenate([base, added[ok]])
        parts["colmap_added_ambiguous"][p] = np.concatenate([base, added[~ok]])
        allm = s.matches(i1, i2)
        lacked = base[~np.isin(_keys(base), _keys(m))]
        in_matches = np.isin(_keys(lacked), _keys(allm))
        untouched = ~np.isin(lacked[:, 0], allm[:, 0]) & ~np.isin(lacked[:, 1], allm[:, 1])
        parts["ours_lacked_unmatched"][p] = union_free(m, lacked[untouched])
        parts["ours_lacked_selection"][p] = union_free(m, lacked[in_matches])
        err = _model_error(s.db.read_two_view_geometry(i1, i2), s.kp(i1)[allm[:, 0]], s.kp(i2)[allm[:, 1]])
        if err is None:
            parts["ours_d4"][p] = parts["ours_distinct4"][p] = m
            continue
        near = allm[err <= 4.0]
        dist = near[global_test(s.desc(i1)[near[:, 0]], s.desc(i2), near[:, 1], 0.8)]
        parts["ours_d4"][p] = union_free(m, dist)
        parts["ours_distinct4"][p] = dist if len(dist) >= 15 else m
    s.db.close()
    for name, new in parts.items():
        if sys.argv[4:] and name not in sys.argv[4].split(","):
            continue
        base = folder / ("colmap" if name.startswith("colmap") else "ours") / "database.db"
        dst = out / f"{name}.db"
        shutil.copy(base, dst)
        info = rewrite_geometries(dst, new, folder / "ours" / "database.db" if name.startswith("colmap") else None)
        print(name, info)


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("breakdown", "variants"):
        sys.exit(__doc__)
    if sys.argv[1] == "breakdown":
        breakdown(Path(sys.argv[2]))
    else:
        variants(Path(sys.argv[2]), Path(sys.argv[3]))
