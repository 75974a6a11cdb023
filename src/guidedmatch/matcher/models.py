"""Step 3 of a guided match: the models (§III-B..E) -- F, the alignment homographies, the spatial-order model -- and
the search regions they define (§III-C/D)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .. import kernels
from ..epipolar import map_points
from ..results import ModelUpdate


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
    the band only; with ``"band_all"`` every feature outside ω* is (when there is an F).

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
    x_range = (-np.inf, np.inf) if outside_window == "band_all" else inlier_x1_range
    rescue = use_so and outside_window in ("band", "band_all") and F_aligned is not None and x_range is not None
    r_lo, r_hi = (float(x_range[0]), float(x_range[1])) if rescue else (0.0, 0.0)
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
        from ..spatial_order import admissible_x_ranges

        keep, lo, hi, _ = admissible_x_ranges(so, pts1a[:, 0])
        keep, lo, hi = np.asarray(keep, bool), np.asarray(lo, np.float64).copy(), np.asarray(hi, np.float64).copy()
        x_range = (-np.inf, np.inf) if outside_window == "band_all" else inlier_x1_range
        if outside_window in ("band", "band_all") and F_aligned is not None and x_range is not None:
            rescued = ~keep & (pts1a[:, 0] >= x_range[0]) & (pts1a[:, 0] <= x_range[1])
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
        band_px: epipolar band half-width (aligned pixels). outside_window: the run's policy ("drop" | "band" | "band_all").
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



class ModelFits:
    """Step 3 of :class:`~guidedmatch.matcher.run._GuidedRun` (a mixin: the run's state lives in ``run.py``)."""

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
            from ..epipolar import transform_fundamental

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
        from .. import epipolar

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
        from ..geometry import VerdictConfig, fundamental_support

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
        from .. import epipolar
        from ..geometry import VerdictConfig, fundamental_support

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
        from .. import alignment

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
        from ..alignment import apply_homography

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
        from .. import spatial_order

        c = self.c
        so = spatial_order.fit_spatial_order(
            pts1a[acc_i, 0], pts2a[acc_j, 0], spatial_order.SpatialOrderConfig(threshold=c.so_threshold, overlap=c.so_overlap),
            y1=pts1a[acc_i, 1], y2=pts2a[acc_j, 1], likely_correct=likely_correct)
        if not so.usable:
            self.fallback("spatial_order", f"spatial-order model unusable ({so.reason}); "
                          + ("epipolar band only" if likely_correct is not None else "unguided"))
        return so
