# The rendered 5-view scene (make_multiview seed N): COLMAP SIFT, then COLMAP's matcher and ours (old defaults,
# scale check, scale check + second look), each mapped with one self-calibrated camera per image.
# python tools/rendered_calibration.py /tmp/rfcN N   (writes /tmp/rfcN/{images,features.db,<variant>/})
import subprocess, sys, json, shutil
from pathlib import Path
import numpy as np, pycolmap
from guidedmatch.testing import multiview as mv
from guidedmatch.evaluation.poses import CameraPose, evaluate_poses
root = Path(sys.argv[1]); root.mkdir(parents=True, exist_ok=True)
seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
scene = mv.make_multiview(n_views=5, size=(640, 480), seed=seed, isolated=False)
images = root / "images"
if not images.exists():
    mv.write_views(scene, images)
db0 = root / "features.db"
def cli(*a):
    p = subprocess.run([sys.executable, "-m", "guidedmatch.cli", *map(str, a)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return p.stdout
if not db0.exists():
    cli("extract", images, db0, "--quiet", "--detector", "colmap")
gt = {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)}
variants = [("colmap", None), ("def", []), ("fc", ["--config", "frame_check=true"]), ("fcsl", ["--config", "frame_check=true", "--second-look"])]
for name, extra in variants:
    d = root / name; shutil.rmtree(d, ignore_errors=True); d.mkdir()
    db = d / "database.db"; shutil.copy(db0, db)
    if extra is None:
        o = pycolmap.FeatureMatchingOptions(); o.num_threads = 1
        pycolmap.match_exhaustive(str(db), matching_options=o, device=pycolmap.Device.cpu)
    else:
        cli("colmap", db, "--max-inliers-per-pair", "1000", "--workers", "0", "--no-progress", *extra)
    errs = []
    for th in (1,):
        cli("map", db, images, d / "sparse", "--threads", "1", "--quiet")
        rec = pycolmap.Reconstruction(str(d / "sparse" / "0"))
        ev = evaluate_poses(rec, gt)
        errs.append((ev.num_registered, round(ev.median_error_deg, 3), round(max(r["error_deg"] for r in ev.per_pair), 3)))
    from guidedmatch.sfm import database_pair_stats
    st = database_pair_stats(db) if True else None
    print(seed, name, errs, [(r['inliers']) for r in st], flush=True)
