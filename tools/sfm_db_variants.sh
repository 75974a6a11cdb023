#!/bin/bash
# tools/sfm_db_variants.sh TAG [guidedmatch colmap flags...]: in the current folder, match a copy of feat.db (a database with
# features only, e.g. guidedmatch sfm's database with its matches and geometries deleted) with `guidedmatch colmap
# --max-inliers-per-pair 1000 FLAGS`, map it (guidedmatch map, incremental, seed 0) and score it against Herz-Jesus-P8's GT.
export GUIDEDMATCH_DATA=${GUIDEDMATCH_DATA:-../shared/data}   # run with the venv active
T=$1; shift
rm -rf $T; mkdir $T; cp feat.db $T/db.db
guidedmatch colmap $T/db.db --max-inliers-per-pair 1000 --no-progress --log none "$@" > $T/colmap.out 2>&1
guidedmatch map $T/db.db $GUIDEDMATCH_DATA/pose_pairs/strecha/Herz-Jesus-P8/images $T/sparse > $T/map.out 2>&1
python - $T <<'PY'
import sys, pycolmap
from pathlib import Path
from guidedmatch.evaluation.bench_sfm import read_strecha_cameras
from guidedmatch.evaluation.poses import evaluate_poses, poses_from_reconstruction
import os
T=sys.argv[1]; scene=Path(os.environ['GUIDEDMATCH_DATA'])/'pose_pairs/strecha/Herz-Jesus-P8'
gt=read_strecha_cameras(scene/'gt_dense_cameras')
best=max((pycolmap.Reconstruction(str(d)) for d in Path(T,'sparse').iterdir() if d.name.isdigit()), key=lambda r: r.num_reg_images())
ev=evaluate_poses(poses_from_reconstruction(best), gt)
import sqlite3
con=sqlite3.connect(f'{T}/db.db'); vi=con.execute('select count(*), sum(rows) from two_view_geometries where rows>0').fetchone()
print(T, 'reg', best.num_reg_images(), 'median %.3f'%ev.median_error_deg, 'auc', {k: round(v,3) for k,v in ev.auc.items()}, 'verified', vi)
PY
