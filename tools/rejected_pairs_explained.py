"""Why our verdict calls "no overlap" a pair COLMAP's matcher verifies: every such pair of a scene (from
``analysis.json`` of ``python -m guidedmatch.evaluation.accuracy_analysis``) matched again on its own, three ways:

* ``first pass``: the collection's matcher settings, image 1 = the first name (what ``guidedmatch colmap`` did);
* ``swapped``: the same, the other image as image 1;
* ``bf``: every image-1 feature against all of image 2 (no budget) -- the verdict on the complete evidence.

A pair verified by ``bf`` but not by the first pass was starved by the unguided start's budget (the second look's
case); a pair that ``bf`` rejects too is one our verdict rejects on all the evidence (COLMAP accepts 15 inliers; our
verdict asks that the inliers be unlikely by chance). Prints a table by the reference's true / false and by COLMAP's
inlier count; writes the per-pair rows as JSON.

    python tools/rejected_pairs_explained.py SCENE_CACHE ANALYSIS.json SCENE OUT.json
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from guidedmatch.collection.colmap_source import ColmapSource
from guidedmatch.collection.config import collection_matcher_config
from guidedmatch.matcher import match


def verdict(f1, f2, mode, cfg) -> tuple[bool, int]:
    r = match(f1, f2, mode, cfg)
    g = r.geometry
    return bool(g), int(g.num_inliers) if g is not None else 0


def main(cache: Path, analysis: Path, scene: str, out: Path) -> None:
    rows = json.loads(analysis.read_text())[scene]["rejected"]["pairs"]
    src = ColmapSource(cache / "features.db")
    cfg = collection_matcher_config()
    t0 = time.time()
    res = []
    for p in rows:
        f1, f2 = src.load(p["name1"]), src.load(p["name2"])
        a = verdict(f1, f2, "so+epi+ia", cfg)
        b = verdict(f2, f1, "so+epi+ia", cfg)
        c = verdict(f1, f2, "bf", cfg)
        res.append(dict(p, first_pass=a, swapped=b, bf=c))
    out.write_text(json.dumps(res, indent=1))
    print(f"{scene}: {len(res)} pairs COLMAP verifies and we do not, matched again in {time.time() - t0:.0f} s")
    print("| reference | COLMAP's inliers | pairs | first pass verifies | swapped verifies | bf verifies | bf's inliers (median) |")
    print("|---|---|---|---|---|---|---|")
    for truth in (True, False):
        for lo, hi in ((15, 30), (30, 100), (100, 10**9)):
            sel = [r for r in res if r["true"] == truth and lo <= r["inliers"] < hi]
            if not sel:
                continue
            bfi = [r["bf"][1] for r in sel if r["bf"][0]]
            print(f"| {'true' if truth else 'false'} | {lo}-{hi - 1 if hi < 10**9 else ''} | {len(sel)} | "
                  f"{sum(r['first_pass'][0] for r in sel)} | {sum(r['swapped'][0] for r in sel)} | "
                  f"{sum(r['bf'][0] for r in sel)} | {np.median(bfi) if bfi else '-'} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], Path(sys.argv[4]))
