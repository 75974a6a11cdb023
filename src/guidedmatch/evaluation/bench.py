"""``guidedmatch bench oxford|synthetic|real|alignment|all``: the paper's experiments, side by side with the
paper's numbers and with peer matchers run in the same process on the same features.

Outputs in ``--out`` (default ``reports/``): ``report.md`` (tables), ``results.json`` (every raw number + run
metadata), PNG figures (motion fields BF vs SO+EPI+IA on real pairs, aligned second images, the alignment
simulation plot). Timings: matching only (detection excluded), median of ``--repeats`` runs; ratios to BF are
computed within the same run. "# comparisons" = descriptor distances evaluated (the paper's "# matches").
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..config import MODES as OURS  # our modes, in the one order every table uses
from .meta import cpu_label

PAPER_MODES = {"bf": "BF", "so": "SO", "so+epi": "SO+EPI", "so+epi+ia": "SO+EPI+IA"}
LABEL = {"bf": "BF", "bf-1nn": "BF 1-NN (no ratio)", "epi": "EPI", "so": "SO", "so+epi": "SO+EPI",
         "so+epi+ia": "SO+EPI+IA", "opencv_bf": "OpenCV BF", "opencv_flann": "OpenCV FLANN", "faiss_flat": "faiss exact",
         "gms": "GMS"}
QUICK = dict(oxford=[("bikes", 2), ("boat", 3), ("graf", 2)], synthetic_pairs=1, synthetic_side=1000, real_pairs=1,
             real_max_features=6000, alignment_pairs=300)


# --------------------------------------------------------------------------------------------- peers
def run_peer(name: str, f1, f2, rotated: bool = False):
    """Run one peer of :mod:`guidedmatch.evaluation.peers` on the same features -> MatchResult.

    GMS gets its rotation/scale options on the rotated sets (synthetic 2-3, boat, graf, bark)."""
    from . import peers

    if name == "gms":
        return peers.match_gms(f1, f2, with_rotation=rotated, with_scale=rotated)
    return peers.PEERS[name](f1, f2)


def available_peers() -> list[str]:
    from . import peers

    return peers.available_peers()


# --------------------------------------------------------------------------------------------- one pair
def ransac_precision(pts1, pts2, distances) -> float:
    """The paper's real-image precision: share of matches that are RANSAC-F inliers
    (:func:`guidedmatch.evaluation.metrics.ransac_fundamental`: PROSAC by descriptor distance, 3 px symmetric)."""
    from .metrics import ransac_fundamental

    if len(pts1) < 8:
        return float("nan")
    res = ransac_fundamental(pts1, pts2, distances)
    return float(res[1].mean()) if res else 0.0


def evaluate_pair(pair, f1, f2, *, repeats=1, peers=(), config=None, rotated=False, real=False, keep_pairs=()):
    """Run every method on one pair's features; returns a row dict (raw numbers only)."""
    from ..bruteforce import match_bruteforce
    from ..matcher import MatcherConfig, match

    config = config or MatcherConfig()
    row = dict(name=pair.name, n1=len(f1), n2=len(f2), bf_comparisons=len(f1) * len(f2), methods={}, kept={})

    def record(key, pairs, times, comp, stats=None, distances=None):
        p1 = f1.keypoints[pairs[:, 0]] if len(pairs) else np.zeros((0, 2))
        p2 = f2.keypoints[pairs[:, 1]] if len(pairs) else np.zeros((0, 2))
        ok = pair.gt.correct(p1, p2) if len(pairs) else np.zeros(0, bool)
        m = dict(comparisons=comp, matches=int(len(pairs)), true=int(ok.sum()),
                 precision=float(ok.mean()) if len(ok) else float("nan"),
                 time_s=float(np.median(times)), times_s=[float(t) for t in times])
        if stats:
            m.update(model_fit_s=stats.timing.model_fit_s if stats.timing else None,
                     fallbacks=[f"{f.what}: {f.reason}" for f in stats.fallbacks],
                     candidates_p50=stats.candidates_per_query.p50 if stats.candidates_per_query else None,
                     alignment_H2=stats.alignment_H2, roll_deg=stats.updates[-1].roll_deg if stats.updates else None)
        if real:
            m["ransac_precision"] = ransac_precision(p1, p2, distances)
        row["methods"][key] = m
        if key in keep_pairs:
            row["kept"][key] = dict(pts1=p1, pts2=p2, correct=ok)

    for mode in OURS:
        times, res = [], None
        for _ in range(repeats):
            res = match(f1, f2, mode, config)
            times.append(res.stats.time_s)
        record(mode, res.pairs, times, res.stats.comparisons, res.stats, res.distances)
    r = match_bruteforce(f1, f2, ratio=None)
    record("bf-1nn", r.pairs, [r.stats.time_s], r.stats.comparisons, distances=r.distances)
    for peer in peers:
        times, out = [], None
        for _ in range(repeats if peer != "opencv_bf" else 1):
            out = run_peer(peer, f1, f2, rotated=rotated)
            times.append(out.stats.time_s)
        record(peer, out.pairs, times, out.stats.comparisons, distances=out.distances)
    return row


# --------------------------------------------------------------------------------------------- datasets
def _detect(img, detector, max_features=None):
    from ..features import detect

    return detect(img, detector, max_features)


def _progress(it, total, desc):
    from tqdm import tqdm

    return tqdm(it, total=total, desc=desc, unit="pair", dynamic_ncols=True, leave=True)


def run_oxford(root, out, quick, repeats, detector, peers):
    from ..datasets import oxford_pairs

    pairs = oxford_pairs(root)
    if quick:
        want = {f"oxford/{s}/1-{t}" for s, t in QUICK["oxford"]}
        pairs = [p for p in pairs if p.name in want]
    rows, figs = [], []
    for p in _progress(pairs, len(pairs), "oxford"):
        i1, i2 = p.load()
        f1, f2 = _detect(i1, detector), _detect(i2, detector)
        seq = p.name.split("/")[1]
        row = evaluate_pair(p, f1, f2, repeats=repeats, peers=peers, rotated=seq in ("boat", "graf", "bark"))
        rows.append(row)
        if p.name in ("oxford/boat/1-3", "oxford/graf/1-3") or (quick and p.name in ("oxford/boat/1-3", "oxford/graf/1-2")):
            H = row["methods"]["so+epi+ia"].get("alignment_H2")
            if H is not None:
                figs.append(_aligned_figure(out / f"aligned_{seq}_{p.name[-3:]}.png", i1, i2, np.array(H), p.name))
    return rows, figs


def run_synthetic(root, out, quick, repeats, detector, peers, seed, n_pairs=None, max_side=None):
    from ..datasets import synthetic_pairs

    n = n_pairs or (QUICK["synthetic_pairs"] if quick else 100)
    side = max_side or (QUICK["synthetic_side"] if quick else 2000)
    sets = {}
    for set_id in (1, 2, 3):
        rows = []
        for p in _progress(synthetic_pairs(root, set_id, n_pairs=n, seed=seed, max_side=side), n, f"synthetic set {set_id}"):
            i1, i2 = p.load()
            f1, f2 = _detect(i1, detector), _detect(i2, detector)
            if len(f1) < 10 or len(f2) < 10:
                rows.append(dict(name=p.name, skipped=f"too few features ({len(f1)}, {len(f2)})"))
                continue
            rows.append(evaluate_pair(p, f1, f2, repeats=repeats, peers=peers, rotated=set_id >= 2))
        sets[set_id] = rows
    return sets


def run_real(root, out, quick, repeats, detector, peers):
    from ..datasets import strecha_pairs

    pairs = strecha_pairs(root)
    if quick:
        pairs = pairs[: QUICK["real_pairs"]]
    maxf = QUICK["real_max_features"] if quick else None
    rows, figs, cache = [], [], {}
    for k, p in enumerate(_progress(pairs, len(pairs), "real (Strecha)")):
        i1, i2 = p.load()
        for path, img in ((p.image1, i1), (p.image2, i2)):
            if str(path) not in cache:
                cache[str(path)] = _detect(img, detector, maxf)
        f1, f2 = cache[str(p.image1)], cache[str(p.image2)]
        keep = ("bf", "so+epi+ia") if k < 2 else ()
        row = evaluate_pair(p, f1, f2, repeats=repeats, peers=[q for q in peers if q != "opencv_bf"], real=True, keep_pairs=keep)
        if row["kept"]:
            figs.append(_motion_figure(out / f"motion_{Path(str(p.image1)).stem}_{Path(str(p.image2)).stem}.png", i1, row, p.name))
            H = row["methods"]["so+epi+ia"].get("alignment_H2")
            if H is not None and k == 0:
                figs.append(_aligned_figure(out / "aligned_real.png", i1, i2, np.array(H), p.name))
        row.pop("kept", None)
        rows.append(row)
    for r in rows:
        r.pop("kept", None)
    return rows, figs


# --------------------------------------------------------------------------------------------- figures
def _small(img, max_side=900):
    import cv2

    s = max_side / max(img.shape[:2])
    return cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else img


def _motion_figure(path, image1, row, title):
    from ..plots import motion_field_panels

    panels = []
    for key in ("bf", "so+epi+ia"):
        k = row["kept"][key]
        m = row["methods"][key]
        panels.append(dict(pts1=k["pts1"], pts2=k["pts2"], correct=k["correct"],
                           title=f"{LABEL[key]}: {m['matches']} matches, {100 * m['precision']:.1f} % within 3 px of GT epipolar line"))
    motion_field_panels(path, image1, panels, ncols=2, suptitle=f"{title}: motion field on image 1 (green = GT-consistent)")
    return path


def _aligned_figure(path, image1, image2, H2, title):
    from ..alignment import warp_to_canvas
    from ..plots import _plt, save_figure

    plt = _plt()
    warped, _ = warp_to_canvas(image2, H2)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for ax, img, t in zip(axes, (image1, image2, warped), ("image 1", "image 2", "image 2 aligned (SO+EPI+IA, H from F)")):
        ax.imshow(_small(img), cmap="gray", vmin=0, vmax=255)
        ax.set_title(t, fontsize=9)
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=80)
    return path


# --------------------------------------------------------------------------------------------- report
def paper_tables() -> dict | None:
    """The paper's table values (``shared/design/paper_tables.json`` beside the repository or beside the data
    folder), or None when neither is there."""
    from ..datasets import data_root

    cands = [Path(__file__).resolve().parents[3].parent / "shared" / "design" / "paper_tables.json"]
    root = data_root()
    if root is not None:
        cands.append(Path(root).parent / "design" / "paper_tables.json")
    for p in cands:
        if p.exists():
            return json.loads(p.read_text())
    return None


def _fmt(v, kind):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    if kind == "int":
        return f"{int(v):,}"
    if kind == "pct":
        return f"{100 * v:.2f}%"
    if kind == "s":
        return f"{v:.3f}"
    return str(v)


def oxford_tables(rows, paper) -> str:
    out = []
    specs = [("# descriptor comparisons (the paper's '# matches')", "comparisons", "int", "oxford_num_matches", None),
             ("true correspondences (GT homography, < 3 px)", "true", "int", "oxford_true_correspondences", None),
             ("precision", "precision", "pct", "oxford_precision_percent", 0.01),
             ("matching time (s; ours: median, this machine; paper: 20-run mean, Ryzen 9 3900)", "time_s", "s", "oxford_matching_time_s", None)]
    cols = ["bf", "epi", "so", "so+epi", "so+epi+ia"]
    for title, key, kind, pkey, pscale in specs:
        out.append(f"\n#### {title}\n")
        head = "| pair | " + " | ".join(LABEL[c] for c in cols) + " | paper: " + " | paper: ".join(PAPER_MODES[c] for c in cols if c in PAPER_MODES) + " |"
        out.append(head)
        out.append("|" + "---|" * (1 + len(cols) + 4))
        for r in rows:
            pname = r["name"].split("/")[1] + " " + r["name"].split("/")[2]
            ours = [_fmt(r["methods"][c][key], kind) for c in cols]
            pv = (paper or {}).get(pkey, {}).get(pname, {})
            pap = [(_fmt(pv[PAPER_MODES[c]] * (pscale or 1), kind) if PAPER_MODES[c] in pv else "–") for c in cols if c in PAPER_MODES]
            out.append(f"| {pname} | " + " | ".join(ours) + " | " + " | ".join(pap) + " |")
    # ratios to BF, ours vs paper
    out.append("\n#### comparisons and time as a fraction of BF (ours | paper)\n")
    out.append("| pair | SO+EPI+IA comparisons / BF | paper | SO+EPI+IA time / BF | paper | true SO+EPI+IA − BF | paper |")
    out.append("|---|---|---|---|---|---|---|")
    for r in rows:
        pname = r["name"].split("/")[1] + " " + r["name"].split("/")[2]
        m = r["methods"]
        pc = (paper or {}).get("oxford_num_matches", {}).get(pname)
        pt = (paper or {}).get("oxford_matching_time_s", {}).get(pname)
        pn = (paper or {}).get("oxford_true_correspondences", {}).get(pname)
        out.append(f"| {pname} | {m['so+epi+ia']['comparisons'] / m['bf']['comparisons']:.3f} | "
                   f"{pc['SO+EPI+IA'] / pc['BF']:.3f} | " if pc else f"| {pname} | {m['so+epi+ia']['comparisons'] / m['bf']['comparisons']:.3f} | – | ")
        out[-1] += (f"{m['so+epi+ia']['time_s'] / m['bf']['time_s']:.2f} | " + (f"{pt['SO+EPI+IA'] / pt['BF']:.2f}" if pt else "–") +
                    f" | {m['so+epi+ia']['true'] - m['bf']['true']:+d} | " + (f"{pn['SO+EPI+IA'] - pn['BF']:+d}" if pn else "–") + " |")
    return "\n".join(out)


def summary_table(rows, methods, real=False) -> str:
    rows = [r for r in rows if "methods" in r]
    lines = ["| method | # comparisons | % of BF | matches | true | precision | time (s) | time / BF |" + (" RANSAC precision |" if real else ""),
             "|---|---|---|---|---|---|---|---|" + ("---|" if real else "")]
    if not rows:
        return "\n".join(lines + ["| (no pairs) |"])
    bf_comp = sum(r["methods"]["bf"]["comparisons"] for r in rows)
    bf_time = sum(r["methods"]["bf"]["time_s"] for r in rows)
    for m in methods:
        rs = [r["methods"][m] for r in rows if m in r["methods"]]
        if not rs:
            continue
        comp = None if any(x["comparisons"] is None for x in rs) else sum(x["comparisons"] for x in rs)
        matches = sum(x["matches"] for x in rs)
        true = sum(x["true"] for x in rs)
        t = sum(x["time_s"] for x in rs)
        line = (f"| {LABEL[m]} | {_fmt(comp, 'int')} | {(100 * comp / bf_comp) if comp is not None else float('nan'):.2f}% | {matches:,} | "
                f"{true:,} | {100 * true / max(matches, 1):.2f}% | {t:.2f} | {t / bf_time:.2f} |")
        if real:
            rp = [x.get("ransac_precision", np.nan) for x in rs]
            line += f" {100 * np.nanmean(rp):.2f}% |"
        lines.append(line)
    return "\n".join(lines)


def paper_synthetic_table(paper, key) -> str:
    d = (paper or {}).get(key)
    if not d:
        return ""
    bf = d["BF"]
    lines = ["| paper (SURF, 100 ImageNet pairs) | # matches | % of BF | true | precision | time (s) | time / BF |", "|---|---|---|---|---|---|---|"]
    for m, v in d.items():
        lines.append(f"| {m} | {v['num_matches']:,} | {100 * v['num_matches'] / bf['num_matches']:.2f}% | {v['true_correspondences']:,} | "
                     f"{v['precision_percent']:.2f}% | {v['matching_time_s']} | {v['matching_time_s'] / bf['matching_time_s']:.2f} |")
    return "\n".join(lines)


def real_table(rows) -> str:
    lines = ["| pair | features | BF matches | BF precision GT / RANSAC | SO+EPI+IA matches | SO+EPI+IA precision GT / RANSAC | "
             "BF time (s) | SO+EPI+IA time (s) | comparisons SO+EPI+IA / BF |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b, g = r["methods"]["bf"], r["methods"]["so+epi+ia"]
        lines.append(f"| {r['name'].split('/', 1)[1]} | {r['n1']:,} x {r['n2']:,} | {b['matches']:,} | {100 * b['precision']:.1f}% / "
                     f"{100 * b['ransac_precision']:.1f}% | {g['matches']:,} | {100 * g['precision']:.1f}% / {100 * g['ransac_precision']:.1f}% | "
                     f"{b['time_s']:.3f} | {g['time_s']:.3f} | {g['comparisons'] / b['comparisons']:.4f} |")
    return "\n".join(lines)


def write_report(out: Path, results: dict, command: str) -> Path:
    from ..features import atomic_write_text

    paper = paper_tables()
    peers = results.get("peers", [])
    all_methods = ["bf", "bf-1nn", "epi", "so", "so+epi", "so+epi+ia"] + list(peers)
    meta = results["meta"]
    md = ["# guidedmatch benchmark report\n",
          f"Command: `{command}`  \nGenerated: {meta.get('timestamp_utc', '')}, commit `{meta.get('git_commit', '?')}`"
          f"{' (dirty)' if meta.get('git_dirty') else ''}, {cpu_label(meta)}, {meta.get('logical_cores', '?')} logical cores, "
          f"run time {results.get('elapsed_s', 0) / 60:.1f} min{' (--quick)' if results.get('quick') else ''}.\n",
          "Detector: OpenCV SIFT (the paper used SURF, which is not in the pip OpenCV builds: it is patented and excluded). "
          "All methods of a pair share the same features. Ratio test 0.8 everywhere (ours inside the candidate set); "
          "'BF 1-NN' is brute force without a ratio test, which is what the paper's BF column most resembles "
          "(its real-image BF kept 71 % of the features). Times are matching only (detection excluded), median of "
          f"{results.get('repeats')} run(s) on this machine; the paper's are 20-run means on a Ryzen 9 3900. "
          "Compare ratios to BF, not absolute seconds. Paper values: Teng & Dong, transcribed in `shared/design/paper_tables.json`.\n"]
    if "oxford" in results:
        rows = results["oxford"]
        md += ["## Oxford (img1 vs img2/img3, GT homography, correct = within 3 px)\n", summary_table(rows, all_methods),
               oxford_tables(rows, paper)]
    if "synthetic" in results:
        md.append("\n## Synthetic sets (paper §IV-B transforms on `photos/unsplash`, GT homography, sums over pairs)\n")
        names = {1: ("colour + translation + scaling", "synthetic_set1_color_translation_scale"),
                 2: ("colour + scaling + rotation", "synthetic_set2_color_scale_rotation"),
                 3: ("set 2 + perspective", "synthetic_set3_plus_perspective")}
        for sid, rows in results["synthetic"].items():
            sid = int(sid)
            ok = [r for r in rows if "methods" in r]
            md += [f"\n### Set {sid}: {names[sid][0]} ({len(ok)} pairs"
                   + (f", {len(rows) - len(ok)} skipped" if len(rows) > len(ok) else "") + ")\n",
                   summary_table(ok, all_methods), "", paper_synthetic_table(paper, names[sid][1])]
    if "real" in results:
        rows = results["real"]
        md += ["\n## Real high-resolution pairs (Strecha Herz-Jesus-P8, 3072x2048, GT poses)\n",
               "Precision two ways: against the GT (symmetric epipolar distance < 3 px under the GT F) and the paper's way "
               "(share of RANSAC-F inliers: PROSAC by descriptor distance, 1 px fit, inlier = symmetric epipolar distance < 3 px). The paper's own real pairs (4000x3000, not public) are different images; "
               "its table is shown for the ratios.\n", summary_table(rows, [m for m in all_methods if m != "opencv_bf"], real=True), "",
               real_table(rows)]
        pr = (paper or {}).get("real_4000x3000")
        if pr:
            md.append("\nPaper, real 4000x3000 pairs (a-d): BF vs SO+EPI+IA precision "
                      + ", ".join(f"{pr['Precision']['BF'][k]}% → {pr['Precision']['SO+EPI+IA'][k]}%" for k in pr["Precision"]["BF"])
                      + "; time ratio " + ", ".join(f"{pr['Matching time (s)']['SO+EPI+IA'][k] / pr['Matching time (s)']['BF'][k]:.3f}"
                                                   for k in pr["Matching time (s)"]["BF"]) + ".")
    if "alignment" in results:
        md += ["\n## Alignment simulation (paper Fig. 'Ratio of normalized Kendall distance vs. viewing angle')\n",
               results["alignment"].get("table_md", ""), "\n![alignment](alignment/alignment_ratio.png)\n"]
    figs = results.get("figures", [])
    if figs:
        md.append("\n## Figures\n")
        md += [f"![{Path(f).stem}]({Path(f).name})" for f in figs]
    fb = []
    for key in ("oxford", "real"):
        for r in results.get(key, []):
            for m, v in r["methods"].items():
                for f in v.get("fallbacks", []) or []:
                    fb.append(f"{r['name']} {m}: {f}")
    if fb:
        md += ["\n## Fallbacks taken\n"] + [f"- {x}" for x in fb[:60]]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(md) + "\n")
    return path


# --------------------------------------------------------------------------------------------- entry
def _warm_up(detector):
    """Load/compile the Numba kernels once so the first timed pair does not pay for it."""
    from ..bruteforce import match_bruteforce
    from ..matcher import MatcherConfig, match
    from ..testing.scenes import make_scene

    s = make_scene((480, 360), roll_deg=20, seed=1)
    f1, f2 = _detect(s.image1, detector), _detect(s.image2, detector)
    for mode in OURS:
        match(f1, f2, mode, MatcherConfig(update_every=40, num_updates=1))
    match_bruteforce(f1, f2, ratio=None)


BENCHMARKS = ("oxford", "synthetic", "real", "alignment", "all")


def run_benchmarks(which: str, *, data=None, out="reports", quick: bool = False, repeats: int | None = None,
                   detector: str = "sift", seed: int = 0) -> Path:
    """Run the benchmark(s) ``which`` (one of :data:`BENCHMARKS`) and write ``report.md``, ``results.json`` and the
    figures into ``out``; returns the report's path.

    ``data``: data folder (default ``$GUIDEDMATCH_DATA`` or ``../shared/data``); ``quick``: a few pairs per set;
    ``repeats``: timing repeats per method (default 1 with ``quick``, else 3). Raises
    :class:`~guidedmatch.errors.ConfigError` for an unknown benchmark, :class:`~guidedmatch.errors.InputError`
    when the data is missing and :class:`~guidedmatch.errors.OutputError` when ``out`` cannot be written, before
    any work.
    """
    from ..datasets import data_root
    from ..errors import ConfigError, InputError
    from ..features import DETECTORS, writable_folder
    from .meta import run_metadata, write_json

    if which not in BENCHMARKS:
        raise ConfigError(f"unknown benchmark {which!r}; choose one of {', '.join(BENCHMARKS)}")
    if detector not in DETECTORS:
        raise ConfigError(f"unknown detector {detector!r}; choose one of {', '.join(DETECTORS)}")
    parts = ("oxford", "synthetic", "real", "alignment") if which == "all" else (which,)
    root = data_root(data)
    if (root is None or not root.is_dir()) and any(w != "alignment" for w in parts):
        where = "" if root is None else f" ({root} is not a folder)"
        raise InputError(f"no evaluation data{where}: pass --data DIR or set GUIDEDMATCH_DATA "
                         "(expects oxford/, pose_pairs/, photos/)")
    out = writable_folder(out)
    t0 = time.perf_counter()
    repeats = repeats or (1 if quick else 3)
    peers = available_peers()
    _warm_up(detector)
    results = dict(meta=run_metadata(seed=seed), quick=bool(quick), repeats=repeats, peers=peers,
                   detector=detector, figures=[])
    if "oxford" in parts:
        results["oxford"], figs = run_oxford(root, out, quick, repeats, detector, peers)
        results["figures"] += [str(f) for f in figs]
    if "synthetic" in parts:
        results["synthetic"] = run_synthetic(root, out, quick, 1, detector, [p for p in peers if p != "opencv_bf"], seed)
    if "real" in parts:
        results["real"], figs = run_real(root, out, quick, repeats, detector, peers)
        results["figures"] += [str(f) for f in figs]
    if "alignment" in parts:
        from .alignment_sim import run_alignment_experiment

        n = QUICK["alignment_pairs"] if quick else 3000
        results["alignment"] = run_alignment_experiment(n_pairs=n, out_dir=out / "alignment", seed=seed, progress=True)
    results["elapsed_s"] = time.perf_counter() - t0
    command = "guidedmatch bench " + which + (" --quick" if quick else "")
    write_json(out / "results.json", results)
    rep = write_report(out, results, command)
    print(f"wrote {rep}, {out / 'results.json'} and {len(results['figures'])} figure(s) in {results['elapsed_s'] / 60:.1f} min")
    return rep
