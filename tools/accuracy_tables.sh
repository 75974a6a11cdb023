#!/bin/bash
# Rebuild benchmarks/results/accuracy from the accuracy cache (nothing is computed; run the bench first)
cd "$(dirname "$0")/.."
export PYTHONPATH=$PWD/src
PY=${PYTHON:-python}
rm -f benchmarks/results/accuracy/accuracy.json
$PY -m guidedmatch.evaluation.bench_accuracy --scenes Herz-Jesus-P8 --seeds 0 --cached-only --methods colmap,ours-added,ours-f1,ours-scale,ours-epi1,ours-contra
$PY -m guidedmatch.evaluation.bench_accuracy --scenes Herz-Jesus-P25,buddha --seeds 0 --cached-only --methods colmap,ours,ours+cap,ours+rejected,ours+rescue,ours-added,ours-f1,colmap+added,ours-epi,ours-3view,ours-contra,ours-scale,ours+rejected-scale,ours@max_unguided=0.1
$PY -m guidedmatch.evaluation.bench_accuracy --scenes Herz-Jesus-P8 --seeds 0,1,2 --repeats 3 --cached-only --methods colmap,ours,ours+cap
$PY -m guidedmatch.evaluation.accuracy_analysis --scenes Herz-Jesus-P8,Herz-Jesus-P25,buddha
