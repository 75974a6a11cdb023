"""tools/ordered_exhaustive.py FEATURES_DB OUT_DB K: exhaustive pairs in order of evidence (a prototype, not kept): retrieval:K shortlist, the
verified expansion with the prior, then every remaining pair with the prior, then the second look (skipping every
pair matched with a prior). Prints stage times and counts as JSON."""
import sys, json, time, shutil
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.sinks import ColmapSink
from guidedmatch.collection.config import CollectionConfig
from guidedmatch.collection.engine import match_collection
from guidedmatch.collection.expansion import match_collection_expanded
from guidedmatch.collection.retrieval import retrieval_pairs
from guidedmatch.collection.second_look import second_look, _read_inliers, priors
from guidedmatch.sfm import verified_inliers
feat, out, K = sys.argv[1], sys.argv[2], int(sys.argv[3])
rest_prior = len(sys.argv) < 5 or sys.argv[4] != "noprior"
shutil.copyfile(feat, out)
t0 = time.perf_counter(); rec = {}
source = ColmapSource(out)
names = source.names()
cconf = CollectionConfig(progress=False)
sl = retrieval_pairs(source, names, dict(k=K, progress=False), cache=True)
with ColmapSink(out, geometry="ours") as sink:
    rep = match_collection_expanded(source, list(sl.pairs), sink, cconf, {})
    rec["expanded"] = dict(wall=rep.wall_s, stages=[(s["stage"], s.get("pairs"), s.get("verified"), round(s.get("time_s", 0), 1)) for s in rep.stages])
    tried, inliers, nkp = _read_inliers(sink)
    rest = [(a, b) for i, a in enumerate(names) for b in names[i + 1:] if frozenset((a, b)) not in tried]
    t = time.perf_counter()
    first = priors(rest, inliers, nkp) if rest_prior else None
    tp = time.perf_counter() - t
    r2 = match_collection(source, rest, sink, cconf, first=first)
    rec["rest"] = dict(pairs=len(rest), prior_s=tp, wall=time.perf_counter() - t)
    t = time.perf_counter()
    look = second_look(source, sink, cconf, {}, looked=list(rep.prior_pairs) + (rest if rest_prior else []))
    rec["second_look"] = dict(looked=look["looked"], verified=look["verified"], wall=time.perf_counter() - t)
rec["total_wall"] = time.perf_counter() - t0
rec["verified_pairs"], rec["verified_inliers"] = verified_inliers(out)
print(json.dumps(rec))
