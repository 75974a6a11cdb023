#!/bin/bash
# Pose accuracy over draws of the approximate neighbours (accuracy history, twenty-first round): for each scene and
# k-means seed, a copy of an accuracy cache's scene (features, COLMAP's matches and models, retime.json) whose `ours`
# database is matched by tools/kmeans_draw.py, then `guidedmatch bench accuracy` maps it with 3 mapper seeds.
#   bash tools/kmeans_draws.sh CACHE OUTROOT "Herz-Jesus-P8 Herz-Jesus-P25 buddha" "1 2"
set -e
CACHE=$1; OUT=$2; SCENES=$3; SEEDS=$4
for scene in $SCENES; do
 for seed in $SEEDS; do
  C=$OUT/km_${scene}_$seed
  rm -rf "$C"; mkdir -p "$C/$scene/ours"
  cp "$CACHE/$scene"/{features.db,extract.json,scene.json,retime.json} "$C/$scene/"; cp -r "$CACHE/$scene/colmap" "$C/$scene/"
  cp "$C/$scene/features.db" "$C/$scene/ours/database.db"
  python tools/kmeans_draw.py "$C/$scene/ours/database.db" kmeans "$seed" > "$C/match.out" 2>&1
  v=$(python -c "import sqlite3,sys; print('|'.join(map(str, sqlite3.connect(sys.argv[1]).execute('select count(*), sum(rows) from two_view_geometries where rows>0').fetchone())))" "$C/$scene/ours/database.db")
  python -c "import json,sys; p,i=sys.argv[1].split('|'); json.dump({'method':'ours','match_s':0.0,'command':'tools/kmeans_draw.py kmeans $seed (time not measured)','load':0.0,'verified_pairs':int(p),'verified_inliers':int(i)}, open(sys.argv[2],'w'))" "$v" "$C/$scene/ours/match.json"
  guidedmatch bench accuracy --scenes "$scene" --methods colmap,ours --seeds 0,1,2 --repeats 3 --cache "$C" --out "$C/out" > "$C/bench.log" 2>&1
 done
done
