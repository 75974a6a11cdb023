"""What the second look's rejected candidates yield, by their chain support: for a first-pass database (``guidedmatch
colmap DB --no-second-look --inlier-px 0``, every pair of the images tried) and the same database after the second
look, the rejected pairs the second look would take (``collection.second_look._candidates``) binned by chained
correspondences, with how many of them the second look verified and their inliers (closing note of 2026-12-06).

Usage::

    python tools/second_look_candidates.py FIRST_PASS.db AFTER_SECOND_LOOK.db
"""
from __future__ import annotations

import collections
import itertools
import sys

import numpy as np


def verified_inliers(path: str) -> tuple[dict, dict]:
    """``({(name1, name2): inlier matches} of the verified pairs, {name: keypoints})``."""
    import pycolmap

    db = pycolmap.Database.open(path)
    try:
        names = {i.image_id: i.name for i in db.read_all_images()}
        nkp = {names[i]: db.read_keypoints(i).shape[0] for i in names}
        inl = {}
        pids, counts = db.read_two_view_geometry_num_inliers()
        for pid, n in zip(pids, counts):
            if n > 0:
                i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
                inl[(names[i1], names[i2])] = np.asarray(db.read_two_view_geometry(i1, i2).inlier_matches).reshape(-1, 2)
    finally:
        db.close()
    return inl, nkp


def main() -> None:
    from guidedmatch.collection.second_look import SecondLookConfig, _candidates

    inl, nkp = verified_inliers(sys.argv[1])
    after, _ = verified_inliers(sys.argv[2])
    tried = {frozenset(p) for p in itertools.combinations(sorted(nkp), 2)}
    pairs, support, _ = _candidates(tried, inl, nkp, set(), SecondLookConfig())
    have = {frozenset(p) for p in inl}
    got = {frozenset(p): len(m) for p, m in after.items()}
    bins = [(16, 24), (24, 32), (32, 48), (48, 64), (64, 128), (128, None)]
    rows = collections.defaultdict(lambda: [0, 0, 0])
    weak = [0, 0]
    for (a, c), s in zip(pairs, support):
        p = frozenset((a, c))
        if p in have:   # a weak verified pair: its inliers gained
            weak[0] += 1
            weak[1] += got.get(p, 0) - s
            continue
        lo, hi = next((lo, hi) for lo, hi in bins if s >= lo and (hi is None or s < hi))
        r = rows[(lo, hi)]
        r[0] += 1
        r[1] += p in got
        r[2] += got.get(p, 0)
    print(f"weak verified pairs: {weak[0]}, inliers gained {weak[1]:+,}")
    for lo, hi in bins:
        n, v, k = rows.get((lo, hi), [0, 0, 0])
        print(f"rejected, {lo}-{'' if hi is None else hi - 1} chains: {n} candidates, {v} verified, {k:,} inliers")


if __name__ == "__main__":
    main()
