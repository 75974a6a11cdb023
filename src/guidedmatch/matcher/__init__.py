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

Flow of a guided match (:func:`match` -> ``run._GuidedRun.run``, one method per step, in this order)
----------------------------------------------------------------------------------------------------
The package's files follow the method: ``run.py`` (the flow, top to bottom, and the result), ``start.py`` (steps 1-2:
draw order, unguided start, verdict), ``models.py`` (step 3: F, alignment, spatial order, search regions),
``guided.py`` (steps 4-5: strips, guided batches, final pass), ``filters.py`` (steps 6-7 and the ratio test).

1. **Draw order** (§III-A, "Feature Grouping", :func:`draw_order`): image-1 features are put into ``num_groups``
   x-intervals and drawn round-robin (within a group strongest response first, else a seeded random order), so the
   first matches cover the whole image width. With a prior (``match(first=...)``: e.g. the keypoints a collection's
   other images tie to image 2, :mod:`guidedmatch.collection.second_look`) its tiers are drawn first, each in this
   order (:func:`tiered_draw_order`); nothing else changes.
2. **Unguided start** (§III-A; the gate and the exit are beyond the paper, ``start.py``):
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
3. **Model fit** (§III-B..E, ``models.py``): the first fit (with ``frame_hypotheses`` its F must pass
   the verdict's rule on the evidence, else the verdict's F guides, ``fit_fundamental``), then after
   every ``update_every`` (200) newly accepted correspondences the models are refit on *all* correspondences so far
   (``num_updates`` = 3 fits in all): F by robust RANSAC (§III-D), the alignment homographies from F (mode IA,
   §III-E; validated over the keypoints by :func:`~guidedmatch.alignment.safe_alignment` -- local scale,
   orientation, line at infinity -- with the fallback requested approach -> ``c_inplane`` -> none, each rejection
   reported), then the spatial-order model on aligned x-coordinates (§III-B, §III-C).
4. **Guided phase**: between updates, batches are matched in their search regions under the current models; the
   batch size follows the observed acceptance rate so the next update comes after about one batch.
5. **Final pass**: after the last update, all remaining image-1 features are matched in one vectorized call of the
   Numba candidate kernel (:func:`~guidedmatch.kernels.guided_top2` over the
   :class:`~guidedmatch.strip_index.StripIndex` of the aligned image-2 points): features outside the overlap window
   ω* are dropped unmatched; each remaining feature's candidates are the image-2 features in its admissible x-range
   (aligned coordinates) and within ``band_px`` of its epipolar line (:func:`search_regions`).
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

from __future__ import annotations

from ..config import MODES, MatcherConfig, Mode
from .filters import mutual_check, one_to_one
from .models import GuidanceModels, Regions, search_regions
from .run import match
from .start import draw_order, tiered_draw_order
from . import warmup  # noqa: E402,F401 - registers the matcher's kernel warm-ups with guidedmatch.jit

__all__ = ["match", "MatcherConfig", "Mode", "MODES", "GuidanceModels", "Regions", "search_regions", "draw_order", "tiered_draw_order",
           "one_to_one", "mutual_check"]
