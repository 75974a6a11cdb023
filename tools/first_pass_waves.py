"""A first pass in two waves, against the defaults (collection history, eighteenth round: tried, not kept).

Usage::

    python tools/first_pass_waves.py FEATURES_DB OUT_DB K [SECOND_LOOK_JSON]

Copies FEATURES_DB (a COLMAP database with features) to OUT_DB and matches every pair into it. K = 0: the defaults'
path (``match_into_database``: exhaustive, second look, the mapper's inlier selection). K > 0: wave 1 = each image's
K most similar images by visual words (no prior), wave 2 = every other pair with the second look's prior (chained,
then tracked keypoints) from wave 1's verified pairs, then the default second look over everything and the same
inlier selection; one local cluster for all of it. Prints one JSON line: stage times, verified pairs, inliers.
"""
from __future__ import annotations

import json
import shutil
import sqlite3
import sys
import time


def main() -> None:
    # imported here, not at the top: the cluster's worker processes import this file as their __main__
    from guidedmatch.base import DEFAULT_INLIER_PX, DEFAULT_REFIT_DEG
    from guidedmatch.collection.config import CollectionConfig
    from guidedmatch.collection.engine import match_collection, shared_cluster
    from guidedmatch.collection.pairs import pairs_from_spec
    from guidedmatch.collection.second_look import _read_inliers, priors, second_look
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.sfm.stages import match_into_database

    feat, out, k = sys.argv[1], sys.argv[2], int(sys.argv[3])
    look = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    shutil.copy(feat, out)
    src = ColmapSource(out)
    names = src.names()
    every = pairs_from_spec("exhaustive", names).pairs
    cconf = CollectionConfig(progress=False)
    t0 = time.perf_counter()
    rec: dict = {"K": k}
    if k == 0:
        r = match_into_database(src, every, out, cconf, second_look=look, inlier_px=DEFAULT_INLIER_PX,
                                refit_below_deg=DEFAULT_REFIT_DEG)
        rec["second_look_s"] = r["second_look"]["time_s"]
    else:
        with ColmapSink(out, geometry="ours") as sink:
            with shared_cluster(src, every, sink, cconf) as client:
                t = time.perf_counter()
                wave1 = pairs_from_spec(f"retrieval:{k}", names, src, retrieval=dict(progress=False),
                                        retrieval_cache=False).pairs
                rec["retrieval_s"] = time.perf_counter() - t
                match_collection(src, wave1, sink, cconf, client=client)
                rec.update(wave1_pairs=len(wave1), wave1_s=time.perf_counter() - t)
                t = time.perf_counter()
                _, inliers, nkp = _read_inliers(sink)
                done = {frozenset(p) for p in wave1}
                wave2 = [p for p in every if frozenset(p) not in done]
                match_collection(src, wave2, sink, cconf, client=client, first=priors(wave2, inliers, nkp))
                rec.update(wave2_pairs=len(wave2), wave2_s=time.perf_counter() - t)
                t = time.perf_counter()
                lk = second_look(src, sink, cconf, look, client=client)
                rec.update(second_look_s=time.perf_counter() - t, looked=lk["looked"], sl_verified=lk["verified"])
            rec["tighten_s"] = sink.tighten_inliers(DEFAULT_INLIER_PX, refit_below_deg=DEFAULT_REFIT_DEG)["time_s"]
    rec["match_s"] = time.perf_counter() - t0
    with sqlite3.connect(f"file:{out}?mode=ro", uri=True) as db:
        rec["verified_pairs"], rec["inliers"] = db.execute(
            "select count(*), sum(rows) from two_view_geometries where rows > 0").fetchone()
    print(json.dumps(rec))


if __name__ == "__main__":
    main()
