"""The large collection's models: COLMAP's mapper on every method's database, the models judged by scene, and the
whole ``photos -> model`` pipelines (``guidedmatch sfm`` vs pycolmap's) -- the second half of
:mod:`guidedmatch.evaluation.bench_large`.

* :func:`map_method`: ``pycolmap.incremental_mapping`` (``guidedmatch.sfm.run_mapping``, seed 0, 2 threads) on a
  method's matched database, a fresh timed process, cached as ``WORK/<method>.map.json`` + ``WORK/<method>.sparse``;
* :func:`judge_models`: every model's images by scene: models that mix scenes (any two scene labels in one model --
  every Unsplash photo is a scene of its own), registered images per scene (the scene's largest model), and pose
  accuracy per scene with reference poses (:data:`POSE_SCENES`: relative pose errors over all pairs of the scene's
  images, as ``guidedmatch bench accuracy`` measures them; Herz-Jesus-P8 against its own ground truth);
* :func:`run_sfm`: ``guidedmatch sfm`` on the 220 images (a folder of symbolic links to the data, read in place,
  giving the images the same names), a fresh timed process, its report (stage times, peak memory) cached as
  ``WORK/sfm_ours/``.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from .bench_collection import THREADS, _timed

#: scene label -> (image name prefix in the collection, scene of :mod:`accuracy_scenes` with the reference poses)
POSE_SCENES = {
    "Herz-Jesus-P25": [("collections/Herz-Jesus-P25/images/", "Herz-Jesus-P25"),
                       ("pose_pairs/strecha/Herz-Jesus-P8/images/", "Herz-Jesus-P8")],
    "buddha": [("collections/buddha/images/", "buddha")],
    "fox": [("collections/fox/images/", "fox")],
}

MAP_CODE = """
import json, sys
from guidedmatch.sfm import run_mapping
r = run_mapping(sys.argv[1], sys.argv[2], sys.argv[3], num_threads={threads}, seed=0)
print(json.dumps(dict(time_s=r["time_s"], models=[m["registered_names"] for m in r["models"]],
                      points=[m["points3D"] for m in r["models"]])))
"""


_WARM: dict = {}


def warm_up(work: Path) -> float:
    """Run ``guidedmatch colmap`` once, untimed, on one pair of a scratch copy of the features, so that our timed
    runs load the matcher's compiled kernels from Numba's on-disk cache (a first-ever run compiles them once, as
    ``benchmarks/results/startup`` measures); returns its wall seconds (0 when already done in this process)."""
    if "s" in _WARM:
        return 0.0
    scratch, pairs = work / "warmup.db", work / "warmup_pairs.txt"
    shutil.copyfile(work / "features.db", scratch)
    names = json.loads((work / "features.json").read_text())["names"][:2]
    pairs.write_text(f"{names[0]} {names[1]}\n")
    print("[bench large] warm-up (one pair, untimed: Numba's on-disk cache) ...", file=sys.stderr, flush=True)
    r = _timed([sys.executable, "-m", "guidedmatch.cli", "colmap", str(scratch), "--pairs", str(pairs),
                "--no-progress", "--log", "none"])
    for q in work.glob("warmup*"):
        q.unlink()
    _WARM["s"] = r["wall_s"]
    return r["wall_s"]


def map_method(work: Path, method: str, image_dir: Path, rerun: bool = False) -> dict:
    """COLMAP's incremental mapper on ``WORK/<method>.db`` (module doc); cached."""
    res, sparse = work / f"{method}.map.json", work / f"{method}.sparse"
    if res.exists() and sparse.exists() and not rerun:
        return dict(json.loads(res.read_text()), reused=True)
    print(f"[bench large] mapping {method} ...", file=sys.stderr, flush=True)
    load0 = os.getloadavg()
    r = _timed([sys.executable, "-c", MAP_CODE.format(threads=THREADS), str(work / f"{method}.db"), str(image_dir),
                str(sparse)])
    inner = json.loads(r["stdout_tail"][-1])
    out = dict(method=method, wall_s=r["wall_s"], cpu_s=r["cpu_s"], map_s=inner["time_s"], models=inner["models"],
               points=inner["points"], load_before=load0, load_after=os.getloadavg())
    res.write_text(json.dumps(out))
    return dict(out, reused=False)


def judge_models(models: list[list[str]], sparse: Path, scenes: dict, data: Path) -> dict:
    """Models by scene (module doc): ``{"models", "mixed": [...], "registered": {scene: n}, "scene_images":
    {scene: n}, "poses": {scene: {median_error_deg, auc, registered, images}}}``."""
    import pycolmap

    from .accuracy_scenes import reference_cameras
    from .poses import evaluate_poses, poses_from_reconstruction

    per_model = []
    for names in models:
        count: dict = {}
        for n in names:
            count[scenes[n]] = count.get(scenes[n], 0) + 1
        per_model.append(count)
    mixed = [dict(model=i, scenes=c) for i, c in enumerate(per_model) if len(c) > 1]
    all_scenes = sorted(set(scenes.values()))
    total = {s: sum(v == s for v in scenes.values()) for s in all_scenes}
    best = {s: max(range(len(per_model)), key=lambda i: per_model[i].get(s, 0), default=None) for s in all_scenes}
    registered = {s: (per_model[best[s]].get(s, 0) if best[s] is not None else 0) for s in all_scenes}
    poses = {}
    for scene, parts in POSE_SCENES.items():
        if best.get(scene) is None or registered.get(scene, 0) < 2:
            poses[scene] = dict(registered=registered.get(scene, 0), images=total.get(scene, 0),
                                median_error_deg=float("inf"), auc={"1": 0.0, "2": 0.0, "5": 0.0})
            continue
        rec = pycolmap.Reconstruction(str(sparse / str(best[scene])))
        est = poses_from_reconstruction(rec)
        for prefix, ref_scene in parts:
            ref = reference_cameras(data, ref_scene)
            mine = {n[len(prefix):]: p for n, p in est.items() if n.startswith(prefix)}
            ev = evaluate_poses(mine, ref)
            poses[ref_scene] = dict(registered=ev.num_registered, images=ev.num_images,
                                    median_error_deg=ev.median_error_deg, auc=ev.auc)
    return dict(models=len(models), mixed=mixed, registered=registered, scene_images=total, poses=poses)


def image_links(data: Path, names: list[str], folder: Path) -> Path:
    """A folder of symbolic links ``folder/<name> -> data/<name>`` (the data read in place, the names kept)."""
    for n in names:
        link = folder / n
        if not link.is_symlink():
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to((data / n).resolve())
    return folder


def sfm_tag(mapper: str) -> str:
    """The cache name of a ``guidedmatch sfm`` run with ``mapper`` (incremental keeps the first rounds' name)."""
    return "sfm_ours" if mapper == "incremental" else f"sfm_ours_{mapper}"


def run_sfm(data: Path, work: Path, names: list[str], rerun: bool = False, extra: tuple = (),
            mapper: str = "incremental") -> dict:
    """``guidedmatch sfm --mapper MAPPER`` from an empty project on the collection (module doc); cached."""
    tag = sfm_tag(mapper)
    out, res = work / tag, work / f"{tag}.json"
    if res.exists() and (out / "report.json").exists() and not rerun:
        return dict(json.loads(res.read_text()), reused=True)
    if out.exists():
        shutil.rmtree(out)
    images = image_links(data, names, work / "images")
    warm_up(work)  # Numba's on-disk cache, as for the matching rows
    print(f"[bench large] guidedmatch sfm --mapper {mapper} ...", file=sys.stderr, flush=True)
    load0 = os.getloadavg()
    extra = ("--mapper", mapper, *extra)
    r = _timed([sys.executable, "-m", "guidedmatch.cli", "sfm", str(images), str(out), "--quiet", *extra])
    report = json.loads((out / "report.json").read_text())
    row = dict(method=tag, wall_s=r["wall_s"], cpu_s=r["cpu_s"], load_before=load0,
               load_after=os.getloadavg(), command=f"guidedmatch sfm IMAGES OUT --quiet {' '.join(extra)}".strip(),
               report=report)
    res.write_text(json.dumps(row))
    return dict(row, reused=False)


def sfm_models(row: dict, work: Path, mapper: str = "incremental") -> tuple[list[list[str]], Path]:
    """The models' image lists (largest first) and the sparse folder of a :func:`run_sfm` row."""
    models = [m["registered_names"] for m in row["report"]["stages"]["mapping"].get("models", [])]
    return models, work / sfm_tag(mapper) / "sparse"


def models_section(data: Path, work: Path, names: list[str], scenes: dict, rows: dict, map_methods, sfm: bool,
                   rerun=(), sfm_mappers=("incremental",)) -> dict:
    """Map every method of ``map_methods`` that has a database, judge the models, and run ``guidedmatch sfm`` when
    ``sfm``; returns ``{"maps": {method: map row + judged models}, "pipelines": {...}}``."""
    maps = {}
    for m in map_methods:
        if not (work / f"{m}.db").exists():
            continue
        r = map_method(work, m, data, rerun=m in rerun)
        r["judged"] = judge_models(r["models"], work / f"{m}.sparse", scenes, data)
        maps[m] = r
    pipelines = {}
    ext = json.loads((work / "features.json").read_text()) if (work / "features.json").exists() else {}
    for m in ("colmap_exhaustive", "colmap_vocabtree"):
        if m in rows and m in maps and ext:
            parts = dict(extraction=ext["wall_s"], matching=rows[m]["wall_s"], mapping=maps[m]["wall_s"])
            pipelines[f"pycolmap ({m.split('_')[1]})"] = dict(parts, total=sum(parts.values()),
                                                              judged=maps[m]["judged"])
    for mapper in sfm_mappers if sfm else ():
        r = run_sfm(data, work, names, rerun=sfm_tag(mapper) in rerun, mapper=mapper)
        models, sparse = sfm_models(r, work, mapper)
        st = r["report"]["stages"]
        pipelines["guidedmatch sfm" + ("" if mapper == "incremental" else f" ({mapper} mapper)")] = dict(
            extraction=st["extraction"]["time_s"], matching=st["matching"]["time_s"], mapping=st["mapping"]["time_s"],
            total=r["wall_s"], peak_rss_mb=r["report"]["peak_rss_mb"],
            peak_rss_by_stage={k: v.get("peak_rss_mb") for k, v in st.items()},
            judged=judge_models(models, sparse, scenes, data), command=r["command"], load_before=r["load_before"])
    return dict(maps=maps, pipelines=pipelines)


def _scene_cells(j: dict) -> str:
    reg = " / ".join(f"{j['registered'].get(s, 0)}/{j['scene_images'].get(s, 0)}"
                     for s in ("Herz-Jesus-P25", "buddha", "fox", "lund"))
    pose = " / ".join(f"{p['median_error_deg']:.3f}° {p['auc']['1']:.3f}" if p["registered"] >= 2 else "-"
                      for p in (j["poses"].get(s, {"registered": 0}) for s in ("Herz-Jesus-P8", "Herz-Jesus-P25",
                                                                                  "buddha", "fox")))
    return f"{j['models']} | {len(j['mixed'])} | {reg} | {pose}"


def models_markdown(sec: dict) -> str:
    """The models table (one row per mapped method) and the photos -> model table."""
    lines = ["", "## Models (COLMAP's incremental mapper, seed 0)", "",
             "Registered per scene = images of the scene in its largest model (Herz-Jesus-P25 with the 8 P8 images, "
             "of 33). Pose: median relative pose error and AUC@1° over all image pairs of the scene, against the "
             "reference poses (P8, P25: ground truth; buddha: the authors' SfM; fox: COLMAP's, favouring COLMAP).", "",
             "| method | mapping s | models | models mixing scenes | registered P25+P8 / buddha / fox / lund | "
             "pose P8 / P25 / buddha / fox (median, AUC@1°) |", "|---|---|---|---|---|---|"]
    for m, r in sec["maps"].items():
        lines.append(f"| {m} | {r['wall_s']:.0f} | {_scene_cells(r['judged'])} |")
    if sec["pipelines"]:
        lines += ["", "## Photos -> model", "",
                  "pycolmap rows: the stages above in fresh processes, summed (COLMAP SIFT extraction + matching + "
                  "mapper); guidedmatch sfm: one process from an empty project (its own OpenCV SIFT extraction, "
                  "`--pairs auto`, the mapper).", "",
                  "| pipeline | total s | x pycolmap exhaustive | x pycolmap vocabtree | extraction | matching | mapping | "
                  "peak memory MB | models | mixing | registered P25+P8 / buddha / fox / lund | pose P8 / P25 / buddha / "
                  "fox |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        base = sec["pipelines"].get("pycolmap (exhaustive)", {}).get("total")
        vt = sec["pipelines"].get("pycolmap (vocabtree)", {}).get("total")
        for name, p in sec["pipelines"].items():
            x = f"{p['total'] / base:.3f}" if base else ""
            xv = f"{p['total'] / vt:.3f}" if vt else ""
            lines.append(f"| {name} | {p['total']:.0f} | {x} | {xv} | {p['extraction']:.0f} | {p['matching']:.0f} | "
                         f"{p['mapping']:.0f} | {p.get('peak_rss_mb', '')} | {_scene_cells(p['judged'])} |")
    return "\n".join(lines) + "\n"
