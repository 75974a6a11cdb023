#!/bin/bash
# Capture the behaviour of one checkout for tools/behaviour_hash.py (counts and hashes, never times):
#   tools/behaviour_capture.sh CHECKOUT OUT [FEATURES_DB]
# runs, with CHECKOUT/src first on PYTHONPATH: guidedmatch demo, bench oxford --quick, bench pairs --features 8192
# --repeats 1, and guidedmatch colmap on a copy of FEATURES_DB (a pycolmap extraction of Herz-Jesus-P8, made once
# and shared between the captures to compare; default OUT/../p8_features.db), then the sha256 of its matches and
# two_view_geometries tables. PYTHON: the interpreter to use (default python3). Compare two captures: python tools/behaviour_hash.py OUT_BEFORE OUT_AFTER
set -euo pipefail
REPO=$(cd "$1" && pwd); OUT=$2; FEATURES=${3:-$(dirname "$OUT")/p8_features.db}
DATA=${GUIDEDMATCH_DATA:-$REPO/../shared/data}
export PYTHONPATH=$REPO/src MPLBACKEND=Agg GUIDEDMATCH_DATA=$DATA
PY=${PYTHON:-python3}   # the interpreter of the environment guidedmatch's dependencies are installed in
gm() { "$PY" -m guidedmatch.cli "$@"; }
mkdir -p "$OUT"; OUT=$(cd "$OUT" && pwd); cd "$OUT"
git -C "$REPO" rev-parse HEAD > commit.txt
gm demo > demo.txt 2>&1
gm bench oxford --quick --out "$OUT/oxford" > oxford.log 2>&1
gm bench pairs --features 8192 --out "$OUT/pairs" --repeats 1 > pairs.log 2>&1
if [ ! -f "$FEATURES" ]; then
  "$PY" - "$DATA/pose_pairs/strecha/Herz-Jesus-P8/images" "$FEATURES" <<'PY'
import os, sys, pycolmap
tmp = sys.argv[2] + ".tmp"
pycolmap.extract_features(tmp, sys.argv[1], camera_mode=pycolmap.CameraMode.SINGLE)
os.replace(tmp, sys.argv[2])
PY
fi
cp "$FEATURES" "$OUT/p8.db"
gm colmap "$OUT/p8.db" --no-progress --log none > colmap.log 2>&1
"$PY" - "$OUT/p8.db" > colmap_hash.txt <<'PY'
import hashlib, sqlite3, sys
con = sqlite3.connect(sys.argv[1])
for table in ("matches", "two_view_geometries"):
    h = hashlib.sha256()
    rows = con.execute(f"SELECT * FROM {table} ORDER BY pair_id").fetchall()
    for r in rows:
        h.update(repr(r).encode())
    print(table, len(rows), h.hexdigest())
PY
echo "captured $OUT"
