"""A/B of the second look's start on a matched COLMAP database: the candidates the second look would take (weak
verified pairs, rejected pairs with enough chained correspondences), a random sample of them matched one by one in
this process with

* ``paper@B``: the paper's draw order, unguided budget ``B`` (``max_unguided``);
* ``prior@B``: image 1's chained keypoints first, then its tracked ones (``second_look.priors``, the shipped rule);
* ``chained@B`` / ``tracked@B``: one of the two tiers only.

Every variant runs with the database's first-pass settings plus the scale check (the defaults). Prints one line per
pair and a summary (verified, verified with >= 64 inliers, inliers, seconds summed over the pairs).

    python tools/prior_ab.py DATABASE [--pairs 60] [--min-chained 64] [--variants paper@0.02,paper@0.1,prior@0.02]

Example (buddha, the old defaults' database of ``guidedmatch bench accuracy``)::

    python tools/prior_ab.py ~/.cache/guidedmatch/accuracy/buddha/ours_olddefaults/database.db --pairs 60
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("database")
    ap.add_argument("--pairs", type=int, default=60, help="candidates sampled (default 60)")
    ap.add_argument("--min-chained", type=int, default=64, help="chains a rejected candidate needs (default 64)")
    ap.add_argument("--variants", default="paper@0.02,paper@0.1,prior@0.02,chained@0.02,tracked@0.02,prior@0.1")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args(argv)

    from guidedmatch.collection.second_look import (SecondLookConfig, _candidates, _read_inliers, priors)
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.config import MatcherConfig
    from guidedmatch.matcher import match
    from guidedmatch.prepared import prepare

    with tempfile.TemporaryDirectory() as tmp:      # read through a copy: the database is never written
        db = Path(tmp) / "database.db"
        shutil.copyfile(a.database, db)
        src = ColmapSource(db)
        with ColmapSink(db, geometry="ours") as sink:
            tried, inliers, nkp = _read_inliers(sink)
        pairs, support, total = _candidates(tried, inliers, nkp, set(), SecondLookConfig(min_chained=a.min_chained))
        rng = np.random.default_rng(a.seed)
        pick = sorted(rng.choice(len(pairs), size=min(a.pairs, len(pairs)), replace=False).tolist())
        chosen = [pairs[i] for i in pick]
        prior = priors(chosen, inliers, nkp)
        print(f"candidates {total}, sampled {len(chosen)}", flush=True)
        prepared: dict = {}

        def P(n):
            if n not in prepared:
                prepared[n] = prepare(src.load(n))
            return prepared[n]

        match(P(chosen[0][0]), P(chosen[0][1]), "so+epi+ia", MatcherConfig())   # compile / warm up, untimed
        rows = []
        variants = a.variants.split(",")
        for x, y in chosen:
            have = inliers.get((x, y), inliers.get((y, x)))
            chained, tracked = prior[(x, y)]
            row = dict(pair=[x, y], before=0 if have is None else len(have), chained=len(chained))
            for v in variants:
                kind, budget = v.split("@")
                first = {"paper": None, "prior": [chained, tracked], "chained": [chained],
                         "tracked": [tracked]}[kind]
                t0 = time.perf_counter()
                res = match(P(x), P(y), "so+epi+ia", MatcherConfig(max_unguided=float(budget)), first=first)
                dt = time.perf_counter() - t0
                g = res.geometry
                row[v] = [g.verdict, int(g.num_inliers) if g else 0, round(dt, 4)]
            rows.append(row)
            print(json.dumps(row), flush=True)
    print()
    print("| start | verified | >= 64 inliers | inliers | seconds (summed) |")
    print("|---|---|---|---|---|")
    for v in variants:
        ver = [r[v] for r in rows if r[v][0] == "verified"]
        print(f"| {v} | {len(ver)} / {len(rows)} | {sum(n >= 64 for _, n, _ in ver)} | {sum(n for _, n, _ in ver):,} "
              f"| {sum(r[v][2] for r in rows):.1f} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
