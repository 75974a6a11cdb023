"""Regenerate the generated sections of the benchmark summary page (docs/benchmarks.md): "The paper's experiments"
from reports/report.md + reports/results.json, and the one-pair performance table from benchmarks/results/guided.json.

    python tools/readme_results.py      (after: guidedmatch bench all --out reports,
                                          python benchmarks/bench_guided.py --sizes 5000 10000 20000 all ...)

The collection headline (totals over every Herz-Jesus-P8 pair + the unrelated pairs) from ``guidedmatch bench pairs``:

    python tools/readme_results.py --pairs benchmarks/results/pairs/pairs.json           (print the block)
    python tools/readme_results.py --pairs benchmarks/results/pairs/pairs.json --write   (put it in docs/benchmarks.md
                                      between <!-- pairs:start --> / <!-- pairs:end -->, or before "## Performance")

Links in the generated text are relative to docs/ (the page's folder).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the page that holds the generated sections (the README keeps one headline table and links here)
TARGET = ROOT / "docs" / "benchmarks.md"
START, END = "<!-- results:start -->", "<!-- results:end -->"
PSTART, PEND = "<!-- perf:start -->", "<!-- perf:end -->"
LABELS = {"so+epi+ia": "so+epi+ia", "bf": "guidedmatch BF (GEMM)", "faiss": "faiss exact 2-NN", "flann": "OpenCV FLANN (KD-tree)"}


def perf_table(guided: dict) -> str:
    """Markdown table of benchmarks/results/guided.json (speed-up = faiss median / method median, same run)."""
    rows = ["| features | method | time (s) | speed-up vs faiss | comparisons (% of BF) | matches | GT inliers | precision |",
            "|---|---|---|---|---|---|---|---|"]
    last = guided["rows"][-1]
    for row in guided["rows"]:
        ft = row["methods"].get("faiss", {}).get("time_s")
        for name, m in row["methods"].items():
            if name not in LABELS or (row is not last and name in ("bf", "flann")):
                continue
            bold = row is last and name == "so+epi+ia"
            b = (lambda v: f"**{v}**") if bold else (lambda v: v)  # noqa: E731
            comp = f"{100 * m['comparisons'] / row['bf_comparisons']:.2f} %" if m["comparisons"] else "n/a"
            t, sp = f"{m['time_s']:.3f}", f"{ft / m['time_s']:.1f}x" if ft else "n/a"
            gi, pr = f"{m['gt_inliers']:,}", f"{100 * m['precision']:.1f} %"
            rows.append(f"| {row['n1'] / 1000:.0f}k x {row['n2'] / 1000:.0f}k | {b(LABELS[name])} | {b(t)} | {b(sp)} | "
                        f"{b(comp)} | {m['matches']:,} | {b(gi)} | {b(pr)} |")
    meta = guided.get("meta", {})
    rows += ["", f"(`{guided.get('command', '')}`, commit `{str(meta.get('git_commit'))[:10]}`"
             f"{' + local changes' if meta.get('git_dirty') else ''}, {str(meta.get('timestamp_utc', ''))[:16]} UTC, "
             f"{meta.get('cpu_model')}.)"]
    return "\n".join(rows)


PAIRS_START, PAIRS_END = "<!-- pairs:start -->", "<!-- pairs:end -->"
PAIRS_ROWS = (("so+epi+ia", "**guidedmatch so+epi+ia**"),
              ("so+epi+ia+prep", "guidedmatch so+epi+ia, image preparation (its index) amortized"), ("bf", "guidedmatch BF (GEMM)"), ("faiss_flat", "faiss exact 2-NN"),
              ("faiss_ivf", "COLMAP-style cached IVF-SQ8 (search only)"), ("faiss_ivf+build", "IVF-SQ8, index build amortized"),
              ("opencv_flann", "OpenCV FLANN (KD-tree)"))


def pairs_headline(res: dict, link: str = "../benchmarks/results/pairs/pairs.md") -> str:
    """Benchmark-page block from ``guidedmatch bench pairs`` JSON: per feature set, totals over the scene pairs (time, ratio to
    the cached IVF search, slowest pair, GT inliers, precision) and the unrelated pairs (verdicts, comparisons)."""
    meta = res.get("meta", {})
    out = [PAIRS_START]
    for name, s in res.get("sets", {}).items():
        scene, unrel = s["totals"]["scene"], s["totals"]["unrelated"]
        ns = [v["n"] for v in s["images"].values()]
        npairs = next(iter(scene.values()))["pairs"]
        nun = next(iter(unrel.values()))["pairs"] if unrel else 0
        angles = [r["rotation_deg"] for r in s["rows"] if r.get("rotation_deg") is not None]
        label = "8192 strongest SIFT features (COLMAP's default count)" if name == "8192" else \
            f"SIFT `contrastThreshold={name}` ({min(ns) / 1000:.0f}k-{max(ns) / 1000:.0f}k features)"
        out += ["", f"**{label}**, all {npairs} Herz-Jesus-P8 pairs ({min(angles):.0f}-{max(angles):.0f}° between the cameras) + {nun} unrelated pairs:", "",
                "| method | total time, all pairs (s) | vs cached IVF search | slowest pair (s, x BF there) | GT inliers | precision "
                "| unrelated pairs: verdict, % of N1·N2 compared |", "|---|---|---|---|---|---|---|"]
        ivf = scene.get("faiss_ivf", {}).get("time_s")
        for key, lab in PAIRS_ROWS:
            m = scene.get(key)
            if m is None:
                continue
            u = unrel.get(key)
            uv = (", ".join(f"{v} {k}" for k, v in sorted(u["verdicts"].items())) +
                  (f", {100 * u['comparisons_frac']:.1f} %" if u.get("comparisons_frac") is not None else "")) if u else "–"
            prec = f"{100 * m['precision']:.1f} %" if m.get("precision") is not None else "n/a"
            out.append(f"| {lab} | {m['time_s']:.2f} | {m['time_s'] / ivf:.2f}x | {m['slowest_pair'].rsplit('/', 1)[1]}: "
                       f"{m['slowest_time_s']:.2f} ({m['slowest_vs_bf']:.1f}x) | {m['gt_inliers']:,} | {prec} | {uv} |")
    verdict = "verdicts: the matcher's own `result.geometry` (peers: a robust fit on their matches)" \
        if res.get("verdict_source_ours") == ["matcher"] else "verdicts: a robust fit on the returned matches"
    out += ["", f"(`{res.get('command', 'guidedmatch bench pairs')}`, commit `{str(meta.get('git_commit'))[:10]}`"
            f"{' + local changes' if meta.get('git_dirty') else ''}, {str(meta.get('timestamp_utc', ''))[:16]} UTC, "
            f"{meta.get('cpu_model')}, {res.get('machine_note', '2 cores shared with other jobs: times are noisy, same-run ratios hold')}. Matching only, "
            f"detection excluded; GT inliers = symmetric epipolar distance < 3 px under the GT cameras; {verdict}"
            + (f"; guidedmatch rows: prepared images with the settings of a collection run ("
               + ", ".join(f"`{k}={v}`" for k, v in res["set_config_changes"].items()) + ")"
               if res.get("set_config_changes") else "") + ". "
            f"Per pair, targets and the plot against the camera angle: [{link.removeprefix('../')}]({link}).)", PAIRS_END]
    return "\n".join(out)


def section(md: str, title: str) -> str:
    """The first Markdown table after the heading that starts with ``title``."""
    i = md.index(title)
    m = re.search(r"(\|.*\|\n)+", md[i:])
    return m.group(0).strip()


def main(argv=None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", default=str(ROOT / "reports"))
    ap.add_argument("--pairs", metavar="PAIRS_JSON", help="only the collection headline from `guidedmatch bench pairs`")
    ap.add_argument("--write", action="store_true", help="with --pairs: write the block into docs/benchmarks.md")
    ap.add_argument("--target", default=str(TARGET), help="the page to update (default docs/benchmarks.md)")
    args = ap.parse_args(argv)
    if args.pairs:
        block = pairs_headline(json.loads(Path(args.pairs).read_text()))
        if not args.write:
            print(block)
            return
        target = Path(args.target)
        readme = target.read_text()
        if PAIRS_START in readme:
            readme = readme[: readme.index(PAIRS_START)] + block + readme[readme.index(PAIRS_END) + len(PAIRS_END):]
        else:
            readme = readme.replace("## Performance", block + "\n\n## Performance", 1)
        target.write_text(readme)
        print(f"{target.name}: pairs headline updated")
        return
    rep = Path(args.reports)
    md = (rep / "report.md").read_text()
    res = json.loads((rep / "results.json").read_text())
    meta = res["meta"]
    out = [START, "## The paper's experiments", "",
           f"Regenerated by `guidedmatch bench all --out reports` ({res['elapsed_s'] / 60:.0f} min on a 2-core "
           f"{meta.get('cpu_model')}, {meta.get('timestamp_utc', '')[:10]}, commit `{str(meta.get('git_commit'))[:10]}`), "
           "then `python tools/readme_results.py`. Full tables with the paper's numbers side by side, per pair: "
           "[reports/report.md](../reports/report.md); every raw number: `reports/results.json`. SIFT (the paper used SURF), "
           "ratio 0.8 for every method; times = matching only, median of 3 runs (1 on the synthetic sets), same machine and features for all methods.",
           "", "**Oxford** (12 pairs img1–img2/img3, the paper's set; true = within 3 px of the GT homography):", "",
           section(md, "## Oxford"), ""]
    names = {1: "colour + translation + scaling", 2: "colour + scaling + rotation", 3: "set 2 + perspective"}
    out += ["**Synthetic sets** (paper §IV-B transforms of the 24 photos, 100 pairs per set, long side 2000 px; "
            "sums over pairs). Rows: BF, SO+EPI+IA, faiss; the paper's BF and SO+EPI+IA ratios for comparison:", "",
            "| set | method | % of BF comparisons | true | precision | time / BF | paper: % of BF | paper: true vs BF | paper: precision |",
            "|---|---|---|---|---|---|---|---|---|"]
    pkeys = {1: "synthetic_set1_color_translation_scale", 2: "synthetic_set2_color_scale_rotation", 3: "synthetic_set3_plus_perspective"}
    from guidedmatch.evaluation.bench import paper_tables

    ptab = paper_tables() or {}
    for sid in (1, 2, 3):
        rows = [r for r in res["synthetic"][str(sid)] if "methods" in r]
        tot = lambda m, k: sum(r["methods"][m][k] for r in rows if r["methods"][m].get(k) is not None)  # noqa: E731
        bfc, bft = tot("bf", "comparisons"), tot("bf", "time_s")
        p = ptab.get(pkeys[sid], {})
        for m, label in (("bf", "BF"), ("so+epi+ia", "SO+EPI+IA"), ("faiss_flat", "faiss exact")):
            if not rows or m not in rows[0]["methods"]:
                continue
            pm = p.get({"bf": "BF", "so+epi+ia": "SO+EPI+IA"}.get(m, ""), {})
            pb = p.get("BF", {})
            paper = (f"{100 * pm['num_matches'] / pb['num_matches']:.2f} % | {pm['true_correspondences'] / pb['true_correspondences']:.2f} x | "
                     f"{pm['precision_percent']:.1f} %") if pm else "– | – | –"
            out.append(f"| {sid}: {names[sid]} | {label} | {100 * tot(m, 'comparisons') / bfc:.2f} % | {tot(m, 'true') / tot('bf', 'true'):.2f} x BF "
                       f"({tot(m, 'true'):,}) | {100 * tot(m, 'true') / max(tot(m, 'matches'), 1):.1f} % | {tot(m, 'time_s') / bft:.2f} | {paper} |")
    out += ["", "**Real** (Strecha Herz-Jesus-P8, 18 pairs at 3072x2048, default SIFT, GT poses; precision vs the GT "
            "and the paper's RANSAC-inlier way):", "", section(md, "## Real high-resolution pairs"), "",
            "![BF vs SO+EPI+IA motion fields on a real pair](../reports/motion_0000_0001.png)", "",
            "Where guided matching loses: SO alone on rotated sets (no alignment, as in the paper); wall-clock time at a few "
            "thousand features, where the fixed cost of the three model fits (~15-20 ms) exceeds GEMM brute force "
            "(see the one-pair table below for the large-N regime); the printed approach (c) vs (a) at large viewing "
            "angles ([alignment.md](alignment.md)).", END]
    target = Path(args.target)
    readme = target.read_text()
    block = "\n".join(out)
    if START in readme:
        readme = readme[: readme.index(START)] + block + readme[readme.index(END) + len(END):]
    else:
        readme = readme.replace("## Performance", block + "\n\n## Performance", 1)
    gpath = ROOT / "benchmarks" / "results" / "guided.json"
    if PSTART in readme and gpath.exists():
        table = perf_table(json.loads(gpath.read_text()))
        readme = readme[: readme.index(PSTART)] + PSTART + "\n" + table + "\n" + readme[readme.index(PEND):]
    target.write_text(readme)
    print(f"{target.name}: results and performance sections updated")


if __name__ == "__main__":
    main()
