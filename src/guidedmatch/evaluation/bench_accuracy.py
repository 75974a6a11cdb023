"""``guidedmatch bench accuracy``: pose accuracy per scene, COLMAP's matcher vs ours, in COLMAP's own mapper.

Protocol, per scene with reference poses (:data:`SCENES`):

1. pycolmap SIFT at COLMAP's defaults (8192 features, ``max_image_size`` 3200, one camera per image, SIMPLE_RADIAL),
   extracted once into ``<cache>/<scene>/features.db``; every method matches a *copy* of it (same keypoints);
2. matching, each in a fresh process, wall time of the process (what a user waits for):
   * ``colmap``: ``pycolmap.match_exhaustive`` (CPU, COLMAP's defaults: ratio 0.8, cross-check, RANSAC);
   * ``ours``: ``guidedmatch colmap DB`` at its defaults;
   * ``ours+cap``: the same database, then :func:`guidedmatch.collection.sinks.cap_two_view_inliers` with 1000 --
     exactly what ``guidedmatch colmap --max-inliers-per-pair 1000`` runs after matching (``guidedmatch sfm``'s
     default, whatever the total); its time is ``ours``' plus the cap's; ``ours+capN``: the same with a cap of N
     (e.g. ``ours+cap500``);
   * ``ours+sfm``: the same with ``guidedmatch sfm``'s rule -- the cap of 1000 only when the database holds more than
     :data:`~guidedmatch.sfm.config.CAP_ABOVE_INLIERS` inliers in all (``--cap-above``), else ``ours``' database;
   * analysis variants (:mod:`guidedmatch.evaluation.accuracy_analysis`): a method's database rewritten to remove or
     restore one candidate cause;
3. ``pycolmap.incremental_mapping`` with ``IncrementalPipelineOptions.random_seed`` = 0, 1, 2 (largest model);
4. relative pose errors over all image pairs against the reference (:mod:`guidedmatch.evaluation.poses`; errors of
   relative poses do not depend on the gauge, so no alignment enters them; the camera centres are also compared after
   a similarity alignment); the table shows the median over the seeds of each column;
5. wrong inliers, two judges: the model mapped from COLMAP's own matches with seed 0 (a verified inlier > 10 px from
   the reprojection of the other keypoint's 3-D point; :mod:`guidedmatch.evaluation.consistency`), and the reference
   cameras (an inlier > 4 px from the reference epipolar line in either image; fox's keypoints are undistorted first).

Every stage is cached under ``<cache>/<scene>/<method>/`` (matched database + ``match.json``, ``seed<k>/map.json``
and the model), so a rerun redoes only what is missing; ``--redo`` names methods to redo. Writes ``accuracy.json``
(with run metadata), ``accuracy.md`` and ``accuracy_drift.png`` (pose error against the distance along the capture
sequence, ``|i - j|`` in image-name order).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .accuracy_scenes import SCENES, copy_database, distortion, reference_cameras, scene_paths
from .consistency import EPI_WRONG_PX, epipolar_distances, pair_table, undistort
from .meta import cpu_label, default_cache
from .poses import (CameraPose, aligned_centre_errors, error_by_sequence_distance, evaluate_poses,
                    poses_from_reconstruction)

BASE_METHODS = ("colmap", "ours", "ours+cap", "ours+sfm")
#: ours, then :func:`guidedmatch.collection.rescue.rescue_pairs` (the rejected pairs a third view confirms), with and
#: without the cap
RESCUE_METHODS = ("ours+rescue", "ours+rescue+cap")
SEEDS = (0, 1, 2)
CAP = 1000  # inliers per pair of ``ours+cap`` (guidedmatch sfm's default)


def cap_of(method: str) -> int | None:
    """The inlier cap of a capped method: ``ours+cap`` and ``ours+sfm`` -> :data:`CAP`, ``ours+capN`` -> N (another
    cap to compare), else None.

    >>> cap_of("ours+cap"), cap_of("ours+sfm"), cap_of("ours+cap500"), cap_of("ours"), cap_of("ours+capx")
    (1000, 1000, 500, None, None)
    """
    if method in ("ours+cap", "ours+sfm"):
        return CAP
    tail = method[len("ours+cap"):] if method.startswith("ours+cap") else ""
    return int(tail) if tail.isdigit() and int(tail) > 0 else None


def command_line(argv: list[str]) -> str:
    """The command as a user types it, from ``guidedmatch bench accuracy ...`` or ``python -m`` this module.

    >>> command_line(["bench", "accuracy", "--scenes", "buddha"]), command_line(["--scenes", "buddha"])
    ('guidedmatch bench accuracy --scenes buddha', 'guidedmatch bench accuracy --scenes buddha')
    """
    argv = list(argv[2:] if argv[:2] == ["bench", "accuracy"] else argv)
    return " ".join(["guidedmatch bench accuracy", *argv])


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _load() -> float:
    return os.getloadavg()[0]


def _read_json(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def _write_json(path: Path, obj) -> None:
    from .meta import write_json

    write_json(path, obj)


def _inf(v):
    return math.inf if v is None else v


# --------------------------------------------------------------------------- stages
def extract(image_dir: Path, cache: Path, threads: int) -> dict:
    """Stage 1, cached: ``cache/features.db`` + ``cache/extract.json``."""
    from ..sfm import colmap_log_level, extract_colmap_sift, list_images

    rec = _read_json(cache / "extract.json")
    if rec and (cache / "features.db").is_file():
        return dict(rec, cached=True)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / "features.tmp.db"
    for p in cache.glob("features.tmp.db*"):
        p.unlink()
    names = list_images(image_dir)
    t0 = time.perf_counter()
    with colmap_log_level(1):
        extract_colmap_sift(tmp, image_dir, names, num_threads=threads)
    rec = {"time_s": time.perf_counter() - t0, "images": len(names), "load": _load()}
    os.replace(tmp, cache / "features.db")
    _write_json(cache / "extract.json", rec)
    return dict(rec, cached=False)


COLMAP_MATCH_SCRIPT = """
import sys, pycolmap
mo = pycolmap.FeatureMatchingOptions(); mo.num_threads = int(sys.argv[2]); mo.use_gpu = False
pycolmap.match_exhaustive(sys.argv[1], matching_options=mo, device=pycolmap.Device.cpu)
"""
OURS_MATCH_SCRIPT = "import sys; from guidedmatch.cli import main; sys.exit(main())"   # as the console script


def _timed_process(cmd: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=dict(os.environ, GLOG_minloglevel="1"))
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:3])}... exited {proc.returncode}; see {log}")
    return elapsed


_WARM: set = set()


def warm_up(cache: Path, mdir: Path) -> None:
    """Run ``guidedmatch colmap`` once, untimed, on one pair of a scratch copy of the features, so that the timed run
    loads compiled kernels from Numba's on-disk cache instead of compiling them (once per process)."""
    if _WARM:
        return
    import pycolmap

    scratch = mdir / "warmup.db"
    shutil.copyfile(cache / "features.db", scratch)
    db = pycolmap.Database.open(str(scratch))
    names = sorted(img.name for img in db.read_all_images())[:2]
    db.close()
    (mdir / "warmup_pairs.txt").write_text(f"{names[0]} {names[1]}\n")
    _timed_process([sys.executable, "-c", OURS_MATCH_SCRIPT, "colmap", str(scratch), "--pairs",
                    str(mdir / "warmup_pairs.txt"), "--no-progress", "--log", "none"], mdir / "warmup.log")
    for p in mdir.glob("warmup*"):
        p.unlink()
    _WARM.add(True)


OURS_FLAGS = ("second_look", "no_second_look")   # ours@...;no_second_look: `guidedmatch colmap --no-second-look`, not a matcher setting


def ours_words(method: str) -> list[str]:
    """The ``guidedmatch colmap`` words of an ``ours@...`` method (";" between several settings): a flag of
    :data:`OURS_FLAGS` as itself, ``inlier_px=X`` as ``--inlier-px X`` and ``refit_below_deg=X`` as
    ``--refit-below-deg X`` (options of the command),
    ``second_look.KEY=X`` as ``--second-look-config KEY=X``, anything else a matcher ``--config``.

    >>> ours_words("ours@inlier_px=0;second_look;max_unguided=0.1;second_look.weak_below=0")
    ['--inlier-px', '0', '--second-look', '--config', 'max_unguided=0.1', '--second-look-config', 'weak_below=0']
    """
    words = []
    for kv in (kv for kv in method[len("ours@"):].split(";") if kv):
        words += ([f"--{kv.replace('_', '-')}"] if kv in OURS_FLAGS else
                  ["--inlier-px", kv.split("=", 1)[1]] if kv.startswith("inlier_px=") else
                  ["--refit-below-deg", kv.split("=", 1)[1]] if kv.startswith("refit_below_deg=") else
                  ["--second-look-config", kv[len("second_look."):]] if kv.startswith("second_look.") else
                  ["--config", kv])
    return words


def match(method: str, cache: Path, threads: int, redo: bool = False) -> dict:
    """Stage 2, cached: ``cache/<method>/database.db`` + ``match.json``."""
    mdir = cache / method.replace("+", "_")
    rec = _read_json(mdir / "match.json")
    if rec and not redo and (mdir / "database.db").is_file():
        return dict(rec, cached=True)
    if mdir.exists():
        shutil.rmtree(mdir)
    mdir.mkdir(parents=True)
    db = mdir / "database.db"
    load = _load()
    if method == "colmap":
        shutil.copyfile(cache / "features.db", db)
        t = _timed_process([sys.executable, "-c", COLMAP_MATCH_SCRIPT, str(db), str(threads)], mdir / "match.log")
        rec = {"method": method, "match_s": t, "command": "pycolmap.match_exhaustive (CPU, defaults)"}
    elif method == "ours":
        shutil.copyfile(cache / "features.db", db)
        warm_up(cache, mdir)
        t = _timed_process([sys.executable, "-c", OURS_MATCH_SCRIPT, "colmap", str(db), "--no-progress", "--log",
                            "none"], mdir / "match.log")
        rec = {"method": method, "match_s": t, "command": "guidedmatch colmap DB"}
    elif cap_of(method):
        base = match("ours", cache, threads)
        copy_database(cache / "ours" / "database.db", db)
        from ..collection.sinks import cap_two_view_inliers

        from ..sfm.config import CAP_ABOVE_INLIERS

        above = CAP_ABOVE_INLIERS if method == "ours+sfm" else 0   # guidedmatch sfm's rule, or the cap whatever the total
        cap = cap_two_view_inliers(db, cap_of(method), above=above)
        rec = {"method": method, "match_s": base["match_s"] + cap["time_s"], "cap": cap,
               "command": f"guidedmatch colmap DB --max-inliers-per-pair {cap_of(method)} --cap-above {above}"}
    elif method.startswith("ours@"):   # ours with matcher settings: ours@max_unguided=0.1 (guidedmatch colmap --config), ";" between several
        copy_database(cache / "features.db", db)
        warm_up(cache, mdir)
        words = ours_words(method)
        t = _timed_process([sys.executable, "-c", OURS_MATCH_SCRIPT, "colmap", str(db), "--no-progress", "--log", "none",
                            *words], mdir / "match.log")
        rec = {"method": method, "match_s": t, "command": "guidedmatch colmap DB " + " ".join(words)}
    elif method in ("ours+rescue", "ours+rescue+cap"):
        base = match("ours", cache, threads)
        copy_database(cache / "ours" / "database.db", db)
        from ..collection.rescue import RescueConfig, rescue_pairs

        rescue = rescue_pairs(db, RescueConfig(num_threads=threads, matcher="colmap"))
        rec = {"method": method, "match_s": base["match_s"] + rescue["time_s"], "rescue": rescue,
               "command": "guidedmatch colmap DB, then collection.rescue.rescue_pairs(DB)"}
        if method.endswith("+cap"):
            from ..collection.sinks import cap_two_view_inliers

            rec["cap"] = cap_two_view_inliers(db, CAP)
            rec["match_s"] += rec["cap"]["time_s"]
    else:
        from .accuracy_analysis import make_variant

        rec = make_variant(method, cache, db, threads, match=match)
    rec["load"] = load
    from ..sfm import verified_inliers

    rec["verified_pairs"], rec["verified_inliers"] = verified_inliers(db)
    _write_json(mdir / "match.json", rec)
    return dict(rec, cached=False)


_TIGHTENED = re.compile(r"mapper\s*: ([\d,]+) of ([\d,]+) inliers within")


def verdict_inliers(method: str, cache: Path, verified: int) -> int | None:
    """The inliers a method's verification accepted, before any selection for the mapper: COLMAP's ``verified``;
    for a ``guidedmatch colmap`` run the count its ``--inlier-px`` line reports (``match.log``; ``ours+cap`` /
    ``ours+sfm``: that of ``ours``), ``verified`` when it printed none (nothing tightened), None when no log."""
    if method == "colmap":
        return verified
    log = cache / ("ours" if cap_of(method) else method.replace("+", "_")) / "match.log"
    if not method.startswith("ours") or not log.is_file():
        return None
    found = _TIGHTENED.search(log.read_text(errors="replace"))
    return int(found.group(2).replace(",", "")) if found else verified


def retime(cache: Path, repeats: int, threads: int) -> dict:
    """Matching time of ``colmap`` and ``ours`` again, ``repeats`` fresh processes each in alternating order on
    scratch copies of the features (cached in ``retime.json``, extended when more repeats are asked)."""
    rec = _read_json(cache / "retime.json") or {"colmap": [], "ours": [], "load": []}
    scratch = cache / "retime"
    scratch.mkdir(exist_ok=True)
    warm_up(cache, scratch)
    while len(rec["ours"]) < repeats:
        r = len(rec["ours"])
        for who in (("ours", "colmap") if r % 2 == 0 else ("colmap", "ours")):
            db = scratch / "database.db"
            for p in scratch.glob("database.db*"):
                p.unlink()
            shutil.copyfile(cache / "features.db", db)
            rec["load"].append(_load())
            if who == "colmap":
                cmd = [sys.executable, "-c", COLMAP_MATCH_SCRIPT, str(db), str(threads)]
            else:
                cmd = [sys.executable, "-c", OURS_MATCH_SCRIPT, "colmap", str(db), "--no-progress", "--log", "none"]
            rec[who].append(_timed_process(cmd, scratch / "match.log"))
            _say(f"[retime] {cache.name} {who} run {r + 1}: {rec[who][-1]:.1f} s (load {rec['load'][-1]:.1f})")
        _write_json(cache / "retime.json", rec)
    shutil.rmtree(scratch)
    return rec


def same_database_as(method: str, cache: Path) -> str | None:
    """``ours+sfm``'s database is, byte for byte, ``ours+cap``'s when sfm's rule applied the cap and ``ours``'s when
    it did not (the cap is deterministic): the method whose models it shares, or None (any other method, or not
    matched yet).

    >>> same_database_as("ours", Path("nowhere"))
    """
    if method != "ours+sfm":
        return None
    rec = _read_json(cache / method.replace("+", "_") / "match.json")
    if not rec or "cap" not in rec:
        return None
    return "ours+cap" if rec["cap"].get("applied", True) else "ours"


def mapping(method: str, cache: Path, image_dir: Path, seed: int, threads: int, redo: bool = False) -> dict:
    """Stage 3, cached: ``cache/<method>/seed<k>/sparse/0`` (largest model) + ``map.json``. A method whose database
    is another's (:func:`same_database_as`) takes that method's model of the seed, mapped if need be (``same_as``)."""
    from ..sfm import colmap_log_level, run_mapping

    sdir = cache / method.replace("+", "_") / f"seed{seed}"
    rec = _read_json(sdir / "map.json")
    if rec and not redo:
        return dict(rec, cached=True)
    same = same_database_as(method, cache)
    same_dir = cache / same.replace("+", "_") if same is not None else None
    if same_dir is not None and (same_dir / "database.db").is_file():
        other = mapping(same, cache, image_dir, seed, threads)
        if sdir.exists():
            shutil.rmtree(sdir)
        shutil.copytree(same_dir / f"seed{seed}", sdir)
        rec = dict({k: v for k, v in other.items() if k != "cached"}, same_as=same)
        _write_json(sdir / "map.json", rec)
        return dict(rec, cached=False)
    sdir.mkdir(parents=True, exist_ok=True)
    load = _load()
    with colmap_log_level(1):
        m = run_mapping(cache / method.replace("+", "_") / "database.db", image_dir, sdir / "sparse",
                        num_threads=threads, seed=seed)
    rec = {"mapping_s": m["time_s"], "models": len(m["models"]), "best": m["models"][0] if m["models"] else None,
           "load": load}
    _write_json(sdir / "map.json", rec)
    return dict(rec, cached=False)


# --------------------------------------------------------------------------- judges
def judge(method: str, cache: Path, ref, dist, redo: bool = False) -> dict:
    """Wrong inliers of a method's database by COLMAP's seed-0 model and by the reference epipolar geometry
    (cached in ``judge.json``; the per-pair table in ``pairs.json``)."""
    from .consistency import inlier_consistency

    mdir = cache / method.replace("+", "_")
    out = _read_json(mdir / "judge.json")
    model = cache / "colmap" / "seed0" / "sparse" / "0"
    if out and not redo and (out.get("model_judge") or not model.is_dir()):
        return out
    pairs = pair_table(mdir / "database.db", ref, dist)
    _write_json(mdir / "pairs.json", pairs)
    n = sum(p["inliers"] for p in pairs)
    out = {"epipolar": {"px": EPI_WRONG_PX, "inliers": n, "wrong": n - sum(p["epi_ok"] for p in pairs),
                        "wrong_rate": (n - sum(p["epi_ok"] for p in pairs)) / n if n else float("nan")},
           "model_judge": inlier_consistency(mdir / "database.db", model) if model.is_dir() else None}
    _write_json(mdir / "judge.json", out)
    return out


def evaluate(method: str, cache: Path, seed: int, ref: dict[str, CameraPose]) -> dict:
    """Pose errors of one seed's largest model against the reference."""
    import pycolmap

    sdir = cache / method.replace("+", "_") / f"seed{seed}"
    model = sdir / "sparse" / "0"
    est = poses_from_reconstruction(pycolmap.Reconstruction(str(model))) if model.is_dir() else {}
    ev = evaluate_poses(est, ref)
    order = sorted(ref)
    return {"seed": seed, "registered": ev.num_registered, "images": ev.num_images,
            "median_error_deg": ev.median_error_deg, "auc": ev.auc,
            "centres": {k: v for k, v in aligned_centre_errors(est, ref).items() if k != "per_image"},
            "drift": error_by_sequence_distance(ev.per_pair, order), "unregistered": ev.unregistered,
            "errors": [r["error_deg"] for r in ev.per_pair]}


# --------------------------------------------------------------------------- aggregation
def _median(vals):
    v = [_inf(x) for x in vals]
    return float(np.median(v)) if v else float("nan")


def aggregate(runs: list[dict]) -> dict:
    """The median over seeds of each column of one (scene, method) (``runs``: :func:`evaluate`'s records plus
    ``mapping_s``), and the range of AUC@1.

    >>> runs = [dict(registered=8, median_error_deg=0.2, auc={"1": 0.7, "2": 0.8}, mapping_s=3.0),
    ...         dict(registered=7, median_error_deg=float("inf"), auc={"1": 0.5, "2": 0.6}, mapping_s=5.0),
    ...         dict(registered=8, median_error_deg=0.3, auc={"1": 0.6, "2": 0.7}, mapping_s=4.0)]
    >>> a = aggregate(runs)
    >>> a["registered"], a["median_error_deg"], a["auc"], a["auc1_range"], a["mapping_s"]
    (8.0, 0.3, {'1': 0.6, '2': 0.7}, [0.5, 0.7], 4.0)
    """
    keys = list(runs[0]["auc"]) if runs else []
    return {"seeds": len(runs), "registered": _median([r["registered"] for r in runs]),
            "median_error_deg": _median([r["median_error_deg"] for r in runs]),
            "auc": {k: _median([r["auc"][k] for r in runs]) for k in keys},
            "auc1_range": [min(r["auc"]["1"] for r in runs), max(r["auc"]["1"] for r in runs)] if runs else None,
            "mapping_s": _median([r["mapping_s"] for r in runs]),
            "centre_rel": _median([r.get("centres", {}).get("median_rel", float("nan")) for r in runs])}


def pooled_drift(runs: list[dict], names: list[str]) -> list[dict]:
    """:func:`guidedmatch.evaluation.poses.error_by_sequence_distance` over the pairs of all seeds together."""
    import itertools

    pairs = list(itertools.combinations(sorted(names), 2))
    rows = [{"name1": a, "name2": b, "error_deg": _inf(e)} for r in runs for (a, b), e in zip(pairs, r["errors"])]
    return error_by_sequence_distance(rows, sorted(names))


def _f(v, spec):
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else ("inf" if v == math.inf else spec.format(v))


def markdown_table(rows: list[dict]) -> str:
    """One line per (scene, method): medians over seeds, ratios against ``colmap`` of the same scene.

    >>> r = dict(scene="s", method="colmap", images=8, registered=8.0, median_error_deg=0.2, auc={"1": .7, "2": .8,
    ...          "5": .9}, auc1_range=[.6, .7], verified_pairs=28, verified_inliers=1000, wrong_model=0.01,
    ...          wrong_epi=0.02, match_s=10.0, mapping_s=3.0, seeds=3, centre_rel=0.01)
    >>> markdown_table([r, dict(r, method="ours", verified_inliers=1500, verdict_inliers=1700, match_s=4.0)]).splitlines()[-1]
    '| s | ours | 3 | 8/8 | 0.200° | 0.700 (0.600-0.700) / 0.800 / 0.900 | 28 | 1,500 (1.50x) | 1,700 (1.70x) | 1.00 % | 2.00 % | 4.0 (0.40x) | 3.0 | 1.00 % |'
    """
    out = ["| scene | method | seeds | registered | median error | AUC@1° (min-max) / 2° / 5° | verified pairs | "
           "mapper's inliers (/ COLMAP) | verified inliers (/ COLMAP) | wrong inliers: COLMAP's model | "
           "wrong inliers: reference epipolar | matching s (/ COLMAP) | mapping s | centre error / extent |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ref = next((x for x in rows if x["scene"] == r["scene"] and x["method"] == "colmap"), None)
        if "error" in r:
            out.append(f"| {r['scene']} | {r['method']} | | failed: {r['error']} |" + " |" * 10)
            continue
        a = r["auc"]
        rng = r.get("auc1_range") or [float("nan")] * 2
        ri = f" ({r['verified_inliers'] / max(1, ref['verified_inliers']):.2f}x)" if ref else ""
        vi = r.get("verdict_inliers")
        rv = (f"{vi:,}" + (f" ({vi / max(1, ref['verified_inliers']):.2f}x)" if ref else "")) if vi is not None else "–"
        rt = f" ({r['match_s'] / ref['match_s']:.2f}x)" if ref and ref.get("match_s") else ""
        out.append(f"| {r['scene']} | {r['method']} | {r.get('seeds', '?')} | {r['registered']:g}/{r['images']} | "
                   f"{_f(r['median_error_deg'], '{:.3f}°')} | {a['1']:.3f} ({rng[0]:.3f}-{rng[1]:.3f}) / {a['2']:.3f} / "
                   f"{a['5']:.3f} | {r['verified_pairs']:,} | {r['verified_inliers']:,}{ri} | {rv} | "
                   f"{_f(100 * r['wrong_model'] if r.get('wrong_model') is not None else None, '{:.2f} %')} | "
                   f"{_f(100 * r['wrong_epi'] if r.get('wrong_epi') is not None else None, '{:.2f} %')} | "
                   f"{r['match_s']:.1f}{rt} | {r['mapping_s']:.1f} | {_f(100 * r['centre_rel'], '{:.2f} %')} |")
    return "\n".join(out)


def plot_drift(rows: list[dict], path: Path) -> Path:
    """Median pose error (all seeds' pairs pooled) against ``|i - j|`` per scene (one panel each) and method."""
    from ..plots import _plt, save_figure

    plt = _plt()
    scenes = list(dict.fromkeys(r["scene"] for r in rows if "drift" in r))
    fig, axes = plt.subplots(1, max(1, len(scenes)), figsize=(4.5 * max(1, len(scenes)), 4), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for r in rows:
            if r["scene"] != scene or "drift" not in r:
                continue
            x = [math.sqrt(g["lo"] * (g["hi"] - 1)) if g["hi"] != math.inf and g["hi"] is not None else g["lo"]
                 for g in r["drift"]]
            y = [min(_inf(g["median_error_deg"]), 20.0) for g in r["drift"]]
            ax.plot(x, y, marker="o", label=r["method"])
        ax.set_xscale("log", base=2)
        ax.set_xlabel("|i - j| along the capture sequence")
        ax.set_ylabel("median relative pose error (deg)")
        ax.set_title(scene)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("pose error vs distance in the sequence (all mapper seeds of a row pooled; see the seeds column)")
    fig.tight_layout()
    return save_figure(fig, path)


# --------------------------------------------------------------------------- driver
def run_scene(root: Path, scene: str, cache: Path, methods, seeds, threads: int, redo=(), repeats: int = 0,
              cached_only: bool = False) -> list[dict]:
    """Every stage of one scene (cached); one aggregated row per method."""
    image_dir, _ = scene_paths(root, scene)
    ref = reference_cameras(root, scene)
    dist = distortion(root, scene)
    cache = cache / scene
    _say(f"[{scene}] extraction")
    ext = extract(image_dir, cache, threads)
    _write_json(cache / "scene.json", {"root": str(root), "scene": scene})
    order = ["colmap"] + [m for m in methods if m != "colmap"]   # COLMAP's seed-0 model judges the others
    rows = []
    for method in order:
        mdir = cache / method.replace("+", "_")
        if cached_only and not ((mdir / "match.json").is_file() and
                                all((mdir / f"seed{k}" / "map.json").is_file() for k in seeds)):
            _say(f"[{scene}] {method}: not in the cache for seeds {seeds}, skipped (--cached-only)")
            continue
        try:
            rec = match(method, cache, threads, redo=method in redo)
            _say(f"[{scene}] {method}: matched in {rec['match_s']:.1f} s{' (cached)' if rec['cached'] else ''}, "
                 f"{rec['verified_pairs']} pairs, {rec['verified_inliers']:,} inliers")
            runs = []
            for seed in seeds:
                m = mapping(method, cache, image_dir, seed, threads, redo=method in redo and not rec["cached"])
                ev = evaluate(method, cache, seed, ref)
                ev["mapping_s"] = m["mapping_s"]
                ev["best_model"] = {k: v for k, v in (m["best"] or {}).items() if k != "registered_names"}
                runs.append(ev)
                _say(f"[{scene}] {method} seed {seed}: {ev['registered']}/{ev['images']} registered, median "
                     f"{ev['median_error_deg']:.3f} deg, AUC@1 {ev['auc']['1']:.3f}, mapping {m['mapping_s']:.1f} s"
                     f"{' (cached)' if m['cached'] else ''}")
            j = judge(method, cache, ref, dist, redo=not rec["cached"])
            mj = j.get("model_judge")
            row = {"scene": scene, "method": method, "images": len(ref), "match_s": rec["match_s"],
                   "match_load": rec.get("load"), "verified_pairs": rec["verified_pairs"],
                   "verified_inliers": rec["verified_inliers"],
                   "verdict_inliers": verdict_inliers(method, cache, rec["verified_inliers"]), "wrong_model": mj["wrong_rate"] if mj else None,
                   "wrong_epi": j["epipolar"]["wrong_rate"], "judge": j, "match": rec, **aggregate(runs),
                   "drift": pooled_drift(runs, list(ref)), "runs": runs, "extraction": ext,
                   "reference": SCENES[scene][2]}
        except Exception as exc:  # noqa: BLE001 - recorded in the table; the other methods still run
            import traceback

            row = {"scene": scene, "method": method, "error": f"{type(exc).__name__}: {exc}",
                   "traceback": traceback.format_exc()}
            _say(f"[{scene}] {method} failed: {row['error']}")
        rows.append(row)
    if repeats and not (cached_only and len((_read_json(cache / "retime.json") or {}).get("ours", [])) < repeats):
        rt = retime(cache, repeats, threads)
        med = {w: float(np.median(rt[w])) for w in ("colmap", "ours")}
        for r in rows:
            base = r["method"] if r["method"] in med else ("ours" if cap_of(r["method"]) else None)
            if base and "error" not in r:
                r["match_s_first"] = r["match_s"]
                r["match_s"] = med[base] + (r["match"].get("cap", {}).get("time_s", 0.0) if cap_of(r["method"])
                                            else 0.0)
                r["retime"] = {"runs": rt[base], "load": rt["load"]}
    return [next(r for r in rows if r["method"] == m) for m in methods if any(r["method"] == m for r in rows)]


def run(root: Path, out: Path, scenes, methods=BASE_METHODS, seeds=SEEDS, threads: int = 2,
        cache: Path | None = None, redo=(), command: str = "", repeats: int = 0,
        cached_only: bool = False) -> dict:
    """Run the scenes; merge with the rows of an existing ``out/accuracy.json`` for other (scene, method); write
    ``accuracy.json``, ``accuracy.md``, ``accuracy_drift.png``."""
    from ..features import atomic_write_text
    from .meta import default_cache, run_metadata

    cache = Path(default_cache("accuracy") if cache is None else cache)
    out.mkdir(parents=True, exist_ok=True)
    old = _read_json(out / "accuracy.json") or {}
    rows = []
    for scene in scenes:
        rows += run_scene(root, scene, Path(cache), list(methods), list(seeds), threads, redo, repeats, cached_only)
        done = {(r["scene"], r["method"]) for r in rows}
        kept = [r for r in old.get("rows", []) if (r["scene"], r["method"]) not in done]
        order = {s: i for i, s in enumerate(SCENES)}
        allrows = sorted(rows + kept, key=lambda r: order.get(r["scene"], 99))
        res = {"meta": run_metadata(0), "command": command, "threads": threads, "seeds": list(seeds),
               "cache": str(cache), "scenes": {s: SCENES[s][2] for s in dict.fromkeys(r["scene"] for r in allrows)},
               "rows": allrows}
        _write_json(out / "accuracy.json", res)
        md = ["# Pose accuracy per scene: COLMAP's matcher vs guidedmatch in COLMAP's mapper", "",
              f"`{command}` -- {res['meta'].get('timestamp_utc')}, commit `{(res['meta'].get('git_commit') or '')[:10]}`, "
              f"{cpu_label(res['meta'])}, {threads} threads; load average at each timed stage in accuracy.json "
              "(2 shared cores: compare times within a scene).", "",
              "Same pycolmap SIFT features (COLMAP defaults, 8192) for every method of a scene, same mapper "
              "(pycolmap.incremental_mapping), median over the mapper seeds (0, 1, 2, ...; how many in the seeds column) "
              "of each column; AUC@1 range over the seeds in brackets. Wrong inliers: > 10 px from the model mapped "
              "from COLMAP's matches (seed 0), and > 4 px from the reference epipolar lines.", "",
              markdown_table(allrows), "", "Reference poses:", ""]
        md += [f"* {s}: {d}" for s, d in res["scenes"].items()]
        from ..sfm.config import CAP_ABOVE_INLIERS
        from .accuracy_analysis import VARIANTS

        legend = {"colmap": "pycolmap.match_exhaustive, COLMAP's defaults", "ours": "guidedmatch colmap DB (defaults)",
                  "ours+cap": f"guidedmatch colmap DB --max-inliers-per-pair {CAP} --cap-above 0 (the cap whatever "
                              "the total)",
                  "ours+sfm": f"guidedmatch colmap DB --max-inliers-per-pair {CAP} (--cap-above {CAP_ABOVE_INLIERS}: "
                              f"guidedmatch sfm's defaults -- the cap only above {CAP_ABOVE_INLIERS:,} inliers in all)",
                  "ours+rescue": "ours, then collection.rescue.rescue_pairs (rejected pairs matched by COLMAP's matcher, "
                                 "kept when a third view confirms them)",
                  "ours+rescue+cap": "ours+rescue, then the cap",
                  **{m: f"guidedmatch colmap DB --max-inliers-per-pair {cap_of(m)} (another cap)"
                     for m in (r["method"] for r in allrows) if cap_of(m) and m not in ("ours+cap", "ours+sfm")},
                  **{m: "guidedmatch colmap DB " + " ".join(ours_words(m)) for m in (r["method"] for r in allrows)
                     if m.startswith("ours@")},
                  **{k: f"analysis, not a method: {v[1]} (matching time: the base's)" for k, v in VARIANTS.items()}}
        md += ["", "Methods:", ""] + [f"* `{m}`: {legend.get(m, '')}" for m in dict.fromkeys(r["method"] for r in allrows)]
        md += ["", "![drift](accuracy_drift.png)", ""]
        atomic_write_text(out / "accuracy.md", "\n".join(md))
        plot_drift([r for r in allrows if "error" not in r], out / "accuracy_drift.png")
    return res


def add_arguments(p: argparse.ArgumentParser, standalone: bool = False) -> None:
    """The options of this benchmark; ``standalone`` adds those that ``guidedmatch bench`` already has (``--methods``,
    ``--threads``, ``--repeats``, ``--data``, ``--out``)."""
    p.add_argument("--scenes", default=",".join(SCENES),
                   help="accuracy: comma-separated scenes (default: all with poses: " + ", ".join(SCENES) + ")")
    p.add_argument("--seeds", default="0,1,2", help="accuracy: mapper seeds (IncrementalPipelineOptions.random_seed)")
    p.add_argument("--cache", default=default_cache("accuracy"),
                   help="accuracy: where extracted / matched databases and models are kept between runs")
    p.add_argument("--cached-only", action="store_true", help="accuracy: tabulate what the cache holds; a method "
                   "not matched and mapped there for every seed is skipped, nothing is computed")
    p.add_argument("--redo", default="", help="accuracy: comma-separated methods to match and map again")
    if standalone:
        p.add_argument("--methods", default=None, help="comma-separated methods (default " + ",".join(BASE_METHODS)
                       + "; analysis variants: see guidedmatch.evaluation.accuracy_analysis.VARIANTS)")
        p.add_argument("--threads", type=int, default=2, help="threads of COLMAP's matcher and mapper (default 2)")
        p.add_argument("--repeats", type=int, default=None, help="time COLMAP's and our matching again in N "
                       "alternating fresh processes each and report the median (default: the one timed run of each)")
        p.add_argument("--data", default=None, help="data root (default GUIDEDMATCH_DATA or ../shared/data)")
        p.add_argument("--out", default="benchmarks/results", help="output folder (writes OUT/accuracy/)")


def main(args) -> int:
    from ..datasets import data_root
    from ..errors import ConfigError, InputError

    root = data_root(args.data)
    if root is None:
        raise InputError("no data folder found (set GUIDEDMATCH_DATA or pass --data)")
    scenes = [s for s in args.scenes.split(",") if s]
    bad = [s for s in scenes if s not in SCENES]
    if bad:
        raise ConfigError(f"unknown scene(s) {bad}; known: {', '.join(SCENES)}")
    from .accuracy_analysis import VARIANTS

    methods = [m for m in (args.methods or ",".join(BASE_METHODS)).split(",") if m]
    known = BASE_METHODS + RESCUE_METHODS + tuple(VARIANTS)
    bad = [m for m in methods if m not in known and not m.startswith("ours@") and not cap_of(m)]
    if bad:
        raise ConfigError(f"unknown method(s) {bad}; known: {', '.join(known)}, ours+capN (a cap of N inliers), "
                          "ours@KEY=VALUE (a matcher setting)")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s]
    except ValueError:
        raise ConfigError(f"--seeds takes integers, got {args.seeds!r}") from None
    res = run(root, Path(args.out) / "accuracy", scenes, methods, seeds, args.threads, Path(args.cache),
              redo=tuple(m for m in args.redo.split(",") if m), command=command_line(sys.argv[1:]),
              repeats=args.repeats or 0, cached_only=args.cached_only)
    print(markdown_table(res["rows"]))
    return 0


if __name__ == "__main__":
    from ..sfm import colmap_log_level

    parser = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.bench_accuracy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser, standalone=True)
    with colmap_log_level(1):
        sys.exit(main(parser.parse_args()))
