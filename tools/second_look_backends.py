"""The first pass and the second look of an exhaustive collection, with the second look on its own backend (``own``:
the engine's auto rule per round, in-process threads for fox's rounds) or on the first pass's local cluster (``shared``:
one cluster of 2 worker processes for both); prints the stage times (closing note of 2026-12-06: fox 16.8 s shared vs
16.9 s own, not kept; 2026-12-07 on an Intel Xeon VM: buddha 11.5 vs 14.2 s, fox 20.8 vs 25 s -- kept, the default of
``match_into_database``: collection history). The matches are the same either way.

Usage::

    python tools/second_look_backends.py FEATURES.db WORK own|shared
"""
from __future__ import annotations

import itertools
import json
import shutil
import sys
import time
from pathlib import Path


def main() -> None:
    from guidedmatch.collection.config import CollectionConfig
    from guidedmatch.collection.engine import match_collection
    from guidedmatch.collection.second_look import second_look
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    feats, work, mode = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    work.mkdir(parents=True, exist_ok=True)
    db = work / "s.db"
    for p in work.glob("s.db*"):
        p.unlink()
    shutil.copyfile(feats, db)
    cconf = CollectionConfig(progress=False)
    src = ColmapSource(db)
    pairs = list(itertools.combinations(sorted(src.names()), 2))
    t0 = time.perf_counter()
    client = cluster = None
    if mode == "shared":
        from guidedmatch.collection.dask_backend import _start_local_cluster

        cluster, client = _start_local_cluster(2)
    t1 = time.perf_counter()
    with ColmapSink(db, geometry="ours") as sink:
        match_collection(src, pairs, sink, cconf, client=client)
        t2 = time.perf_counter()
        look = second_look(src, sink, cconf, {}, client=client)
        t3 = time.perf_counter()
    if client is not None:
        client.close()
        cluster.close()
    t4 = time.perf_counter()
    print(json.dumps(dict(mode=mode, total=round(t4 - t0, 2), start=round(t1 - t0, 2), first=round(t2 - t1, 2),
                          look=round(t3 - t2, 2), close=round(t4 - t3, 2), verified=look["verified"],
                          gained=look["inliers_gained"],
                          rounds=[(r["pairs"], round(r["time_s"], 2)) for r in look["rounds"]])))


if __name__ == "__main__":
    main()
