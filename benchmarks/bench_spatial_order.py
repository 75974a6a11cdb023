"""Benchmark of guidedmatch.spatial_order: fit time, lookup time, first-call JIT time, synthetic accuracy.

Usage::

    /work/venv/bin/python benchmarks/bench_spatial_order.py [--repeats 30] [--seeds 10] [--out PATH]

Prints a table and writes JSON (default ``benchmarks/results/spatial_order.json``) with run metadata.
Runs single-threaded (thread env vars are pinned to 1 before NumPy/Numba load). Targets: fit with
omega* (K1D) and the gap table <= 10 ms at N = 600, <= 100 ms at N = 2000; lookup of 100k features <= 20 ms.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from guidedmatch.spatial_order import (  # noqa: E402
    SpatialOrderConfig,
    admissible_x_ranges,
    fit_spatial_order,
    inversions_per_match,
    probability_correct,
)
from guidedmatch.testing.permutations import generate_permutation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def run_metadata() -> dict:
    from guidedmatch.evaluation.meta import run_metadata as rm

    return rm()


def first_call_times() -> dict:
    """First fit in a fresh interpreter with an empty Numba cache (true JIT compile) and with the warm cache."""
    code = ("import time; t=time.perf_counter(); import numpy as np; "
            "from guidedmatch.spatial_order import fit_spatial_order; "
            "from guidedmatch.testing.permutations import generate_permutation; t1=time.perf_counter(); "
            "sp=generate_permutation(600,300,seed=0); t2=time.perf_counter(); fit_spatial_order(sp.x1,sp.x2); "
            "t3=time.perf_counter(); fit_spatial_order(sp.x1,sp.x2); t4=time.perf_counter(); "
            "print(t1-t, t3-t2, t4-t3)")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, env_extra in (("cold_cache", {"NUMBA_CACHE_DIR": tmp}), ("warm_cache", {"NUMBA_CACHE_DIR": tmp})):
            env = dict(os.environ, **env_extra)
            res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
            vals = [float(v) for v in res.stdout.split()] if res.returncode == 0 else [float("nan")] * 3
            out[label] = {"import_s": vals[0], "first_fit_s": vals[1], "second_fit_s": vals[2]}
    return out


def time_fit(n: int, repeats: int, overlap: str = "k1d") -> dict:
    cfg = SpatialOrderConfig(overlap=overlap)
    times, stages = [], []
    for r in range(repeats):
        sp = generate_permutation(n, n // 2, seed=1000 + r)
        t = time.perf_counter()
        m = fit_spatial_order(sp.x1, sp.x2, cfg)
        times.append(time.perf_counter() - t)
        stages.append(m.timings)
    keys = [k for k in ("ranks", "overlap", "probabilities", "gap_table") if all(k in s for s in stages)]
    return {"n": n, "overlap": overlap, "median_ms": 1e3 * float(np.median(times)), "min_ms": 1e3 * float(np.min(times)),
            "max_ms": 1e3 * float(np.max(times)),
            "stages_median_ms": {k: 1e3 * float(np.median([s[k] for s in stages])) for k in keys}}


def time_lookup(n: int, m: int, repeats: int) -> dict:
    sp = generate_permutation(n, n // 2, seed=7)
    model = fit_spatial_order(sp.x1, sp.x2)
    xq = np.random.default_rng(0).uniform(0, 1000, m)
    admissible_x_ranges(model, xq)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        admissible_x_ranges(model, xq)
        times.append(time.perf_counter() - t)
    return {"n": n, "queries": m, "median_ms": 1e3 * float(np.median(times)), "min_ms": 1e3 * float(np.min(times))}


def accuracy(n: int, seeds: int, frac: float = 0.5) -> dict:
    err, pg, pb, cov, adm, keep_frac = [], [], [], [], [], []
    for s in range(seeds):
        sp = generate_permutation(n, int(frac * n), n_holdout=max(20, n // 20), seed=s)
        m = fit_spatial_order(sp.x1, sp.x2)
        err.append(abs(m.n_good - sp.n_good) / n)
        p = m.probabilities
        pg.append(p[sp.is_good].mean())
        pb.append(p[~sp.is_good].mean())
        keep, lo, hi, _ = admissible_x_ranges(m, sp.holdout_x1)
        cov.append(np.mean(keep & (sp.holdout_x2 >= lo) & (sp.holdout_x2 <= hi)))
        keep_frac.append(keep.mean())
        h = np.searchsorted(m.x1_sorted, sp.holdout_x1, side="left")
        adm.append(np.mean(m.gap_count[h] / (m.n_window + 1)))
    return {"n": n, "n_good_frac": frac, "seeds": seeds, "ng_abs_err_over_n": float(np.mean(err)),
            "ng_abs_err_over_n_max": float(np.max(err)), "mean_p_correct": float(np.mean(pg)),
            "mean_p_incorrect": float(np.mean(pb)), "gap_coverage": float(np.mean(cov)),
            "gap_coverage_min": float(np.min(cov)), "admitted_gap_fraction": float(np.mean(adm)),
            "holdout_kept_fraction": float(np.mean(keep_frac))}


def exact_vs_gaussian(seeds: int = 3) -> dict:
    d_all, d_valid = [], []
    t_exact = []
    for s in range(seeds):
        sp = generate_permutation(200, 120, overlap=(1.0, 1.0), seed=s)
        n = 200
        hl, hr = inversions_per_match(sp.sigma)
        idx = np.arange(n)
        args = (idx, sp.sigma, hl + hr, n - 1, 120.0, n)
        t = time.perf_counter()
        pe = probability_correct(*args, method="exact")
        t_exact.append(time.perf_counter() - t)
        pgs = probability_correct(*args, method="gaussian")
        d = np.abs(pe - pgs)
        d_all.append(d)
        d_valid.append(d[(idx / n >= 0.2) & (idx / n <= 0.8)])
    da, dv = np.concatenate(d_all), np.concatenate(d_valid)
    return {"n": 200, "n_good": 120, "max_abs_diff_all": float(da.max()), "max_abs_diff_interior": float(dv.max()),
            "mean_abs_diff_interior": float(dv.mean()), "exact_time_s_per_200": float(np.median(t_exact))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "spatial_order.json"))
    ap.add_argument("--no-jit-probe", action="store_true", help="skip the fresh-interpreter JIT measurement")
    args = ap.parse_args()

    t = time.perf_counter()
    sp = generate_permutation(600, 300, seed=0)
    fit_spatial_order(sp.x1, sp.x2)  # in-process first call (Numba cache load or compile)
    first_in_process = time.perf_counter() - t

    fits = [time_fit(n, args.repeats) for n in (200, 600, 2000)]
    fits.append(time_fit(600, max(3, args.repeats // 5), "k2d"))
    fits.append(time_fit(2000, max(3, args.repeats // 5), "none"))
    lookups = [time_lookup(600, 100_000, args.repeats), time_lookup(2000, 100_000, args.repeats)]
    acc = [accuracy(n, args.seeds if n < 2000 else max(3, args.seeds // 2)) for n in (200, 600, 2000)]
    acc.append(accuracy(600, args.seeds, frac=0.8))
    acc.append(accuracy(600, args.seeds, frac=0.3))
    evg = exact_vs_gaussian()
    jit = {"in_process_first_fit_s": first_in_process}
    if not args.no_jit_probe:
        jit.update(first_call_times())

    print("\nfit_spatial_order (generated permutations, N_G = N/2, random partial overlap)")
    print(f"{'N':>6} {'overlap':>8} {'median ms':>10} {'min ms':>8} {'max ms':>8}  stages (median ms)")
    for f in fits:
        st = " ".join(f"{k}={v:.2f}" for k, v in f["stages_median_ms"].items())
        print(f"{f['n']:>6} {f['overlap']:>8} {f['median_ms']:>10.2f} {f['min_ms']:>8.2f} {f['max_ms']:>8.2f}  {st}")
    print("\nadmissible_x_ranges")
    for lk in lookups:
        print(f"  N={lk['n']:>5}, {lk['queries']} queries: median {lk['median_ms']:.2f} ms (min {lk['min_ms']:.2f})")
    print("\nfirst call / JIT:", json.dumps(jit, indent=None))
    print("\naccuracy (mean over seeds)")
    print(f"{'N':>6} {'N_G/N':>6} {'|dN_G|/N':>9} {'max':>6} {'P(good)':>8} {'P(bad)':>7} {'cover':>6} {'cov min':>7} "
          f"{'admit':>6} {'kept':>5}")
    for a in acc:
        print(f"{a['n']:>6} {a['n_good_frac']:>6.1f} {a['ng_abs_err_over_n']:>9.3f} {a['ng_abs_err_over_n_max']:>6.3f} "
              f"{a['mean_p_correct']:>8.3f} {a['mean_p_incorrect']:>7.3f} {a['gap_coverage']:>6.3f} "
              f"{a['gap_coverage_min']:>7.3f} {a['admitted_gap_fraction']:>6.3f} {a['holdout_kept_fraction']:>5.2f}")
    print("\nexact vs gaussian P(G|H):", json.dumps(evg))

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {"benchmark": "spatial_order", "command": " ".join([Path(sys.executable).as_posix()] + sys.argv),
              "meta": run_metadata(), "fit": fits, "lookup": lookups, "jit": jit, "accuracy": acc,
              "exact_vs_gaussian": evg}
    out.write_text(json.dumps(result, indent=2))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
