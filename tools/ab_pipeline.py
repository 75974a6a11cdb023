"""``guidedmatch sfm --pipeline off`` (extraction, then matching) vs ``--pipeline on`` (overlapped), in alternating
fresh processes, each into a fresh output folder: total, extraction, matching, mapping (report.json), peak memory,
the load average (``/proc/loadavg``) before each run, and the pose errors against the Strecha ground truth.

    python tools/ab_pipeline.py --scene p8 --runs 4 --out /tmp/ab_pipeline_p8
    python tools/ab_pipeline.py --scene p25 --runs 1 --out /tmp/ab_pipeline_p25

Round ``i`` runs ``off`` then ``on`` when ``i`` is even and ``on`` then ``off`` when odd (the machine's load drifts;
with more than two ``--settings`` the order rotates by one each round).
Writes ``runs.json`` and ``table.md`` into ``--out`` and prints them. The stage times of an overlapped run: extraction
up to the last image written, matching = what ran after it (``report.json``'s ``pipeline`` block has the rest).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = {"p8": ("pose_pairs/strecha/Herz-Jesus-P8/images", "pose_pairs/strecha/Herz-Jesus-P8/gt_dense_cameras"),
          "p25": ("collections/Herz-Jesus-P25/images", "collections/Herz-Jesus-P25/gt_dense_cameras")}


def one_run(images: Path, gt_dir: Path, out: Path, setting: str, extra: list[str]) -> dict:
    import pycolmap

    from guidedmatch.evaluation.poses import evaluate_poses, read_strecha_cameras

    if out.exists():
        shutil.rmtree(out)
    load = Path("/proc/loadavg").read_text().split()[:3]
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "guidedmatch.cli", "sfm", str(images), str(out), "--pipeline",
                           setting, "--quiet", *extra], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        raise SystemExit(f"run failed ({setting}): {proc.stderr[-2000:]}")
    rep = json.loads((out / "report.json").read_text())
    st = rep["stages"]
    ev = evaluate_poses(pycolmap.Reconstruction(str(out / "sparse" / "0")), read_strecha_cameras(gt_dir))
    pl = rep.get("pipeline", {})
    return dict(setting=setting, load=load, process_wall_s=wall, process_cpu_s=cpu, total_s=rep["total_time_s"],
                extraction_s=st["extraction"]["time_s"], matching_s=st["matching"]["time_s"],
                mapping_s=st["mapping"]["time_s"], peak_rss_mb=rep["peak_rss_mb"], overlapped=pl.get("overlapped"),
                during=pl.get("pairs_matched_during_extraction"), first_pair_s=pl.get("first_pair_s"),
                pairs=st["matching"]["pairs"], verified=st["matching"]["verified_pairs"],
                inliers=st["matching"]["verified_inliers"], registered=ev.num_registered,
                median_pose_error_deg=ev.median_error_deg, auc1=ev.auc.get("1"))


def table(runs: list[dict]) -> str:
    keys = ("total_s", "extraction_s", "matching_s", "mapping_s", "process_wall_s", "process_cpu_s", "peak_rss_mb",
            "median_pose_error_deg")
    lines = ["| run | setting | load (1/5/15 min) | total | extraction | matching | mapping | process wall | process CPU | "
             "peak MB | pairs during extraction | registered | median pose error (deg) | AUC@1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(runs):
        lines.append(f"| {i + 1} | {r['setting']} | {' '.join(r['load'])} | {r['total_s']:.1f} | "
                     f"{r['extraction_s']:.1f} | {r['matching_s']:.2f} | {r['mapping_s']:.1f} | "
                     f"{r['process_wall_s']:.1f} | {r['process_cpu_s']:.1f} | {r['peak_rss_mb']:,.0f} | "
                     f"{r['during'] if r['overlapped'] else '-'} | "
                     f"{r['registered']} | {r['median_pose_error_deg']:.3f} | {r['auc1']:.3f} |")
    lines += ["", "| setting | runs | " + " | ".join(f"median {k}" for k in keys) + " |",
              "|---|---|" + "---|" * len(keys)]
    for s in dict.fromkeys(r["setting"] for r in runs):
        rs = [r for r in runs if r["setting"] == s]
        if rs:
            lines.append(f"| {s} | {len(rs)} | " + " | ".join(f"{statistics.median(r[k] for r in rs):.3f}"
                                                               for k in keys) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="p8")
    ap.add_argument("--runs", type=int, default=3, help="rounds (each one run of off and one of on)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("GUIDEDMATCH_DATA", "data")))
    ap.add_argument("--settings", default="off,on", help="settings compared, in the order of round 0 (rotated by one "
                    "each round)")
    ap.add_argument("--sfm-options", default="", help="more options for guidedmatch sfm, e.g. '--threads 2'")
    args = ap.parse_args(argv)
    images, gt = (args.data / p for p in SCENES[args.scene])
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for i in range(args.runs):
        settings = args.settings.split(",")
        k = i % len(settings)
        order = (settings[k:] + settings[:k]) if len(settings) > 2 else (settings if i % 2 == 0 else settings[::-1])
        for setting in order:
            r = one_run(images, gt, args.out / f"{setting}_{i}", setting, args.sfm_options.split())
            runs.append(r)
            print(json.dumps(r), flush=True)
            (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    text = table(runs)
    (args.out / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
