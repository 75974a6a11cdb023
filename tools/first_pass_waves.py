"""A first pass in two waves, against the defaults (collection history, eighteenth round: tried, not kept).

Usage::

    python tools/first_pass_waves.py FEATURES_DB OUT_DB K [SECOND_LOOK_JSON]

Copies FEATURES_DB (a COLMAP database with features) to OUT_DB and matches every pair into it. K = 0: the defaults'
path (``match_into_database``: exhaustive, second look, 1.5 px selection). K > 0: wave 1 = each image's K most similar
images by visual words (no prior), wave 2 = every other pair with the second look's prior (chained, then tracked
keypoints) from wave 1's verified pairs, then the default second look over everything and the 1.5 px selection; one
local cluster for all of it. Prints one JSON line: stage times, verified pairs, inliers.
"""
import json, shutil, sys, time
t00 = time.perf_counter()
from guidedmatch.collection.config import CollectionConfig
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.pairs import pairs_from_spec
from guidedmatch.collection.engine import match_collection, shared_cluster
from guidedmatch.collection.sinks import ColmapSink
from guidedmatch.collection.second_look import second_look, priors, _read_inliers
from guidedmatch.sfm.stages import match_into_database
def main():
    feat, out, K = sys.argv[1], sys.argv[2], int(sys.argv[3])
    look = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    shutil.copy(feat, out)
    src = ColmapSource(out)
    names = src.names()
    allp = pairs_from_spec("exhaustive", names).pairs
    cconf = CollectionConfig(progress=False)
    t0 = time.perf_counter()
    rec = {}
    if K == 0:
        r = match_into_database(src, allp, out, cconf, second_look=look, inlier_px=1.5, refit_below_deg=3.0)
        rec["second_look_s"] = r["second_look"]["time_s"]
    else:
        with ColmapSink(out, geometry="ours") as sink:
            with shared_cluster(src, allp, sink, cconf) as client:
                t1 = time.perf_counter()
                w1 = pairs_from_spec(f"retrieval:{K}", names, src, retrieval=dict(progress=False), retrieval_cache=False).pairs
                rec["retrieval_s"] = time.perf_counter() - t1
                match_collection(src, w1, sink, cconf, client=client)
                rec["wave1_pairs"] = len(w1); rec["wave1_s"] = time.perf_counter() - t1
                t2 = time.perf_counter()
                tried, inl, nkp = _read_inliers(sink)
                w1s = {frozenset(p) for p in w1}
                w2 = [p for p in allp if frozenset(p) not in w1s]
                first = priors(w2, inl, nkp)
                match_collection(src, w2, sink, cconf, client=client, first=first)
                rec["wave2_pairs"] = len(w2); rec["wave2_s"] = time.perf_counter() - t2
                t3 = time.perf_counter()
                lk = second_look(src, sink, cconf, look, client=client)
                rec["second_look_s"] = time.perf_counter() - t3; rec["looked"] = lk["looked"]; rec["sl_verified"] = lk["verified"]
            rec["tighten"] = sink.tighten_inliers(1.5, refit_below_deg=3.0)["time_s"]
    rec["match_s"] = time.perf_counter() - t0
    rec["total_s"] = time.perf_counter() - t00
    import pycolmap
    db = pycolmap.Database.open(out) if hasattr(pycolmap.Database, "open") else pycolmap.Database(out)
    pids, counts = db.read_two_view_geometry_num_inliers()
    rec["verified_pairs"] = int(sum(1 for c in counts if c > 0)); rec["inliers"] = int(sum(counts))
    rec["K"] = K
    print(json.dumps(rec))

if __name__ == "__main__":
    main()
