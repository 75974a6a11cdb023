"""A hash of the matcher's output on sampled pairs of COLMAP databases: equal hashes before and after a change that
must not change any match (collection history, eighteenth round).

Usage::

    python tools/match_hash.py DATABASE:NPAIRS [DATABASE:NPAIRS ...]
    PYTHONPATH=OTHER_CHECKOUT/src python tools/match_hash.py ...     # the same pairs with another version

NPAIRS pairs of each database (all when fewer; ``random.seed(1)``), matched with the collection's matcher settings;
the hash covers every pair's matches, distances, inlier flags and comparison count. Prints the hash and the matching
seconds (indexes built inside the first pairs: not a benchmark).
"""
from __future__ import annotations

import hashlib
import random
import sqlite3
import sys
import time

import numpy as np


def main() -> None:
    from guidedmatch.collection.config import collection_matcher_config
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.matcher import match
    from guidedmatch.prepared import prepare

    cfg = collection_matcher_config()
    h, spent = hashlib.sha256(), 0.0
    for arg in sys.argv[1:]:
        path, _, k = arg.rpartition(":")
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            names = [r[0] for r in db.execute("select name from images order by image_id")]
        pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
        random.seed(1)
        pairs = random.sample(pairs, min(int(k), len(pairs)))
        src, prepared = ColmapSource(path), {}
        for a, b in pairs:
            for n in (a, b):
                if n not in prepared:
                    prepared[n] = prepare(src.load(n))
            t = time.perf_counter()
            r = match(prepared[a], prepared[b], "so+epi+ia", cfg)
            spent += time.perf_counter() - t
            for x in (r.pairs, r.distances, np.asarray(r.geometry.inliers)):
                h.update(np.ascontiguousarray(x).tobytes())
            h.update(str(r.stats.comparisons).encode())
    print(h.hexdigest()[:16], f"{spent:.2f} s")


if __name__ == "__main__":
    main()
