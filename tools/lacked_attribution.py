"""Why the matcher does not match the keypoints of COLMAP's inliers it misses: each missed inlier (a, b) of random
pairs both verify, attributed by the final models (``match(..., return_models=True)``) -- a drawn before the final
pass (unguided start or progressive batches), or in the final pass: dropped outside the spatial-order window, b
outside a's admissible x-range, b outside the epipolar band, or b a candidate (then the ratio test, one-to-one, the
re-check or the frame check decided) (accuracy history, twenty-third round).

    python tools/lacked_attribution.py CACHE/SCENE NPAIRS
"""
from __future__ import annotations

import collections
import sys
from pathlib import Path

import numpy as np

from guidedmatch import kernels  # noqa: F401 -- before faiss (OpenBLAS set-up)
from guidedmatch.collection.config import collection_matcher_config
from guidedmatch.evaluation.accuracy_analysis import _keys
from guidedmatch.matcher import match

sys.path.insert(0, str(Path(__file__).resolve().parent))
from colmap_inliers_found import sampled_pairs  # noqa: E402


def main() -> None:
    pairs, prep = sampled_pairs(Path(sys.argv[1]), int(sys.argv[2]))
    cfg = collection_matcher_config(None)
    why = collections.Counter()
    for a, b, cm in pairs:
        res, models = match(prep[a], prep[b], "so+epi+ia", cfg, return_models=True)
        m = np.asarray(res.pairs, np.int64)
        why["COLMAP's inliers"] += len(cm)
        miss = cm[~np.isin(_keys(cm), _keys(m))]
        other = np.isin(miss[:, 0], m[:, 0]) | np.isin(miss[:, 1], m[:, 1])
        why["missed: a or b matched to another"] += int(other.sum())
        miss = miss[~other]
        if not res.geometry or models is None:
            why["missed: pair not verified here, or no final models"] += len(miss)
            continue
        final = np.isin(miss[:, 0], models.final_queries)
        why["missed: a drawn before the final pass"] += int((~final).sum())
        f = miss[final]
        if len(f) == 0:
            continue
        r = models.regions(f[:, 0])
        x2 = models.pts2a[f[:, 1]]
        in_x = (x2[:, 0] >= r.lo) & (x2[:, 0] <= r.hi)
        in_band = (np.abs((x2 * r.lines[:, :2]).sum(1) + r.lines[:, 2])
                   <= models.band_px) if r.lines is not None else np.ones(len(f), bool)
        why["final pass: a outside the window, dropped"] += int((~r.keep).sum())
        k = r.keep
        why["final pass: b outside a's x-range"] += int((k & ~in_x).sum())
        why["final pass: b in x-range, outside the band"] += int((k & in_x & ~in_band).sum())
        why["final pass: b a candidate (ratio / one-to-one / checks)"] += int((k & in_x & in_band).sum())
    for key, v in why.items():
        print(f"{key}: {v}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main()
