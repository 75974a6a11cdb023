"""``guidedmatch bench pairs``, its results: totals and targets over the rows of a run, the markdown report
(``pairs.md``) and the figure (``pairs_angle.png``). The benchmark itself: :mod:`guidedmatch.evaluation.bench_pairs`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .bench_pairs_data import OURS, SCENE, _field
from .meta import cpu_label

#: Report columns: ``faiss_ivf+build`` is the IVF run with the index builds amortized over the image's pairs,
#: ``so+epi+ia+prep`` ours with its per-image preparation (descriptor forms + its own IVF index) amortized the same way.
COLUMNS = ("so+epi+ia", "so+epi+ia+prep", "epi", "bf", "faiss_flat", "faiss_ivf", "faiss_ivf+build", "opencv_flann")
AMORTIZED = ("so+epi+ia+prep", "faiss_ivf+build")
LABEL = {"so+epi+ia": "so+epi+ia", "so+epi+ia+prep": "so+epi+ia (+ prepare amortized)", "epi": "epi", "bf": "our BF",
         "faiss_flat": "faiss exact",
         "faiss_ivf": "IVF-SQ8 cached (search)", "faiss_ivf+build": "IVF-SQ8 (+ build amortized)",
         "opencv_flann": "OpenCV FLANN"}


def machine_note(meta: dict) -> str:
    """What the load average said when the run started (``run_metadata()["load_average"]``; 2 cores: above ~1,
    other jobs were running)."""
    import os

    load = meta.get("load_average") or float("nan")
    busy = "other jobs were running: absolute times are noisy" if load > 1.2 else "no other heavy job was running"
    return f"load average {load:.1f} on {os.cpu_count()} cores when the run started ({busy}); ratios between methods " \
           "measured in the same run and the comparison counts are the robust numbers"


MACHINE_NOTE = ("the machine (2 cores) was shared with several other agents' jobs during the run: absolute times are "
                "noisy; ratios between methods measured in the same run and the comparison counts are the robust numbers")


# --------------------------------------------------------------------------------------------- totals
def totals(rows: list[dict], columns=COLUMNS) -> dict:
    """Per method over ``rows``: total time, comparisons (None if any unknown), matches, GT inliers, wrong,
    verdict counts, slowest pair and the pair with the largest time / BF ratio."""
    out = {}
    for c in columns:
        ms = [(r, r["methods"][c]) for r in rows if c in r["methods"]]
        if not ms:
            continue
        comp = None if any(m["comparisons"] is None for _, m in ms) else sum(m["comparisons"] for _, m in ms)
        n1n2 = sum(r["bf_comparisons"] for r, _ in ms)
        slow_r, slow_m = max(ms, key=lambda x: x[1]["time_s"])
        ratio = [(r, m["time_s"] / r["methods"]["bf"]["time_s"]) for r, m in ms if "bf" in r["methods"]]
        worst_r, worst_ratio = max(ratio, key=lambda x: x[1]) if ratio else (None, None)
        verdicts: dict[str, int] = {}
        for _, m in ms:
            verdicts[m["verdict"]] = verdicts.get(m["verdict"], 0) + 1
        matches = sum(m["matches"] for _, m in ms)
        gt = sum(m["gt_inliers"] for _, m in ms)
        out[c] = dict(time_s=sum(m["time_s"] for _, m in ms), comparisons=comp,
                      comparisons_frac=None if comp is None else comp / max(n1n2, 1), matches=matches, gt_inliers=gt,
                      wrong=matches - gt, precision=gt / matches if matches else None, verdicts=verdicts,
                      slowest_pair=slow_r["name"], slowest_time_s=slow_m["time_s"],
                      slowest_vs_bf=slow_m["time_s"] / slow_r["methods"]["bf"]["time_s"] if "bf" in slow_r["methods"] else None,
                      worst_vs_bf_pair=None if worst_r is None else worst_r["name"], worst_vs_bf=worst_ratio,
                      verdict_sources=sorted({m["verdict_source"] for _, m in ms}), pairs=len(ms))
    return out


def targets(set_name: str, scene_rows: list[dict], unrel_rows: list[dict]) -> list[dict]:
    """The pair-matching targets measured on this run: ``[{target, value, ok}]`` (so+epi+ia unless named)."""
    t = totals(scene_rows)
    g = t.get("so+epi+ia")
    out = []
    if not g:
        return out

    def add(what, value, ok):
        out.append(dict(target=what, value=value, ok=bool(ok)))

    ivf, fx = t["faiss_ivf"]["time_s"], t["faiss_flat"]["time_s"]
    if set_name == "0.01":
        add("28-pair total <= 1/2 of the cached IVF-SQ8 search total", f"{g['time_s'] / ivf:.2f}x IVF", g["time_s"] <= ivf / 2)
        add("28-pair total <= 1/25 of faiss exact", f"1/{fx / g['time_s']:.1f} of faiss", g["time_s"] <= fx / 25)
    else:
        add("28-pair total <= the cached IVF-SQ8 search total", f"{g['time_s'] / ivf:.2f}x IVF", g["time_s"] <= ivf)
    gp, ivb = t.get("so+epi+ia+prep"), t.get("faiss_ivf+build")
    if gp and ivb:  # the same comparison with both sides' per-image index builds amortized over their pairs
        lim = 0.5 if set_name == "0.01" else 1.0
        add(f"(both builds amortized) 28-pair total <= {lim:g}x IVF-SQ8 + build",
            f"{gp['time_s'] / ivb['time_s']:.2f}x", gp["time_s"] <= lim * ivb["time_s"])
    add("worst pair <= 1/2 of BF on that pair", f"{g['worst_vs_bf']:.2f}x BF ({g['worst_vs_bf_pair'].rsplit('/', 1)[1]})",
        g["worst_vs_bf"] <= 0.5)
    for r in unrel_rows:
        m, bf = r["methods"]["so+epi+ia"], r["methods"]["bf"]
        short = r["name"].rsplit("/", 1)[1]
        add(f"unrelated {short}: verdict no-overlap", m["verdict"] + (" (post-hoc)" if m["verdict_source"] != "matcher" else ""),
            m["verdict"] == "no-overlap")
        add(f"unrelated {short}: <= 3 % of N1*N2 comparisons", f"{100 * m['comparisons_frac']:.1f} %", m["comparisons_frac"] <= 0.03)
        add(f"unrelated {short}: <= 1/10 of BF time", f"{m['time_s'] / bf['time_s']:.2f}x BF", m["time_s"] <= bf["time_s"] / 10)
    bad_gt, bad_wrong = [], []
    for r in scene_rows:
        m, bf, iv = r["methods"]["so+epi+ia"], r["methods"]["bf"], r["methods"]["faiss_ivf"]
        short = r["name"].rsplit("/", 1)[1]
        if bf["gt_inliers"] >= 50:
            if m["gt_inliers"] < bf["gt_inliers"] or m["gt_inliers"] < iv["gt_inliers"]:
                bad_gt.append(f"{short} ({m['gt_inliers']} vs BF {bf['gt_inliers']}, IVF {iv['gt_inliers']})")
        elif m["wrong"] > bf["wrong"]:
            bad_wrong.append(f"{short} ({m['wrong']} vs BF {bf['wrong']})")
    n50 = sum(r["methods"]["bf"]["gt_inliers"] >= 50 for r in scene_rows)
    add(f"GT inliers >= BF and >= IVF on every pair where BF finds >= 50 ({n50} pairs)",
        "fails on " + ", ".join(bad_gt) if bad_gt else "all pairs", not bad_gt)
    add(f"pairs where BF finds < 50 ({len(scene_rows) - n50}): no more wrong matches than BF",
        "fails on " + ", ".join(bad_wrong) if bad_wrong else "all pairs", not bad_wrong)
    return out


# --------------------------------------------------------------------------------------------- report
_FORMATS = {"s": lambda v: f"{v:.2f}" if v >= 0.1 else f"{v:.3f}", "pct": lambda v: f"{100 * v:.1f} %",
            "x": lambda v: f"{v:.2f}x"}


def _f(v, kind="s"):
    """Table cell: seconds (3 significant-ish digits), percentage, ratio; "n/a" for None / NaN."""
    from .bench import _fmt

    if kind not in _FORMATS or v is None or not np.isfinite(v):
        return _fmt(v, kind)
    return _FORMATS[kind](v)


def _short(name: str) -> str:
    return name.rsplit("/", 1)[1]


def totals_table(t: dict) -> str:
    ref = {k: t[k]["time_s"] for k in ("faiss_ivf", "faiss_flat", "bf") if k in t}
    lines = ["| method | total time (s) | / IVF search | / faiss exact | / our BF | slowest pair: s (x BF there) | "
             "largest time / BF (pair) | comparisons (% of N1·N2) | matches | GT inliers | precision | verdicts |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in COLUMNS:
        if c not in t:
            continue
        m = t[c]
        ver = ", ".join(f"{v} {k}" for k, v in sorted(m["verdicts"].items()))
        src = " (post-hoc)" if m["verdict_sources"] == ["post-hoc"] else ""
        lines.append(
            f"| {LABEL[c]} | {m['time_s']:.2f} | {_f(m['time_s'] / ref['faiss_ivf'], 'x') if 'faiss_ivf' in ref else 'n/a'} | "
            f"{_f(m['time_s'] / ref['faiss_flat'], 'x') if 'faiss_flat' in ref else 'n/a'} | "
            f"{_f(m['time_s'] / ref['bf'], 'x') if 'bf' in ref else 'n/a'} | "
            f"{_short(m['slowest_pair'])}: {_f(m['slowest_time_s'])} ({_f(m['slowest_vs_bf'], 'x')}) | "
            f"{_f(m['worst_vs_bf'], 'x')} ({_short(m['worst_vs_bf_pair']) if m['worst_vs_bf_pair'] else 'n/a'}) | "
            f"{_f(m['comparisons_frac'], 'pct')} | {m['matches']:,} | {m['gt_inliers']:,} | {_f(m['precision'], 'pct')} | "
            f"{ver}{src} |")
    return "\n".join(lines)


def pair_tables(rows: list[dict]) -> str:
    cols = [c for c in COLUMNS if c not in AMORTIZED]
    head = "| pair | angle (°) | N1 x N2 | " + " | ".join(LABEL[c] for c in cols) + " |"
    sep = "|---|---|---|" + "---|" * len(cols)
    t1 = ["Time in s (comparisons as % of N1·N2; IVF: search only, `+b` = with its build share; so+epi+ia: prepared "
          "images, `+p` = with their preparation share)", "", head, sep]
    t2 = ["GT inliers / matches, verdict (V = verified, N = no-overlap, T = too-few-matches; F/H = model; "
          "* = post-hoc fit on the returned matches)", "", head, sep]
    for r in rows:
        ang = "unrelated" if r.get("rotation_deg") is None else f"{r['rotation_deg']:.1f}"
        pre = f"| {_short(r['name'])} | {ang} | {r['n1']:,} x {r['n2']:,} |"
        c1, c2 = [], []
        for c in cols:
            m = r["methods"].get(c)
            if m is None:
                c1.append("–")
                c2.append("–")
                continue
            comp = f" ({_f(m['comparisons_frac'], 'pct')})" if m["comparisons"] is not None else ""
            extra = (f" +b {_f(r['methods']['faiss_ivf+build']['time_s'])}" if c == "faiss_ivf" else
                     f" +p {_f(r['methods']['so+epi+ia+prep']['time_s'])}" if c == "so+epi+ia" and
                     "so+epi+ia+prep" in r["methods"] else "")
            c1.append(f"{_f(m['time_s'])}{comp}{extra}")
            v = {"verified": "V", "no-overlap": "N", "too-few-matches": "T"}.get(m["verdict"], m["verdict"])
            v += m["verdict_model"] if m["verdict_model"] in ("F", "H") else ""
            c2.append(f"{m['gt_inliers']:,} / {m['matches']:,} {v}{'*' if m['verdict_source'] != 'matcher' else ''}")
        t1.append(pre + " " + " | ".join(c1) + " |")
        t2.append(pre + " " + " | ".join(c2) + " |")
    return "\n".join(t1) + "\n\n" + "\n".join(t2)


def _changes(res: dict) -> str:
    ch = res.get("set_config_changes") or {}
    return ", ".join(f"`{k}={v}`" for k, v in ch.items()) or "none"


def _targets_md(ts: list[dict]) -> str:
    lines = ["| target (so+epi+ia) | measured | met |", "|---|---|---|"]
    lines += [f"| {t['target']} | {t['value']} | {'yes' if t['ok'] else '**no**'} |" for t in ts]
    return "\n".join(lines)


def write_report(out: Path, res: dict, command: str) -> Path:
    from ..features import atomic_write_text

    meta = res["meta"]
    md = [f"# Pairs benchmark: {SCENE}, all pairs + unrelated pairs", "",
          f"`{command}` -- commit `{str(meta.get('git_commit'))[:10]}`{' + local changes' if meta.get('git_dirty') else ''}, "
          f"{str(meta.get('timestamp_utc', ''))[:16]} UTC, {cpu_label(meta)}, {meta.get('usable_cores')} usable cores, "
          f"{res['elapsed_s'] / 60:.1f} min.", "",
          f"**Timing caveat**: {res.get('machine_note', MACHINE_NOTE)}.", "",
          f"Times: the matching call only (detection excluded, features cached), median of {res['repeats']} run(s), "
          "after a warm-up of every method. GT inliers: symmetric epipolar distance < 3 px under the GT cameras "
          "(unrelated pairs: every match is wrong). Comparisons: descriptor distances evaluated, exact counts "
          "(IVF: coarse quantizer + scanned codes, both directions of its cross-check; FLANN does not report them). "
          "Ratio 0.8 for every method; IVF-SQ8 as COLMAP's CPU matcher: one index per image "
          "(nlist = 4·sqrt(N), nprobe = 8, QT_8bit_direct), max distance 0.7·512, cross-check; "
          "'+ build amortized' adds each image's index build divided by the number of pairs it takes part in. "
          "FLANN: KD-tree, 4 trees, 64 checks.", ""]
    if res.get("verdict_note"):
        md += [f"**Verdicts**: {res['verdict_note']}", ""]
    for name, s in res.get("sets", {}).items():
        scene = [r for r in s["rows"] if not r["unrelated"]]
        unrel = [r for r in s["rows"] if r["unrelated"]]
        ns = [v["n"] for v in s["images"].values()]
        md += [f"## Feature set `{name}` ({'8192 strongest of ' if name == '8192' else 'all '}SIFT contrastThreshold=0.01"
               f"{', quick: ' + str(s['features']['strongest']) + ' strongest at scale ' + str(s['features']['scale']) if res['quick'] else ''}; "
               f"{min(ns):,}-{max(ns):,} features per image)", "",
               f"### Totals over the {len(scene)} {SCENE} pairs", "", totals_table(totals(scene)), ""]
        if s.get("prepared"):
            tot_prep = sum(v.get("prepare_s", 0.0) for v in s["images"].values())
            lazy = sum(float(_field(r["methods"]["so+epi+ia"].get("timing") or {}, "index_build_s", 0.0) or 0.0)
                       for r in s["rows"])
            md += [f"Our modes were given prepared images (`guidedmatch.prepared.prepare` and its approximate index "
                   f"built once per image, as the IVF-SQ8 peer's index): {tot_prep:.2f} s in all, not in the "
                   f"so+epi+ia / epi times, amortized over each image's pairs in the '+ prepare amortized' row "
                   f"(index builds left inside a match: {lazy:.2f} s). With prepared images our modes run with the "
                   f"settings of a collection run (`guidedmatch colmap` / `hloc`): `MatcherConfig` defaults except "
                   f"{_changes(res)} (`guidedmatch.collection.engine.COLLECTION_MATCHER_DEFAULTS`: the index is "
                   f"searched from the first query; a one-off `match` first rents exact search, docs/collections.md).",
                   ""]
        if unrel:
            md += [f"### Totals over the {len(unrel)} unrelated pairs ({SCENE} image vs an Unsplash photo, long side "
                   f"{s['features']['unrelated_long_side']} px, its {s['features'].get('unrelated_photo_cap', 0):,} "
                   "strongest features at most: as many as the largest Herz-Jesus image has)", "",
                   totals_table(totals(unrel)), ""]
        md += ["### Targets on this run", "", _targets_md(s["targets"]), "", "### Per pair", "",
               pair_tables(s["rows"]), "",
               f"IVF index builds per image (s): " + ", ".join(f"{k} {v['ivf_build_s']:.2f}" for k, v in s["images"].items()), ""]
    if res.get("dense"):
        d = res["dense"]
        m = d["methods"]
        md += [f"## Dense pair {_short(d['name'])} at contrastThreshold={d['contrastThreshold']} ({d['n1']:,} x {d['n2']:,} features)", "",
               "| method | time (s) | speed-up of so+epi+ia | comparisons (% of N1·N2) | matches | GT inliers | precision |",
               "|---|---|---|---|---|---|---|"]
        for c in ("so+epi+ia", "bf", "faiss_flat", "opencv_flann"):
            x = m[c]
            md.append(f"| {LABEL[c]} | {_f(x['time_s'])} | {_f(d['speedup'].get(c), 'x') if c in d['speedup'] else '–'} | "
                      f"{_f(x['comparisons_frac'], 'pct')} | {x['matches']:,} | {x['gt_inliers']:,} | {_f(x['precision'], 'pct')} |")
        md += ["", _targets_md(d["targets"]), ""]
    if res.get("oxford"):
        md += ["## Oxford, the paper's 12 pairs: so+epi+ia vs BF+ratio (true = within 3 px of the GT homography)", "",
               "| pair | precision so+epi+ia | precision BF | true so+epi+ia | true BF | precision >= BF | true >= BF |",
               "|---|---|---|---|---|---|---|"]
        for r in res["oxford"]:
            g, bf = r["methods"]["so+epi+ia"], r["methods"]["bf"]
            md.append(f"| {r['name'].split('/', 1)[1]} | {_f(g['precision'], 'pct')} | {_f(bf['precision'], 'pct')} | "
                      f"{g['true']:,} | {bf['true']:,} | {'yes' if r['ok_precision'] else '**no**'} | {'yes' if r['ok_true'] else '**no**'} |")
        md.append("")
    if res.get("figure"):
        md += [f"![time and GT inliers vs camera angle]({Path(res['figure']).name})", ""]
    path = out / "pairs.md"
    atomic_write_text(path, "\n".join(md))
    return path


def plot(out: Path, res: dict) -> Path | None:
    """Time (log) and GT inliers of each method against the angle between the GT cameras, one column per set."""
    from ..plots import _plt, save_figure

    sets = res.get("sets", {})
    if not sets:
        return None
    plt = _plt()
    fig, axes = plt.subplots(2, len(sets), figsize=(6.5 * len(sets), 8), squeeze=False)
    marks = dict(zip(COLUMNS, "o.sD^vx+"))
    for j, (name, s) in enumerate(sets.items()):
        rows = sorted((r for r in s["rows"] if not r["unrelated"]), key=lambda r: r["rotation_deg"])
        x = [r["rotation_deg"] for r in rows]
        for c in COLUMNS:
            if not rows or c not in rows[0]["methods"]:
                continue
            axes[0, j].plot(x, [r["methods"][c]["time_s"] for r in rows], marker=marks[c], lw=0.8, ms=4, label=LABEL[c])
            if c not in AMORTIZED:
                axes[1, j].plot(x, [r["methods"][c]["gt_inliers"] for r in rows], marker=marks[c], lw=0.8, ms=4, label=LABEL[c])
        axes[0, j].set_yscale("log")
        axes[0, j].set_ylabel("matching time (s, log)")
        axes[1, j].set_ylabel("GT inliers (< 3 px epipolar)")
        axes[1, j].set_yscale("symlog", linthresh=10)
        for i in range(2):
            axes[i, j].set_xlabel("angle between the two GT cameras (relative rotation, °)")
            axes[i, j].grid(alpha=0.3)
        n = [v["n"] for v in s["images"].values()]
        axes[0, j].set_title(f"{SCENE}, {len(rows)} pairs, set {name} ({min(n):,}-{max(n):,} features)", fontsize=9)
        axes[0, j].legend(fontsize=7)
    fig.suptitle("guidedmatch bench pairs (shared 2-core machine: times noisy)", fontsize=10)
    return save_figure(fig, out / "pairs_angle.png", dpi=80)


def _verdict_note(res: dict) -> None:
    """Set ``verdict_source_ours`` and ``verdict_note``: where our modes' verdicts came from."""
    srcs = {m["verdict_source"] for s in res["sets"].values() for r in s["rows"]
            for k, m in r["methods"].items() if k in OURS}
    res["verdict_source_ours"] = sorted(srcs)
    if "post-hoc" in srcs:
        res["verdict_note"] = ("this matcher returns no `result.geometry`: the verdicts of our modes were computed "
                               "after timing by `guidedmatch.geometry.two_view_geometry` on the returned matches "
                               "(for guided modes biased towards 'verified': their matches were selected with their own F). "
                               "Peers' verdicts are always post-hoc.")
    else:
        res["verdict_note"] = ("our modes' verdicts are the matcher's own `result.geometry`; peers' verdicts are "
                               "post-hoc `two_view_geometry` fits on their returned matches.")
