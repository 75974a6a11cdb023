"""Per-phase matching time of a collection's pairs in one thread, every image loaded, prepared and indexed first (no
index build, load or scheduling counted): ``guidedmatch.matcher.match`` on ``ColmapSource`` images with the
collection's matcher settings, ``PhaseTimes`` summed over the pairs (accuracy history, "fourteenth round").

Usage::

    python tools/pair_phase_times.py DATABASE PAIRS_FILE [REPEATS] ['{"band_px": 3}']

PAIRS_FILE: ``name1 name2`` lines; the JSON: matcher settings over the collection defaults, and
``"shared_quantizer": "on" | "off" | "auto"`` (default "off", as ``guidedmatch colmap``; "on": one coarse quantizer
for the database's images, ``guidedmatch.collection.quantizer``). Prints one JSON object (the best of
REPEATS): wall time, per pair, phase times, matches, inliers, verified pairs, the quantizer used.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import sys
import time


def prepared_images(db: str, pairs, quantizer=None) -> dict:
    """``{name: PreparedImage}`` of every image of ``pairs`` in the COLMAP database ``db``, its index built (with the
    collection's ``quantizer``, a ``SharedQuantizer``, when given)."""
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.prepared import prepare

    src, prepared = ColmapSource(db), {}
    for a, b in pairs:
        for n in (a, b):
            if n not in prepared:
                prepared[n] = prepare(src.load(n), quantizer=quantizer)
                if getattr(prepared[n], "has_index", False):
                    prepared[n].index()
    return prepared


def main() -> None:
    from guidedmatch import kernels  # before faiss: it sets OPENBLAS_CORETYPE for faiss' bundled OpenBLAS

    import cv2
    import faiss
    from guidedmatch.bruteforce import blas_one_thread
    from guidedmatch.collection.config import collection_matcher_config
    from guidedmatch.collection.quantizer import collection_quantizer
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.matcher import match

    db, pairfile = sys.argv[1], sys.argv[2]
    reps = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    settings = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    mode = settings.pop("shared_quantizer", "off")
    cfg = collection_matcher_config(settings or None)
    kernels.limit_threads_here(1)
    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    pairs = [line.split() for line in open(pairfile) if line.strip()]
    quantizer, qinfo = collection_quantizer(ColmapSource(db), cfg, mode)
    prepared = prepared_images(db, pairs, quantizer)
    match(prepared[pairs[0][0]], prepared[pairs[0][1]], "so+epi+ia", cfg)  # Numba's kernels loaded
    best = None
    with blas_one_thread(load_scipy=False):
        for _ in range(reps):
            phases, out = collections.Counter(), []
            t0 = time.perf_counter()
            for a, b in pairs:
                res = match(prepared[a], prepared[b], "so+epi+ia", cfg)
                phases.update(dataclasses.asdict(res.stats.timing))
                out.append((len(res), int(res.geometry.num_inliers), res.geometry.verdict))
            wall = time.perf_counter() - t0
            if best is None or wall < best[0]:
                best = (wall, phases, out)
    wall, phases, out = best
    print(json.dumps({"pairs": len(pairs), "wall_s": round(wall, 3), "per_pair_ms": round(1000 * wall / len(pairs), 2),
                      "phases_s": {k: round(v, 3) for k, v in sorted(phases.items(), key=lambda kv: -kv[1])},
                      "matches": sum(o[0] for o in out), "inliers": sum(o[1] for o in out),
                      "verified": sum(o[2] == "verified" for o in out), "quantizer": qinfo}))


if __name__ == "__main__":
    main()
