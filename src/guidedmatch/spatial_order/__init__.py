"""Spatial-order model of a match set (Talker, Moses & Shimshoni 2016 §4-§5; Teng & Dong §III-B, §III-C).

Pipeline of :func:`fit_spatial_order` (called by the matcher at every model update):

1. **Ranks** (:func:`match_ranks`): matches are sorted by x in each image; the match set becomes the permutation
   ``sigma`` (``sigma[i]`` = image-2 x-rank of the match with image-1 x-rank ``i``, both 0-based). Ties are broken
   stably: by x, then by y (when given), then by match index.
2. **Kendall distance** ``K`` (Talker Eq. 2) in O(N log N) with a Fenwick tree (Numba), ``K_hat = 2K/(N(N-1))``.
3. **N_G** from Talker Eq. 8 (:func:`estimate_n_good`).
4. **Overlap** ``omega* = argmax_omega N_G(omega)`` (Talker §4.3, Eq. 10-11) on a grid of window ends with step
   ``q = round(grid_fraction * N)``: ``"k1d"`` (image-1 windows first, then image-2 windows) or ``"k2d"`` (all 4-tuples).
   Our additions (config ``refine``, ``trim_rounds``): the grid ends are refined to single ranks by ascent on N_G,
   and a self-consistency pass re-windows to the extreme matches with P >= 1/2 when the probabilities contradict
   N_G (a window that swallowed a non-overlapping corner). Without them the error is Talker's (grid quantization).
5. **Per-match inversions** ``H^l, H^r`` (Talker §4.2) and the probability that a match is correct
   ``P(i in G | H)`` (Talker Eq. 12, Teng & Dong Eq. 6-9), ``"gaussian"`` (fast) or ``"exact"``
   (``SpatialOrderConfig.probability``; the self-consistency pass of step 4 always uses ``"gaussian"``).
6. **Search-range table** (Teng & Dong §III-C): for every image-1 gap ``h`` and image-2 gap ``k`` of the matches
   inside ``omega*``, the inversion count ``H = h + k - 2 C[h, k]`` with ``C[h, k] = #{m < h : sigma(m) < k}`` and its
   probability (always the ``"gaussian"`` model: the exact one costs O(|S_beta| H) per cell); gaps with
   probability ``>= threshold`` are admissible. Stored compactly per image-1 gap as the hull
   ``[gap_lo, gap_hi]``, the count and the exact run-length encoding of the admissible set.

Conventions: ranks and windows are 0-based, windows are half-open rank ranges ``[lo, hi)``; coordinates are pixels
(OpenCV convention, only x is used, y only breaks ties). Gap ``h`` of image 1 lies between image-1 ranks ``h-1`` and
``h`` (``h = 0..n``); for a query x it is ``np.searchsorted(x1_sorted, x, side="left")``, the number of matched
x strictly smaller than the query.

Probability model (``n`` matches inside ``omega*``, ``N_G`` good, ``N_B = n - N_G`` bad; a match/gap with ``l1``
matches to its left in image 1 and ``l2`` in image 2, ``n_o`` other matches)::

    P(G | H) = P(H|G) P_G / (P(H|G) P_G + P(H|B) P_B),    P_G = N_G / n (clipped to [0.01, 0.99])
    P(H|G)   = sum_beta P(beta) P(H | G, beta)
    P(beta)  = Hyp(l1, b1; n_o, N_B) Hyp(l2, b2; n_o, N_B)           (b1 = beta_1^l, b2 = beta_2^l)
    H = H^l + H^r,  H^l ~ Hyp(b1, .; N_B, N_B - b2),  H^r ~ Hyp(b2, .; N_B, N_B - b1)  (independent given beta)

The last line is Teng & Dong Eq. 9; we condition on the total ``H`` as in Talker Eq. 12 (``H^r - H^l = l2 - l1`` is
fixed by the ranks, so ``H`` carries all the order information). ``"exact"`` sums the hypergeometric pmfs
(log-factorials) over ``b1, b2`` within 8 standard deviations of their means (the neglected mass is < 1e-14) and
convolves the two pmfs at ``H``. ``"gaussian"`` is Talker's fast version: ``k = num_beta`` values per ``b`` around
its expectation (Gauss-Hermite nodes of a Gaussian with the hypergeometric mean and variance, clipped to the
support) and Gaussian pmfs for ``H | beta``; the k x k mixture is collapsed to one Gaussian with the mixture's mean
and variance (law of total variance), which needs only the first two moments of the node values per image and
makes every cell of the (n+1)^2 table O(1). ``var_floor`` is added to Var(H|G) (tolerance for local order noise).

``P(H|B)`` is uniform on ``[H_lo, H_hi]`` (Talker §5 states the form; the bounds are unpublished), derived in
:func:`bad_inversion_range`; outside it, ``P(H|B)`` is ``1e-3`` of the in-range value.

Modules (every public name is re-exported here: ``from guidedmatch.spatial_order import X``):

* :mod:`.ranks` -- steps 1-3: ranks, the permutation, Kendall distance, per-match inversions, ``N_G``.
* :mod:`.window` -- step 4: overlap window search (:class:`Window`, :func:`search_overlap`, :func:`refine_window`).
* :mod:`.probability` -- step 5: ``P(H|B)`` bounds, ``P(H|G)`` (Gaussian / exact), ``P(G|H)``, order noise.
* :mod:`.gap_table` -- step 6: the search-range table (fused Numba pass and dense references).
* :mod:`.config` -- :class:`SpatialOrderConfig` (validated at construction).
* :mod:`.model` -- :class:`SpatialOrderModel`, :func:`fit_spatial_order` (steps 1-6), :func:`admissible_x_ranges`,
  :func:`match_probabilities`.
* :mod:`._kernels` -- every Numba kernel (``cache=True``; one file, so the on-disk cache is invalidated together).
"""
from __future__ import annotations

from .config import OVERLAP_METHODS, SpatialOrderConfig
from .gap_table import GapTable, build_gap_table, gap_inversion_table, gap_probability_table
from .model import SpatialOrderModel, admissible_x_ranges, fit_spatial_order, match_probabilities
from .probability import (
    PROBABILITY_METHODS,
    OrderNoise,
    bad_inversion_range,
    good_inversion_moments,
    order_noise,
    probability_correct,
)
from .ranks import (
    estimate_n_good,
    inversions_per_match,
    kendall_distance,
    match_ranks,
    normalized_kendall_distance,
    permutation_from_coordinates,
)
from .window import Window, refine_window, search_overlap

__all__ = [
    "SpatialOrderConfig",
    "SpatialOrderModel",
    "fit_spatial_order",
    "admissible_x_ranges",
    "match_probabilities",
    "match_ranks",
    "permutation_from_coordinates",
    "kendall_distance",
    "normalized_kendall_distance",
    "inversions_per_match",
    "estimate_n_good",
    "search_overlap",
    "refine_window",
    "Window",
    "gap_inversion_table",
    "gap_probability_table",
    "build_gap_table",
    "GapTable",
    "bad_inversion_range",
    "good_inversion_moments",
    "probability_correct",
    "order_noise",
    "OrderNoise",
    "OVERLAP_METHODS",
    "PROBABILITY_METHODS",
]
