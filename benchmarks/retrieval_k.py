# usage: python benchmarks/retrieval_k.py 5,10,20,30  (needs the bench_large cache in /work/cache/large)
"""Shortlist vs scene labels for several K (retrieval stage only; vocabulary reused across K)."""
import json, sys, time
from pathlib import Path
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.collection.retrieval import retrieval_pairs
from guidedmatch.evaluation.bench_large import scene_of, image_names
work = Path("/work/cache/large"); data = Path("/work/shared/data")
names = image_names(data); scenes = scene_of(data, names)
n = len(names)
same = {(names[i], names[j]) if names[i] < names[j] else (names[j], names[i]) for i in range(n) for j in range(i + 1, n) if scenes[names[i]] == scenes[names[j]]}
src = ColmapSource(work / "features.db")
cache = Path("/tmp/scale/kstudy.npz")
for k in [int(x) for x in sys.argv[1].split(",")]:
    t = time.perf_counter()
    r = retrieval_pairs(src, None, dict(k=k, progress=False), cache=cache)
    got = {tuple(sorted(p)) for p in r.pairs}
    row = dict(k=k, pairs=len(got), same_scene_pairs=len(same), same_in_shortlist=len(same & got),
               same_recall=len(same & got) / len(same), across_in_shortlist=len(got - same), time_s=time.perf_counter() - t,
               reused=r.info["reused"], vocabulary_s=r.info["vocabulary_s"], assign_s=r.info["assign_s"])
    print(json.dumps(row), flush=True)
