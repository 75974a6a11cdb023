"""Collection benchmark: ``guidedmatch colmap DB --pairs exhaustive`` vs ``pycolmap.match_exhaustive``.

``python -m guidedmatch.evaluation.bench_collection [--out benchmarks/results/collection] [--work DIR]``

On Herz-Jesus-P8 (8 images, 3072x2048, 28 pairs), for each feature set -- and on ``mixed``: the same 8 images plus
8 unrelated Unsplash photos (16 images, 120 pairs, 92 of them without overlap, the common case of a real collection):

1. one COLMAP database with ``pycolmap.extract_features`` (SIFT, CPU, 2 threads; ``default`` and ``mixed``: COLMAP's
   defaults, 8192 features; ``50k``: ``peak_threshold=0.002``, ``max_num_features=60000``), copied for every run;
2. as fresh processes (Python start-up and imports included in the wall time):
   * ``guidedmatch colmap DB --pairs exhaustive`` (auto backend: the in-process / local-cluster rule), and with
     ``--workers 1`` / ``--workers 2`` (the 1 vs 2 local workers scaling) and ``--workers 0`` (in-process, one thread
     per core) / ``--workers 0 --threads 1``;
   * ``pycolmap.match_exhaustive`` on a copy (CPU, ``num_threads=2``, COLMAP's matching and verification
     defaults);
   * the rerun of our command on the finished database (every pair skipped);
3. verified inliers = sum over the database's two-view geometries of their inlier matches;
   ``pycolmap.incremental_mapping`` on both databases: registered images of the largest model;
4. the CPU time (user + system) of every fresh process and of the worker processes it waited for; for each round of
   1 vs 2 local workers :func:`scaling_accounting`: the CPU bound on the 2-worker wall time, the repeated image loads
   and the per-pair slowdown when both cores are busy.

Writes ``collection.json`` (every number + run metadata), ``collection.md`` (tables) and ``collection.png``.
The machine is shared by other jobs while it runs: times are noisy, ratios within one run are the numbers to read.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .meta import cpu_label

DATA_REL = "pose_pairs/strecha/Herz-Jesus-P8/images"
FEATURE_SETS = {
    "default": dict(),  # COLMAP's defaults: max_num_features 8192, peak_threshold 0.00667
    "50k": dict(peak_threshold=0.002, max_num_features=60000),
    "mixed": dict(),    # COLMAP's defaults on Herz-Jesus-P8 + MIXED_PHOTOS unrelated photos: most pairs do not overlap
}
#: unrelated photos added to the 8 Herz-Jesus-P8 images in the "mixed" set (the first of photos/unsplash, by name)
MIXED_PHOTOS = 8


def mixed_images(image_dir: Path, data_root: Path, work: Path) -> Path:
    """A folder of symbolic links (the data stays in place): the Herz-Jesus-P8 images and the first
    :data:`MIXED_PHOTOS` Unsplash photos -- 16 images, 120 pairs of which 92 do not overlap."""
    from ..datasets import list_photos

    d = work / "mixed-images"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    for src in sorted(image_dir.iterdir()) + list_photos(data_root)[:MIXED_PHOTOS]:
        (d / src.name).symlink_to(src.resolve())
    return d
THREADS = 2
#: the backend runs of the scaling part: tag -> options of ``guidedmatch colmap``
WORKER_RUNS = {"0": "--workers 0", "0t1": "--workers 0 --threads 1", "1": "--workers 1", "2": "--workers 2"}
SRC = str(Path(__file__).resolve().parents[2])


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _timed(cmd: list[str], log: Path | None = None, env: dict | None = None) -> dict:
    """Run ``cmd`` as a fresh process (environment ``env``, default :func:`_env`: this source tree first on the
    path); wall time, CPU time (user + system) of the process and of every process it waited for (its cluster's
    workers), return code, last lines of output; with a per-pair ``log``: its summary, the pairs' spans ``[worker,
    start, end]`` in seconds since the process was started (timeline) and each pair's matching time. Raises when the
    process fails."""
    unix0 = time.time()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env if env is not None else _env())
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    user, sys_ = after.ru_utime - before.ru_utime, after.ru_stime - before.ru_stime
    out = dict(cmd=" ".join(cmd[2:]) if cmd[1] == "-c" else " ".join(cmd), wall_s=wall, returncode=r.returncode,
               cpu_s=user + sys_, cpu_user_s=user, cpu_sys_s=sys_,
               stdout_tail=r.stdout.strip().splitlines()[-8:], stderr_tail=r.stderr.strip().splitlines()[-3:])
    if log is not None and log.exists():
        lines = log.read_text().splitlines()
        recs = [json.loads(x) for x in lines[:-1]]
        out["spans"] = [[x.get("worker", "?"), round(x["t_start"] - unix0, 4), round(x["t_end"] - unix0, 4)]
                        for x in recs if x.get("event") == "pair" and "t_start" in x]
        out["pair_match_s"] = {" ".join(x["pair"]): x["match_s"] for x in recs
                               if x.get("event") == "pair" and "match_s" in x}
        summary = json.loads(lines[-1]) if lines else {}
        out["summary"] = {k: summary.get(k) for k in ("done", "skipped", "failed", "wall_s", "backend", "workers",
                                                      "backend_reason", "matches", "inliers", "verified_pairs",
                                                      "match_s", "load_s", "startup_s", "shutdown_s", "threads",
                                                      "image_loads", "cache_hits", "work")}
    if r.returncode != 0:
        raise RuntimeError(f"{out['cmd']} failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return out


def _backend(s: dict) -> str:
    from ..collection.report import _workers_text

    return f"{s.get('backend')} ({_workers_text(s)})"


def extract(image_dir: Path, db: Path, options: dict) -> dict:
    """A COLMAP database of the folder with pycolmap's SIFT (CPU, 2 threads) in a fresh process."""
    code = f"""
import pycolmap, time
o = pycolmap.FeatureExtractionOptions()
o.num_threads = {THREADS}
o.use_gpu = False
for k, v in {options!r}.items():
    setattr(o.sift, k, v)
t = time.perf_counter()
pycolmap.extract_features({str(db)!r}, {str(image_dir)!r}, camera_mode=pycolmap.CameraMode.AUTO,
                          extraction_options=o, device=pycolmap.Device.cpu)
print(time.perf_counter() - t)
"""
    return _timed([sys.executable, "-c", code])


def colmap_match(db: Path) -> dict:
    code = f"""
import pycolmap, time
m = pycolmap.FeatureMatchingOptions()
m.num_threads = {THREADS}
m.use_gpu = False
t = time.perf_counter()
pycolmap.match_exhaustive({str(db)!r}, matching_options=m, device=pycolmap.Device.cpu)
print(time.perf_counter() - t)
"""
    out = _timed([sys.executable, "-c", code])
    out["inner_s"] = float(out["stdout_tail"][-1])
    return out


def ours(db: Path, log: Path, *extra: str) -> dict:
    if log.exists():
        log.unlink()
    return _timed([sys.executable, "-m", "guidedmatch.cli", "colmap", str(db), "--pairs", "exhaustive", "--no-progress",
                   "--log", str(log), *extra], log)


def _image_names(db: Path) -> list[str]:
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        return sorted(im.name for im in d.read_all_images())
    finally:
        d.close()


def db_stats(db: Path) -> dict:
    """Features per image, pairs with matches, raw matches, verified pairs and their inlier matches."""
    import numpy as np
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        images = d.read_all_images()
        nf = [d.num_keypoints_for_image(im.image_id) for im in images]
        pids, nm = d.read_num_matches()
        gids, ni = d.read_two_view_geometry_num_inliers()
        ni = np.asarray(ni, np.int64)
        return dict(images=len(images), features_mean=float(np.mean(nf)), features_min=int(min(nf)),
                    features_max=int(max(nf)), pairs_with_matches=len(pids), matches=int(np.sum(nm)),
                    verified_pairs=int(np.sum(ni > 0)), verified_inliers=int(ni.sum()))
    finally:
        d.close()


def mapping(db: Path, image_dir: Path, out: Path) -> dict:
    code = f"""
import pycolmap, time
t = time.perf_counter()
recs = pycolmap.incremental_mapping({str(db)!r}, {str(image_dir)!r}, {str(out)!r})
best = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
print(len(recs), 0 if best is None else best.num_reg_images(), time.perf_counter() - t)
"""
    r = _timed([sys.executable, "-c", code])
    n_models, registered, t = r["stdout_tail"][-1].split()
    return dict(models=int(n_models), registered=int(registered), time_s=float(t))


def _repeat_runs(row: dict, repeats: int, scaling: bool, copy, log: Path) -> dict:
    """``repeats - 1`` more rounds of COLMAP vs ours (and, with ``scaling``, 1 vs 2 local workers), each on a fresh
    copy of the database, the order alternating from round to round; with the first runs already in ``row``:
    ``{method: {"walls", "median", "min", "max", "cpu"}}``, plus with ``scaling`` ``"scaling_rounds"``: each round's
    1- vs 2-worker :func:`scaling_accounting`. A single run moves by +-0.1-0.2 s at ~2 s on this machine."""
    import statistics

    runs = {"colmap": lambda: colmap_match(copy("rep-colmap")), "ours": lambda: ours(copy("rep-ours"), log)}
    if scaling:
        runs.update(workers_1=lambda: ours(copy("rep-w1"), log, "--workers", "1"),
                    workers_2=lambda: ours(copy("rep-w2"), log, "--workers", "2"))
    done = {k: [row[k]] for k in runs}  # every run of each method, the first one included
    for i in range(repeats - 1):
        for pair in (("colmap", "ours"), ("workers_1", "workers_2")):
            for key in (pair if i % 2 else pair[::-1]):
                if key in runs:
                    r = runs[key]()
                    if r["returncode"] != 0:
                        raise RuntimeError(f"repeat run {key} failed: {r['stderr_tail']}")
                    done[key].append(r)
    out = {}
    for k, rs in done.items():
        walls = [r["wall_s"] for r in rs]
        out[k] = dict(walls=walls, median=statistics.median(walls), min=min(walls), max=max(walls),
                      cpu=[r.get("cpu_s") for r in rs])
    if scaling:  # round k's 1-worker run against round k's 2-worker run
        out["scaling_rounds"] = [scaling_accounting(a, b) for a, b in zip(done["workers_1"], done["workers_2"])]
    return out


def scaling_accounting(w1: dict, w2: dict, cores: int = THREADS, target: float = 0.6) -> dict:
    """Where the time of 2 local workers goes, against 1 (the ``<= 0.6x`` scaling target), from the CPU time of the
    two fresh processes (:func:`_timed`: the command, its cluster's scheduler and its workers) and their pair logs.

    On ``cores`` cores no schedule finishes before ``cpu_2 / cores``: that is ``cpu_bound_s``, a lower bound on the
    2-worker wall time even with no start-up, no idle worker and no tail. ``cpu_bound_without_extra_loads_s`` also
    takes away the loads the second worker repeats (``load_s`` beyond the 1-worker run's: the images both workers
    read and prepare), i.e. the bound with a perfect shared image cache. ``pair_slowdown``: the median over pairs
    of (matching time with 2 workers) / (with 1 worker) -- the same pair, the same code, both cores busy against one.
    ``bound_over_1`` = bound / 1-worker wall; the target is out of reach on this machine when it exceeds ``target``.

    >>> w1 = dict(wall_s=13.0, cpu_s=14.0, summary=dict(load_s=0.8, image_loads=8), pair_match_s={"a b": 1.0, "a c": 2.0})
    >>> w2 = dict(wall_s=9.0, cpu_s=17.0, summary=dict(load_s=1.8, image_loads=15), pair_match_s={"a b": 1.1, "a c": 2.4})
    >>> acc = scaling_accounting(w1, w2)
    >>> acc["ratio"], acc["cpu_bound_s"], acc["cpu_bound_without_extra_loads_s"], acc["pair_slowdown"]
    (0.6923, 8.5, 8.0, 1.15)
    >>> acc["bound_over_1"], acc["bound_without_extra_loads_over_1"], acc["target_reachable"]
    (0.6538, 0.6154, False)
    """
    import statistics

    def num(x, key):
        v = x.get(key)
        return float(v) if v is not None else None

    wall1, wall2, cpu1, cpu2 = num(w1, "wall_s"), num(w2, "wall_s"), num(w1, "cpu_s"), num(w2, "cpu_s")
    s1, s2 = w1.get("summary") or {}, w2.get("summary") or {}
    extra_load = max(0.0, float(s2.get("load_s") or 0.0) - float(s1.get("load_s") or 0.0))
    m1, m2 = w1.get("pair_match_s") or {}, w2.get("pair_match_s") or {}
    common = [k for k in m1 if k in m2 and m1[k] > 0]
    out = dict(wall_1_s=wall1, wall_2_s=wall2, ratio=round(wall2 / wall1, 4) if wall1 and wall2 else None,
               cpu_1_s=cpu1, cpu_2_s=cpu2, cpu_2_over_1=round(cpu2 / cpu1, 4) if cpu1 and cpu2 else None,
               image_loads_1=s1.get("image_loads"), image_loads_2=s2.get("image_loads"), extra_load_s=extra_load,
               pair_slowdown=round(statistics.median(m2[k] / m1[k] for k in common), 4) if common else None,
               pairs_compared=len(common), cores=cores, target=target)
    if cpu2 is not None and wall1:
        bound = cpu2 / cores
        bound_nl = (cpu2 - extra_load) / cores
        out.update(cpu_bound_s=round(bound, 4), cpu_bound_without_extra_loads_s=round(bound_nl, 4),
                   bound_over_1=round(bound / wall1, 4), bound_without_extra_loads_over_1=round(bound_nl / wall1, 4),
                   target_reachable=bool(bound_nl / wall1 <= target))
    return out


def run(image_dir: Path, out_dir: Path, work: Path, sets=("default", "50k"), scaling: bool = True, note: str = "",
        map_colmap_sets=("default", "mixed"), reuse: bool = False, data_root: Path | None = None,
        repeats: int = 1) -> dict:
    from .meta import run_metadata, write_json

    if not image_dir.is_dir():
        raise FileNotFoundError(f"Herz-Jesus-P8 images not found: {image_dir}")
    work.mkdir(parents=True, exist_ok=True)
    meta = run_metadata()
    from .._runtime import byte_compile_package

    meta["byte_compiled"] = byte_compile_package()  # as an installed copy is (no per-process compile of our modules)
    result = dict(meta=meta, threads=THREADS, images=str(image_dir), sets={}, run_note=note,
                  note=f"load average {meta['load_average'] or float('nan'):.1f} when the run started (2 cores): wall "
                       "times are noisy when it is > 1")
    old = out_dir / "collection.json"
    if old.exists():  # keep the sets of an earlier run that this one does not redo
        with open(old) as fh:
            result["sets"] = {k: v for k, v in json.load(fh).get("sets", {}).items() if k not in sets}
    herz = image_dir
    for name in sets:
        map_colmap = name in map_colmap_sets
        image_dir = mixed_images(herz, data_root, work) if name == "mixed" else herz
        print(f"== {name}: extracting", flush=True)
        base = work / f"{name}.db"
        row = dict(extraction_options=FEATURE_SETS[name])
        if reuse and base.exists():  # the features of an earlier run of this bench (same options), not re-extracted
            row["extract"] = dict(reused=str(base))
        else:
            for stale in (base, *(base.with_name(base.name + x) for x in ("-wal", "-shm", "-journal"))):
                if stale.exists():  # a killed earlier extraction's SQLite side files make the new one fail
                    stale.unlink()
            row["extract"] = extract(image_dir, base, FEATURE_SETS[name])
        row["features"] = db_stats(base)

        def copy(tag: str) -> Path:
            p = work / f"{name}-{tag}.db"
            for stale in (p.with_name(p.name + x) for x in ("-wal", "-shm", ".lock")):
                if stale.exists():
                    stale.unlink()
            shutil.copy(base, p)
            return p

        print(f"== {name}: warm-up (Numba compiles the matcher's kernels into its on-disk cache once)", flush=True)
        wdb = copy("warmup")
        names = _image_names(wdb)
        (work / "warmup-pairs.txt").write_text(f"{names[0]} {names[1]}\n")
        row["warmup"] = ours(wdb, work / f"{name}-warmup.jsonl", "--workers", "0", "--pairs",
                             str(work / "warmup-pairs.txt"))
        print(f"== {name}: COLMAP match_exhaustive", flush=True)
        cdb = copy("colmap")
        row["colmap"] = colmap_match(cdb)
        row["colmap"]["db"] = db_stats(cdb)
        print(f"== {name}: guidedmatch colmap (auto)", flush=True)
        odb = copy("ours")
        row["ours"] = ours(odb, work / f"{name}-ours.jsonl")
        row["ours"]["db"] = db_stats(odb)
        print(f"== {name}: rerun", flush=True)
        row["rerun"] = ours(odb, work / f"{name}-rerun.jsonl")
        print(f"== {name}: mapping", flush=True)
        row["mapping_ours"] = mapping(odb, image_dir, work / f"{name}-sparse-ours")
        if map_colmap:
            row["mapping_colmap"] = mapping(cdb, image_dir, work / f"{name}-sparse-colmap")
        if scaling:
            s = row["ours"]["summary"]
            auto = "0" if s["backend"] == "in-process" and s.get("threads", 1) > 1 else (
                "0t1" if s["backend"] == "in-process" else str(s["workers"]))
            for w in WORKER_RUNS:
                if w == auto:  # the auto run was this configuration: not run twice
                    row[f"workers_{w}"] = dict(row["ours"], same_as="auto")
                    continue
                print(f"== {name}: {WORKER_RUNS[w]}", flush=True)
                wdb = copy(f"w{w}")
                row[f"workers_{w}"] = ours(wdb, work / f"{name}-w{w}.jsonl", *WORKER_RUNS[w].split())
                row[f"workers_{w}"]["db"] = db_stats(wdb)
        if repeats > 1:
            row["repeats"] = _repeat_runs(row, repeats, scaling, copy, work / f"{name}-rep.jsonl")
        c, o = row["colmap"], row["ours"]
        row["ratios"] = dict(
            time_ours_over_colmap=o["wall_s"] / c["wall_s"],
            inliers_ours_over_colmap=o["db"]["verified_inliers"] / max(1, c["db"]["verified_inliers"]),
            workers_2_over_1=(row["workers_2"]["wall_s"] / row["workers_1"]["wall_s"]) if scaling else None,
            workers_2_over_1_matching=(row["workers_2"]["summary"]["wall_s"] / row["workers_1"]["summary"]["wall_s"])
            if scaling else None,
            threads_2_over_1=(row["workers_0"]["wall_s"] / row["workers_0t1"]["wall_s"]) if scaling else None)
        if scaling:
            row["scaling_accounting"] = scaling_accounting(row["workers_1"], row["workers_2"])
        if "repeats" in row:
            rp = row["repeats"]
            row["ratios"]["time_ours_over_colmap_median"] = rp["ours"]["median"] / rp["colmap"]["median"]
            if scaling:
                row["ratios"]["workers_2_over_1_median"] = rp["workers_2"]["median"] / rp["workers_1"]["median"]
        result["sets"][name] = row
        write_json(out_dir / "collection.json", result)
    (out_dir / "collection.md").write_text(markdown(result))
    figure(result, out_dir / "collection.png")
    timeline_figure(result, out_dir / "timeline.png")
    return result


def markdown(result: dict) -> str:
    lines = ["# Collection matching: `guidedmatch colmap` vs `pycolmap.match_exhaustive` (Herz-Jesus-P8, 28 pairs)", "",
             f"CPU: {cpu_label(result['meta'])}, {result['meta'].get('usable_cores')} usable cores; COLMAP "
             f"{THREADS} threads. {result['note']}. Wall times of fresh processes (imports, cluster start/stop "
             "included). Verified inliers: sum of the inlier matches of all two-view geometries in the database. "
             "Numba's on-disk cache was warmed first (one pair, untimed: "
             f"{result['sets'][next(iter(result['sets']))]['warmup']['wall_s']:.1f} s); a first-ever run adds that "
             "compilation once." + (f" Code: {result['run_note']}." if result.get("run_note") else ""), "",
             "| features | method | wall (s) | inner (s) | backend | verified pairs | verified inliers | "
             "registered (mapper) |", "|---|---|---|---|---|---|---|---|"]
    for name, row in result["sets"].items():
        f = row["features"]
        feat = f"{name} ({f['features_mean']:.0f}/image)"
        c, o = row["colmap"], row["ours"]
        nimg = f.get("images", 8)
        reg_c = f"{row['mapping_colmap']['registered']}/{nimg}" if "mapping_colmap" in row else "not run"
        lines.append(f"| {feat} | COLMAP match_exhaustive | {c['wall_s']:.2f} | {c['inner_s']:.2f} | 2 threads | "
                     f"{c['db']['verified_pairs']} | {c['db']['verified_inliers']} | {reg_c} |")
        s = o.get("summary", {})
        lines.append(f"| {feat} | guidedmatch colmap (auto) | {o['wall_s']:.2f} | {s.get('wall_s', 0):.2f} | "
                     f"{_backend(s)} | {o['db']['verified_pairs']} | "
                     f"{o['db']['verified_inliers']} | {row['mapping_ours']['registered']}/{nimg} |")
        r = row["rerun"]
        lines.append(f"| {feat} | rerun (all skipped: {r['summary'].get('skipped')}) | {r['wall_s']:.2f} | "
                     f"{r['summary'].get('wall_s', 0):.2f} | - | - | - | - |")
        for w in WORKER_RUNS:
            if f"workers_{w}" in row:
                x = row[f"workers_{w}"]
                same = " (= the auto run)" if x.get("same_as") else ""
                lines.append(f"| {feat} | guidedmatch colmap {WORKER_RUNS[w]}{same} | {x['wall_s']:.2f} | "
                             f"{x['summary'].get('wall_s', 0):.2f} | {_backend(x['summary'])} | "
                             f"{x['db']['verified_pairs']} | {x['db']['verified_inliers']} | - |")
    lines += ["", "| features | ours / COLMAP time | ours / COLMAP verified inliers | 2 / 1 workers (wall) | "
              "2 / 1 workers (inner) | in-process 2 / 1 threads (wall) |", "|---|---|---|---|---|---|"]
    for name, row in result["sets"].items():
        q = row["ratios"]
        fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        lines.append(f"| {name} | {fmt(q['time_ours_over_colmap'])} | {fmt(q['inliers_ours_over_colmap'])} | "
                     f"{fmt(q['workers_2_over_1'])} | {fmt(q['workers_2_over_1_matching'])} | "
                     f"{fmt(q.get('threads_2_over_1'))} |")
    lines += ["", "inner = time inside the process: COLMAP's match_exhaustive call; ours: the engine's wall time "
              "(matching, verdicts, writes, cluster start/stop), without the Python start-up and imports.", ""]
    rep = {n: r["repeats"] for n, r in result["sets"].items() if "repeats" in r}
    if rep:
        lines += ["**Repeated runs** (fresh processes on fresh database copies, the order alternating from round to "
                  "round; median (min-max) of the wall times, the first runs above included):", "",
                  "| features | runs | COLMAP (s) | ours (s) | ours / COLMAP (medians) | 1 worker (s) | 2 workers (s) | "
                  "2 / 1 workers (medians) |", "|---|---|---|---|---|---|---|---|"]

        def mm(d):
            return f"{d['median']:.2f} ({d['min']:.2f}-{d['max']:.2f})" if d else "-"

        for name, r in rep.items():
            q = result["sets"][name]["ratios"]
            w1, w2 = r.get("workers_1"), r.get("workers_2")
            scaling = f"{q['workers_2_over_1_median']:.2f}" if w1 else "-"
            lines.append(f"| {name} | {len(r['ours']['walls'])} | {mm(r['colmap'])} | {mm(r['ours'])} | "
                         f"{q['time_ours_over_colmap_median']:.2f} | {mm(w1)} | {mm(w2)} | {scaling} |")
        lines.append("")
    acc_rows = [(name, k, a) for name, row in result["sets"].items()
                for k, a in ([("1", row["scaling_accounting"])] if "scaling_accounting" in row else [])
                + [(f"{i + 1}", x) for i, x in enumerate(row.get("repeats", {}).get("scaling_rounds", [])[1:],
                                                            start=1)]]
    if acc_rows:
        lines += ["**Where the time of 2 local workers goes** (against 1; CPU = user + system time of the fresh "
                  "process and of the worker processes it waited for; bound = CPU of the 2-worker run / "
                  f"{THREADS} cores: no schedule on this machine finishes sooner, with no start-up, no idle worker "
                  "and no tail; without extra loads: less the loads the second worker repeats, i.e. with a perfect "
                  "shared image cache; pair slowdown: median over pairs of the same pair's matching time with 2 "
                  "workers / with 1):", "",
                  "| features | round | 1 worker wall (s) | 2 workers wall (s) | 2 / 1 | CPU 1 (s) | CPU 2 (s) | "
                  "image loads 1 / 2 | pair slowdown | bound (s) | bound / 1-worker wall | without extra loads |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        f2 = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        for name, k, a in acc_rows:
            lines.append(f"| {name} | {k} | {f2(a['wall_1_s'])} | {f2(a['wall_2_s'])} | {f2(a['ratio'])} | "
                         f"{f2(a['cpu_1_s'])} | {f2(a['cpu_2_s'])} | {a['image_loads_1']} / {a['image_loads_2']} | "
                         f"{f2(a['pair_slowdown'])} | {f2(a.get('cpu_bound_s'))} | {f2(a.get('bound_over_1'))} | "
                         f"{f2(a.get('bound_without_extra_loads_over_1'))} |")
        lines.append("")
    return "\n".join(lines)


def figure(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["sets"])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = range(len(names))
    for ax, key, label in ((axes[0], "wall_s", "wall time of a fresh process (s)"),
                           (axes[1], "verified_inliers", "verified inlier matches (sum over pairs)")):
        for k, (who, color) in enumerate((("colmap", "tab:gray"), ("ours", "tab:blue"))):
            vals = [result["sets"][n][who][key] if key == "wall_s" else result["sets"][n][who]["db"][key]
                    for n in names]
            ax.bar([i + 0.38 * k for i in x], vals, 0.36, color=color,
                   label="pycolmap.match_exhaustive" if who == "colmap" else "guidedmatch colmap")
        ax.set_xticks([i + 0.19 for i in x], [f"{n}\n({result['sets'][n]['features']['features_mean']:.0f} feat.)"
                                             for n in names])
        ax.set_title(label, fontsize=10)
        ax.legend(fontsize=8)
    fig.suptitle(f"Herz-Jesus-P8, 28 pairs, 2 CPU threads ({result.get('note', '')})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


TIMELINE_RUNS = (("ours", "auto"), ("workers_0t1", "in-process, 1 thread"), ("workers_1", "1 local worker"),
                 ("workers_2", "2 local workers"))


def timeline_figure(result: dict, path: Path) -> Path | None:
    """When each pair ran, per worker (or in-process thread), from the fresh process's start to its end: the grey
    band before the first pair is start-up (imports, cluster start, the worker's own imports and Numba load), the
    one after the last pair the tail (writes, cluster stop, exit)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import draw_timeline

    panels = [(name, key, label, row[key]) for name, row in result["sets"].items() for key, label in TIMELINE_RUNS
              if key in row and row[key].get("spans") and not (key != "ours" and row[key].get("same_as"))]
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 0.9 + 0.75 * len(panels)), squeeze=False)
    for ax, (name, key, label, run) in zip(axes[:, 0], panels):
        row_name = "thread" if run["summary"].get("backend") == "in-process" else "worker"
        first, last = draw_timeline(ax, run["spans"], end=run["wall_s"], row_name=row_name)
        ax.set_title(f"{name} ({result['sets'][name]['features']['features_mean']:.0f} feat./image), {label}: "
                     f"{run['wall_s']:.2f} s; first pair at {first:.2f} s, last done at {last:.2f} s",
                     fontsize=8, loc="left")
    axes[-1, 0].set_xlabel("seconds since the process started (grey: before the first pair / after the last)",
                           fontsize=8)
    fig.suptitle(f"guidedmatch colmap, Herz-Jesus-P8 pairs: one bar per pair ({result.get('note', '')})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.bench_collection", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=os.environ.get("GUIDEDMATCH_DATA", "/work/shared/data"))
    p.add_argument("--images", default=None, help=f"image folder (default DATA/{DATA_REL})")
    p.add_argument("--out", default="benchmarks/results/collection")
    p.add_argument("--work", default="/tmp/guidedmatch-bench-collection", help="databases (not in the repo)")
    p.add_argument("--sets", default="default,50k,mixed")
    p.add_argument("--no-scaling", action="store_true", help="skip the --workers 0/1/2 runs")
    p.add_argument("--note", default="", help="what code ran (recorded in the JSON and the table)")
    p.add_argument("--reuse", action="store_true", help="reuse WORK/<set>.db of an earlier run (no re-extraction)")
    p.add_argument("--repeats", type=int, default=1, help="runs of COLMAP vs ours and of 1 vs 2 workers per set, in "
                   "alternating order (medians reported next to the first run); default 1")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = run(Path(a.images) if a.images else Path(a.data) / DATA_REL, out, Path(a.work), tuple(a.sets.split(",")), scaling=not a.no_scaling, note=a.note,
              reuse=a.reuse, data_root=Path(a.data), repeats=max(1, a.repeats))
    print(markdown(res))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
