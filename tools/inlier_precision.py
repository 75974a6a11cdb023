"""Where do the wrong verified inliers of guided matching come from? (analysis behind docs/pairs.md, "Precision")

Re-runs the collection matcher (so+epi+ia, the collection defaults) on every pair of a COLMAP database, keeps each
verified pair's inliers and labels them with a judge model mapped from the same features (by default the one
``guidedmatch bench sfm`` maps from COLMAP's exhaustive matches): the 3-D point of one keypoint projected into the
other image, within 3 px right, beyond 10 px wrong (:mod:`guidedmatch.evaluation.consistency`). For each inlier it
also computes, by brute force, what the guided search did not look at:

* the best distance to any *other* image-2 feature (is the match the global nearest neighbour?);
* the best distance to any other image-2 feature within 5 px of the final epipolar line, over the whole line (the
  guided search only compares the part of the band inside the spatial-order x-range);
* where the true partner is: the image-1 keypoint's 3-D point projected into image 2 by the judge, and the image-2
  keypoint nearest to that projection (within 3 px, else "no keypoint there"): is it the match, a candidate of the
  final models' search region (then the descriptor preferred the wrong one), outside the x-range or outside the
  band (then a wider search would have compared it)?

It prints the labelled counts by descriptor distance, by the whole-line ratio d1 / d2 and by global-NN status.

    python tools/inlier_precision.py /tmp/sfm_bench/final/work/8192/so_epi_ia_ours/database.db \\
        /tmp/sfm_bench/final/work/8192/colmap/sparse/0

(slow: exact distances to every image-2 feature, ~1 min for 28 pairs of 11k features)
"""
from __future__ import annotations

import argparse
import itertools
import sys

import numpy as np


def _pairs_table(name: str, value: np.ndarray, wrong: np.ndarray, right: np.ndarray, edges) -> list[str]:
    out = [f"| {name} | wrong | right | wrong share |", "|---|---|---|---|"]
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (value >= lo) & (value < hi)
        w, r = int((wrong & m).sum()), int((right & m).sum())
        out.append(f"| [{lo:g}, {hi:g}) | {w} | {r} | {w / max(1, w + r):.1%} |")
    return out


PLACES = ("no image-1 3-D point", "no image-2 keypoint within 3 px", "the match itself",
          "a candidate, descriptor farther than the match", "a candidate, descriptor closer",
          "outside the x-range, in the band", "outside the band", "behind the camera")


def _partner_places(judge, n1, n2, P, e, k2, D1, D2, d1, models) -> list[tuple[str, str]]:
    """``(label, place)`` of every right (<= 3 px) or wrong (> 10 px) inlier: where its image-1 keypoint's true
    partner is (:data:`PLACES`)."""
    from scipy.spatial import cKDTree

    pid = judge.point_ids(n1)
    tree = cKDTree(k2)
    out = []
    for t, (i, j) in enumerate(P):
        lab = "wrong" if e[t] > 10 else "right" if e[t] <= 3 else None
        if lab is None:  # NaN (unlabelled) or 3-10 px
            continue
        if pid[i] < 0:
            out.append((lab, PLACES[0]))
            continue
        uv = judge.project(n2, judge.xyz(int(pid[i]))[None])[0]
        if not np.all(np.isfinite(uv)):
            out.append((lab, PLACES[7]))
            continue
        dist, jj = tree.query(uv)
        if dist > 3.0:
            place = PLACES[1]
        elif jj == j:
            place = PLACES[2]
        elif models is None or jj in set(models.candidates(int(i)).tolist()):  # no models: all were candidates
            place = PLACES[4] if np.linalg.norm(D1[i] - D2[jj]) < d1[t] else PLACES[3]
        else:
            reg = models.regions(np.array([i]))
            line = None if reg.lines is None else reg.lines[0]
            in_band = line is None or abs(models.pts2a[jj] @ line[:2] + line[2]) <= models.band_px
            place = PLACES[5] if in_band else PLACES[6]
        out.append((lab, place))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("database", help="COLMAP database with the features (its matches are not used)")
    p.add_argument("judge", help="a model folder mapped from the same features (e.g. COLMAP's exhaustive run)")
    p.add_argument("--band", type=float, default=5.0, help="epipolar band half-width, px (default 5)")
    a = p.parse_args(argv)

    from guidedmatch.collection.engine import collection_matcher_config
    from guidedmatch.collection.sources import open_source
    from guidedmatch.evaluation.consistency import ModelJudge
    from guidedmatch.matcher import match
    from guidedmatch.prepared import prepare

    src = open_source(a.database)
    names = src.names()
    judge = ModelJudge(a.judge)
    feats = {n: src.load(n) for n in names}
    prep = {n: prepare(feats[n]) for n in names}
    rows, partners = [], []
    cfg = collection_matcher_config()
    for n1, n2 in itertools.combinations(names, 2):
        r, models = match(prep[n1], prep[n2], "so+epi+ia", cfg, return_models=True)
        g = r.geometry
        if not g or g.model != "F" or not judge.has(n1) or not judge.has(n2):
            continue
        P, d1 = r.pairs[g.inliers], r.distances[g.inliers].astype(float)
        k1, k2 = feats[n1].keypoints[:, :2], feats[n2].keypoints[:, :2]
        D1, D2 = feats[n1].descriptors.astype(np.float32), feats[n2].descriptors.astype(np.float32)
        lines = np.c_[k1[P[:, 0]], np.ones(len(P))] @ g.F.T
        lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        h2 = np.c_[k2, np.ones(len(k2))]
        other, other_line = np.empty(len(P)), np.empty(len(P))
        for s in range(0, len(P), 512):
            q = D1[P[s:s + 512, 0]]
            D = np.sqrt(np.maximum((q * q).sum(1)[:, None] + (D2 * D2).sum(1)[None] - 2 * q @ D2.T, 0))
            D[np.arange(len(D)), P[s:s + 512, 1]] = np.inf
            other[s:s + 512] = D.min(1)
            D[np.abs(h2 @ lines[s:s + 512].T).T > a.band] = np.inf
            other_line[s:s + 512] = D.min(1)
        e = judge.errors(n1, n2, P, feats[n1].keypoints, feats[n2].keypoints)
        rows.append(np.c_[d1, other, other_line, e])
        partners.extend(_partner_places(judge, n1, n2, P, e, k2, D1, D2, d1, models))
    if not rows:
        print("no verified F pair with both images in the judge model", file=sys.stderr)
        return 1
    d1, other, other_line, e = np.concatenate(rows).T
    lab = np.isfinite(e)
    wrong, right = lab & (e > 10), lab & (e <= 3)
    nn = d1 <= other
    lines = [f"verified inliers {len(d1)}, labelled {int(lab.sum())}, wrong (> 10 px) {int(wrong.sum())} "
             f"({wrong.sum() / max(1, lab.sum()):.2%}), right (<= 3 px) {int(right.sum())}", "",
             f"global nearest neighbour: {nn[wrong].mean():.0%} of the wrong, {nn[right].mean():.0%} of the right", ""]
    lines += _pairs_table("descriptor distance", d1, wrong, right, [0, 200, 250, 300, np.inf]) + [""]
    lines += _pairs_table("d1 / d2 over the whole epipolar band", d1 / other_line, wrong, right,
                          [0, 0.6, 0.7, 0.8, 0.9, 1.0001, np.inf])
    lines += ["", "| where the true partner is (image-1 keypoint's 3-D point projected into image 2) | wrong | right |",
              "|---|---|---|"]
    for place in PLACES:
        lines.append(f"| {place} | {sum(1 for lab, p in partners if lab == 'wrong' and p == place)} "
                     f"| {sum(1 for lab, p in partners if lab == 'right' and p == place)} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
