"""Extraction options and mappers, judged on GT poses: ``python -m guidedmatch.evaluation.bench_extract``.

Protocol, per scene (Herz-Jesus-P8: 8 photos of 3072x2048; Herz-Jesus-P25: 25 of 2048x1365; both with Strecha GT):

1. **Extraction options** (:data:`OPTIONS`), each from an empty folder, every step a fresh process (timed from
   start to exit, wall and CPU): extraction (:func:`guidedmatch.extraction.extract_to_database`) ->
   ``guidedmatch colmap DB`` (our matcher, exhaustive pairs, our two-view geometry) + at most 1000 inliers per pair
   for the mapper (what ``guidedmatch sfm`` hands it) -> ``pycolmap.incremental_mapping``. Peer row ``colmap``:
   pycolmap's default extraction + ``pycolmap.match_exhaustive`` + ``incremental_mapping``. ``--runs`` rounds, the
   option order reversed every other round; the table shows the median round of each row.
2. **Mappers** (``--mappers``): on the last round's databases of ``--mapper-options`` (matched once, all inliers
   kept), ``pycolmap.incremental_mapping`` vs ``pycolmap.global_mapping`` (COLMAP's global SfM), each with at most
   ``K`` inliers per pair for ``K`` in ``--caps`` (0 = all), each mapping a fresh process.

Columns: extraction / matching / mapping time (s, wall; CPU in the JSON), features per image (median), registered
images, median relative-pose error and AUC@1/2/5 deg over all GT pairs (:mod:`guidedmatch.evaluation.poses`).
Writes ``extract.json`` (run metadata, load averages before each round), ``extract.md`` and ``extract.png``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from .meta import cpu_label

#: Extraction options: name -> ExtractionConfig fields (``colmap`` = the pycolmap peer pipeline's extraction).
OPTIONS = {
    "colmap": {"extractor": "pycolmap"},
    "pycolmap-fo0": {"extractor": "pycolmap", "first_octave": 0},
    "opencv": {"extractor": "opencv"},
    "opencv-scale": {"extractor": "opencv", "selection": "scale"},
    "opencv-1600": {"extractor": "opencv", "max_image_size": 1600},
    "opencv-1thread": {"extractor": "opencv", "workers": 1},
}
#: Scenes: name -> (images folder, GT camera folder), relative to the data root.
SCENES = {"p8": ("pose_pairs/strecha/Herz-Jesus-P8/images", "pose_pairs/strecha/Herz-Jesus-P8/gt_dense_cameras"),
          "p25": ("collections/Herz-Jesus-P25/images", "collections/Herz-Jesus-P25/gt_dense_cameras")}
#: Inliers per pair handed to the mapper in the option rows (``guidedmatch sfm``'s default).
CAP = 1000
MAPPERS = ("incremental", "global")


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _py() -> list[str]:
    return [sys.executable, "-m", "guidedmatch.evaluation.bench_extract", "_step"]


# --------------------------------------------------------------------------- steps (each a fresh process)
def _step(argv: list[str]) -> int:
    """``_step extract OPTION IMAGE_DIR DB`` | ``_step match_colmap DB`` | ``_step map MAPPER DB IMAGE_DIR OUT``:
    prints one JSON line."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    kind = argv[0]
    if kind == "extract":
        from ..extraction import ExtractionConfig, extract_to_database

        conf = ExtractionConfig(**OPTIONS[argv[1]], progress=False)
        rep = extract_to_database(argv[2], argv[3], conf)
        print(json.dumps({k: rep[k] for k in ("time_s", "extracted", "failed", "keypoints", "per_image")}))
    elif kind == "match_colmap":
        mo = pycolmap.FeatureMatchingOptions()
        mo.use_gpu = False
        t0 = time.perf_counter()
        pycolmap.match_exhaustive(argv[1], matching_options=mo, device=pycolmap.Device.cpu)
        print(json.dumps({"time_s": time.perf_counter() - t0}))
    elif kind == "map":
        mapper, db, image_dir, out = argv[1:5]
        os.makedirs(out, exist_ok=True)
        t0 = time.perf_counter()
        if mapper == "incremental":
            opts = pycolmap.IncrementalPipelineOptions()
            opts.random_seed = 0
            recs = pycolmap.incremental_mapping(db, image_dir, out, options=opts)
        else:
            opts = pycolmap.GlobalPipelineOptions()
            opts.random_seed = 0
            recs = pycolmap.global_mapping(db, image_dir, out, options=opts)
        elapsed = time.perf_counter() - t0
        best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
        if best is not None:
            os.makedirs(os.path.join(out, "best"), exist_ok=True)
            best.write(os.path.join(out, "best"))
        print(json.dumps({"time_s": elapsed, "models": len(recs),
                          "registered": best.num_reg_images() if best else 0,
                          "points3D": best.num_points3D() if best else 0}))
    else:
        raise SystemExit(f"unknown step {kind!r}")
    return 0


def _run(cmd: list[str]) -> dict:
    """A fresh process, timed (wall + CPU of it and its children); its last stdout line parsed as JSON."""
    from .bench_collection import _timed

    r = _timed(cmd)
    out = {"wall_s": r["wall_s"], "cpu_s": r["cpu_s"]}
    for line in reversed(r["stdout_tail"]):
        if line.startswith("{"):
            out["result"] = json.loads(line)
            break
    return out


def _evaluate(model: Path, gt: dict) -> dict:
    from .poses import evaluate_poses, poses_from_reconstruction

    if not (model / "best").is_dir():
        ev = evaluate_poses({}, gt)
    else:
        ev = evaluate_poses(poses_from_reconstruction(str(model / "best")), gt)
    return {"median_pose_error_deg": ev.median_error_deg, "auc": ev.auc, "registered": ev.num_registered,
            "median_rotation_deg": ev.median_rotation_deg, "median_translation_deg": ev.median_translation_deg}


def run_option(option: str, image_dir: Path, gt: dict, work: Path) -> dict:
    """One row of one round: extraction -> matching (+ cap) -> incremental mapping, from an empty folder."""
    from ..collection.sinks import cap_two_view_inliers

    d = work / option
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    db = d / "database.db"
    ext = _run(_py() + ["extract", option, str(image_dir), str(db)])
    if option == "colmap":
        match = _run(_py() + ["match_colmap", str(db)])
        cap_s = 0.0
    else:
        match = _run([sys.executable, "-m", "guidedmatch.cli", "colmap", str(db), "--no-progress"])
        shutil.copyfile(db, d / "uncapped.db")   # for the mapper study
        t0 = time.perf_counter()
        cap_two_view_inliers(db, CAP)
        cap_s = time.perf_counter() - t0
    if option == "colmap":
        shutil.copyfile(db, d / "uncapped.db")
    mp = _run(_py() + ["map", "incremental", str(db), str(image_dir), str(d / "sparse")])
    kp = ext["result"]["keypoints"]
    row = {"option": option, "config": OPTIONS[option], "extraction_s": ext["wall_s"], "extraction_cpu_s": ext["cpu_s"],
           "extraction_inner_s": ext["result"]["time_s"], "failed": ext["result"]["failed"],
           "features_median": kp["median"], "features_total": kp["total"],
           "matching_s": match["wall_s"] + cap_s, "matching_cpu_s": match["cpu_s"], "cap_s": cap_s,
           "mapping_s": mp["wall_s"], "mapping_cpu_s": mp["cpu_s"], "mapper_s": mp["result"]["time_s"],
           "points3D": mp["result"]["points3D"]}
    row["total_s"] = row["extraction_s"] + row["matching_s"] + row["mapping_s"]
    row["total_cpu_s"] = row["extraction_cpu_s"] + row["matching_cpu_s"] + row["mapping_cpu_s"]
    row.update(_evaluate(d / "sparse", gt))
    return row


def run_mappers(option: str, image_dir: Path, gt: dict, work: Path, mappers, caps) -> list[dict]:
    """The mapper study on ``work/option/uncapped.db``: each cap, each mapper, a fresh mapping process."""
    from ..collection.sinks import cap_two_view_inliers
    from ..sfm import verified_inliers

    rows = []
    src = work / option / "uncapped.db"
    for cap in caps:
        db = work / option / f"cap{cap}.db"
        shutil.copyfile(src, db)
        if cap:
            cap_two_view_inliers(db, cap)
        _, inliers = verified_inliers(db)
        for mapper in mappers:
            out = work / option / f"map_{mapper}_cap{cap}"
            if out.exists():
                shutil.rmtree(out)
            _say(f"    mapper {mapper}, cap {cap}")
            try:
                mp = _run(_py() + ["map", mapper, str(db), str(image_dir), str(out)])
            except RuntimeError as exc:
                rows.append({"option": option, "mapper": mapper, "cap": cap, "error": str(exc)[-500:]})
                continue
            rows.append({"option": option, "mapper": mapper, "cap": cap, "inliers": inliers,
                         "mapping_s": mp["wall_s"], "mapping_cpu_s": mp["cpu_s"], "mapper_s": mp["result"]["time_s"],
                         "models": mp["result"]["models"], "points3D": mp["result"]["points3D"],
                         **_evaluate(out, gt)})
    return rows


# --------------------------------------------------------------------------- tables and figure
def _f(v, spec="{:.1f}") -> str:
    return "–" if v is None else spec.format(v)


def _pose(r: dict) -> str:
    med = r.get("median_pose_error_deg")
    med = "inf" if med is None or not np.isfinite(med) else f"{med:.3f}°"
    return f"{med} | " + " / ".join(f"{v:.3f}" for v in r["auc"].values())


def median_rows(rows: list[dict]) -> list[dict]:
    """Per (scene, option): the round with the median total time, with every time column replaced by its median
    over the rounds and ``runs`` = the rounds' totals.

    >>> rs = [dict(scene="s", option="o", total_s=t, extraction_s=t) for t in (3.0, 1.0, 2.0)]
    >>> m = median_rows(rs)[0]; m["total_s"], m["runs"]
    (2.0, [3.0, 1.0, 2.0])
    """
    out = []
    for r in rows:   # rows written before the CPU total was recorded
        if "total_cpu_s" not in r and "extraction_cpu_s" in r:
            r["total_cpu_s"] = r["extraction_cpu_s"] + r["matching_cpu_s"] + r["mapping_cpu_s"]
    for key in dict.fromkeys((r["scene"], r["option"]) for r in rows):
        rs = [r for r in rows if (r["scene"], r["option"]) == key]
        order = sorted(range(len(rs)), key=lambda k: rs[k]["total_s"])
        row = dict(rs[order[(len(rs) - 1) // 2]])
        for k in [k for k in row if k.endswith("_s") and isinstance(row[k], (int, float))]:
            row[k] = float(np.median([x[k] for x in rs if isinstance(x.get(k), (int, float))]))
        row["runs"] = [x["total_s"] for x in rs]
        out.append(row)
    return out


def options_table(rows: list[dict]) -> str:
    out = ["| scene | extraction | extraction (s) | extraction CPU (s) | features / image | matching (s) | mapping (s) "
           "| total (s): median (range, runs) | total / colmap | total CPU (s) | CPU / colmap | registered "
           "| median pose error | AUC@1°/2°/5° |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ref = next((x for x in rows if x["scene"] == r["scene"] and x["option"] == "colmap"), None)
        runs = r.get("runs", [r["total_s"]])
        total = f"{r['total_s']:.1f} ({min(runs):.1f}-{max(runs):.1f}, {len(runs)})"
        ratio = f"{r['total_s'] / ref['total_s']:.2f}" if ref else "–"
        cpu_ratio = f"{r['total_cpu_s'] / ref['total_cpu_s']:.2f}" if ref else "–"
        name = r["option"] + (" + match_exhaustive (peer)" if r["option"] == "colmap" else " + guidedmatch colmap")
        out.append(f"| {r['scene']} | {name} | {r['extraction_s']:.1f} | {r['extraction_cpu_s']:.1f} | "
                   f"{r['features_median']:.0f} | {r['matching_s']:.1f} | {r['mapping_s']:.1f} | {total} | {ratio} | "
                   f"{r['total_cpu_s']:.1f} | {cpu_ratio} | {r['registered']} | {_pose(r)} |")
    return "\n".join(out)


def mappers_table(rows: list[dict]) -> str:
    out = ["| scene | features + matches | mapper | inliers per pair | inliers to the mapper | mapping (s) | mapping CPU (s) "
           "| registered | 3D points | median pose error | AUC@1°/2°/5° |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cap = "all" if not r["cap"] else f"<= {r['cap']}"
        what = "colmap (COLMAP's matcher)" if r["option"] == "colmap" else f"{r['option']} + guidedmatch"
        if "error" in r:
            out.append(f"| {r['scene']} | {what} | {r['mapper']} | {cap} | failed: {r['error'][-120:]} | | | | | | |")
            continue
        out.append(f"| {r['scene']} | {what} | {r['mapper']} | {cap} | {r['inliers']:,} | {r['mapping_s']:.1f} | "
                   f"{r['mapping_cpu_s']:.1f} | {r['registered']} | {r['points3D']:,} | {_pose(r)} |")
    return "\n".join(out)


def plot(res: dict, path: Path) -> Path:
    """Left: total time (log) vs AUC@1 per extraction option and scene; right: mapping time vs AUC@1 per mapper /
    cap."""
    from ..plots import _plt, save_figure

    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(14, 5.5))
    marks = {"p8": "o", "p25": "s"}
    for r in res["table"]:
        a1.scatter(r["total_s"], r["auc"]["1"], marker=marks.get(r["scene"], "^"), s=50)
        a1.annotate(f"{r['scene']} {r['option']}", (r["total_s"], r["auc"]["1"]), fontsize=7, xytext=(4, 3),
                    textcoords="offset points")
    for r in res["mappers"]:
        if "error" in r:
            continue
        c = "tab:blue" if r["mapper"] == "incremental" else "tab:red"
        a2.scatter(r["mapping_s"], r["auc"]["1"], marker=marks.get(r["scene"], "^"), c=c, s=50)
        a2.annotate(f"{r['scene']} {r['option']} {r['mapper'][:4]} {r['cap'] or 'all'}",
                    (r["mapping_s"], r["auc"]["1"]), fontsize=6, xytext=(4, 3), textcoords="offset points")
    a1.set_xscale("log")
    a1.set_xlabel("extraction + matching + mapping (s, wall, log)")
    a1.set_title("extraction options (o P8, s P25)")
    a2.set_xlabel("mapping (s, wall)")
    a2.set_title("mappers x inlier cap (blue incremental, red global)")
    for a in (a1, a2):
        a.set_ylabel("AUC@1° of the relative poses")
        a.grid(alpha=0.3)
    return save_figure(fig, path)


def write_report(res: dict, out: Path) -> None:
    from ..features import atomic_write_text
    from .meta import write_json

    res["table"] = median_rows(res["rows"])
    write_json(out / "extract.json", res)
    meta = res["meta"]
    loads = ", ".join(f"{x:.1f}" for x in res["load_before_round"])
    md = ["# Extraction options and mappers (Herz-Jesus-P8 / P25, GT poses)", "",
          f"`{res['command']}` -- {meta.get('timestamp_utc')}, commit `{(meta.get('git_commit') or '')[:10]}`, "
          f"{cpu_label(meta)}, {meta.get('logical_cores')} logical cores. 1-minute load average before each "
          f"round: {loads} (other jobs shared the machine: compare rows within a round / by their ratio to the "
          "colmap row; CPU seconds are less sensitive to the load than wall seconds).", "",
          "Each stage a fresh process from an empty folder; our rows hand the mapper at most "
          f"{CAP} inliers per pair (`guidedmatch sfm`'s default). Medians over the rounds.", "",
          options_table(res["table"]), ""]
    if res["mappers"]:
        md += ["## Mappers and the inlier cap (same databases, one mapping each)", "", mappers_table(res["mappers"]), ""]
    md += ["![time vs AUC](extract.png)", ""]
    atomic_write_text(out / "extract.md", "\n".join(md))
    if res["table"]:
        plot(res, out / "extract.png")
    write_json(out / "extract.json", res)


# --------------------------------------------------------------------------- entry
def add_arguments(parser) -> None:
    parser.add_argument("--scenes", default="p8,p25", help="comma-separated subset of p8,p25 (default both)")
    parser.add_argument("--options", default=",".join(OPTIONS),
                        help=f"extraction options (comma-separated subset of {', '.join(OPTIONS)})")
    parser.add_argument("--options-p25", default=None, help="extraction options on P25 (default: --options)")
    parser.add_argument("--runs", type=int, default=3, help="rounds on P8 (alternating order; default 3)")
    parser.add_argument("--runs-p25", type=int, default=1, help="rounds on P25 (default 1)")
    parser.add_argument("--mappers", default="incremental,global", help="mapper study: mappers ('' = none)")
    parser.add_argument("--caps", default="0,500,1000,2000", help="mapper study: inliers per pair (0 = all)")
    parser.add_argument("--mapper-options", default="opencv,colmap",
                        help="mapper study: the extraction options whose last databases are mapped")
    parser.add_argument("--out", default="benchmarks/results/extract", help="folder of extract.json/.md/.png")
    parser.add_argument("--work", default=None, help="databases and models (default: a temp folder, kept)")
    parser.add_argument("--render", default=None, metavar="JSON",
                        help="only rewrite extract.md / extract.png in --out from an existing extract.json")
    parser.add_argument("--data", default=None, help="data root (default GUIDEDMATCH_DATA or ../shared/data)")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "_step":
        return _step(argv[1:])
    p = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.bench_extract", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    if args.render:
        res = json.loads(Path(args.render).read_text())
        write_report(res, Path(args.out))
        print(options_table(res["table"]))
        return 0
    from ..datasets import data_root
    from ..errors import ConfigError, InputError
    from .meta import run_metadata
    from .poses import read_strecha_cameras

    scenes = [s for s in args.scenes.split(",") if s]
    options = [o for o in args.options.split(",") if o]
    options_p25 = [o for o in (args.options_p25 or args.options).split(",") if o]
    mappers = [m for m in args.mappers.split(",") if m]
    caps = [int(c) for c in args.caps.split(",") if c]
    bad = [s for s in scenes if s not in SCENES] + [o for o in options + options_p25 if o not in OPTIONS] + \
        [m for m in mappers if m not in MAPPERS]
    if bad:
        raise ConfigError(f"unknown scene / option / mapper: {bad}")
    root = data_root(args.data)
    if root is None:
        raise InputError("no data folder found (set GUIDEDMATCH_DATA or pass --data)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import tempfile

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="gm_bench_extract_"))
    res = {"meta": run_metadata(0), "command": "python -m guidedmatch.evaluation.bench_extract " + " ".join(argv),
           "work": str(work), "options": {o: OPTIONS[o] for o in dict.fromkeys(options + options_p25)}, "cap": CAP, "rows": [], "mappers": [],
           "load_before_round": [], "errors": []}
    from .bench_sfm import warm_up

    for scene in scenes:
        image_dir, gt_dir = root / SCENES[scene][0], root / SCENES[scene][1]
        gt = read_strecha_cameras(gt_dir)
        runs = args.runs if scene == "p8" else args.runs_p25
        scene_options = options if scene == "p8" else options_p25
        for r in range(max(1, runs)):
            order = scene_options if r % 2 == 0 else scene_options[::-1]
            res["load_before_round"].append(os.getloadavg()[0])
            for option in order:
                _say(f"[{scene}] round {r + 1}/{runs}: {option} (load {os.getloadavg()[0]:.1f})")
                if option != "colmap" and not res.get("warm"):   # Numba kernels compiled once, outside the timing
                    tmp = work / "warm"
                    tmp.mkdir(parents=True, exist_ok=True)
                    from ..extraction import ExtractionConfig, extract_to_database
                    from ..sfm import list_images

                    extract_to_database(image_dir, tmp / "warm.db", ExtractionConfig(progress=False, max_features=3000),
                                        image_names=list_images(image_dir)[:2])
                    warm_up(tmp / "warm.db")
                    res["warm"] = True
                try:
                    row = run_option(option, image_dir, gt, work / scene / f"round{r}")
                except RuntimeError as exc:   # a failed step: recorded, the other rows still run
                    res["errors"].append({"scene": scene, "round": r, "option": option, "error": str(exc)[-1000:]})
                    _say(f"    failed: {str(exc)[-300:]}")
                    continue
                row.update(scene=scene, round=r, load_1min=os.getloadavg()[0])
                res["rows"].append(row)
                _say(f"    total {row['total_s']:.1f} s (extraction {row['extraction_s']:.1f}, matching "
                     f"{row['matching_s']:.1f}, mapping {row['mapping_s']:.1f}), {row['registered']} registered, "
                     f"median {row['median_pose_error_deg']:.3f} deg, AUC@1 {row['auc']['1']:.3f}")
                write_report(res, out)
        last = work / scene / f"round{max(1, runs) - 1}"
        for option in [o for o in args.mapper_options.split(",") if o in scene_options]:
            if mappers:
                _say(f"[{scene}] mapper study on {option}")
                for row in run_mappers(option, image_dir, gt, last, mappers, caps if option != "colmap" else [0]):
                    row["scene"] = scene
                    res["mappers"].append(row)
                    write_report(res, out)
    write_report(res, out)
    print(options_table(res["table"]))
    if res["mappers"]:
        print(mappers_table(res["mappers"]))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
