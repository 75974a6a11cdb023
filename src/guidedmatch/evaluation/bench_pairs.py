"""``guidedmatch bench pairs``: every pair of a collection, wide baselines and unrelated images.

What it measures
----------------
All 28 pairs of Strecha Herz-Jesus-P8 (3072x2048, GT cameras from ``gt_dense_cameras``,
:func:`guidedmatch.datasets.strecha_scene_pairs`) plus 5 *unrelated* pairs (Herz-Jesus image ``k`` vs the ``k``-th
Unsplash photo, resized so its long side is 3072 px, the Herz-Jesus long side, and cut to its strongest features,
as many as the largest Herz-Jesus image has), for two feature sets:

* ``8192``: the 8192 strongest (by response) of the ``contrastThreshold=0.01`` SIFT features (COLMAP's default count);
* ``0.01``: all SIFT features at ``contrastThreshold=0.01`` (~40k per image).

Methods, all on the same features and in the same process: ``so+epi+ia``, ``epi``, our BF (``mode="bf"``), faiss
exact (:func:`~guidedmatch.evaluation.peers.match_faiss`), the COLMAP-style cached IVF-SQ8 index
(:func:`~guidedmatch.evaluation.peers.build_ivf_index` once per image, :func:`~guidedmatch.evaluation.peers.match_faiss_ivf`
per pair: ratio 0.8 + max distance + cross-check) -- reported as search only and with the index builds amortized
over the pairs each image takes part in -- and OpenCV FLANN (KD-tree, 4 trees, 64 checks, as
``benchmarks/bench_guided.py``). Ratio 0.8 everywhere.

Per pair and method: wall time of the matching call (``time.perf_counter``, detection excluded, median of
``--repeats``), exact descriptor comparisons (``None`` for FLANN, which does not report them), matches, GT inliers
(symmetric epipolar distance < 3 px under the GT cameras, :meth:`guidedmatch.datasets.EpipolarGT.correct`; 0 by
definition on unrelated pairs), precision, and the two-view verdict: ``result.geometry`` when the matcher returns one,
otherwise :func:`guidedmatch.geometry.two_view_geometry` run on the returned matches after timing (marked
``verdict_source = "post-hoc"``; for guided modes this is biased towards "verified", since their matches were
selected with their own F). If :mod:`guidedmatch.prepared` exists, each image is prepared once per feature set and
the prepared objects are passed to ``match`` (preparation time reported and amortized like the IVF builds).

Extra targets: ``--dense`` (pair 0002/0003 at ``contrastThreshold=0.002``, ~92k features: so+epi+ia vs faiss exact,
FLANN and our BF) and ``--oxford`` (the 12 Oxford pairs of the paper: precision and true correspondences of
so+epi+ia vs BF+ratio).

Outputs in ``--out``: ``pairs.json`` (run metadata + every per-pair row), ``pairs.md`` (totals, targets, per-pair
tables), ``pairs_angle.png`` (time and GT inliers against the angle between the two GT cameras). Features are
cached as ``.npz`` in ``<out>/features/`` (a ``.gitignore`` there keeps them out of git), so reruns skip detection.
"""
from __future__ import annotations

import dataclasses
import importlib
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

SCENE = "Herz-Jesus-P8"
LONG_SIDE = 3072  # long side of the Herz-Jesus images; unrelated photos are resized to it
NUM_UNRELATED = 5
FEATURE_SETS = ("8192", "0.01")
OURS = ("so+epi+ia", "epi", "bf")
PEERS = ("faiss_flat", "faiss_ivf", "opencv_flann")
#: Report columns: ``faiss_ivf+build`` is the IVF run with the index builds amortized over the image's pairs,
#: ``so+epi+ia+prep`` ours with its per-image preparation (descriptor forms + its own IVF index) amortized the same way.
COLUMNS = ("so+epi+ia", "so+epi+ia+prep", "epi", "bf", "faiss_flat", "faiss_ivf", "faiss_ivf+build", "opencv_flann")
AMORTIZED = ("so+epi+ia+prep", "faiss_ivf+build")
LABEL = {"so+epi+ia": "so+epi+ia", "so+epi+ia+prep": "so+epi+ia (+ prepare amortized)", "epi": "epi", "bf": "our BF",
         "faiss_flat": "faiss exact",
         "faiss_ivf": "IVF-SQ8 cached (search)", "faiss_ivf+build": "IVF-SQ8 (+ build amortized)",
         "opencv_flann": "OpenCV FLANN"}
FLANN = dict(trees=4, checks=64)  # as benchmarks/bench_guided.py (the FLANN ratios of its table)
QUICK = dict(scale=0.5, pairs=("0000-0001", "0000-0005"), unrelated=1, cap={"8192": 2048, "0.01": 6000})
DENSE_PAIR = ("0002", "0003")
DENSE_CT = 0.002


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


# --------------------------------------------------------------------------------------------- CLI
def add_arguments(parser) -> None:
    """Options of ``guidedmatch bench pairs`` (added to the ``bench`` sub-parser; ignored by the other benches)."""
    parser.add_argument("--features", action="append", choices=("8192", "0.01", "50k", "both", "none"),
                        help="pairs: feature set(s) to run: 8192 strongest, 0.01 = contrastThreshold 0.01 (~40k), both "
                        "(default), none; sfm: 8192 and/or 50k (repeatable; default both)")
    parser.add_argument("--dense", action="store_true",
                        help="pairs: also pair 0002/0003 at contrastThreshold=0.002 (~92k) vs faiss exact and FLANN")
    parser.add_argument("--oxford", action="store_true",
                        help="pairs: also the 12 Oxford pairs: precision / true of so+epi+ia vs BF+ratio")


# --------------------------------------------------------------------------------------------- data
def _cache_dir(out: Path) -> Path:
    d = out / "features"
    d.mkdir(parents=True, exist_ok=True)
    ign = d / ".gitignore"
    if not ign.exists():
        ign.write_text("*\n")
    return d


def _load_grey(path: Path, long_side: int | None, scale: float) -> np.ndarray:
    """Grey uint8 image; resized so its long side is ``long_side`` (if given), then by ``scale``."""
    import cv2

    from ..features import load_image

    img = load_image(path, grey=True)
    h, w = img.shape[:2]
    f = (long_side / max(h, w) if long_side else 1.0) * scale
    if f != 1.0:
        size = (max(1, round(w * f)), max(1, round(h * f)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
    return img


def cached_features(path: Path, cache: Path, ct: float, *, long_side: int | None = None, scale: float = 1.0):
    """SIFT (``contrastThreshold=ct``) of one image, from ``cache`` when there, else detected and saved."""
    from ..features import Features, detect

    tag = f"{path.parent.parent.name}_{path.stem}" if path.parent.name == "images" else path.stem
    f = cache / f"{tag}_ls{long_side or 0}_s{scale:g}_ct{ct:g}.npz"
    if f.exists():
        return Features.load(f)
    feats = detect(_load_grey(path, long_side, scale), "sift", contrastThreshold=ct)
    feats.save(f)
    return feats


def strongest(f, n: int | None):
    """The ``n`` strongest features by detector response (index order kept)."""
    if n is None or n >= len(f):
        return f
    idx = np.sort(np.argsort(-f.responses, kind="stable")[:n])
    return f.subset(idx)


def pair_list(root, quick: bool):
    """``(scene pairs, unrelated pairs)``; unrelated = ``(name, herz-jesus image path, photo path)``."""
    from ..datasets import list_photos, strecha_scene_pairs

    pairs = strecha_scene_pairs(root, SCENE)
    images = sorted({Path(p.image1) for p in pairs} | {Path(p.image2) for p in pairs})
    photos = list_photos(root)
    n_unrel = QUICK["unrelated"] if quick else NUM_UNRELATED
    if quick:
        pairs = [p for p in pairs if p.name.rsplit("/", 1)[1] in QUICK["pairs"]]
    unrelated = [(f"unrelated/{images[k].stem}-vs-{'-'.join(photos[k].stem.split('-')[:2])}", images[k], photos[k])
                 for k in range(n_unrel)]
    return pairs, unrelated


# --------------------------------------------------------------------------------------------- methods
def _prepare_fn():
    """``guidedmatch.prepared.prepare`` when the prepared-image API exists, else None."""
    try:
        mod = importlib.import_module("guidedmatch.prepared")
    except ImportError:
        return None
    return getattr(mod, "prepare", None)


def _timed(fn, repeats: int):
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t0)
    return res, times


def _verdict(res, f1, f2):
    """``(TwoViewGeometry, source)``: the matcher's own ``result.geometry`` or a post-hoc robust fit."""
    g = getattr(res, "geometry", None)
    if g is not None:
        return g, "matcher"
    from ..geometry import two_view_geometry

    p1, p2 = f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]]
    return two_view_geometry(p1, p2, f1.image_size, f2.image_size), "post-hoc"


def _record(res, times, f1, f2, gt, comparisons, extra=None) -> dict:
    n1n2 = len(f1) * len(f2)
    pairs = res.pairs
    if gt is not None and len(pairs):
        ok = gt.correct(f1.keypoints[pairs[:, 0]], f2.keypoints[pairs[:, 1]])
    else:  # unrelated pair: no match can be right
        ok = np.zeros(len(pairs), bool)
    g, source = _verdict(res, f1, f2)
    m = dict(time_s=float(statistics.median(times)), times_s=[float(t) for t in times],
             comparisons=None if comparisons is None else int(comparisons),
             comparisons_frac=None if comparisons is None else float(comparisons) / max(n1n2, 1),
             matches=int(len(pairs)), gt_inliers=int(ok.sum()), wrong=int(len(pairs) - ok.sum()),
             precision=float(ok.mean()) if len(ok) else None,
             verdict=g.verdict, verdict_model=g.model, verdict_inliers=int(g.num_inliers), verdict_source=source,
             verdict_gt_inliers=int((ok & np.asarray(g.inliers, bool)).sum()) if len(ok) == len(g.inliers) else None)
    if extra:
        m.update(extra)
    return m


def _field(obj, name, default=None):
    """``obj[name]`` for dicts, ``getattr`` otherwise (stats and fallbacks are dataclasses or, before, dicts)."""
    if isinstance(obj, dict):
        return obj.get(name, default)
    return getattr(obj, name, default)


def _ours_extra(stats) -> dict:
    """The parts of our matcher's stats kept per pair (fallbacks, phase times, updates, what was chosen)."""
    details = _field(stats, "details") or {}
    fallbacks = _field(stats, "fallbacks") or ()
    return dict(fallbacks=[f"{_field(f, 'what')}: {_field(f, 'reason')}" for f in fallbacks],
                timing=_field(stats, "timing"), alignment_scale=details.get("alignment_scale", _field(stats, "alignment_scale")),
                stats_time_s=_field(stats, "time_s"), num_updates=len(_field(stats, "updates") or ()),
                details={k: v for k, v in details.items() if isinstance(v, (str, int, float, bool, type(None)))})


def run_pair(name, f1, f2, gt, *, repeats, config, ivf1, ivf2, prep1=None, prep2=None, angles=None,
             methods=OURS + PEERS) -> dict:
    """Every method on one pair's features -> row dict (raw numbers only)."""
    from ..matcher import match
    from . import peers

    row = dict(name=name, n1=len(f1), n2=len(f2), bf_comparisons=len(f1) * len(f2), methods={},
               **(angles or {}))
    a = prep1 if prep1 is not None else f1
    b = prep2 if prep2 is not None else f2
    for mode in OURS:
        if mode not in methods:
            continue
        res, times = _timed(lambda: match(a, b, mode, config), repeats)
        row["methods"][mode] = _record(res, times, f1, f2, gt, _field(res.stats, "comparisons"), _ours_extra(res.stats))
    if "faiss_flat" in methods:
        res, times = _timed(lambda: peers.match_faiss(f1, f2, ratio=0.8), repeats)
        row["methods"]["faiss_flat"] = _record(res, times, f1, f2, gt, _field(res.stats, "comparisons"))
    if "faiss_ivf" in methods:
        res, times = _timed(lambda: peers.match_faiss_ivf(f1, f2, ratio=0.8, index1=ivf1, index2=ivf2), repeats)
        d = _field(res.stats, "details") or res.stats
        row["methods"]["faiss_ivf"] = _record(res, times, f1, f2, gt, _field(res.stats, "comparisons"),
                                              dict(nlist=d["nlist"], nprobe=d["nprobe"]))
    if "opencv_flann" in methods:
        res, times = _timed(lambda: peers.match_opencv_flann(f1, f2, ratio=0.8, **FLANN), repeats)
        row["methods"]["opencv_flann"] = _record(res, times, f1, f2, gt, None, dict(FLANN))
    return row


def warm_up(f1, f2, config) -> None:
    """Untimed calls before timing: the peers on small subsets (thread pools, first-call costs) and our modes on the
    full pair, prepared when the prepared-image API exists (Numba compiles per code path and argument types, and a
    matcher may take another path at full size than on a subset)."""
    from ..geometry import two_view_geometry
    from ..matcher import match
    from . import peers

    a, b = strongest(f1, 1500), strongest(f2, 1500)
    r = match(a, b, "bf", config)
    two_view_geometry(a.keypoints[r.pairs[:, 0]], b.keypoints[r.pairs[:, 1]], a.image_size, b.image_size)
    peers.match_faiss(a, b)
    peers.match_faiss_ivf(a, b)
    peers.match_opencv_flann(a, b, **FLANN)
    prep = _prepare_fn()
    for x, y in ((a, b), (f1, f2)):
        if prep is not None:
            x, y = prep(x), prep(y)
        for mode in OURS:
            match(x, y, mode, config)


# --------------------------------------------------------------------------------------------- one feature set
def run_set(set_name, root, out, *, quick, repeats, config, progress=True) -> dict:
    """All pairs of one feature set -> ``{"features", "images", "pairs", "unrelated"}``."""
    from . import peers

    cache = _cache_dir(out)
    scale = QUICK["scale"] if quick else 1.0
    cap = (QUICK["cap"][set_name] if quick else (8192 if set_name == "8192" else None))
    scene_pairs, unrelated = pair_list(root, quick)
    log = print if progress else (lambda *a, **k: None)

    feats, sources = {}, {}
    for p in scene_pairs:
        for path in (Path(p.image1), Path(p.image2)):
            sources[path.stem] = (path, None)
    for _, img, photo in unrelated:
        sources[img.stem] = (img, None)
        sources[photo.stem] = (photo, LONG_SIDE)
    t0 = time.perf_counter()
    for key, (path, ls) in sources.items():
        feats[key] = strongest(cached_features(path, cache, 0.01, long_side=ls, scale=scale), cap)
    # A textured photo gives far more features than a Herz-Jesus image at the same size (117k vs 42k at ct=0.01):
    # keep its strongest ones, as many as the largest Herz-Jesus image has, so N1*N2 stays comparable.
    photo_cap = max(len(feats[k]) for k, (_, ls) in sources.items() if ls is None)
    for key, (_, ls) in sources.items():
        if ls is not None:
            feats[key] = strongest(feats[key], photo_cap)
    log(f"[{set_name}] features of {len(feats)} images ready in {time.perf_counter() - t0:.1f} s "
        f"({min(map(len, feats.values()))}-{max(map(len, feats.values()))} per image)", flush=True)

    items = []  # (name, key1, key2, gt, angles)
    for p in scene_pairs:
        gt = p.gt.rescaled(scale, scale) if scale != 1.0 else p.gt
        items.append((p.name, Path(p.image1).stem, Path(p.image2).stem, gt,
                      dict(rotation_deg=p.meta["rotation_deg"], axis_deg=p.meta["axis_deg"])))
    for name, img, photo in unrelated:
        items.append((name, img.stem, photo.stem, None, dict(rotation_deg=None, axis_deg=None)))
    uses = {k: 0 for k in feats}
    for _, k1, k2, _, _ in items:
        uses[k1] += 1
        uses[k2] += 1

    k0, k1 = items[0][1], items[0][2]
    warm_up(feats[k0], feats[k1], config)
    images, ivf, prepared = {}, {}, {}
    prep = _prepare_fn()
    for key, f in feats.items():
        if uses[key] == 0:
            continue
        ivf[key] = peers.build_ivf_index(f)
        info = dict(n=len(f), size=list(f.image_size), pairs=uses[key], ivf_build_s=ivf[key].build_s,
                    ivf_nlist=ivf[key].nlist)
        if prep is not None:  # once per image, like the IVF build: descriptor forms and the approximate index
            t = time.perf_counter()
            prepared[key] = prep(f)
            if getattr(prepared[key], "has_index", False):
                prepared[key].index()
            info["prepare_s"] = time.perf_counter() - t
        images[key] = info

    rows = []
    for i, (name, a, b, gt, angles) in enumerate(items):
        row = run_pair(name, feats[a], feats[b], gt, repeats=repeats, config=config, ivf1=ivf[a], ivf2=ivf[b],
                       prep1=prepared.get(a), prep2=prepared.get(b), angles=angles)
        row["unrelated"] = gt is None
        row["images"] = [a, b]
        ivf_m = row["methods"]["faiss_ivf"]
        share = images[a]["ivf_build_s"] / images[a]["pairs"] + images[b]["ivf_build_s"] / images[b]["pairs"]
        row["methods"]["faiss_ivf+build"] = {**ivf_m, "time_s": ivf_m["time_s"] + share, "build_share_s": share,
                                             "times_s": [t + share for t in ivf_m["times_s"]]}
        if prep is not None:
            share = (images[a]["prepare_s"] / images[a]["pairs"] + images[b]["prepare_s"] / images[b]["pairs"])
            row["prepare_share_s"] = share
            ours = row["methods"]["so+epi+ia"]
            row["methods"]["so+epi+ia+prep"] = {**ours, "time_s": ours["time_s"] + share, "prepare_share_s": share,
                                                "times_s": [t + share for t in ours["times_s"]]}
        rows.append(row)
        m = row["methods"]
        log(f"[{set_name}] {i + 1:>2}/{len(items)} {name:<46} {row['n1']}x{row['n2']}  "
            + "  ".join(f"{k}={m[k]['time_s']:.2f}s/{m[k]['gt_inliers']}" for k in ("so+epi+ia", "bf", "faiss_ivf")),
            flush=True)
    return dict(features=dict(detector="sift", contrastThreshold=0.01, strongest=cap, scale=scale,
                              unrelated_long_side=round(LONG_SIDE * scale), unrelated_photo_cap=photo_cap),
                prepared=prep is not None, images=images, rows=rows)


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


# --------------------------------------------------------------------------------------------- extras
def run_dense(root, out, *, quick, repeats, config, progress=True) -> dict:
    """Pair 0002/0003 at ``contrastThreshold=0.002``: so+epi+ia vs faiss exact, FLANN, our BF (a speed target)."""
    from ..datasets import strecha_scene_pairs

    pair = next(p for p in strecha_scene_pairs(root, SCENE) if p.name.endswith("-".join(DENSE_PAIR)))
    scale = QUICK["scale"] if quick else 1.0
    cache = _cache_dir(out)
    f1 = cached_features(Path(pair.image1), cache, DENSE_CT, scale=scale)
    f2 = cached_features(Path(pair.image2), cache, DENSE_CT, scale=scale)
    if quick:
        f1, f2 = strongest(f1, 8000), strongest(f2, 8000)
    gt = pair.gt.rescaled(scale, scale) if scale != 1.0 else pair.gt
    if progress:
        print(f"[dense] {pair.name} at contrastThreshold={DENSE_CT}: {len(f1)} x {len(f2)} features", flush=True)
    warm_up(f1, f2, config)
    row = run_pair(pair.name, f1, f2, gt, repeats=repeats, config=config, ivf1=None, ivf2=None,
                   methods=("so+epi+ia", "bf", "faiss_flat", "opencv_flann"), angles=dict(
                       rotation_deg=pair.meta["rotation_deg"], axis_deg=pair.meta["axis_deg"]))
    m = row["methods"]
    g = m["so+epi+ia"]["time_s"]
    row["speedup"] = {k: m[k]["time_s"] / g for k in ("bf", "faiss_flat", "opencv_flann")}
    row["contrastThreshold"] = DENSE_CT
    row["targets"] = [dict(target=">= 60x faiss exact", value=f"{row['speedup']['faiss_flat']:.1f}x",
                           ok=row["speedup"]["faiss_flat"] >= 60),
                      dict(target=">= 15x OpenCV FLANN", value=f"{row['speedup']['opencv_flann']:.1f}x",
                           ok=row["speedup"]["opencv_flann"] >= 15)]
    return row


def run_oxford(root, *, quick, repeats, config, progress=True) -> list[dict]:
    """The paper's 12 Oxford pairs: so+epi+ia vs BF+ratio (true = within 3 px of the GT homography)."""
    from ..datasets import oxford_pairs
    from ..features import detect
    from ..matcher import match

    pairs = oxford_pairs(root)
    if quick:
        pairs = pairs[:2]
    rows = []
    for p in pairs:
        i1, i2 = p.load()
        f1, f2 = detect(i1, "sift"), detect(i2, "sift")
        row = dict(name=p.name, n1=len(f1), n2=len(f2), methods={})
        for mode in ("so+epi+ia", "bf"):
            res, times = _timed(lambda: match(f1, f2, mode, config), repeats)
            ok = p.gt.correct(f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]]) if len(res) else np.zeros(0, bool)
            row["methods"][mode] = dict(matches=len(res), true=int(ok.sum()),
                                        precision=float(ok.mean()) if len(ok) else None,
                                        comparisons=_field(res.stats, "comparisons"), time_s=float(statistics.median(times)))
        g, bf = row["methods"]["so+epi+ia"], row["methods"]["bf"]
        row["ok_precision"] = (g["precision"] or 0) >= (bf["precision"] or 0)
        row["ok_true"] = g["true"] >= bf["true"]
        rows.append(row)
        if progress:
            print(f"[oxford] {p.name}: precision {100 * (g['precision'] or 0):.2f} vs BF {100 * (bf['precision'] or 0):.2f} %, "
                  f"true {g['true']} vs {bf['true']}", flush=True)
    return rows


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
          f"{str(meta.get('timestamp_utc', ''))[:16]} UTC, {meta.get('cpu_model')}, {meta.get('usable_cores')} usable cores, "
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


# --------------------------------------------------------------------------------------------- main
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


def main(args) -> int:
    from ..datasets import data_root
    from ..matcher import MatcherConfig
    from .meta import run_metadata, write_json

    root = data_root(getattr(args, "data", None))
    need = [root / "pose_pairs" / "strecha" / SCENE, root / "photos" / "unsplash"] if root is not None else []
    if getattr(args, "oxford", False) and root is not None:
        need.append(root / "oxford")
    if root is None or not all(p.exists() for p in need):
        from ..errors import InputError

        raise InputError("no evaluation data for bench pairs: pass --data DIR or set GUIDEDMATCH_DATA (expects "
                         f"pose_pairs/strecha/{SCENE}/, photos/unsplash/"
                         f"{', oxford/' if getattr(args, 'oxford', False) else ''})")
    from ..features import writable_folder

    out = writable_folder(args.out)  # OutputError before any work when --out cannot be written
    out.mkdir(parents=True, exist_ok=True)
    quick = bool(getattr(args, "quick", False))
    repeats = getattr(args, "repeats", None) or 1
    from ..errors import ConfigError

    which = getattr(args, "features", None) or ["both"]
    which = "both" if len(which) > 1 else which[0]
    if which not in ("8192", "0.01", "both", "none"):
        raise ConfigError(f"bench pairs --features takes 8192, 0.01, both or none; got {which!r}")
    sets = FEATURE_SETS if which == "both" else (() if which == "none" else (which,))
    config = MatcherConfig()  # one-off pairs: --dense, --oxford
    from ..collection.engine import COLLECTION_MATCHER_DEFAULTS, collection_matcher_config

    # prepared images (every image indexed once for all its pairs) are what a collection run matches: its settings
    set_config = collection_matcher_config() if _prepare_fn() is not None else config
    command = ("guidedmatch bench pairs" + (" --quick" if quick else "") + f" --features {which}"
               + (" --dense" if getattr(args, "dense", False) else "") + (" --oxford" if getattr(args, "oxford", False) else "")
               + f" --repeats {repeats} --out {args.out}")
    t0 = time.perf_counter()

    def checkpoint():  # after each stage: JSON + report + plot of what is finished, marked partial
        _verdict_note(res)
        res["elapsed_s"] = time.perf_counter() - t0
        write_json(out / "pairs.json", {**res, "partial": True})
        write_report(out, {**res, "figure": plot(out, res)}, command + " (partial: still running)")

    meta = run_metadata(seed=getattr(args, "seed", 0))
    res: dict[str, Any] = dict(command=command, meta=meta, quick=quick, repeats=repeats,
                               machine_note=machine_note(meta), config=dataclasses.asdict(config),
                               set_config=dataclasses.asdict(set_config),
                               set_config_changes=dict(COLLECTION_MATCHER_DEFAULTS), sets={})
    for name in sets:
        s = run_set(name, root, out, quick=quick, repeats=repeats, config=set_config)
        scene = [r for r in s["rows"] if not r["unrelated"]]
        unrel = [r for r in s["rows"] if r["unrelated"]]
        s["totals"] = dict(scene=totals(scene), unrelated=totals(unrel))
        s["targets"] = targets(name, scene, unrel)
        res["sets"][name] = s
        checkpoint()  # a late crash keeps the finished sets
    if getattr(args, "dense", False):
        res["dense"] = run_dense(root, out, quick=quick, repeats=repeats, config=config)
        checkpoint()
    if getattr(args, "oxford", False):
        res["oxford"] = run_oxford(root, quick=quick, repeats=repeats, config=config)
    res["partial"] = False
    _verdict_note(res)
    res["elapsed_s"] = time.perf_counter() - t0
    fig = plot(out, res)
    res["figure"] = str(fig) if fig else None
    write_json(out / "pairs.json", res)
    rep = write_report(out, res, command)
    print(f"wrote {rep}, {out / 'pairs.json'}" + (f" and {fig}" if fig else "") + f" in {res['elapsed_s'] / 60:.1f} min")
    for name, s in res["sets"].items():
        print(f"\n## set {name}: totals over the scene pairs\n" + totals_table(s["totals"]["scene"]))
    return 0
