"""What the inlier cap does to Herz-Jesus-P8's poses, and two ideas to keep the cap's speed without its cost, both
rejected (benchmarks/results/sfm/history.md, "2026-12-06, later"):

1. map on the capped database, then re-triangulate every inlier of the uncapped one with the capped model's poses
   (``pycolmap.triangulate_points``) and bundle-adjust everything (``pycolmap.bundle_adjustment``; loss, filter and
   intrinsics varied);
2. COLMAP mapper options on the uncapped and the capped database.

Usage (PROJECT: ``guidedmatch sfm IMAGES PROJECT --max-inliers-per-pair 0``; GT: a Strecha ``gt_dense_cameras``)::

    python tools/p8_cap_refine.py PROJECT IMAGES GT WORK [--cap 1000] [--seed 0]

Prints one JSON line per variant: median pose error (deg) and AUC@1 against GT, points, seconds.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path


def main() -> None:
    import pycolmap

    from guidedmatch.collection.sinks import cap_two_view_inliers
    from guidedmatch.evaluation.accuracy_scenes import copy_database
    from guidedmatch.evaluation.poses import evaluate_poses, read_strecha_cameras
    from guidedmatch.sfm.stages import run_mapping

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project"), ap.add_argument("images"), ap.add_argument("gt"), ap.add_argument("work")
    ap.add_argument("--cap", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    full, imgs, work = Path(a.project) / "database.db", Path(a.images), Path(a.work)
    gt = read_strecha_cameras(a.gt)
    work.mkdir(parents=True, exist_ok=True)
    capped = work / "capped.db"
    if not capped.exists():
        copy_database(full, capped)
        cap_two_view_inliers(capped, a.cap)

    def ev(rec):
        e = evaluate_poses(rec, gt)
        return {"median_deg": round(e.median_error_deg, 4), "auc1": round(e.auc["1"], 4), "points": rec.num_points3D()}

    def say(name, rec, t0):
        print(json.dumps({"variant": name, **ev(rec), "s": round(time.perf_counter() - t0, 2)}), flush=True)

    def incremental(db, **opts):
        o = pycolmap.IncrementalPipelineOptions()
        o.num_threads, o.random_seed = 2, a.seed
        for k, v in opts.items():
            obj, *path = [o, *k.split("__")]
            for part in path[:-1]:
                obj = getattr(obj, part)
            setattr(obj, path[-1], v)
        out = work / "model"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        recs = pycolmap.incremental_mapping(str(db), str(imgs), str(out), options=o)
        return max(recs.values(), key=lambda r: r.num_reg_images())

    t0 = time.perf_counter()
    r = run_mapping(capped, imgs, work / "capped_model", seed=a.seed, num_threads=2)
    model = work / "capped_model" / "0"
    say(f"capped {a.cap} (incremental)", pycolmap.Reconstruction(str(model)), t0)

    def refine(loss="TRIVIAL", scale=1.0, filt=4.0, intrinsics=True, rounds=2):
        rec = pycolmap.Reconstruction(str(model))
        out = work / "tri"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        rec = pycolmap.triangulate_points(rec, str(full), str(imgs), str(out), clear_points=True,
                                          options=pycolmap.IncrementalPipelineOptions())
        for k in range(rounds):
            bo = pycolmap.BundleAdjustmentOptions()
            bo.print_summary = False
            bo.refine_focal_length = bo.refine_extra_params = intrinsics
            bo.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
            bo.ceres.loss_function_scale = scale
            pycolmap.bundle_adjustment(rec, bo)
            if k + 1 < rounds:
                pycolmap.ObservationManager(rec).filter_all_points3D(filt, 1.5)
        return rec

    for kw in (dict(), dict(filt=2.0), dict(loss="SOFT_L1"), dict(loss="CAUCHY"), dict(loss="CAUCHY", scale=2.0),
               dict(intrinsics=False, rounds=1)):
        t0 = time.perf_counter()
        say("capped model + every inlier re-triangulated + BA " + json.dumps(kw), refine(**kw), t0)
    for opts in (dict(), dict(mapper__filter_max_reproj_error=2.0), dict(ba_global_max_num_iterations=100),
                 dict(triangulation__ignore_two_view_tracks=False), dict(ba_refine_extra_params=False)):
        for name, db in (("uncapped", full), (f"capped {a.cap}", capped)):
            t0 = time.perf_counter()
            say(f"{name}, mapper options {json.dumps(opts)}", incremental(db, **opts), t0)


if __name__ == "__main__":
    main()
