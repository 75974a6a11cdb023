"""Steps 6-7 of a guided match and the match filters: the ratio / single-candidate / max-distance selection of 2-NN
results, the re-check under the final models, one-to-one, the mutual check, the planar re-check and the
``unverified="drop"`` rule."""
from __future__ import annotations

import time

import numpy as np

from .. import exact
from ..bruteforce import knn2
from ..config import MatcherConfig
from .models import GuidanceModels
from .state import _Accepted


def one_to_one(q: np.ndarray, j: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the matches kept when every image-2 feature keeps only its closest image-1 match.

    Match ``k`` is ``(q[k], j[k])`` at descriptor distance ``d[k]``; among the matches of one ``j`` the smallest
    ``d`` wins, ties by the smaller ``q``.

    >>> one_to_one(np.array([0, 1, 2]), np.array([5, 5, 6]), np.array([2.0, 1.0, 3.0], np.float32))
    array([1, 2])
    """
    if len(q) == 0:
        return np.zeros(0, np.int64)
    o = np.lexsort((q, d, j))
    first = np.r_[True, np.diff(j[o]) != 0]
    return np.sort(o[first])


def mutual_check(d1: np.ndarray, d2: np.ndarray, q: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, int]:
    """Indices (ascending) of the matches ``(q[k], j[k])`` whose image-1 feature is the nearest of *all* image-1
    descriptors ``d1`` to image-2 descriptor ``d2[j[k]]`` (ties: lowest index, as brute force); also returns the
    number of descriptor distances evaluated (``len(unique(j)) * N1``)."""
    if len(q) == 0:
        return np.zeros(0, np.int64), 0
    uj, inv = np.unique(j, return_inverse=True)
    (nn, _s1, _i2, _s2), _ = knn2(d2[uj], d1, checked=True)
    return np.flatnonzero(nn[inv] == q), len(uj) * len(d1)



def _planar(geometry, F, x1, x2) -> bool:
    """Whether the final matches ``x1 <-> x2`` still look planar: the verdict's homography explains at least
    ``h_ratio`` (COLMAP's rule, :class:`~guidedmatch.geometry.VerdictConfig`) as many of them as the final ``F``
    (Sampson distance within the same threshold). An "H" verdict taken on the few unguided correspondences of a 3-D
    scene with a dominant plane (Herz-Jesus 0004-0005 at ~40k) fails it: the final matches off the plane are F
    inliers, and they are kept."""
    from ..geometry import VerdictConfig, sampson_distance

    if F is None or not np.all(np.isfinite(F)):
        return True  # no F to compare with: the homography is the only model
    c = VerdictConfig()
    with np.errstate(invalid="ignore", divide="ignore"):
        nf = int((sampson_distance(np.asarray(F, np.float64), x1, x2) <= c.threshold_px).sum())
    return geometry.num_inliers >= c.h_ratio * nf


def _drop_unverified(c: MatcherConfig, q, j, d, flags: dict, geometry, report):
    """``unverified="drop"``: a guided match whose verdict is "no-overlap" returns no matches (reported through
    ``report(what, reason)``; "too-few-matches" keeps its few: nothing could be tested); returns ``(q, j, d, flags,
    geometry, number dropped)``."""
    if geometry.verdict != "no-overlap" or c.unverified != "drop" or len(q) == 0:
        return q, j, d, flags, geometry, 0
    n = len(q)
    report("unverified", f"verdict {geometry.verdict!r} ({geometry.reason}): the {n} matches are not returned "
                         "(unverified='drop')")
    keep = np.zeros(n, bool)
    return q[keep], j[keep], d[keep], {k: v[keep] for k, v in flags.items()}, geometry.with_inliers(keep[:0]), n




class Filters:
    """Steps 6-7 of :class:`~guidedmatch.matcher.run._GuidedRun` (a mixin: the run's state lives in ``run.py``)."""

    def select(self, queries, i1, s1, s2, ncand) -> _Accepted:
        """Ratio / single-candidate / max-distance tests on 2-NN results (``s1, s2``: exact squared L2 or Hamming
        bits). Every decision is taken on the reported float32 distances (L2: the float32 square root of the exact
        squared distance, :func:`guidedmatch.exact.l2`), which are the same on every CPU and thread count."""
        c = self.c
        dist1 = np.asarray(s1, np.float32) if self.binary else exact.l2(s1)
        dist2 = np.asarray(s2, np.float32) if self.binary else exact.l2(s2)
        keep = i1 >= 0
        single = keep & (ncand == 1)
        if c.ratio is not None:
            keep &= (dist1 < np.float32(c.ratio) * dist2) | single
        if c.single_candidate == "reject":
            keep &= ~single
        if c.max_distance is not None:
            keep &= dist1 <= c.max_distance
        return _Accepted(queries[keep], i1[keep], dist1[keep].astype(np.float32), single[keep])

    # ------------------------------------------------------------------------------------ steps 6-7: filters
    def recheck(self, models: GuidanceModels | None, q, j, d, flags: dict):
        """Step 6 (beyond the paper; §IV-C suggests it): the in-band flag of every match under the final models, and,
        with ``recheck``, drop matches made before the final models that lie outside the final search region."""
        t0 = time.perf_counter()
        c = self.c
        in_band = np.ones(len(q), bool)
        in_region = np.ones(len(q), bool)
        guided = models is not None and models.guided
        if guided and len(q):
            keep, lo, hi, lines, _ = models.regions(q)
            xa = models.pts2a[j]
            in_region = keep & (xa[:, 0] >= lo) & (xa[:, 0] <= hi)
            if models.F is not None:
                in_band = np.abs(np.sum(lines[:, :2] * xa, axis=1) + lines[:, 2]) <= c.band_px
                in_region &= in_band
        flags = dict(flags, in_band=in_band)
        dropped = 0
        if c.recheck and guided:
            drop = (flags["phase"] < len(self.updates)) & ~in_region
            dropped = int(drop.sum())
            sel = ~drop
            q, j, d = q[sel], j[sel], d[sel]
            flags = {k: v[sel] for k, v in flags.items()}
        self.timing["recheck_s"] = time.perf_counter() - t0
        return q, j, d, flags, dropped

    def filters(self, q, j, d, flags: dict):
        """Step 7: :func:`one_to_one` (``one_to_one``) and the full :func:`mutual_check` (``mutual``; its reverse
        search is counted in ``comparisons``)."""
        t0 = time.perf_counter()
        n0 = len(q)
        if self.c.one_to_one_in(self.mode) and len(q):
            sel = one_to_one(q, j, d)
            q, j, d = q[sel], j[sel], d[sel]
            flags = {k: v[sel] for k, v in flags.items()}
        n1 = len(q)
        self.mutual_comparisons = 0
        if self.c.mutual and len(q):
            sel, self.mutual_comparisons = mutual_check(self.d1, self.d2, q, j)
            q, j, d = q[sel], j[sel], d[sel]
            flags = {k: v[sel] for k, v in flags.items()}
        self.timing["filter_s"] = time.perf_counter() - t0
        return q, j, d, flags, n0 - n1, n1 - len(q)
