"""Per-pair matching metrics and their paper-style totals (Teng & Dong, Sec. IV, Tables 1-8).

One *row* (a plain ``dict``, JSON-ready) per (pair, method):

=========================  =========================================================================
``pair``, ``method``       identifiers
``n_features1/2``          features detected in image 1 / image 2 (paper Table 8 "# Features in view")
``comparisons``            descriptor distances evaluated (paper Table 1 "number of matches"); ``None``
                           when unknown (approximate peers such as FLANN)
``matches``                correspondences returned by the matcher
``true_correspondences``   matches the ground truth calls correct (< 3 px, Sec. IV-A); ``None`` w/o GT
``precision``              ``true_correspondences / matches`` (Sec. IV-A), ``None`` w/o GT or matches
``ransac_inliers``         matches consistent with a fundamental matrix fitted by RANSAC to the matches
``ransac_precision``       ``ransac_inliers / matches``: the paper's precision for real images (Table 8)
``time_s``                 matching wall time from ``MatchResult.stats.time_s``
=========================  =========================================================================

RANSAC-F choice (the paper only says "RANSAC with epipolar geometry"): F is fitted with
:func:`guidedmatch.epipolar.estimate_fundamental` -- ``method="prosac"`` (OpenCV USAC, PROSAC sampling with
the matches ordered by ascending descriptor distance, MSAC score, local optimisation), estimation threshold
1.0 px, confidence 0.999, at most 100 000 iterations, ``seed=0`` (deterministic). Inliers are then counted
with the symmetric point-to-epipolar-line distance (:func:`guidedmatch.epipolar.symmetric_epipolar_distance`)
under the fitted F and **3 px**, the paper's correctness threshold, so on pairs with ground truth the
RANSAC precision estimates the GT precision. Why (measured on Strecha Herz-Jesus pairs at 1536 px, SIFT,
BFMatcher, GT precision vs this estimate): with ratio test 0.904/0.904, 0.809/0.808, 0.692/0.692,
0.670/0.670; without ratio test (12-27 % inliers) 0.273/0.274, 0.164/0.166, 0.117/0.117, 0.129/0.129.
Counting at 1 px instead underestimates (0.866, 0.708, 0.624, 0.578 for the ratio-test rows); plain
MAGSAC++ with 10 000 iterations (``cv2.USAC_MAGSAC``) found a wrong F on 2 of the 4 no-ratio pairs
(0.057 and 0.078 for GT 0.117 and 0.129), PROSAC on distance-ordered matches on none. Caveat: at inlier
ratios of a few percent (the paper's BF on real images: 1.7-13 %) any RANSAC can lock onto a wrong F, so
such low numbers are indicative only. When no F can be fitted (fewer than 8 matches, degenerate
configuration) ``ransac_inliers`` is 0 and ``ransac_failure`` holds the reason.
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from ..datasets import DEFAULT_THRESHOLD
from ..epipolar import symmetric_epipolar_distance
from ..results import Failure, MatchResult

RANSAC_THRESHOLD_PX = 1.0  # USAC inlier threshold used while fitting F, px
RANSAC_INLIER_PX = DEFAULT_THRESHOLD  # symmetric epipolar distance below which a match counts as an inlier, px
RANSAC_CONFIDENCE = 0.999  # RANSAC confidence
RANSAC_MAX_ITERS = 100_000  # RANSAC iteration cap (stops earlier once the confidence is reached)
RANSAC_METHOD = "prosac"  # estimate_fundamental method; PROSAC order = ascending descriptor distance

COUNT_FIELDS = ("n_features1", "n_features2", "comparisons", "matches", "true_correspondences",
                "ransac_inliers", "time_s")


def _keypoints(f: Any) -> np.ndarray:
    """``(N, 2) float64`` keypoints of a ``Features``-like object (``.keypoints``) or an array."""
    kp = getattr(f, "keypoints", f)
    kp = np.asarray(kp, dtype=np.float64)
    return kp.reshape(-1, 2) if kp.size else np.zeros((0, 2))


def ransac_fundamental(
    pts1: np.ndarray,
    pts2: np.ndarray,
    distances: np.ndarray | None = None,
    *,
    threshold: float = RANSAC_THRESHOLD_PX,
    inlier_threshold: float = RANSAC_INLIER_PX,
    method: str = RANSAC_METHOD,
    confidence: float = RANSAC_CONFIDENCE,
    max_iters: int = RANSAC_MAX_ITERS,
) -> tuple[np.ndarray, np.ndarray] | Failure:
    """Fit F to correspondences and return ``(F (3, 3), inlier mask (M,) bool)`` in the input order.

    Args:
        pts1, pts2: ``(M, 2)`` matched pixel coordinates.
        distances: ``(M,)`` descriptor distances; the points are given to USAC in ascending-distance order
            (PROSAC draws the best first). ``None``: input order.
        threshold: USAC threshold while fitting, px. inlier_threshold: the mask is
            ``symmetric_epipolar_distance(F, pts1, pts2) < inlier_threshold`` (see the module docstring).
        method: a key of ``guidedmatch.epipolar.USAC_METHODS``.

    Returns :class:`Failure` for fewer than 8 correspondences, non-finite input or when USAC finds no F.
    """
    p1 = np.asarray(pts1, dtype=np.float64).reshape(-1, 2)
    p2 = np.asarray(pts2, dtype=np.float64).reshape(-1, 2)
    if len(p1) != len(p2):
        return Failure("point arrays differ in length", {"n1": len(p1), "n2": len(p2)})
    if len(p1) < 8:
        return Failure(f"fewer than 8 correspondences ({len(p1)})", {"n": len(p1)})
    if not (np.isfinite(p1).all() and np.isfinite(p2).all()):
        return Failure("non-finite coordinates")
    from ..epipolar import estimate_fundamental

    order = np.arange(len(p1)) if distances is None else np.argsort(np.asarray(distances).reshape(-1), kind="stable")
    res = estimate_fundamental(p1[order], p2[order], method=method, threshold=float(threshold),
                               confidence=float(confidence), max_iters=int(max_iters), seed=0)
    if not res:
        return res
    F = res.F
    mask = symmetric_epipolar_distance(F, p1, p2) < inlier_threshold
    return F, mask


def evaluate_matches(
    result: MatchResult,
    features1: Any,
    features2: Any,
    gt: Any = None,
    *,
    pair: str | None = None,
    method: str | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    ransac: bool = False,
    ransac_threshold: float = RANSAC_THRESHOLD_PX,
    ransac_inlier_threshold: float = RANSAC_INLIER_PX,
) -> dict[str, Any]:
    """One metrics row for one (pair, method).

    Args:
        result: the matcher output; ``stats.comparisons`` (may be ``None``) and ``stats.time_s`` are
            copied, ``stats.method`` is used when ``method`` is not given.
        features1, features2: ``Features`` (anything with ``.keypoints``) or ``(N, 2)`` keypoint arrays.
        gt: ``HomographyGT`` / ``EpipolarGT`` (anything with ``correct(pts1, pts2, threshold)``) or ``None``.
        threshold: GT correctness threshold in px (paper: 3).
        ransac: also compute the RANSAC-F precision (paper Table 8).
        ransac_threshold: USAC threshold while fitting F, px.
        ransac_inlier_threshold: symmetric epipolar distance under the fitted F that counts as inlier, px.

    Returns:
        a dict with the fields listed in the module docstring (+ ``ransac_failure`` when RANSAC failed).
    """
    kp1, kp2 = _keypoints(features1), _keypoints(features2)
    pairs = result.pairs
    m = len(pairs)
    if m and (pairs.min() < 0 or pairs[:, 0].max() >= len(kp1) or pairs[:, 1].max() >= len(kp2)):
        raise IndexError("match indices out of range of the keypoint arrays")
    p1, p2 = kp1[pairs[:, 0]], kp2[pairs[:, 1]]
    stats = result.stats
    comps = stats.comparisons
    row: dict[str, Any] = {
        "pair": pair,
        "method": method if method is not None else stats.method,
        "n_features1": len(kp1),
        "n_features2": len(kp2),
        "comparisons": None if comps is None else int(comps),
        "matches": m,
        "true_correspondences": None,
        "precision": None,
        "ransac_inliers": None,
        "ransac_precision": None,
        "time_s": float(stats.time_s),
    }
    if gt is not None:
        ok = np.asarray(gt.correct(p1, p2, threshold), dtype=bool) if m else np.zeros(0, bool)
        row["true_correspondences"] = int(ok.sum())
        row["precision"] = float(ok.mean()) if m else None
    if ransac:
        res = ransac_fundamental(p1, p2, result.distances, threshold=ransac_threshold,
                                 inlier_threshold=ransac_inlier_threshold)
        if res:
            _, mask = res
            row["ransac_inliers"] = int(mask.sum())
            row["ransac_precision"] = float(mask.mean())
        else:
            row["ransac_inliers"] = 0
            row["ransac_precision"] = 0.0 if m else None
            row["ransac_failure"] = res.reason
    return row


def summarize(rows: Iterable[dict[str, Any]], by: Sequence[str] = ("method",)) -> list[dict[str, Any]]:
    """Totals over pairs, grouped by ``by`` (default: per method), like the paper's tables.

    Counts (:data:`COUNT_FIELDS`) are summed; a sum is ``None`` if any row has ``None`` there (unknown).
    ``precision = sum(true_correspondences) / sum(matches)`` and
    ``ransac_precision = sum(ransac_inliers) / sum(matches)`` -- ratios of sums, not means of per-pair
    ratios (the paper pools over pairs). Also reports ``n_pairs``. Groups keep first-seen order.
    """
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(k) for k in by), []).append(r)
    out = []
    for key, rs in groups.items():
        s: dict[str, Any] = dict(zip(by, key))
        s["n_pairs"] = len(rs)
        for f in COUNT_FIELDS:
            vals = [r.get(f) for r in rs]
            if any(v is None for v in vals):
                s[f] = None
            else:
                s[f] = float(sum(vals)) if f == "time_s" else int(sum(vals))
        m = s["matches"]
        s["precision"] = (s["true_correspondences"] / m) if (m and s["true_correspondences"] is not None) else None
        s["ransac_precision"] = (s["ransac_inliers"] / m) if (m and s["ransac_inliers"] is not None) else None
        out.append(s)
    return out


def median_time(fn: Callable[[], Any], repeats: int = 5, warmup: int = 0) -> tuple[Any, float, list[float]]:
    """Call ``fn()`` ``warmup`` times untimed, then ``repeats`` times timed (``time.perf_counter``).

    Returns ``(result of the last call, median seconds, list of all timed seconds)``.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(int(warmup)):
        fn()
    times = []
    result = None
    for _ in range(int(repeats)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return result, float(statistics.median(times)), times
