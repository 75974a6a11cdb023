#!/bin/bash
# The mapper's inliers within PX instead of 1.5 on the defaults' databases of 3 k-means draws per scene (accuracy
# history, twenty-first round): each database copied, re-selected with ColmapSink.tighten_inliers(PX), then mapped by
# `guidedmatch bench accuracy` (3 mapper seeds) against the cached COLMAP rows. The source paths below are this
# round's caches (draw 0: the accuracy cache; draws 1-2: tools/kmeans_draws.sh); edit them for yours.
#   bash tools/inlier_px_draws.sh 1.0 "fox buddha Herz-Jesus-P25 Herz-Jesus-P8"
. /work/main/.venv/bin/activate; export GUIDEDMATCH_DATA=/work/shared/data; cd /work/main
PX=$1; SCENES=${2:-fox buddha Herz-Jesus-P25 Herz-Jesus-P8}
for scene in $SCENES; do
 for k in 0 1 2; do
  case "$scene:$k" in
   fox:0) D=/work/bench/acc13/fox;; fox:1) D=/work/bench/acc12/fox;; fox:2) D=/work/bench/probe_kmeans2/fox;;
   *:0) D=/work/bench/acc8/$scene;; *) D=/work/bench/km_${scene}_$k/$scene;;
  esac
  C=/work/bench/px${PX}_${scene}_$k
  rm -rf $C; mkdir -p $C/$scene/ours
  cp /work/bench/acc8/$scene/{features.db,extract.json,scene.json,retime.json} $C/$scene/; cp -r /work/bench/acc8/$scene/colmap $C/$scene/
  cp $D/ours/database.db $C/$scene/ours/database.db
  python - $C/$scene/ours/database.db $PX <<'PY'
import sys, json
from guidedmatch.collection.sinks import ColmapSink
db, px = sys.argv[1], float(sys.argv[2])
with ColmapSink(db, geometry="ours") as s:
    r = s.tighten_inliers(px, refit_below_deg=3.0)
print(json.dumps({k: v for k, v in r.items() if k != "time_s"}))
PY
  v=$(sqlite3 $C/$scene/ours/database.db "select count(*), sum(rows) from two_view_geometries where rows>0")
  python3 -c "import json,sys; p,i=sys.argv[1].split('|'); json.dump({'method':'ours','match_s':0.0,'command':'defaults draw $k, inliers re-selected at $PX px (time not measured)','load':0.0,'verified_pairs':int(p),'verified_inliers':int(i)}, open('$C/$scene/ours/match.json','w'))" "$v"
  guidedmatch bench accuracy --scenes $scene --methods colmap,ours --seeds 0,1,2 --repeats 3 --cache $C --out $C/out > $C/bench.log 2>&1
  echo "$scene $k $(grep '| ours' $C/bench.log | cut -d'|' -f6,7)" >> /work/scratch/r21/px$PX.done
 done
done
echo all >> /work/scratch/r21/px$PX.done
