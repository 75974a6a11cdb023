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

Code: this module runs the methods (:func:`run_pair`, :func:`run_set`, :func:`run_dense`, :func:`run_oxford`,
:func:`main`); :mod:`~guidedmatch.evaluation.bench_pairs_data` holds the pair list and the cached features,
:mod:`~guidedmatch.evaluation.bench_pairs_report` the totals, targets, markdown report and figure.
"""
from __future__ import annotations

import dataclasses
import importlib
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from .bench_pairs_data import (DENSE_CT, DENSE_PAIR, FEATURE_SETS, FLANN, LONG_SIDE, NUM_UNRELATED, OURS, PEERS,
                               QUICK, SCENE, _cache_dir, _field, cached_features, pair_list, strongest)
from .bench_pairs_report import (AMORTIZED, COLUMNS, LABEL, MACHINE_NOTE, _verdict_note, machine_note, pair_tables,
                                 plot, targets, totals, totals_table, write_report)

#: the names of the data and report modules, found here too
__all__ = ["SCENE", "LONG_SIDE", "NUM_UNRELATED", "FEATURE_SETS", "OURS", "PEERS", "COLUMNS", "AMORTIZED", "LABEL",
           "FLANN", "QUICK", "DENSE_PAIR", "DENSE_CT", "machine_note", "MACHINE_NOTE", "add_arguments",
           "cached_features", "strongest", "pair_list", "run_pair", "warm_up", "run_set", "totals", "targets",
           "run_dense", "run_oxford", "totals_table", "pair_tables", "write_report", "plot", "main"]


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


# --------------------------------------------------------------------------------------------- main
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
