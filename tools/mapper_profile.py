"""Where COLMAP's incremental mapper spends its time on a database: its bundle adjustments, stage by stage.

Runs ``pycolmap.incremental_mapping`` (2 threads, seed 0) on a *copy* of each database with COLMAP's verbose log
captured, and prints, per database: the wall and CPU time, the model (registered images, points, observations), and
every bundle adjustment in order -- after which registration or retriangulation it ran, its residuals, iterations,
time and whether Ceres converged or stopped at the iteration cap -- then the totals by kind.

    python tools/mapper_profile.py /tmp/sfm_bench/final/work/8192/so_epi_ia_ours/database.db \\
        /tmp/sfm_bench/final/work/8192/colmap/database.db --images $GUIDEDMATCH_DATA/pose_pairs/strecha/Herz-Jesus-P8/images

Measured on Herz-Jesus-P8 (2026-12-01) at 8192 features, two runs each: our database (39,447 observations in the
model) mapped in 6.2 / 7.5 s (8.7 / 10.5 s CPU), 4.8 / 5.6 s of it in bundle adjustments; COLMAP's (29,454) in
4.9 / 5.2 s (5.2 / 5.5 s CPU), 3.7 / 3.7 s. The first local adjustment after each registration stopped at the
25-iteration cap for all 6 of our registrations and for 3 of COLMAP's 6: more residuals per adjustment, and more
adjustments that run to the cap (ours 7 adjustments, 207 iterations, 3.1-3.7 s; COLMAP's 4, 129, 1.5 s).
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

_RUN = r"""
import os, sys, time, pycolmap
db, images, out = sys.argv[1:4]
pycolmap.logging.logtostderr = True
pycolmap.logging.minloglevel = 0
pycolmap.logging.verbose_level = 2
opts = pycolmap.IncrementalPipelineOptions()
opts.num_threads = 2
opts.random_seed = 0
t, c = time.perf_counter(), time.process_time()
recs = pycolmap.incremental_mapping(db, images, out, options=opts)
wall, cpu = time.perf_counter() - t, time.process_time() - c
best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
print("RESULT", wall, cpu, *(0, 0, 0) if best is None else
      (best.num_reg_images(), best.num_points3D(), best.compute_num_observations()), file=sys.stderr)
"""

_EVENT = re.compile(r"(Registering initial image pair #\d+ and #\d+|Registering image #\d+|"
                    r"Retriangulation and Global bundle adjustment|Global bundle adjustment$)|"
                    r"(Bundle adjustment|Pose refinement) report\s+Residuals : (\d+)\s+Parameters : \d+\s+"
                    r"Iterations : (\d+)\s+Time : ([\d.e+-]+) \[s\].*?Termination : (\w+)", re.S | re.M)


def profile(db: Path, images: Path) -> dict:
    """Map a copy of ``db``; the parsed log."""
    with tempfile.TemporaryDirectory(prefix="mapper_profile_") as tmp:
        copy = Path(tmp) / "database.db"
        shutil.copy(db, copy)
        (Path(tmp) / "sparse").mkdir()
        r = subprocess.run([sys.executable, "-c", _RUN, str(copy), str(images), str(Path(tmp) / "sparse")],
                           capture_output=True, text=True)
    if r.returncode != 0 or "RESULT" not in r.stderr:
        raise SystemExit(f"mapping {db} failed:\n{r.stderr[-2000:]}")
    res = r.stderr.rsplit("RESULT", 1)[1].split()
    stage, rows = "", []
    for m in _EVENT.finditer(r.stderr):
        if m.group(1):
            stage = m.group(1)
        elif m.group(2) == "Bundle adjustment":
            rows.append(dict(stage=stage, residuals=int(m.group(3)), iterations=int(m.group(4)),
                             time_s=float(m.group(5)), termination=m.group(6)))
    return dict(wall_s=float(res[0]), cpu_s=float(res[1]), registered=int(res[2]), points=int(res[3]),
                observations=int(res[4]), adjustments=rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("databases", nargs="+", type=Path)
    p.add_argument("--images", type=Path,
                   default=Path(os.environ.get("GUIDEDMATCH_DATA", "../shared/data")) /
                   "pose_pairs/strecha/Herz-Jesus-P8/images")
    a = p.parse_args(argv)
    for db in a.databases:
        out = profile(db, a.images)
        print(f"\n{db}: mapping {out['wall_s']:.2f} s ({out['cpu_s']:.2f} s CPU), {out['registered']} images, "
              f"{out['points']:,} points, {out['observations']:,} observations")
        for row in out["adjustments"]:
            print(f"  {row['stage'][:46]:46s} residuals {row['residuals']:7d}  iterations {row['iterations']:3d}  "
                  f"{row['time_s']:6.3f} s  {row['termination']}")
        for term in sorted({r["termination"] for r in out["adjustments"]}):
            sel = [r for r in out["adjustments"] if r["termination"] == term]
            print(f"  {term}: {len(sel)} adjustments, {sum(r['iterations'] for r in sel)} iterations, "
                  f"{sum(r['time_s'] for r in sel):.2f} s")
        print(f"  all bundle adjustments: {sum(r['time_s'] for r in out['adjustments']):.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
