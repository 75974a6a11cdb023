"""Large multi-scene collection: pair selection and matching of 220 photos vs COLMAP's exhaustive and vocab-tree.

``python -m guidedmatch.evaluation.bench_large [--out benchmarks/results/large] [--work DIR]``

Images (read in place, named by their path relative to the data folder, so names are unique across folders):
``collections/{Herz-Jesus-P25,buddha,fox,lund}/images`` + ``pose_pairs/strecha/Herz-Jesus-P8/images`` +
``photos/unsplash`` -- 220 images, 24,090 pairs. Scenes from ``collections/scenes.txt``; Herz-Jesus-P8 counts as
Herz-Jesus-P25's scene (the same facade); every Unsplash photo is its own scene.

1. one COLMAP database with ``pycolmap.extract_features`` at COLMAP's default SIFT (CPU, 2 threads), extracted once
   into WORK and reused by reruns (``features.json`` lists its image names);
2. every method on a copy of it, as a fresh process (Python start-up and imports in the wall time; before our first
   timed run, one untimed pair fills Numba's on-disk cache, as any run after a user's first does); each method's
   result is cached in WORK (``<method>.json`` + ``<method>.db``) and reused unless ``--rerun METHOD``:

   * ``colmap_exhaustive``: ``pycolmap.match_exhaustive`` (COLMAP's matching and verification defaults);
   * ``colmap_vocabtree``: ``pycolmap.match_vocabtree`` with a tree built by ``pycolmap.VisualIndex`` on this
     collection's own descriptors (favourable to the peer: no downloaded Flickr tree), ``num_images=K``; the tree
     build (``--vt-words`` words from ``--vt-sample`` sampled descriptors) is timed apart from the matching;
   * ``ours_exhaustive``, ``ours_retrieval`` (``--pairs retrieval:K --no-expand``), ``ours_retrieval_expand``
     (``--pairs retrieval:K``, verified expansion on);
3. from each database: pairs tried (our geometry rows / COLMAP's matches rows), pairs verified (a two-view geometry
   with inliers), recall of the reference set, verified across-scene pairs (scene labels).

Reference set of true pairs: COLMAP exhaustive's verified pairs with >= 100 inliers, minus those the scene labels
show to be across scenes (their number is reported).

4. with ``--map METHODS`` (or ``all``): COLMAP's incremental mapper on each of those databases, the models judged by
   scene (models mixing scenes, registered images per scene, pose accuracy per scene with reference poses); with
   ``--sfm``: ``guidedmatch sfm`` from an empty project on the same images, against the pycolmap pipelines (the
   extraction + matching + mapping rows summed) -- :mod:`guidedmatch.evaluation.large_models`.

Writes ``large.json`` (every number + run metadata), ``large.md`` and ``large.png`` (time vs recall). The machine
is shared: times are noisy, ratios within one run are the numbers to read (the load average is recorded).

``--snapshot`` evaluates where the runs stand while they are still running (each method's partial database in WORK):
pairs tried and verified so far, verified across-scene pairs among them, pairs/s and the projected time of the whole
pair list, the reference pairs COLMAP has verified so far and how many of them the retrieval shortlist contains --
``large_snapshot.{json,md,png}``. Methods can run side by side: ``--methods ours_exhaustive`` in one process and
``--methods colmap_scene_pairs`` in another (the same WORK); a final run with every method reuses the cached ones.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sqlite3
import sys
import time
from pathlib import Path

from .bench_collection import THREADS, _env, _timed
from .large_models import warm_up
from .meta import default_cache

FOLDERS = ("collections/Herz-Jesus-P25/images", "collections/buddha/images", "collections/fox/images",
           "collections/lund/images", "pose_pairs/strecha/Herz-Jesus-P8/images", "photos/unsplash")
EXTS = (".jpg", ".jpeg", ".png")
METHODS = ("colmap_exhaustive", "colmap_scene_pairs", "colmap_vocabtree", "ours_exhaustive", "ours_retrieval",
           "ours_retrieval_expand")
REFERENCE_MIN_INLIERS = 100  # COLMAP exhaustive's verified pairs with at least this many inliers are the true pairs
PAIR_ID_BASE = 2147483647
#: k-means iterations (and 1 round) of COLMAP's tree build: its defaults (100 iterations x 3 rounds) on 65,536 words
#: would take hours on 2 shared cores; ours uses 20 iterations too
VT_ITERATIONS = 20


def image_names(data: Path) -> list[str]:
    names = []
    for rel in FOLDERS:
        names += [f"{rel}/{p.name}" for p in sorted((data / rel).iterdir()) if p.suffix.lower() in EXTS]
    return names


def scene_of(data: Path, names: list[str]) -> dict:
    """Scene label of every image (module doc)."""
    labels = {}
    for line in (data / "collections" / "scenes.txt").read_text().splitlines():
        if line.strip():
            rel, scene = line.split()
            labels["collections/" + rel] = scene
    out = {}
    for n in names:
        if n.startswith("pose_pairs/strecha/Herz-Jesus-P8/"):
            out[n] = "Herz-Jesus-P25"
        elif n.startswith("photos/"):
            out[n] = n
        else:
            out[n] = labels[n]
    return out


def extract(data: Path, work: Path) -> dict:
    """WORK/features.db (cached: reused when features.json lists the same images)."""
    names = image_names(data)
    meta = work / "features.json"
    if meta.exists() and (work / "features.db").exists():
        m = json.loads(meta.read_text())
        if m.get("names") == names:
            return dict(m, reused=True)
    tmp = work / "features.tmp.db"
    for p in work.glob("features.tmp.db*"):
        p.unlink()
    code = f"""
import pycolmap, time
o = pycolmap.FeatureExtractionOptions()
o.num_threads = {THREADS}
o.use_gpu = False
t = time.perf_counter()
pycolmap.extract_features({str(tmp)!r}, {str(data)!r}, image_names={names!r}, camera_mode=pycolmap.CameraMode.AUTO,
                          extraction_options=o, device=pycolmap.Device.cpu)
print(time.perf_counter() - t)
"""
    r = _timed([sys.executable, "-c", code])
    os.replace(tmp, work / "features.db")
    m = dict(names=names, extract_s=float(r["stdout_tail"][-1]), wall_s=r["wall_s"])
    meta.write_text(json.dumps(m))
    return dict(m, reused=False)


def _colmap_code(db: Path, method: str, k: int, vt_words: int, vt_sample: int, tree: Path,
                 pairs_file: Path | None = None) -> str:
    head = f"""
import pycolmap, time, json, numpy as np
m = pycolmap.FeatureMatchingOptions()
m.num_threads = {THREADS}
m.use_gpu = False
out = {{}}
"""
    if method == "colmap_exhaustive":
        return head + f"""
t = time.perf_counter()
pycolmap.match_exhaustive({str(db)!r}, matching_options=m, device=pycolmap.Device.cpu)
out["match_s"] = time.perf_counter() - t
print(json.dumps(out))
"""
    if method == "colmap_scene_pairs":
        return head + f"""
po = pycolmap.ImportedPairingOptions(match_list_path={str(pairs_file)!r})
t = time.perf_counter()
pycolmap.match_image_pairs({str(db)!r}, matching_options=m, pairing_options=po, device=pycolmap.Device.cpu)
out["match_s"] = time.perf_counter() - t
print(json.dumps(out))
"""
    return head + f"""
t = time.perf_counter()
d = pycolmap.Database.open({str(db)!r})
ims = d.read_all_images()
rng = np.random.default_rng(0)
per = -(-{vt_sample} // len(ims))
rows = []
for im in ims:
    x = np.asarray(d.read_descriptors(im.image_id).to_float().data, np.float32)
    if len(x) > per:
        x = x[np.sort(rng.choice(len(x), per, replace=False))]
    rows.append(x)
d.close()
x = np.ascontiguousarray(np.concatenate(rows))
vi = pycolmap.VisualIndex.create(128, 64)
bo = pycolmap.VisualIndex.BuildOptions()
bo.num_visual_words = {vt_words}
bo.num_iterations = {VT_ITERATIONS}
bo.num_rounds = 1
bo.num_threads = {THREADS}
vi.build(bo, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, x))
vi.write({str(tree)!r})
out["tree_s"] = time.perf_counter() - t
out["tree_sample"] = int(len(x))
out["tree_words"] = int(vi.num_visual_words())
po = pycolmap.VocabTreePairingOptions(vocab_tree_path={str(tree)!r}, num_images={k})
po.num_threads = {THREADS}
t = time.perf_counter()
pycolmap.match_vocabtree({str(db)!r}, matching_options=m, pairing_options=po, device=pycolmap.Device.cpu)
out["match_s"] = time.perf_counter() - t
print(json.dumps(out))
"""


def db_pairs(db: Path) -> dict:
    """``{"tried": {(a, b)}, "verified": {(a, b): inliers}}`` (names sorted within a pair) of a database."""
    con = sqlite3.connect(Path(db).resolve().as_uri() + "?mode=ro", uri=True)
    try:
        ids = dict(con.execute("SELECT image_id, name FROM images"))

        def pair(pid):
            i2 = int(pid) % PAIR_ID_BASE
            return tuple(sorted((ids[(int(pid) - i2) // PAIR_ID_BASE], ids[i2])))

        geo = {pair(p): int(r) for p, r, c in con.execute("SELECT pair_id, rows, config FROM two_view_geometries")}
        tried = {pair(p) for (p,) in con.execute("SELECT pair_id FROM matches")} | set(geo)
    finally:
        con.close()
    return dict(tried=tried, verified={p: r for p, r in geo.items() if r > 0})


def run_method(method: str, work: Path, k: int, vt_words: int, vt_sample: int, rerun: bool,
               scenes: dict | None = None) -> dict:
    res_path, db = work / f"{method}.json", work / f"{method}.db"
    if res_path.exists() and db.exists() and not rerun:
        return dict(json.loads(res_path.read_text()), reused=True)
    for p in [*work.glob(f"{method}.db*"), *work.glob(f"{method}.tmp.db*")]:  # incl. a killed run's retrieval cache
        p.unlink()
    warm = warm_up(work) if method.startswith("ours") else None
    tmp = work / f"{method}.tmp.db"
    shutil.copyfile(work / "features.db", tmp)
    load0 = os.getloadavg()
    (work / f"{method}.start.json").write_text(json.dumps(dict(unix=time.time(), load=load0)))  # for --snapshot
    if method.startswith("colmap"):
        pf = None
        if method == "colmap_scene_pairs":  # every pair within a scene (names of one scene never contain spaces)
            names = sorted(scenes)
            pf = work / "scene_pairs.txt"
            pf.write_text("".join(f"{a} {b}\n" for i, a in enumerate(names) for b in names[i + 1:]
                                  if scenes[a] == scenes[b]))
        r = _timed([sys.executable, "-c", _colmap_code(tmp, method, k, vt_words, vt_sample, work / "vocabtree.bin",
                                                      pf)])
        inner = json.loads(r["stdout_tail"][-1])
    else:
        log = work / f"{method}.jsonl"
        if log.exists():
            log.unlink()
        spec = "exhaustive" if method == "ours_exhaustive" else f"retrieval:{k}"
        extra = ["--no-expand"] if method == "ours_retrieval" else []
        r = _timed([sys.executable, "-m", "guidedmatch.cli", "colmap", str(tmp), "--pairs", spec, "--no-progress",
                    "--log", str(log), *extra], log)
        inner = dict(stdout=r["stdout_tail"])
        r.pop("spans", None)
        r.pop("pair_match_s", None)
    os.replace(tmp, db)
    out = dict(method=method, wall_s=r["wall_s"], cpu_s=r["cpu_s"], load_before=load0, load_after=os.getloadavg(),
               inner=inner, summary=r.get("summary"), k=k, warmup_s=warm)
    res_path.write_text(json.dumps(out, indent=1))
    return dict(out, reused=False)


def evaluate(rows: dict, work: Path, scenes: dict) -> dict:
    ref_db = work / "colmap_exhaustive.db"
    if not ref_db.exists():  # COLMAP on the same-scene pairs only: the same reference without the across-scene part
        ref_db = work / "colmap_scene_pairs.db"
    ref_all = db_pairs(ref_db)["verified"]
    strong = {p for p, r in ref_all.items() if r >= REFERENCE_MIN_INLIERS}
    across_strong = {p for p in strong if scenes[p[0]] != scenes[p[1]]}
    reference = strong - across_strong
    for m, row in rows.items():
        d = db_pairs(work / f"{m}.db")
        ver = set(d["verified"])
        across = sorted(p for p in ver if scenes[p[0]] != scenes[p[1]])
        row.update(pairs_tried=len(d["tried"]), pairs_verified=len(ver),
                   reference_found=len(reference & ver), recall=len(reference & ver) / max(1, len(reference)),
                   reference_tried=len(reference & d["tried"]),
                   verified_across_scene=len(across), across_examples=[list(p) for p in across[:10]],
                   across_tried=sum(scenes[a] != scenes[b] for a, b in d["tried"]))
        if m.startswith("ours"):
            log = work / f"{m}.jsonl"
            lines = log.read_text().splitlines() if log.exists() else []
            summ = [json.loads(x) for x in lines if '"event": "summary"' in x]
            row["match_s_summed"] = sum(s.get("match_s", 0.0) for s in summ)
    return dict(reference_db=ref_db.name, reference=len(reference), reference_strong=len(strong),
                reference_dropped_across=len(across_strong),
                reference_dropped_examples=[list(p) for p in sorted(across_strong)[:10]],
                min_inliers=REFERENCE_MIN_INLIERS)


def retrieval_share(row: dict) -> dict | None:
    """Retrieval stage time and its share of our matching wall time (from the command's printed summary)."""
    for line in row.get("inner", {}).get("stdout", []):
        if line.startswith("retrieval  :") and " s" in line:
            t = float(line.rsplit(",", 1)[-1].strip().split()[0])
            return dict(retrieval_s=t, share=t / row["wall_s"])
    return None


def markdown(res: dict) -> str:
    ref = res["reference"]
    lines = [f"# Large collection: {res['images']} images, {res['pairs']} pairs ({res['across_pairs']} across scenes)",
             "", f"Reference: {ref['reference']} true pairs = COLMAP exhaustive's verified pairs with >= "
             f"{ref['min_inliers']} inliers ({ref['reference_strong']}) minus {ref['reference_dropped_across']} "
             "across scenes by the labels.", "",
             f"Extraction (once, cached): {res['extraction'].get('extract_s', float('nan')):.0f} s. "
             f"K = {res['k']}. Load average at the start: {res['load_start']}.", "",
             "| method | wall s | x COLMAP exh. | pairs tried | verified | recall | reference tried | verified across "
             "scenes | notes |", "|---|---|---|---|---|---|---|---|---|"]
    base = res["rows"].get("colmap_exhaustive", {}).get("wall_s")
    for m, r in res["rows"].items():
        note = ""
        if m == "colmap_vocabtree":
            i = r["inner"]
            note = (f"tree {i.get('tree_words')} words from {i.get('tree_sample')} descriptors: "
                    f"{i.get('tree_s', 0):.0f} s (in the wall time); matching {i.get('match_s', 0):.0f} s")
        if r.get("retrieval"):
            note = f"retrieval stage {r['retrieval']['retrieval_s']:.1f} s = {100 * r['retrieval']['share']:.1f} %"
        lines.append(f"| {m} | {r['wall_s']:.0f} | {r['wall_s'] / base:.3f} | {r['pairs_tried']} | "
                     f"{r['pairs_verified']} | {100 * r['recall']:.2f} % | {r['reference_tried']} | "
                     f"{r['verified_across_scene']} | {note} |" if base else f"| {m} | {r['wall_s']:.0f} | |")
    return "\n".join(lines) + "\n"


def figure(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for m, r in res["rows"].items():
        ax.scatter(r["wall_s"], 100 * r["recall"], s=40)
        ax.annotate(m, (r["wall_s"], 100 * r["recall"]), fontsize=8, xytext=(4, 4), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("wall time, s (log)")
    ax.set_ylabel("recall of the reference pairs, %")
    ax.set_title(f"{res['images']} images, {res['pairs']} pairs (2 cores, shared)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(data: Path, out: Path, work: Path, k: int, methods, rerun=(), vt_words: int = 4096,
        vt_sample: int = 200_000, note: str = "", map_methods=(), sfm: bool = False,
        sfm_mappers=("incremental",)) -> dict:
    from .meta import run_metadata, write_json

    work.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    ext = extract(data, work)
    names = ext["names"]
    scenes = scene_of(data, names)
    rows = {}
    for m in methods:
        print(f"[bench large] {m} ...", file=sys.stderr, flush=True)
        rows[m] = run_method(m, work, k, vt_words, vt_sample, m in rerun, scenes)
        if m.startswith("ours_retrieval"):
            rows[m]["retrieval"] = retrieval_share(rows[m])
    have_ref = (work / "colmap_exhaustive.db").exists() or (work / "colmap_scene_pairs.db").exists()
    reference = evaluate(rows, work, scenes) if have_ref else {}
    from .large_models import models_section

    models = models_section(data, work, names, scenes, rows, map_methods, sfm, rerun, sfm_mappers)
    n = len(names)
    across = sum(scenes[names[i]] != scenes[names[j]] for i in range(n) for j in range(i + 1, n))
    res = dict(meta=run_metadata(), note=note, images=n, pairs=n * (n - 1) // 2, across_pairs=across, k=k,
               vt_words=vt_words, vt_sample=vt_sample, extraction=ext, reference=reference, rows=rows, models=models,
               load_start=[round(x, 2) for x in load_start], load_end=[round(x, 2) for x in os.getloadavg()],
               command="python -m guidedmatch.evaluation.bench_large " + " ".join(sys.argv[1:]))
    res["extraction"].pop("names", None)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "large.json", res)
    if reference:
        from .large_models import models_markdown

        (out / "large.md").write_text(markdown(res) + models_markdown(models))
        figure(res, out / "large.png")
    return res


def snapshot(data: Path, out: Path, work: Path, k: int) -> dict:
    """Where every method's run stands now (finished or not): pairs tried and verified so far, verified across-scene
    pairs among them, pairs/s since the run started and the projected time of its whole pair list; the reference
    pairs COLMAP's same-scene run has verified so far, and how many of them our retrieval shortlist contains.
    For runs that cannot finish on a crowded machine; the numbers say which runs were unfinished."""
    from .meta import run_metadata, write_json

    names = image_names(data)
    scenes = scene_of(data, names)
    n = len(names)
    now = time.time()
    rows = {}
    for m in METHODS:
        db = work / f"{m}.db" if (work / f"{m}.db").exists() else work / f"{m}.tmp.db"
        start = work / f"{m}.start.json"
        if not db.exists() or not start.exists():
            continue
        d = db_pairs(db)
        ver = set(d["verified"])
        t0 = json.loads(start.read_text())["unix"]
        finished = db.name == f"{m}.db"
        res = json.loads((work / f"{m}.json").read_text()) if finished and (work / f"{m}.json").exists() else {}
        elapsed = res.get("wall_s", now - t0)
        across_tried = sum(scenes[a] != scenes[b] for a, b in d["tried"])
        rows[m] = dict(finished=finished, elapsed_s=elapsed, pairs_tried=len(d["tried"]), pairs_verified=len(ver),
                       across_tried=across_tried, verified_across_scene=sum(scenes[a] != scenes[b] for a, b in ver),
                       across_examples=[[a, b, d["verified"][(a, b)]] for a, b in sorted(ver)
                                        if scenes[a] != scenes[b]][:10],
                       pairs_per_s=len(d["tried"]) / max(elapsed, 1e-9))
        total = {"colmap_exhaustive": n * (n - 1) // 2, "ours_exhaustive": n * (n - 1) // 2,
                 "colmap_scene_pairs": sum(scenes[names[i]] == scenes[names[j]] for i in range(n)
                                           for j in range(i + 1, n))}.get(m)
        if total:
            rows[m].update(pairs_total=total, projected_s=total / max(rows[m]["pairs_per_s"], 1e-9))
    ref = {}
    if "colmap_scene_pairs" in rows:
        db = work / ("colmap_scene_pairs.db" if rows["colmap_scene_pairs"]["finished"] else "colmap_scene_pairs.tmp.db")
        v = db_pairs(db)["verified"]
        refset = {p for p, r in v.items() if r >= REFERENCE_MIN_INLIERS and scenes[p[0]] == scenes[p[1]]}
        ref = dict(reference_so_far=len(refset), colmap_pairs_done=rows["colmap_scene_pairs"]["pairs_tried"])
        for m in ("ours_retrieval_expand", "ours_retrieval"):
            npz = [work / f"{m}{x}.db.retrieval.npz" for x in ("", ".tmp")]
            npz = [p for p in npz if p.exists()]
            if npz:
                import numpy as np

                with np.load(npz[0]) as z:
                    nm = [str(x) for x in z["names"]]
                    short = {tuple(sorted((nm[i], nm[j]))) for i, j in z["pairs"]}
                ref[f"{m}_shortlist_pairs"] = len(short)
                ref[f"{m}_shortlist_contains"] = len(refset & short)
                state = [work / f"{m}{x}.db.expansion.json" for x in ("", ".tmp")]
                state = [p for p in state if p.exists()]
                if state:  # the expansion rounds saved so far (their candidates, matched or not yet)
                    cov, per = set(short), []
                    for r in json.loads(state[0].read_text()).get("rounds", []):
                        cand = {tuple(sorted(p)) for p in r["pairs"]}
                        cov |= cand
                        per.append(dict(candidates=len(cand), capped=r["capped"], contains=len(refset & cov),
                                        across_scene=sum(scenes[a] != scenes[b] for a, b in cand)))
                    ref[f"{m}_rounds"] = per
            if m in rows:
                t = work / (f"{m}.db" if rows[m]["finished"] else f"{m}.tmp.db")
                got = db_pairs(t)
                rows[m]["reference_tried"] = len(refset & got["tried"])
                rows[m]["reference_verified"] = len(refset & set(got["verified"]))
    res = dict(meta=run_metadata(), kind="snapshot", images=n, pairs=n * (n - 1) // 2, k=k, rows=rows, reference=ref,
               load=[round(x, 2) for x in os.getloadavg()], time_utc=time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()))
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "large_snapshot.json", res)
    (out / "large_snapshot.md").write_text(snapshot_markdown(res))
    snapshot_figure(res, out / "large_snapshot.png")
    return res


def snapshot_markdown(res: dict) -> str:
    ref = res["reference"]
    lines = [f"# Large collection, snapshot at {res['time_utc']} UTC (load average {res['load']})", "",
             f"{res['images']} images, {res['pairs']} pairs. Runs marked unfinished were still running: their "
             "numbers cover the pairs done so far; 'projected' = whole pair list / pairs per second so far.", "",
             "| method | finished | elapsed s | pairs tried | verified | across-scene tried | verified across scenes "
             "| pairs/s | projected s (whole list) |", "|---|---|---|---|---|---|---|---|---|"]
    for m, r in res["rows"].items():
        proj = f"{r['projected_s']:.0f} ({r['pairs_total']} pairs)" if "projected_s" in r else ""
        lines.append(f"| {m} | {r['finished']} | {r['elapsed_s']:.0f} | {r['pairs_tried']} | {r['pairs_verified']} | "
                     f"{r['across_tried']} | {r['verified_across_scene']} | {r['pairs_per_s']:.2f} | {proj} |")
    if ref:
        lines += ["", f"Reference pairs found so far (COLMAP, same-scene pairs, >= {REFERENCE_MIN_INLIERS} inliers): "
                  f"{ref['reference_so_far']} in the {ref['colmap_pairs_done']} pairs COLMAP has matched."]
        for m in ("ours_retrieval_expand", "ours_retrieval"):
            if f"{m}_shortlist_pairs" in ref:
                lines.append(f"{m}: the retrieval shortlist ({ref[f'{m}_shortlist_pairs']} pairs, K={res['k']}) "
                             f"contains {ref[f'{m}_shortlist_contains']} of them "
                             f"({100 * ref[f'{m}_shortlist_contains'] / max(1, ref['reference_so_far']):.1f} %).")
                for i, r in enumerate(ref.get(f"{m}_rounds", []), 1):
                    lines.append(f"  + expansion round {i}: {r['candidates']} candidates ({r['across_scene']} across "
                                 f"scenes{', capped' if r['capped'] else ''}): shortlist + rounds contain "
                                 f"{r['contains']} ({100 * r['contains'] / max(1, ref['reference_so_far']):.1f} %).")
                if m in res["rows"] and "reference_tried" in res["rows"][m]:
                    r = res["rows"][m]
                    lines.append(f"  matched so far: {r['reference_tried']} of these reference pairs, "
                                 f"{r['reference_verified']} of them verified.")
    return "\n".join(lines) + "\n"


def snapshot_figure(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = {m: r for m, r in res["rows"].items()}
    fig, ax = plt.subplots(figsize=(6.5, 3.5))
    ax.barh(list(rows), [r["pairs_per_s"] for r in rows.values()], color="tab:blue")
    for i, r in enumerate(rows.values()):
        ax.annotate(f"{r['pairs_tried']} pairs, {r['verified_across_scene']} across-scene verified",
                    (r["pairs_per_s"], i), fontsize=7, xytext=(3, -3), textcoords="offset points")
    ax.set_xlabel("pairs per second so far")
    ax.set_title(f"snapshot {res['time_utc']} UTC, load {res['load'][0]}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=None, help="data folder (default: $GUIDEDMATCH_DATA or ../shared/data)")
    p.add_argument("--out", default="benchmarks/results/large")
    p.add_argument("--work", default=default_cache("large"), help="databases and cached results (not in the repo)")
    p.add_argument("--k", type=int, default=20, help="images per image: our retrieval:K and COLMAP's num_images")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--rerun", default="", help="comma-separated methods to run again instead of reusing")
    p.add_argument("--vt-words", type=int, default=4096, help="visual words of COLMAP's tree built on the collection")
    p.add_argument("--vt-sample", type=int, default=200_000, help="descriptors sampled to build COLMAP's tree")
    p.add_argument("--note", default="")
    p.add_argument("--map", default="", metavar="METHODS",
                   help="methods whose database COLMAP's mapper maps (comma-separated; 'all' = every method run)")
    p.add_argument("--sfm", action="store_true", help="also run guidedmatch sfm from an empty project (photos -> model)")
    p.add_argument("--sfm-mappers", default="incremental", help="--sfm: one run per mapper (comma-separated: "
                   "incremental,global)")
    p.add_argument("--snapshot", action="store_true", help="only evaluate where the (possibly unfinished) runs stand")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.bench_large", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    a = p.parse_args(argv)
    from ..datasets import data_root

    root = data_root(a.data)
    if root is None or not (root / "collections").is_dir():
        p.error(f"no collections/ folder in the data folder {root or a.data or '(none found)'}: pass --data DIR or "
                "set GUIDEDMATCH_DATA")
    a.data = str(root)
    if a.snapshot:
        print(json.dumps(snapshot(Path(a.data), Path(a.out), Path(a.work), a.k), indent=1, default=str))
        return 0
    methods = [m for m in a.methods.split(",") if m]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        p.error(f"unknown methods {bad}; choose from {', '.join(METHODS)}")
    res = run(Path(a.data), Path(a.out), Path(a.work), a.k, methods, rerun=set(a.rerun.split(",")),
              vt_words=a.vt_words, vt_sample=a.vt_sample, note=a.note,
              map_methods=methods if a.map == "all" else [m for m in a.map.split(",") if m], sfm=a.sfm,
              sfm_mappers=[m for m in a.sfm_mappers.split(",") if m])
    if res["reference"]:
        from .large_models import models_markdown

        print(markdown(res) + models_markdown(res["models"]))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
