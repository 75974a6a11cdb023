# After tools/rendered_calibration.py for seeds 0-3: map every variant again with the known intrinsics held fixed.
# python tools/rendered_known_k.py
import sys, shutil, subprocess
from pathlib import Path
import pycolmap
from guidedmatch.testing import multiview as mv
from guidedmatch.evaluation.poses import CameraPose, evaluate_poses
for seed in range(4):
    scene = mv.make_multiview(n_views=5, size=(640, 480), seed=seed, isolated=False)
    gt = {n: CameraPose(R, t) for n, R, t in zip(scene.names, scene.R, scene.t)}
    row = []
    for v in ("colmap", "def", "fc", "fcsl"):
        d = Path(f"/tmp/rfc{seed}/{v}"); db = d / "k.db"; shutil.copy(d / "database.db", db)
        x = pycolmap.Database.open(str(db))
        for cam in x.read_all_cameras():
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [scene.K[0, 0], scene.K[1, 1], scene.K[0, 2] + 0.5, scene.K[1, 2] + 0.5]
            x.update_camera(cam)
        x.close()
        shutil.rmtree(d / "ksparse", ignore_errors=True)
        p = subprocess.run([sys.executable, "-m", "guidedmatch.cli", "map", str(db), f"/tmp/rfc{seed}/images", str(d / "ksparse"), "--threads", "1", "--quiet", "--fixed-intrinsics"], capture_output=True, text=True)
        ev = evaluate_poses(pycolmap.Reconstruction(str(d / "ksparse" / "0")), gt)
        row.append((v, ev.num_registered, round(ev.median_error_deg, 3), round(max(r["error_deg"] for r in ev.per_pair), 2)))
    print(seed, row, flush=True)
