"""The first probe of one IVF coarse quantizer per collection instead of one k-means per image (2026-12-01). The package
has used it in collections of 16 images or more since the twentieth round (``guidedmatch.collection.quantizer``); the
reasons it was not adopted then, below, and what answered them: the recall was checked against verified inliers,
verdicts and poses (accuracy history, twentieth round); ``build_comparisons`` counts the assignment only; the
quantizer is trained once in the calling process from the source's images, not the pairs to do, and sent to every
backend with the task spec; a collection's pair now equals ``match`` of the two images prepared with the same
quantizer (the hloc round trip runs on fewer than 16 images and still compares with ``match`` alone).

``prepared.PreparedImage`` trains a k-means quantizer for every image's faiss index (Herz-Jesus-P8: ~0.04 s per image
at 11.4k SIFT, ~0.3 s at 68k, on one core). This script compares, on a COLMAP database:

* per-image indexes (the package's settings: nlist = 2 sqrt(N), 20 training points per cell, 8 iterations, SQ8
  direct codes, nprobe 4), with
* indexes whose quantizer is trained once, on a pooled sample of the first 3 images, then only filled (``add``),

by build time, 1-NN recall against exact search (every 20th descriptor of image A searched in image B) and distance
evaluations per query (coarse + probed lists).

    python tools/ivf_shared_quantizer.py /tmp/lead_coll/default.db

Measured on Herz-Jesus-P8 (2026-12-01): 11.4k: builds 0.31 s -> 0.03 s training + 0.08-0.10 s adds; 1-NN recall
(all queries, not only ratio-test matches) -0.05 to +0.02 (per-image 0.75-0.87); comparisons +1-2 %. 68k: 2.36 s ->
0.16 + 1.11 s; recall -0.01; comparisons +1.5-4 %. Not adopted: the recall loss at 11.4k needs checking against
verified inliers and verdicts, the matcher's ski-rental uses the build cost (``PreparedImage.build_comparisons``),
every backend must train on the same images (determinism across 1 / 2 workers and in-process), and a pair matched
in a collection would no longer give the same matches as ``guidedmatch.match`` on the pair alone (the hloc round trip
test checks exactly that; the per-image index is what makes the two equal today).
"""
from __future__ import annotations

import sys
import time

import numpy as np


def main(db: str) -> None:
    import faiss

    from guidedmatch.collection.sources import ColmapSource

    faiss.omp_set_num_threads(1)
    src = ColmapSource(db)
    names = src.names()
    desc = {n: np.ascontiguousarray(src.load(n).descriptors, np.float32) for n in names}

    def build(d, quantizer=None):
        n = len(d)
        nlist = quantizer.ntotal if quantizer is not None else int(2 * np.sqrt(n))
        t = time.perf_counter()
        q = quantizer if quantizer is not None else faiss.IndexFlatL2(d.shape[1])
        idx = faiss.IndexIVFScalarQuantizer(q, d.shape[1], nlist, faiss.ScalarQuantizer.QT_8bit_direct,
                                            faiss.METRIC_L2, False)
        if quantizer is None:
            idx.cp.niter, idx.cp.seed = 8, 0
            idx.cp.min_points_per_centroid, idx.cp.max_points_per_centroid = 1, 20
            rng = np.random.default_rng(0)
            idx.train(d[np.sort(rng.choice(n, min(n, 20 * nlist), replace=False))])
        else:
            idx.is_trained = True  # SQ8 direct codes need no training; the quantizer is trained
        idx.add(d)
        idx.nprobe = 4
        return idx, time.perf_counter() - t

    nl = int(2 * np.sqrt(np.median([len(d) for d in desc.values()])))
    pool = np.concatenate([desc[n][np.random.default_rng(i).choice(len(desc[n]), 20 * nl // 3, replace=False)]
                           for i, n in enumerate(names[:3])])
    t = time.perf_counter()
    shared = faiss.IndexFlatL2(pool.shape[1])
    km = faiss.Clustering(pool.shape[1], nl)
    km.niter, km.seed, km.min_points_per_centroid, km.max_points_per_centroid = 8, 0, 1, 20
    km.train(pool, shared)
    print(f"shared quantizer: {nl} cells, trained in {time.perf_counter() - t:.3f} s")
    own, sh, t_own, t_sh = {}, {}, 0.0, 0.0
    for n in names:
        own[n], a = build(desc[n])
        sh[n], b = build(desc[n], shared)
        t_own, t_sh = t_own + a, t_sh + b
    print(f"builds: per-image {t_own:.3f} s, shared-quantizer adds {t_sh:.3f} s")
    for a, b in zip(names[:-1:2], names[1::2]):
        queries = desc[a][::20]
        exact = faiss.IndexFlatL2(queries.shape[1])
        exact.add(desc[b])
        _, nn = exact.search(queries, 1)
        for tag, idx in (("per-image", own[b]), ("shared", sh[b])):
            _, cells = idx.quantizer.search(queries, idx.nprobe)
            sizes = np.array([idx.invlists.list_size(i) for i in range(idx.nlist)])
            comparisons = (len(queries) * idx.nlist + sizes[cells].sum()) / len(queries)
            _, got = idx.search(queries, 1)
            print(f"{a}->{b} {tag:9s} recall {float((got[:, 0] == nn[:, 0]).mean()):.3f}, "
                  f"comparisons/query {comparisons:.0f}")


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/lead_coll/default.db")
