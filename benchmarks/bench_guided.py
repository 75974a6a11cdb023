"""Guided matching vs brute force and peers on a real high-resolution pair.

    python benchmarks/bench_guided.py [--pair 0002 0003] [--sizes 5000 10000 20000 40000] [--repeats 3]

Herz-Jesus-P8 (Strecha, 3072x2048, GT poses) from $GUIDEDMATCH_DATA (default ../shared/data), full
resolution, SIFT with contrastThreshold=0.01 (~40k features per image; --contrast 0.002: ~92k). For each
feature budget (the strongest N by response; 'all' = every feature) the same features are matched by:

* guidedmatch so+epi+ia (all model fits included, detection excluded), median of --repeats runs
* guidedmatch brute force (blocked GEMM) + ratio 0.8
* faiss IndexFlatL2 exact 2-NN + ratio 0.8 (if faiss is installed: pip install -e ".[bench]")
* OpenCV FLANN (KD-tree, 4 trees, 64 checks) + ratio 0.8
  (peers: one warm-up call on 256 features, then median of --peer-repeats runs)

Reports time, speed-up over faiss (same run), descriptor comparisons (exact), matches, GT-epipolar inliers
(symmetric epipolar distance < 3 px under the GT F of the pairs file) and precision; peak traced memory of
the guided run (NumPy allocations via tracemalloc, plus the kernel's O(queries) outputs). Writes
benchmarks/results/guided.json (with run metadata), prints a table, saves a log-log plot guided_scaling.png.
Features are cached in --cache (default ~/.cache/guidedmatch) so reruns skip detection.
"""
from __future__ import annotations

import argparse
import sys
import tracemalloc
from pathlib import Path

import numpy as np


def _features(path, cache: Path, contrast: float = 0.01):
    from guidedmatch.features import Features, detect

    cache.mkdir(parents=True, exist_ok=True)
    tag = "ct001" if contrast == 0.01 else f"ct{contrast:g}".replace(".", "")
    f = cache / (Path(path).parent.parent.name + "_" + Path(path).stem + f"_sift_{tag}.npz")
    if f.exists():
        return Features.load(f)
    feats = detect(path, "sift", contrastThreshold=contrast)
    feats.save(f)
    return feats


def _strongest(f, n):
    if n is None or n >= len(f):
        return f
    idx = np.sort(np.argsort(-f.responses, kind="stable")[:n])
    return f.subset(idx)


def run_peer(name, f1, f2):
    """``(pairs, seconds)`` of a peer matcher from :mod:`guidedmatch.evaluation.peers` (ratio 0.8)."""
    from guidedmatch.evaluation import peers

    if name == "faiss":
        r = peers.match_faiss(f1, f2, ratio=0.8)
    elif name == "flann":
        r = peers.match_opencv_flann(f1, f2, ratio=0.8, trees=4, checks=64)
    else:
        raise ValueError(name)
    return r.pairs, r.stats.time_s


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", nargs=2, default=["0002", "0003"])
    ap.add_argument("--sizes", nargs="+", default=["5000", "10000", "20000", "all"])
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of the guided matcher (median reported)")
    ap.add_argument("--peer-repeats", type=int, default=3, help="timed runs of faiss / FLANN (median reported)")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidedmatch"))
    ap.add_argument("--no-bf", action="store_true", help="skip our brute force (slow at 40k)")
    ap.add_argument("--contrast", type=float, default=0.01,
                    help="SIFT contrastThreshold (0.01: ~40k features per image; 0.002: ~92k)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"))
    args = ap.parse_args(argv)

    from guidedmatch.bruteforce import match_bruteforce
    from guidedmatch.datasets import data_root, strecha_pairs
    from guidedmatch.evaluation.meta import run_metadata, write_json
    from guidedmatch.matcher import match

    root = data_root()
    if root is None:
        raise SystemExit("no data: set GUIDEDMATCH_DATA (see README)")
    pair = next(p for p in strecha_pairs(root) if Path(p.image1).stem == args.pair[0] and Path(p.image2).stem == args.pair[1])
    print(f"pair {pair.name}; detecting / loading SIFT (contrastThreshold={args.contrast:g}) ...", flush=True)
    F1 = _features(pair.image1, Path(args.cache), args.contrast)
    F2 = _features(pair.image2, Path(args.cache), args.contrast)
    print(f"features: {len(F1)} x {len(F2)}", flush=True)
    from guidedmatch.evaluation.peers import faiss_available

    peers = ["faiss", "flann"] if faiss_available() else ["flann"]
    if "faiss" not in peers:
        print("faiss not installed: skipping it (pip install -e '.[bench]')")
    match(_strongest(F1, 2000), _strongest(F2, 2000), "so+epi+ia")  # JIT/cache warm-up
    rows = []
    for size in args.sizes:
        n = None if size == "all" else int(size)
        f1, f2 = _strongest(F1, n), _strongest(F2, n)
        row = dict(budget=size, n1=len(f1), n2=len(f2), bf_comparisons=len(f1) * len(f2), methods={})

        def record(name, pairs, times, comparisons, stats=None):
            ok = pair.gt.correct(f1.keypoints[pairs[:, 0]], f2.keypoints[pairs[:, 1]]) if len(pairs) else np.zeros(0, bool)
            row["methods"][name] = dict(time_s=float(np.median(times)), times_s=[float(t) for t in times],
                                        comparisons=comparisons, matches=int(len(pairs)), gt_inliers=int(ok.sum()),
                                        precision=float(ok.mean()) if len(ok) else float("nan"), stats=stats)

        times = []
        for _ in range(args.repeats):
            res = match(f1, f2, "so+epi+ia")
            times.append(res.stats.time_s)
        # memory in a separate, untimed run: tracemalloc slows every NumPy allocation (+20 % time at 40k)
        tracemalloc.start()
        match(f1, f2, "so+epi+ia")
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        st = res.stats
        record("so+epi+ia", res.pairs, times, st.comparisons,
               dict(timing=st.timing, candidates_per_query=st.candidates_per_query, fallbacks=st.fallbacks,
                    updates=st.updates, peak_traced_mb=peak / 2**20,
                    kernel_outputs_mb=5 * 8 * len(f1) / 2**20, dropped_outside_overlap=st.dropped_outside_overlap))
        if not args.no_bf:
            r = match_bruteforce(f1, f2)
            record("bf", r.pairs, [r.stats.time_s], r.stats.comparisons)
        for name in peers:
            run_peer(name, _strongest(f1, 256), _strongest(f2, 256))  # warm-up: thread pools, first-call costs
            runs = [run_peer(name, f1, f2) for _ in range(args.peer_repeats)]
            record(name, runs[-1][0], [t for _, t in runs], len(f1) * len(f2) if name == "faiss" else None)
        rows.append(row)
        m = row["methods"]
        print(f"  {size:>6}: guided {m['so+epi+ia']['time_s']:.3f}s  faiss {m.get('faiss', {}).get('time_s', float('nan')):.3f}s "
              f"comparisons {100 * m['so+epi+ia']['comparisons'] / row['bf_comparisons']:.2f}%", flush=True)

    names = ["so+epi+ia"] + ([] if args.no_bf else ["bf"]) + peers
    print()
    print(f"{'features':>15} {'method':>10} {'time (s)':>9} {'x faiss':>8} {'comparisons':>15} {'% of BF':>8} {'matches':>8} {'GT inl.':>8} {'prec.':>7}")
    for row in rows:
        ft = row["methods"].get("faiss", {}).get("time_s")
        for nm in names:
            m = row["methods"][nm]
            comp = m["comparisons"]
            print(f"{row['n1']:>7}x{row['n2']:<7} {nm:>10} {m['time_s']:>9.3f} {ft / m['time_s'] if ft else float('nan'):>8.1f} "
                  f"{comp if comp is not None else 'n/a':>15} {(100 * comp / row['bf_comparisons']) if comp else float('nan'):>7.2f}% "
                  f"{m['matches']:>8} {m['gt_inliers']:>8} {100 * m['precision']:>6.1f}%")
    g = rows[-1]["methods"]["so+epi+ia"]["stats"]
    print(f"\nguided run at {rows[-1]['n1']}x{rows[-1]['n2']}: peak traced NumPy memory {g['peak_traced_mb']:.1f} MB "
          f"(+ {g['kernel_outputs_mb']:.1f} MB kernel outputs); timing {g['timing']}")
    out = Path(args.out)
    write_json(out / "guided.json", dict(meta=run_metadata(seed=0), pair=pair.name, contrast=args.contrast,
                                         command="python benchmarks/bench_guided.py " + " ".join(sys.argv[1:] if argv is None else argv), rows=rows))
    _plot(rows, names, out / "guided_scaling.png", args.contrast)
    print(f"wrote {out / 'guided.json'} and {out / 'guided_scaling.png'}")


def _plot(rows, names, path, contrast=0.01):
    from guidedmatch.plots import _plt, save_figure

    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    n = [r["n1"] for r in rows]
    for nm in names:
        a.loglog(n, [r["methods"][nm]["time_s"] for r in rows], "o-", label=nm)
    a.set_xlabel("features per image")
    a.set_ylabel("matching time (s)")
    a.legend()
    a.grid(True, which="both", alpha=0.3)
    if "faiss" in names:
        b.semilogx(n, [r["methods"]["faiss"]["time_s"] / r["methods"]["so+epi+ia"]["time_s"] for r in rows], "o-",
                   label="measured (medians, same run)")
        b.axhline(20.0, color="grey", ls="--", lw=1, label="target at 40k: 20x")
        b.set_ylabel("speed-up of so+epi+ia over faiss exact 2-NN")
        b.legend(loc="upper left")
    b.set_xlabel("features per image")
    b.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"Herz-Jesus-P8 full resolution, SIFT contrastThreshold={contrast:g}")
    save_figure(fig, path)


def replot(json_path=None):
    """Redraw guided_scaling.png from an existing guided.json (no re-run)."""
    import json

    path = Path(json_path or Path(__file__).parent / "results" / "guided.json")
    d = json.loads(path.read_text())
    names = [nm for nm in ("so+epi+ia", "bf", "faiss", "flann") if nm in d["rows"][0]["methods"]]
    _plot(d["rows"], names, path.with_name("guided_scaling.png"))


if __name__ == "__main__":
    main()
