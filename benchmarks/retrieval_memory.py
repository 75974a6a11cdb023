# usage: python benchmarks/retrieval_memory.py db DATABASE | fake N_IMAGES N_FEATURES
"""Peak traced memory of the retrieval stage: the real database (COLMAP default SIFT) and a synthetic 50k-feature source."""
import sys, time, tracemalloc, resource, json
import numpy as np
from guidedmatch.collection.retrieval import retrieval_pairs
from guidedmatch.collection.sources import ColmapSource
from guidedmatch.features import Features

class Fake:
    def __init__(self, n, nf):
        self.n, self.nf = n, nf
    def names(self): return [f"im{i:03d}" for i in range(self.n)]
    def num_features(self, name): return self.nf
    def load(self, name):
        rng = np.random.default_rng(int(name[2:]))
        d = rng.integers(0, 120, (self.nf, 128)).astype(np.float32)
        return Features(rng.uniform(0, 1000, (self.nf, 2)), d, (1000, 1000))

which = sys.argv[1]
src = ColmapSource(sys.argv[2]) if which == "db" else Fake(int(sys.argv[2]), int(sys.argv[3]))
tracemalloc.start()
t = time.perf_counter()
r = retrieval_pairs(src, None, dict(k=20, progress=False), cache=None)
cur, peak = tracemalloc.get_traced_memory()
nf = [src.num_features(n) for n in src.names()]
print(json.dumps(dict(which=which, images=len(nf), features_mean=float(np.mean(nf)), features_max=int(max(nf)),
                      peak_traced_mb=peak / 2**20, maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      time_s=time.perf_counter() - t, info=r.info)))
