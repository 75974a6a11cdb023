"""What the second look's rejected candidates yield, by their chain support: for a first-pass database
(``guidedmatch colmap DB --no-second-look --inlier-px 0``) and the same database after the second look (both read
as the second look reads them), the rejected pairs the second look would take (``collection.second_look._candidates``)
binned by chained correspondences, with how many of them the second look verified and their inliers (closing note of
2026-12-06).

Usage::

    python tools/second_look_candidates.py FIRST_PASS.db AFTER_SECOND_LOOK.db
"""
from __future__ import annotations

import collections
import sys


def read(path: str) -> tuple[set, dict, dict]:
    """The second look's own view of a database (``second_look._read_inliers``): tried pairs, inliers of the verified
    ones, keypoint counts."""
    from guidedmatch.collection.second_look import _read_inliers
    from guidedmatch.collection.sinks import ColmapSink

    with ColmapSink(path, geometry="ours") as sink:
        return _read_inliers(sink)


def main() -> None:
    from guidedmatch.collection.second_look import SecondLookConfig, _candidates

    tried, inl, nkp = read(sys.argv[1])
    _, after, _ = read(sys.argv[2])
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
