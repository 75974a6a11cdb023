"""Match a COLMAP database with ``guidedmatch colmap`` (in this process) under another draw of the approximate
neighbours (accuracy history, twentieth and twenty-first rounds): KIND ``kmeans`` = the defaults with every image's
IVF k-means seeded SEED (``PreparedConfig(seed=SEED)``; the defaults are seed 0); ``shared`` = ``--shared-quantizer on``
with the collection's quantizer trained with seed SEED. The matches differ from the defaults' only through which
approximate neighbours the unguided starts find.

    python tools/kmeans_draw.py DATABASE kmeans|shared SEED
"""
import sys

db, kind, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
import guidedmatch.collection.quantizer as Q  # noqa: E402
import guidedmatch.prepared as P  # noqa: E402

if kind == "kmeans":
    orig = P.prepare

    def prepare(features, config=None, quantizer=None):
        return orig(features, config or P.PreparedConfig(seed=seed), quantizer)

    P.prepare = prepare
    extra = []
elif kind == "shared":
    orig_t = Q.train_quantizer
    Q.train_quantizer = lambda sample, nlist, seed_=0, iters=25, **kw: orig_t(sample, nlist, seed=seed, iters=iters)
    extra = ["--shared-quantizer", "on"]
else:
    sys.exit(f"KIND must be kmeans or shared, got {kind!r}")
from guidedmatch.cli import main  # noqa: E402

sys.exit(main(["colmap", db, "--workers", "0", "--no-progress", "--log", "none"] + extra))
