"""Prepared-image settings swept on every Herz-Jesus-P8 pair: our so+epi+ia vs the cached IVF-SQ8 peer, same run.

    python benchmarks/prepared_sweep.py [--cap 8192|0] [--kmeans-iters 4 8] [--train-per-list 40] [--threads 1]

Features come from the ``guidedmatch bench pairs`` cache (``--cache``, default
``benchmarks/results/pairs/features``; run that bench once to fill it): SIFT ``contrastThreshold=0.01``, all features
(``--cap 0``, ~40k) or the strongest ``--cap``. For each setting: every image prepared (``guidedmatch.prepared``) with
the index built lazily inside the matches (as a one-off user gets it), the 28 scene pairs and the 5 unrelated pairs
matched, and the peer (``peers.match_faiss_ivf`` with cached indexes, faiss limited to ``--threads``) searched on the
same pairs. Prints wall and CPU totals, the index build time, matches, verified pairs and GT inliers (< 3 px
symmetric epipolar distance); used to choose ``PreparedConfig.kmeans_iters`` (docs/pairs.md).
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cap", type=int, default=8192, help="strongest features per image (0: all)")
    ap.add_argument("--kmeans-iters", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--train-per-list", type=int, default=40)
    ap.add_argument("--threads", type=int, default=1, help="faiss threads of the IVF peer")
    ap.add_argument("--cache", default="benchmarks/results/pairs/features")
    a = ap.parse_args()

    import faiss

    import guidedmatch as gm
    from guidedmatch.datasets import data_root
    from guidedmatch.evaluation import bench_pairs as bp
    from guidedmatch.evaluation import peers
    from guidedmatch.prepared import PreparedConfig, prepare

    faiss.omp_set_num_threads(a.threads)
    cache = Path(a.cache)
    scene, unrelated = bp.pair_list(data_root(), False)
    feats = {}
    for p in scene:
        for path in (Path(p.image1), Path(p.image2)):
            feats[path.stem] = bp.strongest(bp.cached_features(path, cache, 0.01), a.cap or None)
    cap2 = max(len(f) for f in feats.values())
    for _, _, photo in unrelated:
        feats[photo.stem] = bp.strongest(bp.cached_features(photo, cache, 0.01, long_side=bp.LONG_SIDE), cap2)
    gts = {p.name: p.gt for p in scene}
    items = [(p.name, Path(p.image1).stem, Path(p.image2).stem) for p in scene]
    items += [(n, img.stem, photo.stem) for n, img, photo in unrelated]
    ivf = {k: peers.build_ivf_index(f) for k, f in feats.items()}
    gm.match(feats[items[0][1]], feats[items[0][2]])  # compile / warm

    def gt_count(name, res, f1, f2):
        if name not in gts or not len(res.pairs):
            return 0
        return int(gts[name].correct(f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]]).sum())

    for ki in a.kmeans_iters:
        prep = {k: prepare(f, PreparedConfig(kmeans_iters=ki, train_per_list=a.train_per_list))
                for k, f in feats.items()}
        tot = dict(ours_wall=0.0, ours_cpu=0.0, ivf_wall=0.0, ivf_cpu=0.0, matches=0, verified=0, gt=0, gt_ivf=0)
        unrel = dict(ours_wall=0.0, ivf_wall=0.0)
        for name, x, y in items:
            c, t = time.process_time(), time.perf_counter()
            r = peers.match_faiss_ivf(feats[x], feats[y], index1=ivf[x], index2=ivf[y])
            ivf_wall, ivf_cpu = time.perf_counter() - t, time.process_time() - c
            c, t = time.process_time(), time.perf_counter()
            res = gm.match(prep[x], prep[y])
            ours_wall, ours_cpu = time.perf_counter() - t, time.process_time() - c
            if name in gts:
                tot["ours_wall"] += ours_wall
                tot["ours_cpu"] += ours_cpu
                tot["ivf_wall"] += ivf_wall
                tot["ivf_cpu"] += ivf_cpu
                tot["matches"] += len(res.pairs)
                tot["verified"] += res.geometry.verdict == "verified"
                tot["gt"] += gt_count(name, res, feats[x], feats[y])
                tot["gt_ivf"] += gt_count(name, r, feats[x], feats[y])
            else:
                unrel["ours_wall"] += ours_wall
                unrel["ivf_wall"] += ivf_wall
        build = sum(p.index_build_s for p in prep.values())
        print(f"kmeans_iters={ki} train_per_list={a.train_per_list} cap={a.cap or 'all'} load={os.getloadavg()[0]:.1f}: "
              f"28 pairs ours {tot['ours_wall']:.2f} s wall / {tot['ours_cpu']:.2f} s CPU, IVF {tot['ivf_wall']:.2f} / "
              f"{tot['ivf_cpu']:.2f} s (CPU ratio {tot['ours_cpu'] / tot['ivf_cpu']:.2f}); index builds {build:.2f} s; "
              f"matches {tot['matches']}, verified {tot['verified']}, GT inliers {tot['gt']} (IVF {tot['gt_ivf']}); "
              f"unrelated ours {unrel['ours_wall']:.2f} s, IVF {unrel['ivf_wall']:.2f} s", flush=True)


if __name__ == "__main__":
    main()
