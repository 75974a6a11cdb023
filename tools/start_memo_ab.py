"""The second look's pairs matched one by one with and without the first pass's start memos (collection history,
twenty-first round): the database's first pass and second look run in this process (one thread), every second-look
pair's prior and memo captured, then each pair matched again with and without its memo, alternating, one thread.
Prints the seconds, the phase times and how many pairs came out bit-identical.

    python tools/start_memo_ab.py FEATURES_DB [REPEATS]

FEATURES_DB: a COLMAP database with features and no matches (copied, not changed).
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path


def capture(features_db: str) -> list:
    """``[(name1, name2, first, memo)]`` of every pair the second look matched, as it matched them."""
    from guidedmatch.collection import inprocess
    from guidedmatch.collection.config import CollectionConfig
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.sfm.stages import match_into_database

    got, real = [], inprocess._match_one

    def spy(cache, a, b, spec, worker, first=None, memo=None):
        if spec.memo_below < 0:  # a second-look stage (it records no memo)
            got.append((a, b, first, memo))
        return real(cache, a, b, spec, worker, first, memo)

    inprocess._match_one = spy
    try:
        with tempfile.TemporaryDirectory() as d:
            db = Path(d) / "db.db"
            shutil.copy(features_db, db)
            src = ColmapSource(db)
            names = sorted(src.names())
            pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
            out = match_into_database(src, pairs, db, CollectionConfig(progress=False, workers=0, threads=1),
                                      second_look={})
            src.close()
    finally:
        inprocess._match_one = real
    print("start memos:", out["second_look"]["start_memos"], flush=True)
    return got


def main() -> None:
    from guidedmatch import kernels  # before faiss (OPENBLAS_CORETYPE for its bundled OpenBLAS)

    import cv2
    import faiss
    import numpy as np
    from guidedmatch.collection.config import collection_matcher_config
    from guidedmatch.collection.memos import load
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.matcher import match
    from guidedmatch.prepared import prepare

    db, reps = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 1
    kernels.limit_threads_here(1)
    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    cap = capture(db)
    src, cfg, P = ColmapSource(db), collection_matcher_config(None), {}
    for a, b, _, _ in cap:
        for n in (a, b):
            if n not in P:
                P[n] = prepare(src.load(n))
                P[n].index()
    secs, phases, same = [0.0, 0.0], [{}, {}], 0
    for _ in range(reps):
        for k, (a, b, first, memo) in enumerate(cap):
            res = [None, None]
            for w in ((0, 1) if k % 2 else (1, 0)):
                m = load(memo) if (w and memo is not None) else None
                t = time.perf_counter()
                res[w] = match(P[a], P[b], "so+epi+ia", cfg, first=first, start_memo=m)
                secs[w] += time.perf_counter() - t
                for key, v in vars(res[w].stats.timing).items():
                    phases[w][key] = phases[w].get(key, 0.0) + v
            same += bool(np.array_equal(res[0].pairs, res[1].pairs) and res[0].distances.tobytes() ==
                         res[1].distances.tobytes() and res[0].geometry.verdict == res[1].geometry.verdict)
    print(f"{len(cap)} pairs x {reps}: without memos {secs[0]:.2f} s, with {secs[1]:.2f} s; bit-identical "
          f"{same}/{len(cap) * reps}")
    for w, name in ((0, "without"), (1, "with")):
        print(name, {k: round(v, 2) for k, v in phases[w].items() if v})


if __name__ == "__main__":
    main()
