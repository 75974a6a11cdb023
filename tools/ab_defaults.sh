#!/bin/bash
# tools/ab_defaults.sh SCENE ROUNDS: alternate old defaults / new defaults / COLMAP exhaustive on fresh copies of the scene's features
F=~/.cache/guidedmatch/accuracy/$1/features.db
PY=/work/main/.venv/bin/python
for r in $(seq 1 $2); do
 for v in old new colmap; do
  rm -f /tmp/ab3.db*; cp $F /tmp/ab3.db
  l1=$(cut -d' ' -f1 /proc/loadavg); st1=$(awk '/^cpu /{print $9}' /proc/stat)
  s=$(date +%s.%N)
  case $v in
   old) $PY -m guidedmatch.cli colmap /tmp/ab3.db --no-progress --log none --no-second-look --config frame_check=false > /tmp/ab3_$v.log 2>&1;;
   new) $PY -m guidedmatch.cli colmap /tmp/ab3.db --no-progress --log none > /tmp/ab3_$v.log 2>&1;;
   colmap) $PY -c "
import pycolmap,sys
o=pycolmap.FeatureMatchingOptions(); o.num_threads=2
pycolmap.match_exhaustive('/tmp/ab3.db', matching_options=o, device=pycolmap.Device.cpu)" > /tmp/ab3_$v.log 2>&1;;
  esac
  e=$(date +%s.%N); st2=$(awk '/^cpu /{print $9}' /proc/stat)
  echo "$1 $v round $r: $(echo "$e - $s" | bc | cut -c1-6) s (load $l1, steal ticks $((st2-st1))); $(grep -h 'second look' /tmp/ab3_$v.log | cut -c1-60)"
 done
done
