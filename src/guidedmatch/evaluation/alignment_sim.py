"""Alignment simulation (Teng & Dong §III-E, figure "Ratio of normalized Kendall distance vs. viewing
angle"): which alignment homography best restores the x-order of the matches?

Per view pair (:func:`guidedmatch.testing.twoview.sphere_pair`): 200 points uniform in the unit ball,
two cameras (f = 800 px, 640x480) at random directions on a sphere about the origin, random distance
in [2.5, 5], looking at the origin, random roll uniform in [-180, 180] deg; 1 px Gaussian noise on the
projections of both images. ``F`` is estimated from the noisy correspondences with MAGSAC++
(:func:`guidedmatch.epipolar.estimate_fundamental`, as the matcher does), the focal length by
Bougnoux with the ``w + h`` fallback, then every approach of :mod:`guidedmatch.alignment` is applied
and the ratio ``K^(after) / K^(before)`` of the normalised Kendall distance of the x-coordinates is
recorded against the angle between the two viewing directions. Side columns: the same with the
true ``K`` (still the estimated ``F``). Approach "d" maps image 1 by ``H_L`` and image 2 by ``H_R``.

Outputs in ``out_dir``: ``alignment_samples.csv`` (one row per pair), ``alignment_ratio.png``
(scatter + per-10-degree-bin median, like the paper's figure), ``alignment_table.md`` (median ratio
per bin per approach) and ``alignment_summary.json`` (table, fallback counts, run metadata).
"""
from __future__ import annotations

import csv
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

__all__ = ["khat", "run_pair", "run_alignment_experiment", "median_table", "khat_impl"]

APPROACHES_SIM = ("a", "b", "c", "c_inplane", "d")
BIN_DEG = 10.0


def _khat_scipy(x1: np.ndarray, x2: np.ndarray) -> float:
    from scipy.stats import kendalltau

    tau = kendalltau(x1, x2).statistic
    return float((1.0 - tau) / 2.0)


def khat(x1: np.ndarray, x2: np.ndarray) -> float:
    """Normalised Kendall distance (Teng & Dong Eq. 2) between the x-orders of matched points:
    ``x1``, ``x2`` are ``(N,)`` x-coordinates of the same matches in image 1 / image 2.

    The one switch point: uses ``guidedmatch.spatial_order.normalized_kendall_distance`` when that
    module exists, else ``(1 - tau) / 2`` from ``scipy.stats.kendalltau`` (O(N log N); exact without
    ties, which noisy float coordinates do not have). ``NaN`` for fewer than 2 finite points."""
    ok = np.isfinite(x1) & np.isfinite(x2)
    x1, x2 = np.asarray(x1)[ok], np.asarray(x2)[ok]
    if len(x1) < 2:
        return float("nan")
    try:
        from ..spatial_order import normalized_kendall_distance  # type: ignore[attr-defined]
    except ImportError:
        return _khat_scipy(x1, x2)
    return float(normalized_kendall_distance(x1, x2))


def khat_impl() -> str:
    """Which implementation :func:`khat` uses."""
    try:
        from ..spatial_order import normalized_kendall_distance  # type: ignore[attr-defined]  # noqa: F401
    except ImportError:
        return "scipy.stats.kendalltau"
    return "guidedmatch.spatial_order.normalized_kendall_distance"


def run_pair(seed_seq) -> dict:
    """One simulated view pair -> one CSV row (see module docstring)."""
    import cv2

    from ..alignment import align_from_fundamental, apply_homography
    from ..epipolar import estimate_fundamental
    from ..testing.twoview import sphere_pair

    cv2.setNumThreads(1)
    rng = np.random.default_rng(seed_seq)
    scene = sphere_pair(rng)
    x1, x2 = scene.x1n, scene.x2n
    row: dict = {"angle_deg": scene.viewing_angle_deg, "n_points": len(x1), "f_true": float(scene.K1[0, 0]),
                 "true_roll_deg": float(np.degrees(np.arctan2(scene.R[1, 0] - scene.R[0, 1],
                                                              scene.R[0, 0] + scene.R[1, 1])))}
    before = khat(x1[:, 0], x2[:, 0])
    row["khat_before"] = before
    fit = estimate_fundamental(x1, x2, seed=0)
    row["F_ok"] = bool(fit)
    row["num_inliers"] = fit.num_inliers if fit else 0
    for tag, kw in (("", {}), ("_trueK", {"K1": scene.K1, "K2": scene.K2})):
        for ap in APPROACHES_SIM:
            res = align_from_fundamental(fit.F, x1[fit.inliers], x2[fit.inliers], scene.size1, scene.size2,
                                         ap, **kw) if fit else fit
            if not res:
                row[f"ratio_{ap}{tag}"] = float("nan")
                row[f"fail_{ap}{tag}"] = res.reason
                continue
            a1 = apply_homography(res.H1, x1)
            a2 = apply_homography(res.H2, x2)
            after = khat(a1[:, 0], a2[:, 0])
            row[f"ratio_{ap}{tag}"] = after / before if before > 0 else float("nan")
            row[f"fail_{ap}{tag}"] = ""
            if tag == "" and ap == "c":
                fr = res.focal
                row.update(f1=fr.f1, f2=fr.f2, raw_f1=fr.raw_f1, raw_f2=fr.raw_f2, fallback1=fr.fallback1,
                           fallback2=fr.fallback2, reason1=fr.reason1, reason2=fr.reason2,
                           R_err_deg=float(np.degrees(np.arccos(np.clip((np.trace(res.R.T @ scene.R) - 1) / 2,
                                                                         -1, 1)))))
            if tag == "_trueK" and ap == "c":
                row["R_err_deg_trueK"] = float(np.degrees(np.arccos(np.clip((np.trace(res.R.T @ scene.R) - 1) / 2,
                                                                           -1, 1))))
    return row


def _run_chunk(seeds: list) -> list[dict]:
    return [run_pair(s) for s in seeds]


def median_table(rows: list[dict], columns: list[str], bin_deg: float = BIN_DEG) -> tuple[list[dict], str]:
    """Median of each ``columns`` entry per viewing-angle bin -> (list of dicts, Markdown table)."""
    ang = np.array([r["angle_deg"] for r in rows], float)
    edges = np.arange(0.0, 180.0 + bin_deg, bin_deg)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (ang >= lo) & (ang < hi) if hi < 180 else (ang >= lo) & (ang <= hi)
        if not m.any():
            continue
        d = {"bin": f"{lo:.0f}-{hi:.0f}", "n": int(m.sum())}
        for c in columns:
            v = np.array([rows[i][c] for i in np.flatnonzero(m)], float)
            v = v[np.isfinite(v)]
            d[c] = float(np.median(v)) if len(v) else float("nan")
        out.append(d)
    d = {"bin": "all", "n": len(rows)}
    for c in columns:
        v = np.array([r[c] for r in rows], float)
        v = v[np.isfinite(v)]
        d[c] = float(np.median(v)) if len(v) else float("nan")
    out.append(d)
    head = "| angle (deg) | n | " + " | ".join(columns) + " |"
    sep = "|" + "---|" * (len(columns) + 2)
    lines = [head, sep] + ["| " + r["bin"] + f" | {r['n']} | " + " | ".join(f"{r[c]:.3f}" for c in columns) + " |"
                           for r in out]
    return out, "\n".join(lines)


def _metadata(n_workers: int) -> dict:
    from .meta import run_metadata

    return {**run_metadata(), "workers": n_workers}


def _plot(rows: list[dict], table: list[dict], path: Path) -> None:
    from ..plots import _plt, save_figure

    plt = _plt()
    colors = {"a": "tab:blue", "b": "tab:orange", "c": "tab:green", "c_inplane": "tab:purple", "d": "tab:red"}
    labels = {"a": "(a) R_Z", "b": "(b) R", "c": "(c) R_u R^T (paper, literal)",
              "c_inplane": "(c') in-plane twist (intended c)", "d": "(d) SVD rectification"}
    ang = np.array([r["angle_deg"] for r in rows])
    centers = [np.mean([float(x) for x in t["bin"].split("-")]) for t in table if t["bin"] != "all"]
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5), sharey=True)
    for ax, tag, title in ((axes[0], "", "estimated F + Bougnoux focal"), (axes[1], "_trueK", "estimated F + true K")):
        for ap in APPROACHES_SIM:
            y = np.array([r[f"ratio_{ap}{tag}"] for r in rows], float)
            ax.scatter(ang, y, s=2, alpha=0.25, color=colors[ap])
            med = [t[f"ratio_{ap}{tag}"] for t in table if t["bin"] != "all"]
            ax.plot(centers, med, "-o", ms=4, lw=2, color=colors[ap], label=labels[ap])
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_xlabel("angle between viewing directions (deg)")
        ax.set_title(title)
        ax.set_xlim(0, 180)
        ax.set_ylim(0, 3)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("K^ after / K^ before")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Ratio of normalized Kendall distance vs. viewing angle ({len(rows)} pairs)")
    save_figure(fig, path)


def run_alignment_experiment(n_pairs: int = 3000, out_dir: Path = Path("out/alignment"), seed: int = 0,
                             progress: bool = True, workers: int | None = None) -> dict:
    """Run the simulation (module docstring) and write CSV, PNG, Markdown table and JSON summary.

    Args:
        n_pairs: number of view pairs. out_dir: output folder (created). seed: master seed (pair ``i``
            uses ``SeedSequence(seed).spawn(n_pairs)[i]``, so results do not depend on ``workers``).
        progress: tqdm progress bar. workers: processes (default ``min(2, cpu_count)``; 1 = in-process).

    Returns:
        dict with ``table`` (list of per-bin medians), ``table_md`` (the Markdown text), ``files``,
        ``n_pairs``, ``time_s``, ``focal_fallback_rate``, ``failures`` (per column), ``khat_impl``, ``meta``.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = np.random.SeedSequence(seed).spawn(n_pairs)
    workers = workers or max(1, min(2, os.cpu_count() or 1))
    chunk = 25
    chunks = [seeds[i:i + chunk] for i in range(0, n_pairs, chunk)]
    rows: list[dict] = []
    bar = tqdm(total=n_pairs, disable=not progress, desc="alignment pairs")
    if workers == 1:
        for c in chunks:
            rows.extend(_run_chunk(c))
            bar.update(len(c))
    else:
        # "spawn", not fork: a fork after Numba/OpenCV/BLAS thread pools have started (e.g. inside
        # `guidedmatch bench all`) can deadlock the children
        import multiprocessing as mp

        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as ex:
            for res in ex.map(_run_chunk, chunks):
                rows.extend(res)
                bar.update(len(res))
    bar.close()
    for i, r in enumerate(rows):
        r["pair"] = i
    cols = [f"ratio_{ap}" for ap in APPROACHES_SIM]
    cols_true = [f"ratio_{ap}_trueK" for ap in APPROACHES_SIM]
    table, md_main = median_table(rows, cols)
    table_true, md_true = median_table(rows, cols_true)
    for t, tt in zip(table, table_true):
        t.update({k: v for k, v in tt.items() if k not in ("bin", "n")})
    fb = np.array([r.get("fallback1", True) or r.get("fallback2", True) for r in rows])
    reasons: dict[str, int] = {}
    for r in rows:
        for k in ("reason1", "reason2"):
            reasons[r.get(k, "F failed")] = reasons.get(r.get(k, "F failed"), 0) + 1
    failures = {c: int(sum(1 for r in rows if r.get(c.replace("ratio_", "fail_"), ""))) for c in cols + cols_true}
    md = ("Median of K^(after)/K^(before) per viewing-angle bin (estimated F + Bougnoux focal):\n\n" + md_main
          + "\n\nSame with the true K (estimated F):\n\n" + md_true + "\n")
    # write outputs
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    keys.remove("pair")
    keys.insert(0, "pair")
    csv_path = out_dir / "alignment_samples.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    md_path = out_dir / "alignment_table.md"
    md_path.write_text(md)
    png_path = out_dir / "alignment_ratio.png"
    _plot(rows, table, png_path)
    elapsed = time.perf_counter() - t0
    summary = {
        "n_pairs": n_pairs, "seed": seed, "time_s": elapsed, "table": table, "table_md": md,
        "focal_fallback_rate": float(fb.mean()) if len(fb) else float("nan"), "focal_reasons": reasons,
        "median_R_err_deg": float(np.nanmedian([r.get("R_err_deg", np.nan) for r in rows])),
        "median_R_err_deg_trueK": float(np.nanmedian([r.get("R_err_deg_trueK", np.nan) for r in rows])),
        "failures": failures, "khat_impl": khat_impl(), "meta": _metadata(workers),
        "files": {"csv": str(csv_path), "png": str(png_path), "table_md": str(md_path),
                  "json": str(out_dir / "alignment_summary.json")},
    }
    (out_dir / "alignment_summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary
