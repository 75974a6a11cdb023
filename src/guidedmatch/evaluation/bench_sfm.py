"""``guidedmatch bench sfm``: COLMAP's matcher vs guidedmatch inside COLMAP's own mapper, judged on GT poses.

Protocol, per feature setting (COLMAP's default 8192 SIFT features; ~50k with peak_threshold 0.002):

1. extract pycolmap SIFT once into a database (CPU, ``--threads`` threads); every method gets a *copy* of it,
   so all methods see the same keypoints and descriptors;
2. match + verify on the copy (timed together):
   * ``colmap``: ``pycolmap.match_exhaustive`` (CPU SIFT matcher, ratio 0.8, cross-check, RANSAC verification);
   * ``colmap_guided``: the same with ``guided_matching=True``;
   * ``<mode>+ours``: :func:`guidedmatch.collection.engine.match_collection` (exhaustive pairs) writing our two-view
     geometries directly (``ColmapSink(geometry="ours")``);
   * ``<mode>+colmap``: the same matches, verified by pycolmap (``ColmapSink(geometry="colmap")`` + ``verify``);
3. ``pycolmap.incremental_mapping`` (timed), largest model;
4. relative pose errors over all image pairs against the Strecha GT cameras (:mod:`guidedmatch.evaluation.poses`).

Columns: match + verify time, verified pairs / inliers, registered images, 3-D points, mapping time, median pose
error, AUC@1/2/5 deg. Writes ``sfm.json`` (with run metadata), ``sfm.md`` and ``sfm_time_vs_inliers.png``.
"""
from __future__ import annotations

import datetime as _dt
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from ..config import MODES as MODES_ALL
from ..sfm import COLMAP_MAX_IMAGE_SIZE, IMAGE_EXTENSIONS, SfmConfig
from .meta import cpu_label
from .poses import evaluate_poses, poses_from_reconstruction, read_strecha_cameras

#: Feature settings: name -> (max_num_features, peak_threshold or None for COLMAP's default).
FEATURE_SETTINGS = {"8192": (8192, None), "50k": (65536, 0.002)}
#: Methods in table order.
COLMAP_METHODS = ("colmap", "colmap_guided")
OUR_MODES = ("so+epi+ia", "epi")
GEOMETRIES = ("ours", "colmap")
#: ``<method>+cap``: the method, then at most ``SfmConfig.max_inliers_per_pair`` (1000) inliers per pair handed to the
#: mapper (``ColmapSink.cap_inliers``: spread over the image, best first) -- what ``guidedmatch sfm`` does by default.
#: Run for COLMAP's own matches too, so the table shows what the selection alone does.
CAP_SUFFIX = "+cap"
CAPPED_METHODS = ("colmap+cap", "so+epi+ia+ours+cap")
DEFAULT_SCENE = Path("pose_pairs") / "strecha" / "Herz-Jesus-P8"


def method_names(modes=OUR_MODES, geometries=GEOMETRIES, colmap=COLMAP_METHODS) -> list[str]:
    return list(colmap) + [f"{m}+{g}" for m in modes for g in geometries] + list(CAPPED_METHODS)


def split_method(method: str) -> tuple[str, bool]:
    """``"so+epi+ia+ours+cap"`` -> ``("so+epi+ia+ours", True)``; ``"colmap"`` -> ``("colmap", False)``.

    >>> split_method("colmap+cap"), split_method("epi+colmap")
    (('colmap', True), ('epi+colmap', False))
    """
    if method.endswith(CAP_SUFFIX):
        return method[: -len(CAP_SUFFIX)], True
    return method, False


def is_known_method(method: str) -> bool:
    base, _ = split_method(method)
    return base in COLMAP_METHODS or (base.rsplit("+", 1)[-1] in GEOMETRIES and base.rsplit("+", 1)[0] in MODES_ALL)


def default_methods(setting: str) -> list[str]:
    """Every method at 8192 features; at ~50k without COLMAP's guided matching (its guided step evaluates a dense
    N1 x N2 geometry matrix per pair: 65 s at 8192 in the issue's measurement, ~40x that at 50k)."""
    names = method_names()
    return names if setting == "8192" else [m for m in names if m != "colmap_guided"]


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def extract_database(image_dir: Path, db: Path, setting: str, threads: int) -> dict:
    """Stage 1 (cached: an existing database with keypoints for every image is reused)."""
    from ..sfm import _db_image_names, extract_colmap_sift, list_images

    names = list_images(image_dir)
    if db.exists():
        have = _db_image_names(db)
        if all(have.get(n, 0) > 0 for n in names):
            return {"time_s": None, "cached": True, "keypoints": sum(have.values()),
                    "per_image": [have[n] for n in names]}
        db.unlink()
    max_features, peak = FEATURE_SETTINGS[setting]
    t0 = time.perf_counter()
    extract_colmap_sift(db, image_dir, names, max_features=max_features, peak_threshold=peak, num_threads=threads)
    elapsed = time.perf_counter() - t0
    have = _db_image_names(db)
    return {"time_s": elapsed, "cached": False, "keypoints": sum(have.values()), "per_image": [have[n] for n in names]}


def match_colmap(db: Path, guided: bool, threads: int) -> dict:
    """``pycolmap.match_exhaustive`` (CPU) on ``db``; returns the timed record."""
    import pycolmap

    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = threads
    mo.use_gpu = False
    mo.guided_matching = guided
    t0 = time.perf_counter()   # verification: COLMAP's defaults (RANSAC single-threaded per pair, pairs in parallel)
    pycolmap.match_exhaustive(str(db), matching_options=mo, device=pycolmap.Device.cpu)
    return {"match_verify_s": time.perf_counter() - t0, "match_s": None, "verify_s": None}


def match_ours(db: Path, mode: str, geometry: str, threads: int, matcher: dict | None = None,
               workers: int | None = None) -> dict:
    """The collection engine over all pairs of ``db`` with ``mode``; ``geometry`` "ours" or "colmap"."""
    import pycolmap

    from ..collection.engine import CollectionConfig, match_collection
    from ..collection.pairs import exhaustive_pairs
    from ..collection.sinks import ColmapSink
    from ..collection.sources import ColmapSource

    source = ColmapSource(db)
    try:
        pairs = exhaustive_pairs(source.names())
        conf = CollectionConfig(mode=mode, matcher=dict(matcher or {}), workers=workers, progress=False)
        t0 = time.perf_counter()
        with ColmapSink(db, geometry=geometry) as sink:
            report = match_collection(source, pairs.pairs, sink, conf)
            t_match = time.perf_counter() - t0
            t1 = time.perf_counter()
            if geometry == "colmap":
                sink.verify(pycolmap.TwoViewGeometryOptions())
        t_verify = time.perf_counter() - t1
    finally:
        source.close()
    return {"match_verify_s": t_match + (t_verify if geometry == "colmap" else 0.0), "match_s": t_match,
            "verify_s": t_verify if geometry == "colmap" else None, "failed_pairs": len(report.failed),
            "collection_totals": report.totals}


def warm_up(db: Path, modes=OUR_MODES) -> None:
    """Compile / load the Numba kernels for this database's descriptor type once (in this process, which writes the
    on-disk cache the engine's worker processes then load), on 3000 features of two of its images, so that no timed
    method pays for compilation."""
    from ..collection.sources import ColmapSource
    from ..matcher import match

    with ColmapSource(db) as src:
        a, b = src.names()[:2]
        f1, f2 = src.load(a), src.load(b)
    f1, f2 = f1.subset(np.arange(min(3000, len(f1)))), f2.subset(np.arange(min(3000, len(f2))))
    for mode in modes:
        match(f1, f2, mode=mode)


def evaluate_database(db: Path, image_dir: Path, gt: dict, work: Path, threads: int, seed: int) -> dict:
    """Verified inliers of ``db``, then incremental mapping and the pose evaluation of its largest model."""
    import pycolmap

    from ..sfm import run_mapping, verified_inliers

    vpairs, inliers = verified_inliers(db)
    mapping = run_mapping(db, image_dir, work / "sparse", num_threads=threads, seed=seed)
    out = {"verified_pairs": vpairs, "verified_inliers": inliers, "mapping_s": mapping["time_s"],
           "models": len(mapping["models"])}
    if mapping["models"]:
        best = mapping["models"][0]
        rec = pycolmap.Reconstruction(str(work / "sparse" / "0"))
        ev = evaluate_poses(poses_from_reconstruction(rec), gt)
        from .consistency import inlier_consistency

        out["inlier_consistency"] = inlier_consistency(db, rec)
        out.update(registered=best["registered"], points3D=best["points3D"],
                   mean_track_length=best["mean_track_length"],
                   mean_reprojection_error_px=best["mean_reprojection_error_px"], poses=ev.to_dict(),
                   median_pose_error_deg=ev.median_error_deg, auc=ev.auc)
    else:
        ev = evaluate_poses({}, gt)
        out.update(registered=0, points3D=0, poses=ev.to_dict(), median_pose_error_deg=ev.median_error_deg, auc=ev.auc)
    return out


def method_dir(work: Path, method: str) -> Path:
    """The folder of one row's database and model under a setting's ``work`` folder (``so+epi+ia+ours`` ->
    ``so_epi_ia_ours``)."""
    return work / method.replace("+", "_")


def judge_with_colmap_model(rows: list[dict], work: Path) -> None:
    """Label every row's verified inliers with one judge per feature setting: the model mapped from COLMAP's own
    exhaustive matches (``work/<setting>/colmap/sparse/0``; 0.1 % of its inliers off its model), whose 3-D points
    are tracks of the same keypoints in every row (one extraction copied per method). A method's own model is a
    weaker judge: its wrong matches also made some of its tracks (Herz-Jesus 8192, guidedmatch: 4.1 % wrong by its
    own model, 2.5 % by COLMAP's). Rows whose database or judge is gone keep their own-model numbers only."""
    from .consistency import inlier_consistency

    for r in rows:
        if "error" in r:
            continue
        judge = method_dir(work / r["setting"], "colmap") / "sparse" / "0"
        db = method_dir(work / r["setting"], r["method"]) / "database.db"
        if judge.is_dir() and db.is_file():
            r["inlier_consistency_colmap_model"] = inlier_consistency(db, judge)


def run_method(method: str, base_db: Path, image_dir: Path, gt: dict, work: Path, threads: int, seed: int,
               matcher: dict | None = None, workers: int | None = None) -> dict:
    """One row: copy the base database, match + verify with ``method``, map, evaluate."""
    mdir = method_dir(work, method)
    if mdir.exists():
        shutil.rmtree(mdir)
    mdir.mkdir(parents=True)
    db = mdir / "database.db"
    shutil.copyfile(base_db, db)
    base, capped = split_method(method)
    if base in COLMAP_METHODS:
        rec = match_colmap(db, guided=(base == "colmap_guided"), threads=threads)
    else:
        mode, geometry = base.rsplit("+", 1)
        rec = match_ours(db, mode, geometry, threads, matcher=matcher, workers=workers)
    if capped:   # timed with the matching: it is part of what the mapper's input costs
        from ..collection.sinks import cap_two_view_inliers

        rec["inlier_cap"] = cap_two_view_inliers(db, SfmConfig.max_inliers_per_pair)
        rec["match_verify_s"] += rec["inlier_cap"]["time_s"]
        if rec.get("match_s") is not None:
            rec["match_s"] += rec["inlier_cap"]["time_s"]
    rec.update(evaluate_database(db, image_dir, gt, mdir, threads, seed))
    rec["method"] = method
    return rec


#: the COLMAP user's pipeline as a script of its own (pycolmap only, nothing of ours imported): the same extraction
#: and mapping options as ``guidedmatch sfm``'s defaults (``sfm.extract_colmap_sift`` / ``sfm.run_mapping``), COLMAP's
#: exhaustive matcher in between, on the images ``guidedmatch sfm`` takes (:data:`guidedmatch.sfm.IMAGE_EXTENSIONS`);
#: prints the stage times and the model's numbers as one JSON line
E2E_COLMAP_SCRIPT = """
import json, os, sys, time
import pycolmap
t0 = time.perf_counter()
image_dir, out, threads, seed = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
pycolmap.logging.minloglevel = 1
db = os.path.join(out, "database.db")
names = sorted(n for n in os.listdir(image_dir) if n.lower().endswith(%(extensions)r))
ext = pycolmap.FeatureExtractionOptions()
ext.num_threads = threads
ext.use_gpu = False
ext.max_image_size = %(max_image_size)d
reader = pycolmap.ImageReaderOptions()
reader.camera_model = %(camera_model)r
pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.AUTO,
                          reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
t1 = time.perf_counter()
mo = pycolmap.FeatureMatchingOptions()
mo.num_threads = threads
mo.use_gpu = False
pycolmap.match_exhaustive(db, matching_options=mo, device=pycolmap.Device.cpu)
t2 = time.perf_counter()
opts = pycolmap.IncrementalPipelineOptions()
opts.num_threads = threads
opts.random_seed = seed
sparse = os.path.join(out, "sparse")
os.makedirs(sparse)
recs = pycolmap.incremental_mapping(db, image_dir, sparse, options=opts)
t3 = time.perf_counter()
best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
if best is not None:
    os.makedirs(os.path.join(out, "best"))
    best.write(os.path.join(out, "best"))
print(json.dumps(dict(extraction_s=t1 - t0, matching_s=t2 - t1, mapping_s=t3 - t2,
                      registered=best.num_reg_images() if best else 0, points3D=best.num_points3D() if best else 0)))
""" % {"extensions": IMAGE_EXTENSIONS, "max_image_size": COLMAP_MAX_IMAGE_SIZE, "camera_model": SfmConfig.camera_model}


def _e2e_ours(image_dir: Path, gt: dict, work: Path, threads: int, seed: int) -> dict:
    """``guidedmatch sfm IMAGE_DIR OUT`` with its defaults as a fresh process, timed from start to exit (Python
    start-up, imports, the report and the figure included); the stage times from its report."""
    d = work / "e2e_guidedmatch"
    if d.exists():
        shutil.rmtree(d)
    from .bench_collection import _timed

    total = _timed([sys.executable, "-m", "guidedmatch.cli", "sfm", str(image_dir), str(d), "--threads", str(threads),
                    "--seed", str(seed), "--quiet"])["wall_s"]
    with open(d / "report.json") as fh:
        rep = json.load(fh)
    st = rep["stages"]
    ev = evaluate_poses(poses_from_reconstruction(str(d / "sparse" / "0")), gt) if rep["registered"] else None
    cap = st["matching"].get("inlier_cap")
    first = st["matching"].get("inlier_px") or cap   # the verdict's inliers, before the mapper's selection
    return {"pipeline": "guidedmatch sfm", "total_s": total, "extraction_s": st["extraction"]["time_s"],
            "matching_s": st["matching"]["time_s"], "mapping_s": st["mapping"]["time_s"],
            "verified_inliers": first["inliers_before"] if first else st["matching"]["verified_inliers"],
            "mapper_inliers": st["matching"]["verified_inliers"], "registered": rep["registered"],
            "points3D": rep["points3D"], "median_pose_error_deg": ev.median_error_deg if ev else None,
            "auc": ev.auc if ev else None}


def _e2e_colmap(image_dir: Path, gt: dict, work: Path, threads: int, seed: int) -> dict:
    """The same pipeline with COLMAP's matcher as a fresh pycolmap-only process (:data:`E2E_COLMAP_SCRIPT`), timed
    from start to exit."""
    from ..sfm import verified_inliers
    from .bench_collection import _timed

    d = work / "e2e_colmap"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    run = _timed([sys.executable, "-c", E2E_COLMAP_SCRIPT, str(image_dir), str(d), str(threads), str(seed)])
    total, rec = run["wall_s"], json.loads(run["stdout_tail"][-1])
    ev = evaluate_poses(poses_from_reconstruction(str(d / "best")), gt) if rec["registered"] else None
    return {"pipeline": "pycolmap: extract + match_exhaustive + incremental_mapping", "total_s": total,
            "extraction_s": rec["extraction_s"], "matching_s": rec["matching_s"], "mapping_s": rec["mapping_s"],
            "verified_inliers": (vi := verified_inliers(d / "database.db")[1]), "mapper_inliers": vi,
            "registered": rec["registered"],
            "points3D": rec["points3D"], "median_pose_error_deg": ev.median_error_deg if ev else None,
            "auc": ev.auc if ev else None}


E2E_STAGES = ("total_s", "extraction_s", "matching_s", "mapping_s")


def end_to_end(image_dir: Path, gt: dict, work: Path, threads: int, seed: int, repeats: int = 1) -> list[dict]:
    """``guidedmatch sfm`` (defaults: COLMAP SIFT at 8192, so+epi+ia, our geometry) vs the same pipeline with
    COLMAP's matcher (extract + ``match_exhaustive`` + mapping), each a fresh process from an empty folder: ``total_s``
    is the process's wall time from start to exit (Python start-up and imports included: ours import Numba, faiss
    and OpenCV, the pycolmap script only pycolmap), the stage times are those the process measured itself.

    ``repeats`` > 1: each pipeline runs that many times, in alternating order (ours first in even rounds, COLMAP's
    in odd ones, so that a drift of the machine hits both alike); each row then holds the median of every stage
    time, the runs themselves (``runs``: the stage times of each) and the reconstruction of the median-total run.
    COLMAP's mapper is multi-threaded and not deterministic: on one database its time varied 6.0-8.5 s (ours) and
    4.5-4.7 s (COLMAP's) across runs, which one run cannot show.

    Run ``r`` maps with the mapper seed ``seed + r`` in both pipelines (the accuracy benchmark's three mapper seeds):
    with repeats the pose columns are the medians over the runs (median pose error, AUC at each threshold), the
    way :mod:`guidedmatch.evaluation.bench_accuracy` reports them, and each run's own values are in ``runs``.
    """
    runs: dict[str, list] = {"ours": [], "colmap": []}
    for r in range(max(1, int(repeats))):
        for who in (("ours", "colmap") if r % 2 == 0 else ("colmap", "ours")):
            _say(f"[e2e] run {r + 1}/{repeats}: {'guidedmatch sfm' if who == 'ours' else 'pycolmap pipeline'}"
                 f" (mapper seed {seed + r})")
            fn = _e2e_ours if who == "ours" else _e2e_colmap
            runs[who].append(dict(fn(image_dir, gt, work, threads, seed + r), seed=seed + r))
    return [_e2e_row(runs[who]) for who in ("ours", "colmap")]


def _e2e_row(rs: list[dict]) -> dict:
    """One pipeline's row from its runs: the (lower) median-total run's model numbers, and with several runs the
    median of every stage time and of the pose accuracy (median error, AUC per threshold) over the runs.

    >>> rs = [dict(total_s=t, extraction_s=1.0, matching_s=1.0, mapping_s=1.0, verified_inliers=9, points3D=5,
    ...            median_pose_error_deg=e, auc={"1": a}, seed=k) for k, (t, e, a) in
    ...       enumerate([(3.0, 0.2, 0.7), (2.0, 0.4, 0.5), (4.0, 0.3, 0.6)])]
    >>> row = _e2e_row(rs)
    >>> row["total_s"], row["median_pose_error_deg"], row["auc"], [r["seed"] for r in row["runs"]]
    (3.0, 0.3, {'1': 0.6}, [0, 1, 2])
    """
    order = sorted(range(len(rs)), key=lambda k: rs[k]["total_s"])
    row = dict(rs[order[(len(rs) - 1) // 2]])  # the (lower) median run: its model's numbers
    if len(rs) > 1:
        for k in E2E_STAGES:
            row[k] = float(np.median([x[k] for x in rs]))
        errs = [x["median_pose_error_deg"] for x in rs if x.get("median_pose_error_deg") is not None]
        row["median_pose_error_deg"] = float(np.median(errs)) if errs else None
        aucs = [x["auc"] for x in rs if x.get("auc")]
        row["auc"] = {t: float(np.median([a[t] for a in aucs])) for t in aucs[0]} if aucs else None
        row["runs"] = [{k: x.get(k) for k in (*E2E_STAGES, "verified_inliers", "points3D", "registered", "seed",
                                               "median_pose_error_deg", "auc")} for x in rs]
    return row


def e2e_table(rows: list[dict]) -> str:
    """Markdown table of :func:`end_to_end`'s rows; with repeats, medians and the range of the runs' totals.

    >>> rows = [dict(pipeline="p", total_s=3.0, extraction_s=1.0, matching_s=1.0, mapping_s=1.0, verified_inliers=10,
    ...              mapper_inliers=8, registered=2, points3D=5, median_pose_error_deg=0.5, auc={"1": 0.4},
    ...              runs=[dict(total_s=2.5), dict(total_s=3.0), dict(total_s=4.0)])]
    >>> e2e_table(rows).splitlines()[-1]
    '| p | 3.0 (2.5-4.0, 3 runs) | 1.0 | 1.0 | 1.0 | 10 | 8 | 2 | 5 | 0.500° | 0.400 |'
    """
    runs = any(r.get("runs") for r in rows)
    out = ["| pipeline (from an empty folder) | total (s)" + (": median (min-max)" if runs else "") + " | extraction (s) "
           "| matching + geometry (s) | mapping (s) | verified inliers | inliers to the mapper | registered | 3D points "
           "| median pose error | AUC@1° |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        med = "–" if r["median_pose_error_deg"] is None else f"{r['median_pose_error_deg']:.3f}°"
        auc1 = "–" if not r["auc"] else f"{r['auc']['1']:.3f}"
        total = f"{r['total_s']:.1f}"
        if r.get("runs"):
            t = [x["total_s"] for x in r["runs"]]
            total += f" ({min(t):.1f}-{max(t):.1f}, {len(t)} runs)"
        out.append(f"| {r['pipeline']} | {total} | {r['extraction_s']:.1f} | {r['matching_s']:.1f} | "
                   f"{r['mapping_s']:.1f} | {r['verified_inliers']:,} | {_fmt(r.get('mapper_inliers'), '{:,}')} | "
                   f"{r['registered']} | {r['points3D']:,} | "
                   f"{med} | {auc1} |")
    return "\n".join(out)


def _fmt(v, spec="{:.2f}"):
    return "–" if v is None else spec.format(v)


def markdown_table(rows: list[dict]) -> str:
    """One table per feature setting: the issue's columns plus mapping time, time / inliers relative to COLMAP
    exhaustive in the same run, and how many verified inliers are wrong by the model mapped from COLMAP's exhaustive
    matches (> 10 px off the 3-D point of the other keypoint; :func:`judge_with_colmap_model`; a row's own model
    when that judge is missing, marked) with the estimated correct inliers relative to COLMAP's ("–" for rows run
    before that check existed)."""
    out = []
    for setting in dict.fromkeys(r["setting"] for r in rows):
        sub = [r for r in rows if r["setting"] == setting]
        ref = next((r for r in sub if r["method"] == "colmap" and "error" not in r), None)
        kp = sub[0].get("keypoints")
        out += [f"**{setting} features** ({kp:,} keypoints in {sub[0].get('images', '?')} images)" if kp else
                f"**{setting} features**", "",
                "| method | match + verify (s) | time / COLMAP | verified inliers | inliers / COLMAP | wrong inliers "
                "(COLMAP's model) | est. correct / COLMAP | registered | 3D points | mapping (s) | median pose error | "
                "AUC@1°/2°/5° |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in sub:
            if "error" in r:
                out.append(f"| {r['method']} | failed: {r['error']} | | | | | | | | | | |")
                continue
            t = _fmt(r["match_verify_s"])
            if r.get("verify_s") is not None:
                t = f"{r['match_s']:.2f} + {r['verify_s']:.2f}"
            rt = f"{r['match_verify_s'] / ref['match_verify_s']:.2f}" if ref else "–"
            ri = f"{r['verified_inliers'] / max(1, ref['verified_inliers']):.2f}x" if ref else "–"
            auc = " / ".join(f"{v:.3f}" for v in r["auc"].values())
            med = r["median_pose_error_deg"]
            key = "inlier_consistency_colmap_model" if r.get("inlier_consistency_colmap_model") and \
                (ref or {}).get("inlier_consistency_colmap_model") else "inlier_consistency"
            own = "" if key == "inlier_consistency_colmap_model" else " (own model)"
            ic, ic_ref = r.get(key), (ref or {}).get(key)
            wrong = f"{100 * ic['wrong_rate']:.2f} %{own}" if ic else "–"
            corr = f"{ic['est_correct'] / ic_ref['est_correct']:.2f}x" if ic and ic_ref else "–"
            out.append(f"| {r['method']} | {t} | {rt} | {r['verified_inliers']:,} | {ri} | {wrong} | {corr} | "
                       f"{r['registered']}/{r.get('images', '?')} | {r['points3D']:,} | {r['mapping_s']:.1f} | "
                       f"{'inf' if med is None or med == float('inf') else f'{med:.3f}°'} | {auc} |")
        out.append("")
    return "\n".join(out)


def plot_time_vs_inliers(rows: list[dict], path: Path) -> Path:
    """Left: match + verify time (log x) vs verified inliers (what the mapper got, for ``+cap`` rows). Right: the time
    to a model (match + verify + mapping, log x) vs AUC@1 deg of the relative poses. One marker per method and
    feature setting."""
    from ..plots import _plt, save_figure

    plt = _plt()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 5.5))
    markers = {"8192": "o", "50k": "s"}
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colors = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
    seen = set()
    for r in rows:
        if "error" in r:
            continue
        kw = dict(marker=markers.get(r["setting"], "^"), color=colors[r["method"]], s=60)
        ax.scatter(r["match_verify_s"], r["verified_inliers"], label=None if r["method"] in seen else r["method"], **kw)
        seen.add(r["method"])
        ax.annotate(r["method"], (r["match_verify_s"], r["verified_inliers"]), fontsize=7, xytext=(4, 3),
                    textcoords="offset points")
        if r.get("auc") and r.get("mapping_s") is not None:
            t = r["match_verify_s"] + r["mapping_s"]
            ax2.scatter(t, r["auc"]["1"], **kw)
            ax2.annotate(r["method"], (t, r["auc"]["1"]), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("match + verify time (s, log)")
    ax.set_ylabel("verified inlier matches (all pairs; +cap: those handed to the mapper)")
    ax.set_title("time vs verified inliers")
    ax.legend(fontsize=7, ncol=2)
    ax2.set_xscale("log")
    ax2.set_xlabel("match + verify + mapping time (s, log)")
    ax2.set_ylabel("AUC@1° of the relative poses (higher is better)")
    ax2.set_title("time to a model vs pose accuracy")
    for a in (ax, ax2):
        a.grid(alpha=0.3)
    fig.suptitle("Herz-Jesus-P8 in COLMAP's mapper (o = 8192 features, s = ~50k)")
    return save_figure(fig, path)


def _merge_rows(new: list[dict], old: list[dict]) -> list[dict]:
    """``new`` plus the rows of ``old`` for (setting, method) not in ``new``, in table order."""
    done = {(r["setting"], r["method"]) for r in new}
    order = {key: i for i, key in enumerate((st, m) for st in FEATURE_SETTINGS for m in method_names())}
    rows = list(new) + [r for r in old if (r["setting"], r["method"]) not in done]
    return sorted(rows, key=lambda r: order.get((r["setting"], r["method"]), len(order)))


def run(*args, colmap_log: bool = False, **kwargs) -> dict:
    """:func:`run_benchmark` with COLMAP's INFO log lines silenced unless ``colmap_log``."""
    from ..sfm import colmap_log_level

    with colmap_log_level(0 if colmap_log else 1):
        return run_benchmark(*args, **kwargs)


def run_benchmark(scene: Path, out: Path, settings=("8192", "50k"), methods=None, threads: int = 2, seed: int = 0,
        matcher: dict | None = None, workers: int | None = None, command: str = "", e2e: bool = True,
        work: Path | None = None, merge: bool = False, e2e_repeats: int = 1) -> dict:
    """Run the benchmark; writes ``out/sfm.json``, ``out/sfm.md``, ``out/sfm_time_vs_inliers.png``. Databases and
    models go to ``work`` (default ``out/work``; the extracted features of each setting are reused by a rerun).
    ``merge``: keep the rows (and end-to-end rows) of an existing ``out/sfm.json`` that this run does not redo; each
    row carries its own ``timestamp_utc``."""
    from ..errors import InputError
    from ..features import atomic_write_text
    from .meta import run_metadata, write_json

    image_dir, cam_dir = scene / "images", scene / "gt_dense_cameras"
    if not image_dir.is_dir() or not cam_dir.is_dir():
        raise InputError(f"{scene}: expected images/ and gt_dense_cameras/ (Strecha layout)")
    gt = read_strecha_cameras(cam_dir)
    explicit = methods is not None
    work = Path(work) if work is not None else out / "work"
    rows = []
    from .._runtime import byte_compile_package

    results = {"meta": {**run_metadata(seed), "byte_compiled": byte_compile_package()}, "command": command,
               "scene": str(scene), "threads": threads,
               "methods": methods, "settings": list(settings), "rows": rows, "end_to_end": None,
               "note": "wall-clock times on 2 cores (see meta.load_average); same features for all methods"}
    old_rows, old_e2e = [], None
    if merge and (out / "sfm.json").is_file():
        old = json.loads((out / "sfm.json").read_text())
        old_rows, old_e2e = old.get("rows", []), old.get("end_to_end")
        results["merged_from"] = old.get("meta", {}).get("timestamp_utc")
    for setting in settings:
        base = work / setting / "features.db"
        base.parent.mkdir(parents=True, exist_ok=True)
        _say(f"[{setting}] extracting pycolmap SIFT ({threads} threads)")
        ext = extract_database(image_dir, base, setting, threads)
        results.setdefault("extraction", {})[setting] = ext
        todo = list(methods) if explicit else default_methods(setting)
        ours = [split_method(m)[0] for m in todo if split_method(m)[0] not in COLMAP_METHODS]
        if ours:
            warm_up(base, modes=sorted({m.rsplit("+", 1)[0] for m in ours}))
        for method in todo:
            _say(f"[{setting}] {method}")
            try:
                r = run_method(method, base, image_dir, gt, work / setting, threads, seed, matcher, workers)
            except Exception as exc:  # noqa: BLE001 - recorded in the table; the other methods still run
                import traceback

                r = {"method": method, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
            r.update(setting=setting, keypoints=ext["keypoints"], images=len(gt),
                     timestamp_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
            rows.append(r)
            if "error" in r:
                _say(f"    failed: {r['error']}")
            else:
                _say(f"    {r['match_verify_s']:.2f} s, {r['verified_inliers']:,} inliers, {r['registered']}/{len(gt)} "
                     f"registered, {r['points3D']:,} points, median {r['median_pose_error_deg']:.3f} deg, "
                     f"AUC@1 {r['auc']['1']:.3f}")
            write_json(out / "sfm.json", dict(results, rows=_merge_rows(rows, old_rows), end_to_end=old_e2e))
    rows[:] = _merge_rows(rows, old_rows)
    judge_with_colmap_model(rows, work)
    results["end_to_end"] = old_e2e
    if e2e:
        _say("[e2e] guidedmatch sfm vs the pycolmap pipeline with COLMAP's matcher, from empty folders")
        results["end_to_end"] = end_to_end(image_dir, gt, work, threads, seed, repeats=e2e_repeats)
        write_json(out / "sfm.json", results)
    md = ["# guidedmatch in COLMAP: Herz-Jesus-P8 sfm benchmark", "",
          f"`{command}` -- {results['meta'].get('timestamp_utc')}, commit `{(results['meta'].get('git_commit') or '')[:10]}`, "
          f"{cpu_label(results['meta'])}, {threads} threads. Load average "
          f"{results['meta'].get('load_average') or float('nan'):.1f} when this run started (2 cores); rows kept from earlier runs "
          "(--merge) may come from a loaded machine: compare times within one run; inlier counts and poses are exact.", "", markdown_table(rows),
          *(["**End to end** (8192 features, defaults of `guidedmatch sfm`" + (
              f"; median of {len(results['end_to_end'][0]['runs'])} runs each, in alternating order, run r with "
              f"mapper seed {seed} + r; poses: the median over the runs)"
              if results["end_to_end"] and results["end_to_end"][0].get("runs") else ")"), "", e2e_table(results["end_to_end"]), ""]
            if results["end_to_end"] else []),
          "![time vs inliers](sfm_time_vs_inliers.png)", ""]
    atomic_write_text(out / "sfm.md", "\n".join(md))
    plot_time_vs_inliers(rows, out / "sfm_time_vs_inliers.png")
    write_json(out / "sfm.json", results)
    return results


def main(args) -> int:
    """Entry of ``guidedmatch bench sfm`` (arguments from the CLI parser)."""
    from ..datasets import data_root

    scene = Path(args.scene) if getattr(args, "scene", None) else None
    if scene is None:
        root = data_root(getattr(args, "data", None))
        if root is None:
            from ..errors import InputError

            raise InputError("no scene given and no data folder found (set GUIDEDMATCH_DATA or pass --scene)")
        scene = root / DEFAULT_SCENE
    from ..errors import ConfigError

    settings = args.features or ["8192", "50k"]
    if "both" in settings:
        settings = ["8192", "50k"]
    bad_settings = sorted(set(settings) - {"8192", "50k"})
    if bad_settings:
        raise ConfigError(f"bench sfm --features takes 8192 and/or 50k; got {', '.join(bad_settings)}")
    methods = args.methods.split(",") if getattr(args, "methods", None) else None
    if methods:
        bad = [m for m in methods if not is_known_method(m)]
        if bad:
            from ..errors import ConfigError

            raise ConfigError(f"unknown method(s) {bad}; known: {', '.join(method_names())}")
    res = run(scene, Path(args.out), settings=settings, methods=methods, threads=args.threads, seed=args.seed,
              command="guidedmatch " + " ".join(sys.argv[1:]), e2e=not args.no_e2e, work=args.work, merge=args.merge,
              e2e_repeats=args.repeats or 1)
    print(markdown_table(res["rows"]))
    return 0
