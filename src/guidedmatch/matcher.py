"""The progressive guided matcher (Teng & Dong §III-A, "System architecture"), read top to bottom as the method.

Modes (:class:`~guidedmatch.config.Mode`)
-----------------------------------------
``bf``          exact brute force (:mod:`guidedmatch.bruteforce`), the paper's baseline.
``epi``         classic epipolar-guided matching: after the first models, candidates = epipolar band only.
``so``          spatial order only: candidates = admissible image-2 x-range (§III-C).
``so+epi``      x-range ∩ band (§III-C + §III-D).
``so+epi+ia``   the same in coordinates aligned by the homography from F (§III-E; the in-plane twist ``c_inplane`` by
                default, validated, see step 3).

Either side of :func:`match` may be a :class:`~guidedmatch.prepared.PreparedImage` (per-image state reused across
pairs: kernel-form descriptors, the approximate index of the unguided start); the matches are the same as with plain
:class:`~guidedmatch.features.Features`. With ``auto_bf`` (default) a guided mode is replaced by brute force where
guidance cannot win (fewer than ``bf_below_float`` / ``bf_below_binary`` features; said in ``stats.details``).
Every result carries the two-view verdict ``result.geometry`` (:class:`~guidedmatch.geometry.TwoViewGeometry`:
``verified`` F or H / ``no-overlap`` / ``too-few-matches``, inlier mask over ``result.pairs``).

Flow of a guided match (:func:`match` -> :class:`_GuidedRun`, one method per step, in this order)
-------------------------------------------------------------------------------------------------
1. **Draw order** (§III-A, "Feature Grouping", :func:`draw_order`): image-1 features are put into ``num_groups``
   x-intervals and drawn round-robin (within a group strongest response first, else a seeded random order), so the
   first matches cover the whole image width.
2. **Unguided start** (§III-A; the gate and the exit are beyond the paper, issue 11, :meth:`_GuidedRun.unguided_start`):
   drawn features are matched in mini-batches against all of image 2 (:class:`~guidedmatch.prepared.UnguidedSearch`):
   exactly (GEMM) for the first queries, until they have cost min(building image 2's index, ``exact_rent`` of the
   exit budget; added to it; none when that buys fewer than max(``batch_size``, 2 ``first_check``) queries)
   comparisons, then through the faiss IVF index of image 2 (~2 sqrt(N2) + 4 cells per query; built then unless
   image 2 was prepared) -- ski-rental: a well-overlapping pair is decided before the index is needed and never
   builds one, and the rule is the same for prepared and fresh images, so are the matches. Exact only: binary
   descriptors (popcount), small images, ``unguided_index=False``. These correspondences are the *evidence*: no
   model selected them. After ``first_check`` (32) of them, and whenever they have grown by ``check_growth``,
   :func:`~guidedmatch.geometry.two_view_geometry` decides whether they share a geometry beyond chance; the first
   model is fitted as soon as the verdict is "verified" (its F is the verdict's), so a model fitted on too little
   evidence never guides. With ``frame_hypotheses`` the verdict also searches the orientation-consistent subset of
   the evidence when RANSAC on all of it verifies nothing (low inlier ratio, geometry step 4). When the start has
   spent ``max_unguided`` of N1*N2 comparisons (2 % with the index) plus the exact rent without a verified
   verdict, it stops: verdict "no-overlap" (or "too-few-matches"), the remaining features are not matched (fallback
   ``early_exit``). ``start="paper"`` (:meth:`MatcherConfig.paper`): the first model after ``update_every`` exact
   unguided correspondences, no gate, no exit.
3. **Model fit** (§III-B..E, :meth:`_GuidedRun.fit_models`): the first fit (with ``frame_hypotheses`` its F must pass
   the verdict's rule on the evidence, else the verdict's F guides, :meth:`_GuidedRun.fit_fundamental`), then after
   every ``update_every`` (200) newly accepted correspondences the models are refit on *all* correspondences so far
   (``num_updates`` = 3 fits in all): F by robust RANSAC (§III-D), the alignment homographies from F (mode IA,
   §III-E; validated over the keypoints by :func:`~guidedmatch.alignment.safe_alignment` -- local scale,
   orientation, line at infinity -- with the fallback requested approach -> ``c_inplane`` -> none, each rejection
   reported), then the spatial-order model on aligned x-coordinates (§III-B, §III-C).
4. **Guided phase**: between updates, batches are matched in their search regions under the current models; the
   batch size follows the observed acceptance rate so the next update comes after about one batch.
5. **Final pass**: after the last update, all remaining image-1 features are matched in one vectorized call of the
   Numba candidate kernel (:func:`~guidedmatch.kernels.guided_top2` over the :class:`~guidedmatch.kernels.StripIndex`
   of the aligned image-2 points): features outside the overlap window ω* are dropped unmatched; each remaining
   feature's candidates are the image-2 features in its admissible x-range (aligned coordinates) and within
   ``band_px`` of its epipolar line (:func:`search_regions`).
6. **Re-check** (beyond the paper, ``recheck``): matches accepted before the final models are tested against the
   final x-range and band and dropped when outside (the fix the paper suggests in §IV-C). When the verdict is a
   homography (planar scene or pure rotation, ``planar_recheck``) and the final matches still look planar
   (:func:`_planar`), guided matches that are not its inliers are dropped at step 8
   (``details["dropped_off_homography"]``): F's band does not constrain matches along the plane.
7. **One-to-one** (beyond the paper, :func:`one_to_one`) and the optional **mutual check** (:func:`mutual_check`).
8. **Result**: matches sorted by image-1 index, per-match flags (incl. the spatial-order probability within the final
   match set, Talker Eq. 12), a typed :class:`~guidedmatch.results.MatchStats` (``details``: ``unguided_search``,
   ``verdict_checks``, ``early_exit``, ``unguided_comparisons``) and the verdict decided on the unguided evidence,
   reported over the final matches (:func:`~guidedmatch.geometry.report_geometry`: inliers of the final F).

Coordinates: the band is applied in the aligned frame, with ``F_a = H2^-T F H1^-1`` and the line normalized there
("the subsequent feature filtering is also performed according to the transformed coordinates", §III-E);
``ModelUpdate.alignment_scale`` reports how much H2 stretches image-2 distances (min/max local scale over the
image-2 keypoints), i.e. the band width in original pixels.

Ratio test inside the candidate set: with >= 2 candidates, keep when ``d1 < ratio * d2``; with exactly 1 candidate
there is no second neighbour and ``single_candidate`` decides ("reject", the default: drop it, since nothing vouches
for it -- on the demo scene this keeps the same true matches at +1.6 points precision; "accept": keep it, flagged in
``flags["single_candidate"]``); with 0 candidates the feature is unmatched.

``one_to_one`` keeps, for every image-2 feature, only the closest of the image-1 features matched to it -- the cheap
half of a mutual check. A small candidate set makes the ratio test easier to pass than in brute force, so this filter
is what brings guided precision back above brute force's (Oxford, 12 pairs, SIFT: 88.9 % -> 94.2 %, BF 93.8 %). Its
default (None) runs it in the guided modes only, so ``bf`` stays the paper's ratio-test baseline. ``mutual`` is the
full check in every mode: ``(i, j)`` survives only if ``i`` is the nearest of *all* image-1 features to ``j``.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from . import kernels
from .bruteforce import check_descriptors, knn2, match_bruteforce
from .config import MODES, MatcherConfig, Mode
from .epipolar import map_points
from .features import as_features
from .jit import compile_monitor, exclude_compile_time
from .results import (CandidateStats, Fallback, MatchResult, MatchStats, ModelUpdate, PhaseTimes, default_flags,
                      empty_pairs)
from .validation import config_from

__all__ = ["match", "MatcherConfig", "Mode", "MODES", "GuidanceModels", "Regions", "search_regions", "draw_order",
           "one_to_one", "mutual_check"]


# ====================================================================================================== entry point
def match(features1, features2, mode: "str | Mode" = "so+epi+ia", config=None, *, return_models: bool = False):
    """Match image-1 features to image-2 features with ``mode`` (the package's one matching entry point).

    Args:
        features1, features2: :class:`~guidedmatch.features.Features`, or a tuple ``(keypoints (N,2) px,
            descriptors (N,D), image_size (w,h))`` (float descriptors: L2; uint8: packed bits, Hamming).
        mode: ``"bf" | "epi" | "so" | "so+epi" | "so+epi+ia"`` (:data:`~guidedmatch.config.MODES`) or a
            :class:`~guidedmatch.config.Mode`.
        config: :class:`~guidedmatch.config.MatcherConfig`, a dict of its fields, or None (defaults).
        return_models: also return the final :class:`GuidanceModels` (None for ``bf`` or when no model was fitted).

    Returns:
        :class:`~guidedmatch.results.MatchResult`: ``pairs (M,2) int64`` sorted by image-1 index, ``distances (M,)
        float32``, ``flags`` (``phase``, ``single_candidate``, ``in_band``, ``so_prob``) and ``stats``
        (:class:`~guidedmatch.results.MatchStats`). With ``return_models=True``: ``(MatchResult, GuidanceModels |
        None)``.

    Raises:
        ConfigError: unknown mode or bad config. InputError: descriptors of different kinds or lengths, bad arrays.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> xy, desc = rng.uniform(0, 100, (50, 2)), rng.integers(0, 255, (50, 32)).astype(np.float32)
    >>> res = match((xy, desc, (100, 100)), (xy[::-1], desc[::-1], (100, 100)), "so+epi+ia")
    >>> bool(np.all(res.pairs[:, 1] == 49 - res.pairs[:, 0])), len(res) == 50
    (True, True)
    >>> res.stats.comparisons == 50 * 50   # too few features for guidance to win: brute force, reported
    True
    >>> res.stats.details["auto_bf"].split(":")[0], res.geometry.verdict
    ('brute force instead of guided matching', 'verified')
    """
    from .prepared import PreparedImage, prepare

    mode = Mode.parse(mode)
    config = config_from(MatcherConfig, config)
    p1 = features1 if isinstance(features1, PreparedImage) else None
    p2 = features2 if isinstance(features2, PreparedImage) else None
    f1 = p1.features if p1 is not None else as_features(features1, "features1")
    f2 = p2.features if p2 is not None else as_features(features2, "features2")
    d1, d2, binary = check_descriptors(f1.descriptors, f2.descriptors,
                                       known_finite=p1 is not None and p2 is not None and p1.finite and p2.finite)
    with compile_monitor() as jit:  # a first call compiles Numba kernels: reported apart from time_s
        why = _bf_wins(config, len(d1), len(d2), binary) if mode.guided else None
        run = None if not mode.guided or why else _GuidedRun(config, mode, p1 or prepare(f1), p2 or prepare(f2),
                                                             d1, d2, binary)
        res = _match_bf(config, f1, f2, d1, d2, binary, mode, why) if run is None else run.run()
    res = exclude_compile_time(res, jit.seconds)
    return (res, run.guidance if run is not None else None) if return_models else res


def _has_frames(c: MatcherConfig, f1, f2) -> bool:
    """The verdict's second search can run: ``frame_hypotheses`` on and both images have detector orientations."""
    return bool(c.frame_hypotheses) and f1.angles is not None and f2.angles is not None


def _frames(c: MatcherConfig, f1, f2, q: np.ndarray, j: np.ndarray):
    """``(angles1[q], angles2[j])`` for the verdict's second search (``frame_hypotheses``), or None when off or
    either image has no detector orientations."""
    if not _has_frames(c, f1, f2):
        return None
    return np.asarray(f1.angles)[q], np.asarray(f2.angles)[j]


def _ransac_draws(verdict, confidence: float = 0.999, sample: int = 7) -> float:
    """Draws RANSAC needs to find an all-inlier ``sample`` with ``confidence`` at the inlier ratio of ``verdict``'s
    F (raw inliers / evidence): ``log(1 - confidence) / log(1 - w^sample)``; inf at ``w = 0``."""
    e = verdict.evidence
    w = float(e.get("F_inliers_raw", e.get("F_inliers", 0))) / max(int(e.get("num_evidence", 0)), 1)
    if w >= 1.0:
        return 1.0
    if w <= 0.0:
        return math.inf
    return math.log(1.0 - confidence) / math.log1p(-(w ** sample))


def _bf_wins(c: MatcherConfig, n1: int, n2: int, binary: bool) -> str | None:
    """Why brute force replaces a guided mode (``auto_bf``), or None.

    Guidance has a fixed cost (three robust fits, the spatial-order model, the verdict checks) that brute force does
    not pay; below a size it cannot win. Measured (CPU time, best of 3, Herz-Jesus-P8 pairs 0002-0003 / 0002-0005 /
    0000-0005, guided with ``auto_bf=False``; ``/tmp/pairs/bintime2.py`` of the pairs helper), guided / BF:
    SIFT 0.99 / 0.63 / 0.25 at 2000 features, 0.72 / 0.61 / 0.50 at 4000, <= 0.41 from 8000 on;
    ORB 1.85 / 2.94 at 2000, 1.37 / 1.91 at 4000, 0.76 / 1.31 at 8000, 0.51 / 0.73 at 12000, 0.30 / 0.45 at 16000;
    AKAZE 2.4-2.7 at 2000, 1.1-1.2 at 4000, 0.57-1.04 at 8000, 0.28 / 0.37 at 12000; BRISK 2.0-2.9 at 2000, 1.4-2.1
    at 4000 (it has < 8000 features here). Hence BF below 2000 float and 12000 binary features.
    """
    if not c.auto_bf:
        return None
    size = (float(n1) * float(n2)) ** 0.5
    limit = c.bf_below_binary if binary else c.bf_below_float
    if size < limit:
        kind = "binary" if binary else "float"
        return (f"brute force instead of guided matching: sqrt(N1*N2) = {size:.0f} < bf_below_{kind} = {limit} "
                f"({kind} descriptors), where guidance cannot win")
    return None


def _match_bf(c: MatcherConfig, f1, f2, d1, d2, binary, mode: Mode, auto_reason: str | None = None) -> MatchResult:
    """Mode ``bf`` (or a guided mode replaced by brute force, ``auto_reason``): exact 2-NN over all of image 2,
    ratio / max-distance / mutual tests, one-to-one if on for ``mode``, and the two-view verdict from one robust
    fit on the matches (:func:`~guidedmatch.geometry.two_view_geometry`; nothing selected them by a model)."""
    from .geometry import VerdictConfig, two_view_geometry

    t0 = time.perf_counter()
    res = match_bruteforce(d1, d2, ratio=c.ratio, mutual=c.mutual, max_distance=c.max_distance)
    pairs, dist = res.pairs, res.distances
    dropped = 0
    if c.one_to_one_in(mode) and len(pairs):
        sel = one_to_one(pairs[:, 0], pairs[:, 1], dist)
        dropped = len(pairs) - len(sel)
        pairs, dist = pairs[sel], dist[sel]
    t1 = time.perf_counter()
    geometry = two_view_geometry(f1.keypoints[pairs[:, 0]], f2.keypoints[pairs[:, 1]], f1.image_size,
                                 f2.image_size, VerdictConfig(seed=c.seed),
                                 frames=_frames(c, f1, f2, pairs[:, 0], pairs[:, 1]))
    n1, n2 = len(d1), len(d2)
    details = dict(res.stats.details, verdict_s=time.perf_counter() - t1)
    flags = default_flags(len(pairs))
    fallbacks = []
    if auto_reason:  # a guided mode answered by brute force: the guided modes' rule for unverified pairs applies
        details.update(requested_mode=mode.name, auto_bf=auto_reason)
        q, j, dist, flags, geometry, n_drop = _drop_unverified(
            c, pairs[:, 0], pairs[:, 1], dist, flags, geometry, lambda w, r: fallbacks.append(Fallback(w, r)))
        pairs = np.stack([q, j], axis=1) if len(q) else empty_pairs()
        details["dropped_unverified"] = n_drop
    stats = dataclasses.replace(res.stats, time_s=time.perf_counter() - t0, dropped_by_one_to_one=dropped,
                                phase_queries=(n1,), phase_comparisons=(n1 * n2,), queries_matched_against=n1,
                                config=c, details=details, fallbacks=tuple(res.stats.fallbacks) + tuple(fallbacks))
    return MatchResult(pairs, dist, stats, flags, geometry)


# ================================================================================================ §III-A draw order
def draw_order(x: np.ndarray, width: float, num_groups: int, key: np.ndarray) -> np.ndarray:
    """Round-robin draw order of image-1 features over x-interval groups (Teng & Dong §III-A, "Feature Grouping").

    Feature ``i`` belongs to group ``g = clip(floor(x_i / width * G), 0, G - 1)``. Within a group features are taken
    by ascending ``key`` (ties by index); the order is: the first of every group (groups left to right), then the
    second of every group, and so on.

    Args:
        x: ``(N,)`` image-1 x-coordinates, px. width: image width, px (>= max x + 1 in practice).
        num_groups: ``G``. key: ``(N,) float32`` rank key (the matcher uses ``-response``, or seeded uniform noise).

    Returns:
        ``(N,) int64`` permutation of ``arange(N)``.

    >>> draw_order(np.array([0.0, 1.0, 60.0, 61.0, 2.0]), 100.0, 2, np.array([3, 1, 2, 1, 2], np.float32))
    array([1, 3, 4, 2, 0])
    """
    n = len(x)
    if n == 0:
        return np.zeros(0, np.int64)
    g = np.clip((np.asarray(x, np.float64) / width * num_groups).astype(np.int64), 0, num_groups - 1)
    by_key = _argsort_f32(key)
    # stable counting sort by group keeps the key order inside each group
    order_g, offsets = kernels.counting_order(g[by_key], num_groups)
    order_g = by_key[order_g]
    within = np.empty(n, np.int64)
    within[order_g] = np.arange(n) - np.repeat(offsets[:-1], np.diff(offsets))  # rank inside the group
    # round-robin: rank within group, then group (a stable sort of within * G + g, done by counting)
    rr, _ = kernels.counting_order(within * num_groups + g, (int(within.max()) + 1) * num_groups)
    return rr


# ============================================================================================ search regions (§III-C/D)
class Regions(NamedTuple):
    """Search regions of Q image-1 features under one set of models (:func:`search_regions`).

    ``keep (Q,) bool``: matched at all (inside ω*, or rescued); ``lo, hi (Q,) float64``: admissible aligned image-2
    x-range (±inf without a spatial-order model); ``lines (Q,3)``: aligned epipolar lines scaled to a²+b²=1 (None
    without F; a query at the epipole gets ``[0, 0, inf]``, which matches nothing); ``rescued (Q,) bool``: outside ω*
    but kept for band-only matching.
    """

    keep: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    lines: np.ndarray | None
    rescued: np.ndarray


def search_regions(pts1a: np.ndarray, so, F_aligned: np.ndarray | None, inlier_x1_range=None,
                   outside_window: str = "drop") -> Regions:
    """Search region of image-1 features (aligned coordinates ``pts1a (Q,2)``) under one set of models.

    The spatial-order x-range (§III-C, :func:`~guidedmatch.spatial_order.admissible_x_ranges`) when ``so`` is given,
    the epipolar band's line (§III-D) when ``F_aligned`` is given. With ``outside_window="band"``, features outside
    ω* whose x lies in ``inlier_x1_range`` (the x-extent of the F inliers in aligned image 1) are rescued: matched in
    the band only.

    One ``nogil`` kernel (:func:`guidedmatch.kernels.search_regions_kernel`; it runs for every guided batch of every
    pair, and a collection's pair threads otherwise held the GIL for it); :func:`_search_regions_numpy` is the same
    computation from :func:`~guidedmatch.spatial_order.admissible_x_ranges` and
    :func:`~guidedmatch.epipolar.map_points` (the tests' reference).
    """
    p = np.ascontiguousarray(np.asarray(pts1a, np.float64).reshape(-1, 2))
    use_so = so is not None and bool(so.usable)
    if use_so and len(so.gap_lo) != so.n_window + 1:
        raise ValueError("this model was fitted with gap_table=False: it has no search-range table")
    if use_so:  # x1_sorted, gap_lo, gap_hi, window1_x bounds, x2_sorted, n_window
        so_args = (np.ascontiguousarray(so.x1_sorted, np.float64), np.ascontiguousarray(so.gap_lo, np.int64),
                   np.ascontiguousarray(so.gap_hi, np.int64), float(so.window1_x[0]), float(so.window1_x[1]),
                   np.ascontiguousarray(so.x2_sorted, np.float64), int(so.n_window))
    else:
        so_args = (np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), 0.0, 0.0, np.zeros(0), 0)
    rescue = use_so and outside_window == "band" and F_aligned is not None and inlier_x1_range is not None
    r_lo, r_hi = (float(inlier_x1_range[0]), float(inlier_x1_range[1])) if rescue else (0.0, 0.0)
    use_F = F_aligned is not None
    F = np.ascontiguousarray(F_aligned, np.float64) if use_F else np.eye(3)
    keep, lo, hi, lines, rescued = kernels.search_regions_kernel(p, use_so, *so_args, rescue, r_lo, r_hi, use_F, F)
    return Regions(keep, lo, hi, lines if use_F else None, rescued)


def _search_regions_numpy(pts1a: np.ndarray, so, F_aligned: np.ndarray | None, inlier_x1_range=None,
                          outside_window: str = "drop") -> Regions:
    """:func:`search_regions` in NumPy."""
    nq = len(pts1a)
    keep, lo, hi = np.ones(nq, bool), np.full(nq, -np.inf), np.full(nq, np.inf)
    rescued = np.zeros(nq, bool)
    if so is not None:
        from .spatial_order import admissible_x_ranges

        keep, lo, hi, _ = admissible_x_ranges(so, pts1a[:, 0])
        keep, lo, hi = np.asarray(keep, bool), np.asarray(lo, np.float64).copy(), np.asarray(hi, np.float64).copy()
        if outside_window == "band" and F_aligned is not None and inlier_x1_range is not None:
            rescued = ~keep & (pts1a[:, 0] >= inlier_x1_range[0]) & (pts1a[:, 0] <= inlier_x1_range[1])
            keep = keep | rescued
            lo[rescued], hi[rescued] = -np.inf, np.inf
    lines = None
    if F_aligned is not None:
        lines = map_points(F_aligned, pts1a)  # element-wise, no BLAS threads (see map_points)
        nrm = np.hypot(lines[:, 0], lines[:, 1])
        bad = ~(nrm > 1e-12)
        lines[bad] = [0.0, 0.0, np.inf]
        nrm[bad] = 1.0
        lines = np.ascontiguousarray(lines / nrm[:, None])
    return Regions(keep, lo, hi, lines, rescued)


@dataclass(frozen=True, eq=False)
class GuidanceModels:
    """The models of one update (§III-B..E); the final ones are returned by ``match(..., return_models=True)``.

    Attributes:
        F: ``(3,3)`` fundamental matrix in original pixel coordinates, or None (no epipolar guidance).
        F_aligned: F in aligned coordinates, ``H2^-T F H1^-1`` (None without F).
        inlier_x1_range: ``(min, max)`` aligned image-1 x of the F inliers (band-only rescue), or None.
        H1, H2: alignment homographies applied to image-1 / image-2 keypoints (identity without IA).
        so: the :class:`~guidedmatch.spatial_order.SpatialOrderModel` (aligned x), or None.
        pts1a, pts2a: aligned keypoints ``(N1,2)``, ``(N2,2)``.
        band_px: epipolar band half-width (aligned pixels). outside_window: the run's policy ("drop" | "band").
        final_queries: image-1 indices matched in the final vectorized pass (set on the final models).
    """

    F: np.ndarray | None
    F_aligned: np.ndarray | None
    inlier_x1_range: tuple[float, float] | None
    H1: np.ndarray
    H2: np.ndarray
    so: object | None
    pts1a: np.ndarray
    pts2a: np.ndarray
    band_px: float
    outside_window: str = "drop"
    final_queries: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def guided(self) -> bool:
        """Some guidance exists (an F model or a usable spatial-order model)."""
        return self.F is not None or self.so is not None

    def regions(self, queries: np.ndarray) -> Regions:
        """:func:`search_regions` of image-1 features ``queries`` -- as the matcher used them."""
        queries = np.asarray(queries, np.int64)
        return search_regions(self.pts1a[queries], self.so, self.F_aligned, self.inlier_x1_range, self.outside_window)

    def candidates(self, i1: int) -> np.ndarray:
        """Reference (O(N2), plain NumPy) candidate set of image-1 feature ``i1``: image-2 indices."""
        r = self.regions(np.array([i1]))
        if not r.keep[0]:
            return np.zeros(0, np.int64)
        x = self.pts2a
        ok = (x[:, 0] >= r.lo[0]) & (x[:, 0] <= r.hi[0])
        if r.lines is not None:
            ok &= np.abs(x @ r.lines[0, :2] + r.lines[0, 2]) <= self.band_px
        return np.flatnonzero(ok)


# ============================================================================================== match filters
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


class _Accepted(NamedTuple):
    """Matches accepted from one batch of queries: image-1 index, image-2 index, distance, single-candidate flag."""

    q: np.ndarray
    j: np.ndarray
    d: np.ndarray
    single: np.ndarray


class _Collected:
    """Matches accumulated over the phases of a run (with the phase each was made in)."""

    def __init__(self):
        self.parts: list[tuple[_Accepted, int]] = []

    def add(self, acc: _Accepted, phase: int) -> None:
        self.parts.append((acc, phase))

    def pairs_so_far(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([a.q for a, _ in self.parts]), np.concatenate([a.j for a, _ in self.parts])

    def arrays(self):
        cat = lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt)  # noqa: E731
        q = cat([a.q for a, _ in self.parts], np.int64)
        j = cat([a.j for a, _ in self.parts], np.int64)
        d = cat([a.d for a, _ in self.parts], np.float32)
        single = cat([a.single for a, _ in self.parts], bool)
        phase = cat([np.full(len(a.q), p, np.int64) for a, p in self.parts], np.int64)
        return q, j, d, single, phase


# ============================================================================================== the guided run
class _GuidedRun:
    """State of one guided match (not public); :meth:`run` is the method in order."""

    def __init__(self, config: MatcherConfig, mode: Mode, p1, p2, d1, d2, binary):
        self.c = config
        self.mode = mode
        self.p1, self.p2 = p1, p2  # guidedmatch.prepared.PreparedImage of each side
        self.f1, self.f2 = p1.features, p2.features
        self.d1, self.d2, self.binary = d1, d2, binary
        # descriptors in the kernel's form, prepared once per image: packed words (binary); byte-valued float
        # descriptors (OpenCV SIFT) as exact uint8 copies (int32 L2 in the kernel) when both sides are byte-valued
        self.byte_exact = bool(p1.byte_exact and p2.byte_exact)
        if binary or self.byte_exact:
            self.kdesc1, self.kdesc2 = p1.kdesc, p2.kdesc
        else:
            self.kdesc1, self.kdesc2 = d1, d2
        self.checks: list[dict] = []            # verdict checks of the unguided start
        self.decision = None                    # the last TwoViewGeometry decided on unguided evidence
        self.early_exit: str | None = None
        self.unguided_search = None             # "gemm" | "gemm+ivf" | "ivf" | "popcount" (UnguidedSearch.used)
        self.unguided_comparisons = 0
        self.last_alignment = None              # SafeAlignment of the latest model fit (mode IA)
        self.fallbacks: list[Fallback] = []
        self.ncand: list[np.ndarray] = []
        self.timing = dict.fromkeys((f.name for f in dataclasses.fields(PhaseTimes)), 0.0)
        self.updates: list[ModelUpdate] = []
        self.dropped_outside_overlap = 0
        self.no_region = 0
        self.band_only = 0
        self.d2_sqnorms = None
        self.phase_queries: dict[int, int] = {}
        self.phase_comparisons: dict[int, int] = {}
        self.guidance: GuidanceModels | None = None
        self.strip_cache: dict[int, kernels.StripIndex] = {}  # strip indexes of the current models' image-2 points
        self.mutual_comparisons = 0
        self.no_strips = kernels.build_strips(np.zeros((0, 2)), 1.0)

    def fallback(self, what: str, reason: str) -> None:
        """Report a degraded step (:class:`~guidedmatch.results.Fallback`)."""
        self.fallbacks.append(Fallback(what, reason, len(self.updates)))

    def account(self, nq: int, ncomp: int) -> None:
        """Count ``nq`` queries and ``ncomp`` descriptor distances in the current phase (= updates done)."""
        k = len(self.updates)
        self.phase_queries[k] = self.phase_queries.get(k, 0) + int(nq)
        self.phase_comparisons[k] = self.phase_comparisons.get(k, 0) + int(ncomp)

    # ------------------------------------------------------------------------------------------ the method
    def run(self) -> MatchResult:
        """The method: steps 1-8 of the module doc, in order (one method each, below in the same order)."""
        t_start = time.perf_counter()
        order = self.draw_order()
        got = _Collected()
        models, rest = self.progressive_phase(order, got)
        self.final_pass(models, rest, got)
        q, j, d, single, phase = got.arrays()
        q, j, d, flags, dropped_recheck = self.recheck(models, q, j, d, dict(phase=phase, single_candidate=single))
        q, j, d, flags, dropped_o2o, dropped_mutual = self.filters(q, j, d, flags)
        o = np.argsort(q, kind="stable")
        q, j, d = q[o], j[o], d[o]
        flags = {k: v[o] for k, v in flags.items()}
        dropped = (self.c.unverified == "drop" and self.decision is not None
                   and self.decision.verdict == "no-overlap")  # result() returns none of them: nothing to score
        flags["so_prob"] = np.full(len(q), np.nan, np.float32) if dropped else self.so_probabilities(models, q, j)
        return self.result(t_start, models, q, j, d, flags, dropped_recheck, dropped_o2o, dropped_mutual)

    def draw_order(self) -> np.ndarray:
        """Step 1 (§III-A): :func:`draw_order` keyed by detector response (strongest first), else seeded noise."""
        n1 = len(self.d1)
        if n1 == 0 or len(self.d2) == 0:
            return np.zeros(0, np.int64)
        x = self.f1.keypoints[:, 0]
        w = max(float(self.f1.image_size[0]), float(x.max()) + 1)
        r = self.f1.responses
        if r is not None and np.any(r != r[0]):
            key = -r.astype(np.float32)
        else:
            key = np.random.default_rng(self.c.seed).random(n1, np.float32)
        return draw_order(x, w, self.c.num_groups, key)

    def progressive_phase(self, order: np.ndarray, got: _Collected) -> tuple[GuidanceModels | None, np.ndarray]:
        """Steps 2-4 (§III-A): mini-batches, unguided until the first models (:meth:`unguided_start`), guided after;
        refit the models after every ``update_every`` new correspondences, ``num_updates`` times. Returns the last
        models and the queries left for the final pass (none after an early exit)."""
        c = self.c
        if c.num_updates == 0 or len(order) == 0:
            return None, order
        models, ptr = self.unguided_start(order, got)
        if models is None:  # no verified evidence: nothing guides; early exit leaves the rest unmatched
            if self.early_exit is None and ptr < len(order):
                return None, order[ptr:]
            return None, order[:0]
        since = 0
        total = sum(len(a.q) for a, _ in got.parts)
        drawn = accepted = 0  # guided queries so far and their accepted matches (the acceptance rate)
        while ptr < len(order) and len(self.updates) < c.num_updates:
            # batches sized by the observed acceptance rate to reach the next update in about one batch (at least
            # batch_size): few kernel calls on low-overlap pairs, the same update points on rich ones
            rate = (accepted + 1.0) / (drawn + 1.0) if drawn else 1.0
            bs = int(min(max(c.batch_size, np.ceil((c.update_every - since) / rate)), 8 * c.batch_size + c.update_every))
            batch = order[ptr: ptr + (bs if drawn else c.batch_size)]
            ptr += len(batch)
            t0 = time.perf_counter()
            acc = self.guided_batch(models, batch) if models.guided else self.unguided_batch(batch)
            self.timing["guided_progressive_s"] += time.perf_counter() - t0
            got.add(acc, len(self.updates))
            drawn += len(batch)
            accepted += len(acc.q)
            since += len(acc.q)
            total += len(acc.q)
            if since >= c.update_every:
                since = 0
                models = self.fit_models(*got.pairs_so_far())
        if len(self.updates) < c.num_updates and len(self.d1):
            self.fallback("updates", f"only {len(self.updates)} of {c.num_updates} model updates: "
                          f"{total} correspondences from all {len(self.d1)} features (need {c.update_every} per update)")
        return models, order[ptr:]

    def unguided_start(self, order: np.ndarray, got: _Collected) -> tuple[GuidanceModels | None, int]:
        """Step 2 (§III-A; the gate is beyond the paper, issue 11): match drawn features against all of image 2
        until a first model may guide. Returns ``(models or None, queries consumed)``.

        ``start="paper"``: the first model is fitted after ``update_every`` correspondences (exact search), whatever
        they are; the verdict on them is only reported. ``start="verified"``: the unguided correspondences are the
        evidence (no model selected them). After ``first_check`` of them, and each time they have grown by
        ``check_growth``, :func:`~guidedmatch.geometry.two_view_geometry` decides; the first model is fitted as soon
        as it says "verified" -- a model fitted on too little evidence never guides. The search is exact for the first
        ``min(index build comparisons, exact_rent * exit budget)`` comparisons, then the approximate index of image 2
        (:class:`~guidedmatch.prepared.UnguidedSearch`, ``unguided_index``, ``exact_rent``). When the
        start has spent ``max_unguided * N1 * N2`` comparisons plus the exact rent without verified evidence it stops
        (early exit, verdict from the last check: "no-overlap" / "too-few-matches"), the remaining features are not
        matched.
        """
        from .prepared import UnguidedSearch

        c = self.c
        n1, n2 = len(self.d1), len(self.d2)
        paper = c.start == "paper"
        kind = UnguidedSearch.choose(self.p2, use_index=c.unguided_index and not paper)
        frac = c.max_unguided if c.max_unguided is not None else (0.02 if kind == "ivf" else 0.5)
        budget = frac * n1 * n2
        # ski-rental: exact search until it has cost what building the index costs (capped at exact_rent of the exit
        # budget), the index after -- the same rule whether or not image 2 was prepared, so the same matches
        rent = min(float(self.p2.build_comparisons), c.exact_rent * budget) if kind == "ivf" else 0.0
        if rent < max(c.batch_size, 2 * c.first_check) * n2:
            rent = 0.0  # too few exact queries to reach a first verdict check: pure overhead (8192 SIFT: 37 queries)
        budget += rent  # the rent is not taken from the index's evidence budget: the exit at <= (1 + exact_rent) frac
        # (up to 1.25x that while fewer than 8 correspondences exist: no model could be tested on them yet)
        models = None
        total = ptr = 0
        next_check = max(c.first_check, c.min_model_matches)
        checked_at = -1
        with UnguidedSearch(self.p1, self.p2, kind, exact_budget=rent) as search:
            while ptr < len(order):
                if search.exact:
                    n = c.batch_size
                    if kind == "ivf":  # the last exact batch is cut to the rent
                        n = int(min(n, max(1, np.ceil((rent - search.exact_comparisons) / max(n2, 1)))))
                else:
                    n = max(c.batch_size, 256)  # an index search has no GEMM to fill
                    if not paper and total and ptr:
                        # the queries expected to reach the next verdict check at the acceptance rate so far (+10 %),
                        # in one call: a faiss call costs ~0.3 ms fixed and its coarse GEMM is 2x faster per query
                        # in batches of 1000+ (8192 SIFT: 4352 queries 17.2 ms in 256s, 13.2 ms in 1024s)
                        n = max(n, min(4096, int(1.1 * (next_check - total) * ptr / total)))
                if not paper and ptr:  # the last batch before the budget is cut to fit it (+ <= 8 queries)
                    left = (budget - self.unguided_comparisons) / max(search.per_query(), 1.0)
                    n = int(min(n, max(8, np.ceil(left)))) if left > 0 else min(n, 64)  # past it (< 8 found): 64 at a time
                batch = order[ptr: ptr + n]
                ptr += len(batch)
                t0 = time.perf_counter()
                acc = self.unguided_batch(batch, search)
                self.timing["initial_bf_s"] += time.perf_counter() - t0
                self.unguided_search = search.used
                got.add(acc, 0)
                total += len(acc.q)
                if paper:
                    if total >= c.update_every and total >= c.min_model_matches:
                        self.decide(got)
                        models = self.fit_models(*got.pairs_so_far())
                        break
                    continue
                if total >= next_check:
                    checked_at = total
                    g = self.decide(got)
                    if g and not self.strong(g):
                        g = self.recheck_weak(got)  # weak at the quick check: a full-strength search decides
                    if self.strong(g):
                        # the first model is fitted anew (ransac_method, 10000 iterations): the verdict's quick F is only a
                        # gate (reusing a quick PROSAC F lost 20-70 % of the true matches on 0000-0003 / 0002-0006),
                        # but it must pass the verdict's rule (frame_hypotheses, fit_fundamental)
                        models = self.fit_models(*got.pairs_so_far(), verdict=g)
                        break
                    next_check = max(next_check + 1, int(np.ceil(total * c.check_growth)))
                if self.unguided_comparisons >= budget and ptr < len(order):
                    if total < 8 and self.unguided_comparisons < 1.25 * budget:
                        continue  # fewer than F's 8 correspondences: nothing could be tested yet; a little longer
                    self.early_exit = (f"unguided start spent {self.unguided_comparisons / max(n1 * n2, 1):.1%} of "
                                       f"N1*N2 ({budget / max(n1 * n2, 1):.1%} allowed) on {ptr} of {n1} features "
                                       f"without evidence strong enough to guide; the remaining {len(order) - ptr} "
                                       "features are not matched")
                    break
            self.timing["index_build_s"] += search.index_build_s
            self.timing["initial_bf_s"] -= search.index_build_s
            self.unguided_search = search.used
        if models is None:
            if checked_at != total or self.decision is None:
                self.decide(got)  # the verdict on all the evidence there is
            if paper:
                self.fallback("updates", f"only 0 of {c.num_updates} model updates: {total} correspondences from all "
                              f"{n1} features (need {c.update_every} per update)")
                return None, ptr
            what = "early_exit" if self.early_exit else "no_model"
            weak = " (verified, but below guide_margin: no model guided)" if self.decision else ""
            why = self.early_exit or (f"the unguided correspondences were never verified strongly enough to guide "
                                      f"(last verdict {self.decision.verdict!r}{weak}); every feature matched "
                                      "against all of image 2")
            self.fallback(what, why + f"; {self.decision.reason}")
        return models, ptr

    def strong(self, g) -> bool:
        """A verified verdict strong enough to guide: the model's inliers reach ``guide_margin`` times
        ``max(random-inlier bound, min_inliers)`` (a weak one is reported, not followed)."""
        if not g:
            return False
        e = g.evidence
        n, bound = (e["H_inliers"], e["random_bound_H"]) if g.model == "H" else (e["F_inliers"], e["random_bound_F"])
        return n >= self.c.guide_margin * max(bound, 15.0)

    def recheck_weak(self, got: _Collected):
        """Redo a verified but weak quick check at full strength (10000 RANSAC iterations): on the
        orientation-consistent subset of the evidence (geometry step 4, ``second_search="only"``; the quick check's F
        stays a hypothesis) when the features have orientations and ``frame_hypotheses`` is on, else over all the
        evidence. At the inlier ratios of weak pairs (20-35 %) 10000 draws over all the evidence never reach RANSAC's
        confidence and cost ~12 ms at 50-130 correspondences; the subset's ratio is 2-4x higher (Herz-Jesus-P8, all
        pairs, 8192 and ~40k SIFT: faster, and more GT inliers on both sets, docs/pairs.md)."""
        if self.c.verdict_iters >= 10000:
            return self.decision
        if _has_frames(self.c, self.f1, self.f2):
            return self.decide(got, second_search="only", second_iters=10000)
        return self.decide(got, 10000)

    def decide(self, got: _Collected, max_iters: int | None = None, **second):
        """The two-view verdict on the unguided correspondences so far (phase 0: no model selected them), with
        ``verdict_iters`` RANSAC iterations (or ``max_iters``); ``second``: ``second_search`` / ``second_iters`` of
        :func:`~guidedmatch.geometry.two_view_geometry`."""
        from .geometry import VerdictConfig, two_view_geometry

        t0 = time.perf_counter()
        q = np.concatenate([a.q for a, p in got.parts if p == 0]) if got.parts else np.zeros(0, np.int64)
        j = np.concatenate([a.j for a, p in got.parts if p == 0]) if got.parts else np.zeros(0, np.int64)
        # uniform MAGSAC++ (the calibrated rule). PROSAC on ratio-sorted evidence finds weak models in fewer
        # iterations (AKAZE 0000-0005 at 12k) but also "verified" a false F on 0001-0007 at 8192 (45 of 247 inliers
        # correct under the GT cameras), so it is not used for the decision.
        prior = self.decision.F if self.decision is not None and self.decision.model == "F" else None
        g = two_view_geometry(self.f1.keypoints[q], self.f2.keypoints[j], self.f1.image_size, self.f2.image_size,
                              VerdictConfig(seed=self.c.seed, max_iters=max_iters or self.c.verdict_iters),
                              F_prior=prior, frames=_frames(self.c, self.f1, self.f2, q, j), **second)
        self.decision = g
        self.checks.append(dict(evidence=int(len(q)), verdict=g.verdict, model=g.model, strong=self.strong(g),
                                iterations=int(second.get("second_iters") or max_iters or self.c.verdict_iters),
                                search="orientation subset" if second else "all",
                                F_inliers=g.evidence.get("F_inliers"), H_inliers=g.evidence.get("H_inliers"),
                                bound_F=round(float(g.evidence.get("random_bound_F", 0.0)), 1),
                                comparisons=int(self.unguided_comparisons)))
        self.timing["verdict_s"] += time.perf_counter() - t0
        return g

    def unguided_batch(self, queries: np.ndarray, search=None) -> _Accepted:
        """Step 2: 2-NN of ``queries`` over all of image 2: ``search`` (:class:`~guidedmatch.prepared.UnguidedSearch`,
        the unguided start) or exact (a final pass without models)."""
        if search is not None:
            i1, s1, i2, s2, comp = search.query(queries)
            self.account(len(queries), comp)
            self.unguided_comparisons += comp
            nq = max(len(queries), 1)
            self.ncand.append(np.full(len(queries), comp // nq, np.int64))
            # single-candidate logic: an index search that found one neighbour has no second to test against
            found = np.where(i2 >= 0, 2, np.where(i1 >= 0, 1, 0))
            return self.select(queries, i1, s1, s2, np.minimum(found, len(self.d2)))
        if self.d2_sqnorms is None and not self.binary:
            self.d2_sqnorms = self.p2.sqnorms
        (i1, s1, _i2, s2), _ = knn2(self.d1[queries], self.d2, d2_sqnorms=self.d2_sqnorms, checked=True)
        # knn2 returns L2 distances; convert back to the kernel's squared form for select()
        if not self.binary:
            s1, s2 = s1 * s1, s2 * s2
        n2 = len(self.d2)
        self.account(len(queries), len(queries) * n2)
        nc = np.full(len(queries), n2, np.int64)
        self.ncand.append(nc)
        return self.select(queries, i1, s1, s2, nc)

    def select(self, queries, i1, s1, s2, ncand) -> _Accepted:
        """Ratio / single-candidate / max-distance tests on 2-NN results (``s1, s2``: squared L2 or Hamming)."""
        c = self.c
        dist1 = s1 if self.binary else np.sqrt(s1)
        dist2 = s2 if self.binary else np.sqrt(s2)
        keep = i1 >= 0
        single = keep & (ncand == 1)
        if c.ratio is not None:
            keep &= (dist1 < np.float32(c.ratio) * dist2) | single
        if c.single_candidate == "reject":
            keep &= ~single
        if c.max_distance is not None:
            keep &= dist1 <= c.max_distance
        return _Accepted(queries[keep], i1[keep], dist1[keep].astype(np.float32), single[keep])

    # ------------------------------------------------------------------------------------------ step 3: models
    def fit_models(self, acc_i: np.ndarray, acc_j: np.ndarray, verdict=None) -> GuidanceModels:
        """Step 3 (§III-B..E): refit F, the alignment and the spatial-order model on all correspondences so far
        (``verdict``: the first fit's verified decision on the same correspondences, see :meth:`fit_fundamental`)."""
        t0 = time.perf_counter()
        self.last_alignment = None
        k1, k2 = self.f1.keypoints, self.f2.keypoints
        p1, p2 = k1[acc_i], k2[acc_j]
        fr = self.fit_fundamental(p1, p2, verdict) if (self.mode.use_epi or self.mode.use_ia) else None
        F, inl = (fr.F, np.asarray(fr.inliers, bool)) if fr is not None else (None, None)
        al = self.fit_alignment(F, p1[inl], p2[inl]) if self.mode.use_ia and F is not None else None
        H1, H2 = (np.asarray(al.H1, float), np.asarray(al.H2, float)) if al is not None else (np.eye(3), np.eye(3))
        H1, H2, pts1a, pts2a = self.aligned_points(H1, H2)
        F_aligned = x1_range = None
        if F is not None:
            from .epipolar import transform_fundamental

            F_aligned = transform_fundamental(F, H1, H2)
            xin = pts1a[acc_i[inl], 0]
            x1_range = (float(xin.min()), float(xin.max()))
        so_fit = self.fit_spatial_order(pts1a, pts2a, acc_i, acc_j, inl) if self.mode.use_so else None
        so = so_fit if so_fit is not None and so_fit.usable else None
        foc = al.focal if al is not None else None
        safe = self.last_alignment if al is not None else None
        self.updates.append(ModelUpdate(
            update=len(self.updates) + 1, num_correspondences=int(len(acc_i)),
            F_inliers=int(fr.num_inliers) if fr is not None else None,
            F_fit=fr.stats.get("fit", "ransac") if fr is not None else None,
            focal=(float(foc.f1), float(foc.f2)) if foc is not None else None,
            focal_fallback=(bool(foc.fallback1), bool(foc.fallback2)) if foc is not None else None,
            roll_deg=float(al.roll_deg) if al is not None else None, H2=H2 if al is not None else None,
            alignment_scale=tuple(float(v) for v in safe.check.scale_range) if safe is not None else None,
            alignment=self.last_alignment.approach if self.last_alignment is not None and self.mode.use_ia else None,
            so_usable=bool(so_fit.usable) if so_fit is not None else None,
            n_good=float(so_fit.n_good) if so_fit is not None else None,
            k_hat=float(so_fit.k_hat) if so_fit is not None else None,
            window1_x=tuple(map(float, so_fit.window1_x)) if so_fit is not None else None,
            window2_x=tuple(map(float, so_fit.window2_x)) if so_fit is not None else None))
        self.strip_cache = {}
        self.timing["model_fit_s"] += time.perf_counter() - t0
        return GuidanceModels(F, F_aligned, x1_range, H1, H2, so, pts1a, pts2a, float(self.c.band_px),
                              self.c.outside_window)

    def fit_fundamental(self, p1, p2, verdict=None):
        """§III-D: F by OpenCV USAC (``ransac_method``): the :class:`~guidedmatch.epipolar.FundamentalResult`, or
        None when it fails (reported).

        ``verdict`` (the first fit, ``frame_hypotheses``): the verified "F" decision on these same correspondences.
        The fresh F must pass the verdict's own rule on them (independent inliers >= ``min_inliers`` and above the
        random bound, :func:`~guidedmatch.geometry.fundamental_support`); at a low inlier ratio RANSAC on all of
        them fails where the verdict's second search succeeded (geometry step 4), and the fresh F would guide
        wrong matches into its band (Herz-Jesus 0000-0006 at ~40k: 72 of 1010 correct). Then F is refitted on the
        verdict F's inliers (kept if it explains at least as much; else the verdict's F), reported as a fallback.
        When the verdict's inlier ratio ``w`` is so low that 10000 draws cannot reach RANSAC's confidence
        (``log(0.001) / log(1 - w^7) > 10000``, i.e. ``w`` < ~0.43), the fresh fit is skipped and F is refitted on the
        verdict F's inliers directly (``ModelUpdate.F_fit = "verdict inliers"``): the fresh fit would run all 10000
        draws (~12 ms at 100 correspondences) for a model the check above mostly rejects (Herz-Jesus-P8, all pairs:
        faster, GT inliers up at 8192 and ~40k, docs/pairs.md). (When the fit fails outright, that failure is
        reported as before.)"""
        from . import epipolar

        c = self.c
        first = verdict is not None and c.frame_hypotheses and verdict.model == "F" and verdict.F is not None
        if first and _ransac_draws(verdict) > 10000:
            fr = self.refit_on_verdict(verdict, p1, p2, None)
        else:
            fr = epipolar.estimate_fundamental(p1, p2, method=c.ransac_method, threshold=c.ransac_threshold,
                                               seed=c.seed)
            if fr and first:
                fr = self.verified_first_F(fr, verdict, p1, p2)
        if fr:
            return fr
        self.fallback("fundamental", f"F estimation failed: {fr.reason}; "
                      + ("spatial order only" if self.mode.use_so else "no epipolar guidance"))
        return None

    def verified_first_F(self, fr, verdict, p1, p2):
        """:meth:`fit_fundamental`'s check of the first F against the verified ``verdict`` on ``p1 <-> p2``."""
        from .geometry import VerdictConfig, fundamental_support

        vc = VerdictConfig(seed=self.c.seed)
        bound = float(verdict.evidence.get("random_bound_F", 0.0))
        n_fresh = fundamental_support(fr.F, p1, p2, self.f1.image_size, self.f2.image_size, vc)
        if n_fresh >= vc.min_inliers and n_fresh > bound:  # the verdict's rule (geometry step 3)
            return fr
        return self.refit_on_verdict(verdict, p1, p2, n_fresh)

    def refit_on_verdict(self, verdict, p1, p2, n_fresh):
        """F refitted (``ransac_method``) on the inliers of the verdict's F among ``p1 <-> p2``, kept when it has at
        least the verdict F's independent inliers, else the verdict's F (``stats["fit"]``: ``"verdict inliers"`` /
        ``"verdict"``, reported as ``ModelUpdate.F_fit``). ``n_fresh``: the support of a rejected fresh fit (reported
        as a fallback), or None (no fresh fit: :meth:`fit_fundamental`'s low-ratio rule)."""
        from . import epipolar
        from .geometry import VerdictConfig, fundamental_support

        c = self.c
        vc = VerdictConfig(seed=c.seed)
        sizes = (self.f1.image_size, self.f2.image_size)
        with np.errstate(invalid="ignore", divide="ignore"):
            inl = epipolar.sampson_distance(np.asarray(verdict.F, np.float64), p1, p2) <= vc.threshold_px
        F, n_v = np.asarray(verdict.F, np.float64), fundamental_support(verdict.F, p1, p2, *sizes, vc)
        refit = epipolar.estimate_fundamental(p1[inl], p2[inl], method=c.ransac_method, threshold=c.ransac_threshold,
                                              seed=c.seed)
        used, fit = "the verdict's F", "verdict"
        if refit and fundamental_support(refit.F, p1, p2, *sizes, vc) >= n_v:
            F, used, fit = refit.F, f"F refitted on the verdict F's {int(inl.sum())} inliers", "verdict inliers"
        with np.errstate(invalid="ignore", divide="ignore"):
            mask = epipolar.sampson_distance(F, p1, p2) <= c.ransac_threshold
        if n_fresh is not None:
            bound = float(verdict.evidence.get("random_bound_F", 0.0))
            self.fallback("fundamental", f"first F fitted on all {len(p1)} correspondences has {n_fresh} independent "
                          f"inliers (the verdict's F {n_v}, random bound {bound:.0f}): {used} guides")
        return epipolar.FundamentalResult(F, mask, int(mask.sum()), c.ransac_method, float(c.ransac_threshold),
                                          dict(fit=fit, fresh_support=n_fresh, verdict_support=int(n_v)))

    def fit_alignment(self, F, p1_in, p2_in):
        """§III-E: the alignment (``H1``, ``H2``, Bougnoux focal, roll) from F and its inliers for the ``alignment``
        approach, validated over the keypoints (:func:`~guidedmatch.alignment.safe_alignment`: local scale,
        orientation, line at infinity) with the fallback requested approach -> in-plane rotation (``c_inplane``) ->
        none, every rejection reported; None when no alignment is used (the run then matches in original
        coordinates). ``self.last_alignment``: the :class:`~guidedmatch.alignment.SafeAlignment`."""
        from . import alignment

        safe = alignment.safe_alignment(F, p1_in, p2_in, self.f1.image_size, self.f2.image_size, self.c.alignment,
                                        self.f2.keypoints, self.f1.keypoints)
        self.last_alignment = safe
        for ap, why in safe.fallbacks:
            nxt = {"c_inplane": "in-plane rotation only (c_inplane)", "none": "original coordinates"}
            used = nxt.get(safe.approach, safe.approach) if (ap, why) == safe.fallbacks[-1] else "the next approach"
            self.fallback("alignment", f"alignment {ap!r} rejected: {why}; {used} used")
        if safe.result is None:
            return None
        al = safe.result
        foc = al.focal
        for k, (fb, why) in enumerate(((foc.fallback1, foc.reason1), (foc.fallback2, foc.reason2)), 1):
            if fb:
                self.fallback(f"focal{k}", f"Bougnoux focal of image {k} unusable ({why}); f = w + h used")
        return al

    def aligned_points(self, H1, H2):
        """Keypoints in the aligned frame; identity (reported) when a homography sends a keypoint to infinity."""
        from .alignment import apply_homography

        k1, k2 = self.f1.keypoints, self.f2.keypoints
        pts1a = k1 if np.allclose(H1, np.eye(3)) else apply_homography(H1, k1)
        pts2a = k2 if np.allclose(H2, np.eye(3)) else apply_homography(H2, k2)
        if not (np.all(np.isfinite(pts1a)) and np.all(np.isfinite(pts2a))):
            self.fallback("alignment", "alignment homography sends keypoints to infinity; matching in original coordinates")
            return np.eye(3), np.eye(3), k1, k2
        return H1, H2, pts1a, pts2a

    def fit_spatial_order(self, pts1a, pts2a, acc_i, acc_j, likely_correct):
        """§III-B, §III-C: the spatial-order model on aligned x (``likely_correct``: the F inliers, which measure its
        order noise); an unusable model is reported (and not used)."""
        from . import spatial_order

        c = self.c
        so = spatial_order.fit_spatial_order(
            pts1a[acc_i, 0], pts2a[acc_j, 0], spatial_order.SpatialOrderConfig(threshold=c.so_threshold, overlap=c.so_overlap),
            y1=pts1a[acc_i, 1], y2=pts2a[acc_j, 1], likely_correct=likely_correct)
        if not so.usable:
            self.fallback("spatial_order", f"spatial-order model unusable ({so.reason}); "
                          + ("epipolar band only" if likely_correct is not None else "unguided"))
        return so

    # ------------------------------------------------------------------------------------ steps 4-5: guided
    def strips(self, m: GuidanceModels, lines: np.ndarray, axis: int) -> kernels.StripIndex:
        """Strip index of the aligned image-2 points for lines mostly along ``axis`` (0: horizontal-ish), built on
        first use under the current models.

        Strip width ``w = sqrt(6 / (rho * s))`` (clipped to [4 band, 256] px) balances the per-strip cost (a visit,
        a loop exit) against the points scanned outside the band in each strip (``rho * s * w`` per unit length;
        ``rho`` = image-2 points per px² of their bounding box, ``s`` = median |slope| of the lines against the
        strip direction); the constant 6 is from Herz-Jesus 0002/0003 (flat optimum 96-192 px at s = 0.07).
        Cells along the strip are band/2 high. Speed only: the candidates are the exact region either way.
        """
        if axis in self.strip_cache:
            return self.strip_cache[axis]
        band = float(self.c.band_px)
        if self.c.strip_px:
            w = float(self.c.strip_px)
        elif len(lines) == 0 or m.F is None:
            w = 64.0
        else:
            x, y = m.pts2a[:, 0], m.pts2a[:, 1]  # (per-column min/max: np.ptp(axis=0) on (N, 2) is 10x slower)
            area = (x.max() - x.min()) * (y.max() - y.min()) if len(x) else 1.0
            rho = len(x) / max(float(area), 1.0)
            s = float(np.median(np.abs(lines[:, axis]) / np.maximum(np.abs(lines[:, 1 - axis]), 1e-12)))
            w = float(np.clip(np.sqrt(6.0 / max(rho * max(s, 1e-3), 1e-12)), 4.0 * band, 256.0))
        self.strip_cache[axis] = kernels.build_strips(m.pts2a, max(w, 1e-3), axis, max(band / 2.0, 0.5))
        return self.strip_cache[axis]

    def guided_batch(self, m: GuidanceModels, queries: np.ndarray) -> _Accepted:
        """Steps 4-5: best two candidates of each query in its search region (:func:`search_regions`), one call of
        the Numba kernel; features outside ω* (not rescued) are dropped unmatched."""
        keep, lo, hi, lines, rescued = m.regions(queries)
        self.dropped_outside_overlap += int((~keep).sum())
        self.band_only += int(rescued.sum())
        if lines is None:
            lines = np.zeros((len(queries), 3))
        q = queries[keep]
        lines, lo, hi = lines[keep], lo[keep], hi[keep]
        # process queries in image-1 position order (32 px cells row by row: the point order of a row-strip index):
        # neighbours share candidates, which stay in cache; the order changes nothing but speed
        o = kernels.build_strips(m.pts1a[q], 32.0, axis=1, cell=32.0).items
        use_band = m.F is not None
        vertical = np.abs(lines[:, 0]) > np.abs(lines[:, 1]) if use_band else np.zeros(len(q), bool)
        cols = self.strips(m, lines[~vertical], 0)
        rows = self.strips(m, lines[vertical], 1) if (1 in self.strip_cache or vertical.any()) else self.no_strips
        i1, s1, _i2, s2, nc = kernels.guided_top2(q[o], self.kdesc1, self.kdesc2, lines[o], use_band,
                                                  float(self.c.band_px), lo[o], hi[o], cols, rows)
        inv = np.empty_like(o)
        inv[o] = np.arange(len(o))
        i1, s1, s2, nc = i1[inv], s1[inv], s2[inv], nc[inv]
        self.account(len(queries), int(nc.sum()))
        self.ncand.append(nc)
        self.no_region += int((nc == 0).sum())
        return self.select(q, i1, s1, s2, nc)

    def final_pass(self, models: GuidanceModels | None, rest: np.ndarray, got: _Collected) -> None:
        """Step 5: every remaining image-1 feature in one vectorized call (unguided when no model was fitted)."""
        if len(rest):
            t0 = time.perf_counter()
            acc = self.guided_batch(models, rest) if models is not None and models.guided else self.unguided_batch(rest)
            self.timing["final_pass_s"] += time.perf_counter() - t0
            got.add(acc, len(self.updates))
        if models is not None and models.guided:
            self.guidance = dataclasses.replace(models, final_queries=np.asarray(rest, np.int64))

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

    # ------------------------------------------------------------------------------------ step 8: result
    def so_probabilities(self, models: GuidanceModels | None, q, j) -> np.ndarray:
        """Per-match spatial-order probability within the final match set (Talker Eq. 12), float32; NaN when not
        computed (mode without SO, < 2 matches) or when the model of the final set is unusable (reported)."""
        t0 = time.perf_counter()
        out = np.full(len(q), np.nan, np.float32)
        if self.mode.use_so and len(q) >= 2:
            from . import spatial_order

            pa1 = models.pts1a if models is not None else self.f1.keypoints
            pa2 = models.pts2a if models is not None else self.f2.keypoints
            # the matches already lie inside the model's overlap window: no new window search, no gap table
            so = spatial_order.fit_spatial_order(pa1[q, 0], pa2[j, 0],
                                                 spatial_order.SpatialOrderConfig(overlap="none", gap_table=False))
            if so.usable:
                out = np.asarray(so.probabilities, np.float32)
            else:
                self.fallback("so_prob", f"per-match probabilities not computed: spatial-order model of the final "
                              f"matches unusable ({so.reason}); so_prob = NaN")
        self.timing["so_prob_s"] = time.perf_counter() - t0
        return out

    def result(self, t_start, models, q, j, d, flags, dropped_recheck, dropped_o2o, dropped_mutual) -> MatchResult:
        """Step 8: the MatchResult with its :class:`~guidedmatch.results.MatchStats` (every count of the run) and the
        two-view verdict decided on the unguided evidence, reported over the final matches
        (:func:`~guidedmatch.geometry.report_geometry`); ``unverified="drop"`` empties an unverified result."""
        from .geometry import VerdictConfig, report_geometry

        t0 = time.perf_counter()
        x1, x2 = self.f1.keypoints[q], self.f2.keypoints[j]
        if self.decision is None:  # no unguided start ran (num_updates = 0): every match is unguided evidence
            got = _Collected()
            got.add(_Accepted(q, j, d, np.zeros(len(q), bool)), 0)
            self.decide(got)
        final_F = models.F if models is not None and models.F is not None else None
        geometry = report_geometry(self.decision, x1, x2, F=final_F, config=VerdictConfig(seed=self.c.seed))
        dropped_planar = 0
        planar = self.c.planar_recheck and geometry and geometry.model == "H" and len(q)
        if planar and _planar(geometry, final_F, x1, x2):
            # a planar scene (or pure rotation): the epipolar band of an F fitted to it constrains nothing along the
            # plane, the verified homography does -- guided matches off it are dropped (unguided ones stay, as in BF)
            keep = (flags["phase"] == 0) | geometry.inliers
            dropped_planar = int((~keep).sum())
            if dropped_planar:
                q, j, d = q[keep], j[keep], d[keep]
                flags = {k: v[keep] for k, v in flags.items()}
                geometry = geometry.with_inliers(geometry.inliers[keep])
        self.timing["verdict_s"] += time.perf_counter() - t0
        q, j, d, flags, geometry, dropped_unverified = _drop_unverified(self.c, q, j, d, flags, geometry,
                                                                        self.fallback)
        n1, n2 = len(self.d1), len(self.d2)
        nphase = len(self.updates) + 1
        phase_comparisons = tuple(self.phase_comparisons.get(k, 0) for k in range(nphase))
        stats = MatchStats(
            method=self.mode.name, comparisons=int(sum(phase_comparisons)) + self.mutual_comparisons,
            time_s=time.perf_counter() - t_start, num_features=(n1, n2), metric="hamming" if self.binary else "l2",
            byte_exact_kernel=self.byte_exact, timing=PhaseTimes(**self.timing), updates=tuple(self.updates),
            candidates_per_query=CandidateStats.of(np.concatenate(self.ncand) if self.ncand else np.zeros(0, np.int64)),
            queries_matched_against=int(sum(len(x) for x in self.ncand)),
            dropped_outside_overlap=self.dropped_outside_overlap, queries_without_candidates=self.no_region,
            band_only_outside_window=self.band_only, dropped_by_recheck=dropped_recheck,
            dropped_by_one_to_one=dropped_o2o, dropped_by_mutual=dropped_mutual,
            F=None if models is None or models.F is None else np.asarray(models.F),
            alignment_H2=None if models is None or np.allclose(models.H2, np.eye(3)) else np.asarray(models.H2),
            phase_queries=tuple(self.phase_queries.get(k, 0) for k in range(nphase)),
            phase_comparisons=phase_comparisons, fallbacks=tuple(self.fallbacks), config=self.c,
            details=dict(unguided_search=self.unguided_search, verdict_checks=tuple(self.checks),
                         early_exit=self.early_exit, unguided_comparisons=int(self.unguided_comparisons),
                         dropped_unverified=dropped_unverified, dropped_off_homography=dropped_planar))
        pairs = np.stack([q, j], axis=1) if len(q) else empty_pairs()
        return MatchResult(pairs, d, stats, flags, geometry)


def _planar(geometry, F, x1, x2) -> bool:
    """Whether the final matches ``x1 <-> x2`` still look planar: the verdict's homography explains at least
    ``h_ratio`` (COLMAP's rule, :class:`~guidedmatch.geometry.VerdictConfig`) as many of them as the final ``F``
    (Sampson distance within the same threshold). An "H" verdict taken on the few unguided correspondences of a 3-D
    scene with a dominant plane (Herz-Jesus 0004-0005 at ~40k) fails it: the final matches off the plane are F
    inliers, and they are kept."""
    from .geometry import VerdictConfig, sampson_distance

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


def _argsort_f32(key: np.ndarray) -> np.ndarray:
    """Stable ascending argsort of float32 ``key`` (ties by index) through one SIMD sort of unique uint64 keys
    (order-preserving float bits << 32 | index); 5x faster than NumPy's stable float sort at 40k."""
    b = np.ascontiguousarray(key, np.float32).view(np.uint32).astype(np.uint64)
    b = np.where(b >> np.uint64(31), ~b & np.uint64(0xFFFFFFFF), b | np.uint64(0x80000000))
    comp = (b << np.uint64(32)) | np.arange(len(b), dtype=np.uint64)
    return (np.sort(comp) & np.uint64(0xFFFFFFFF)).astype(np.int64)
