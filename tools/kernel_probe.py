"""The guided kernel alone, on the final passes of real pairs (collection history, eighteenth round).

Usage::

    python tools/kernel_probe.py DATABASE PAIRS_FILE [NPAIRS]

Matches the first NPAIRS (default 80) pairs of PAIRS_FILE (``name1 name2`` lines) of a COLMAP database with the
collection's matcher settings in one thread, records the arguments of every final-pass call of
``kernels.guided_top2`` (more than 1000 queries), then times those calls again: as recorded (128-D descriptors) and
with the descriptors cut to 8 dimensions (distances almost free: what the scan costs), two rounds each; prints the
seconds, the candidates and the strips visited per query.
"""
from __future__ import annotations

import sys
import time

import numpy as np


def main() -> None:
    from guidedmatch import kernels   # before faiss (its bundled OpenBLAS: guidedmatch._runtime)
    from guidedmatch.collection.config import collection_matcher_config
    from guidedmatch.matcher import match
    from pair_phase_times import prepared_images   # tools/, beside this file

    import cv2
    import faiss

    kernels.limit_threads_here(1)
    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    db, pairfile = sys.argv[1], sys.argv[2]
    npairs = int(sys.argv[3]) if len(sys.argv) > 3 else 80
    cfg = collection_matcher_config()
    pairs = [line.split() for line in open(pairfile) if line.strip()][:npairs]
    prepared = prepared_images(db, pairs)
    calls, orig = [], kernels.guided_top2

    def spy(*args, **kw):
        if len(args[0]) > 1000:
            calls.append(args)
        return orig(*args, **kw)

    kernels.guided_top2 = spy
    try:
        for a, b in pairs:
            match(prepared[a], prepared[b], "so+epi+ia", cfg)
    finally:
        kernels.guided_top2 = orig

    def cut(args):
        args = list(args)
        args[1], args[2] = np.ascontiguousarray(args[1][:, :8]), np.ascontiguousarray(args[2][:, :8])
        return args

    def run(f):
        t = time.perf_counter()
        for args in calls:
            orig(*f(args))
        return time.perf_counter() - t

    nq = sum(len(args[0]) for args in calls)
    run(lambda a: a), run(cut)
    for name, f in (("as recorded", lambda a: a), ("8-D", cut)) * 2:
        print(f"{name}: {run(f):.3f} s")
    cand = vis = 0
    for args in calls:
        r = orig(*args, return_visits=True)
        cand, vis = cand + int(r[4].sum()), vis + int(r[5].sum())
    print(f"{len(calls)} calls, {nq} queries, {cand} candidates ({cand / nq:.1f} a query), "
          f"{vis / nq:.1f} strips visited a query")


if __name__ == "__main__":
    main()
