#!/bin/bash
# usage: tools/ab_hugepages.sh SCENE [ROUNDS] -- alternating: ours (huge pages, default) / ours GUIDEDMATCH_HUGEPAGES=0 / COLMAP match_exhaustive, on copies of a scene's features
S=$1; R=${2:-2}
F=${ACC_CACHE:-$HOME/.cache/guidedmatch/accuracy}/$S/features.db
PY=${PY:-python}
for r in $(seq 1 $R); do
 for who in ours ours_nohp colmap; do
  rm -f ${TMPDIR:-/tmp}/ab_hugepages.db*; cp $F ${TMPDIR:-/tmp}/ab_hugepages.db
  s=$(date +%s.%N)
  if [ $who = ours ]; then $PY -m guidedmatch.cli colmap ${TMPDIR:-/tmp}/ab_hugepages.db --no-progress --log none > /dev/null 2>&1
  elif [ $who = ours_nohp ]; then GUIDEDMATCH_HUGEPAGES=0 $PY -m guidedmatch.cli colmap ${TMPDIR:-/tmp}/ab_hugepages.db --no-progress --log none > /dev/null 2>&1
  else $PY -c "import sys, pycolmap
mo = pycolmap.FeatureMatchingOptions(); mo.num_threads = 2; mo.use_gpu = False
pycolmap.match_exhaustive(sys.argv[1], matching_options=mo, device=pycolmap.Device.cpu)" ${TMPDIR:-/tmp}/ab_hugepages.db > /dev/null 2>&1; fi
  e=$(date +%s.%N); echo "$S round $r $who $(echo "$e - $s" | bc) s load $(cut -d' ' -f1 /proc/loadavg)"
 done
done
