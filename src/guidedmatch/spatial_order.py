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
   ``P(i in G | H)`` (Talker Eq. 12, Teng & Dong Eq. 6-9), ``"gaussian"`` (fast) or ``"exact"``.
6. **Search-range table** (Teng & Dong §III-C): for every image-1 gap ``h`` and image-2 gap ``k`` of the matches
   inside ``omega*``, the inversion count ``H = h + k - 2 C[h, k]`` with ``C[h, k] = #{m < h : sigma(m) < k}`` and its
   probability; gaps with probability ``>= threshold`` are admissible. Stored compactly per image-1 gap as the hull
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
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

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
    "gap_inversion_table",
    "gap_probability_table",
    "bad_inversion_range",
    "good_inversion_moments",
    "probability_correct",
]

_P_G_CLIP = (0.01, 0.99)  # prior P_G clipped away from 0/1 so neither hypothesis is ruled out a priori
_OUT_OF_RANGE = 1e-3  # P(H|B) outside [H_lo, H_hi], relative to the in-range value
_EXACT_NSD = 8.0  # "exact": beta summed over mean +- 8 sd (hypergeometric), intersected with the support


@dataclass(frozen=True)
class SpatialOrderConfig:
    """Parameters of :func:`fit_spatial_order`."""

    threshold: float = 0.01  # Th: keep image-2 gaps whose correctness probability >= Th (Teng & Dong §III-C)
    grid_fraction: float = 0.1  # Talker's window grid step q = round(grid_fraction * N)
    overlap: str = "k1d"  # "k1d" | "k2d" | "none" (full overlap)
    probability: str = "gaussian"  # "gaussian" (Talker fast, k=5 betas) | "exact" (hypergeometric sums)
    num_beta: int = 5  # k values of beta around their expectation
    refine: bool = True  # refine omega*'s grid ends to single ranks (coordinate ascent on N_G; not in Talker)
    trim_rounds: int = 2  # re-window to extreme ranks of matches with P >= 1/2, keep max sum P (not in Talker)
    var_floor: float = 1.0  # added to Var(H | G) (inversions^2): tolerance for local order noise
    gap_table: bool = True  # build the (n+1)^2 search-range table (False: per-match probabilities only, O(n log n))
    order_noise: bool = True  # estimate local order noise from the data and widen P(H|G) by it (not in Talker; see fit)
    min_z: float = 5.0  # usable only if (1/2 - K_hat(omega*)) / sd_null >= min(min_z, 1.5 + 0.6 ln N) (see fit)


@dataclass(frozen=True, eq=False)
class SpatialOrderModel:
    """Spatial-order model of one match set (see module docstring). Arrays are read-only by convention.

    Attributes:
        usable, reason: False + one sentence when the input has no usable order structure ("" when usable).
        n: number of matches given. n_window: matches inside omega*. n_good: N_G(omega*) (Talker Eq. 10).
        k_hat: normalized Kendall distance of the matches inside omega*.
        window1_x, window2_x: x-ranges (inclusive, pixels) of omega*'s rank windows in image 1 / image 2.
        x1_sorted, x2_sorted: ``(n_window,)`` x of the matches inside omega*, ascending, in image 1 / image 2.
        gap_lo, gap_hi: ``(n_window+1,) int64`` per image-1 gap, lowest / highest admissible image-2 gap
            (``gap_lo > gap_hi``: none admissible).
        gap_count: ``(n_window+1,) int64`` number of admissible image-2 gaps per image-1 gap.
        gap_contiguous: ``(n_window+1,) bool`` admissible set equals its hull.
        gap_runs_ptr, gap_runs: exact admissible sets as runs (CSR): runs of image-1 gap ``h`` are
            ``gap_runs[gap_runs_ptr[h]:gap_runs_ptr[h+1]]``, rows ``(first, last)`` image-2 gaps, inclusive.
        sigma: ``(n,) int64`` permutation of all matches (image-1 rank -> image-2 rank).
        rank1, rank2: ``(n,) int64`` x-rank of each given match in image 1 / image 2.
        omega: ``(i1_lo, i1_hi, i2_lo, i2_hi)`` rank windows of omega*, half-open, among all n matches.
        in_window: ``(n,) bool`` per given match: inside omega* (image-1 rank in window 1 and image-2 in window 2).
        sigma_window: ``(n_window,) int64`` the re-ranked sub-permutation inside omega*.
        probabilities: ``(n,) float64`` P(i in G | H) per given match, 0 outside omega*.
        config: the config used. timings: seconds per stage.
        order_noise: ``(mean, var)`` of the inversions among likely-correct matches added to ``H | G``.
    """

    usable: bool
    reason: str
    n: int
    n_window: int
    n_good: float
    k_hat: float
    window1_x: tuple[float, float]
    window2_x: tuple[float, float]
    x1_sorted: np.ndarray
    x2_sorted: np.ndarray
    gap_lo: np.ndarray
    gap_hi: np.ndarray
    gap_count: np.ndarray
    gap_contiguous: np.ndarray
    gap_runs_ptr: np.ndarray
    gap_runs: np.ndarray
    sigma: np.ndarray
    rank1: np.ndarray
    rank2: np.ndarray
    omega: tuple[int, int, int, int]
    in_window: np.ndarray
    sigma_window: np.ndarray
    probabilities: np.ndarray
    config: SpatialOrderConfig = field(default_factory=SpatialOrderConfig)
    timings: dict = field(default_factory=dict)
    order_noise: tuple[float, float] = (0.0, 0.0)  # (mean, variance) of H_G added to H | G (see order_noise())

    def __bool__(self) -> bool:  # falsy when unusable, like guidedmatch.results.Failure
        return bool(self.usable)


# --------------------------------------------------------------------------------------------------------------
# Ranks and Kendall distance
# --------------------------------------------------------------------------------------------------------------


def match_ranks(x: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    """x-rank of every match in one image, ``(N,) int64``, 0-based.

    Ties are broken stably: by x, then by y (if given), then by match index (``np.lexsort`` is stable).
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    keys = (x,) if y is None else (np.asarray(y, dtype=np.float64).reshape(-1), x)
    order = np.lexsort(keys)
    ranks = np.empty(len(x), dtype=np.int64)
    ranks[order] = np.arange(len(x), dtype=np.int64)
    return ranks


def permutation_from_coordinates(x1, x2, y1=None, y2=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The match permutation ``sigma`` from matched coordinates (Teng & Dong §III-B.1).

    Args:
        x1, x2: ``(N,)`` x of match m in image 1 / image 2 (pixels). y1, y2: optional ``(N,)`` tie-breakers.

    Returns:
        ``(sigma, rank1, rank2)``: ``sigma (N,) int64`` with ``sigma[rank1[m]] = rank2[m]``, and the ranks.
    """
    r1, r2 = match_ranks(x1, y1), match_ranks(x2, y2)
    sigma = np.empty(len(r1), dtype=np.int64)
    sigma[r1] = r2
    return sigma, r1, r2


@njit(inline="always", cache=True)
def _fenwick_prefix(tree, q):  # pragma: no cover - numba
    """Sum of the Fenwick tree's counts at 1-based positions <= q."""
    s = 0
    t = q
    while t > 0:
        s += tree[t]
        t -= t & (-t)
    return s


@njit(inline="always", cache=True)
def _fenwick_add(tree, q, size):  # pragma: no cover - numba
    """Add one at 1-based position q of a Fenwick tree of length ``size``."""
    t = q
    while t < size:
        tree[t] += 1
        t += t & (-t)


@njit(inline="always", cache=True)
def _kendall_step(tree, v, lo, size, cnt, kk):  # pragma: no cover - numba
    """Insert value ``v`` (in ``[lo, lo + size - 1)``) after ``cnt`` earlier ones: returns ``(cnt + 1, kk + the
    earlier values larger than v)``."""
    q = v - lo + 1
    kk += cnt - _fenwick_prefix(tree, q)
    _fenwick_add(tree, q, size)
    return cnt + 1, kk


@njit(cache=True)
def _inversions_dense(r, nvals):  # pragma: no cover - numba
    """H^l, H^r for a sequence of dense ranks ``r`` (ties allowed, not inversions) via a Fenwick tree."""
    n = r.shape[0]
    tree = np.zeros(nvals + 1, dtype=np.int64)
    less_total = np.zeros(nvals + 1, dtype=np.int64)  # less_total[v] = #{j : r[j] < v}
    for j in range(n):
        less_total[r[j] + 1] += 1
    for v in range(1, nvals + 1):
        less_total[v] += less_total[v - 1]
    hl = np.empty(n, dtype=np.int64)
    hr = np.empty(n, dtype=np.int64)
    for i in range(n):
        v = r[i]
        # c_le = #{j < i : r[j] <= v}, c_lt = #{j < i : r[j] < v}
        hl[i] = i - _fenwick_prefix(tree, v + 1)
        hr[i] = less_total[v] - _fenwick_prefix(tree, v)
        _fenwick_add(tree, v + 1, nvals + 1)
    return hl, hr


def _dense(seq) -> tuple[np.ndarray, int]:
    a = np.asarray(seq).reshape(-1)
    if a.size == 0:
        return np.zeros(0, dtype=np.int64), 0
    uniq, inv = np.unique(a, return_inverse=True)
    return inv.astype(np.int64).reshape(-1), int(len(uniq))


def inversions_per_match(sigma) -> tuple[np.ndarray, np.ndarray]:
    """Per-match inversion counts (Talker §4.2; Teng & Dong §III-B.3), O(N log N).

    ``H^l[i] = #{j < i : sigma[j] > sigma[i]}``, ``H^r[i] = #{j > i : sigma[j] < sigma[i]}``; ``H = H^l + H^r``.
    Works for any real sequence (ties are not inversions). For a permutation, with ``C[i] = #{j < i : sigma[j] <
    sigma[i]}``: ``H^l = i - C``, ``H^r = sigma[i] - C``.

    Returns:
        ``(H^l, H^r)``, each ``(N,) int64``.
    """
    r, nv = _dense(sigma)
    if r.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return _inversions_dense(r, nv)


def kendall_distance(sigma) -> int:
    """Kendall distance ``K = #{(i, j) : i < j, sigma[i] > sigma[j]}`` (Talker Eq. 1-2), O(N log N) Fenwick tree.

    ``sigma``: ``(N,)`` any real sequence (ties count as no inversion); ``N in {0, 1}`` gives 0.
    """
    hl, _ = inversions_per_match(sigma)
    return int(hl.sum())


def normalized_kendall_distance(x1, x2, y1=None, y2=None) -> float:
    """``K_hat = 2K / (N(N-1))`` of the permutation of matched coordinates (Talker Eq. 5; Teng & Dong Eq. 2).

    Ties are broken as in :func:`match_ranks`. Returns nan when ``N < 2``.
    """
    sigma, _, _ = permutation_from_coordinates(x1, x2, y1, y2)
    n = len(sigma)
    if n < 2:
        return float("nan")
    return 2.0 * kendall_distance(sigma) / (n * (n - 1.0))


def estimate_n_good(k_hat, n):
    """Number of correct matches N_G from Talker Eq. 8 (Teng & Dong Eq. 1).

    Solves ``(1/6) N_G^2 - (1/2 - N/3) N_G - N(N-1)(1/2 - K_hat) = 0`` for the root in ``[0, N]``:
    ``N_G = 3 [ -(N/3 - 1/2) + sqrt((N/3 - 1/2)^2 + (2/3) N (N-1)(1/2 - K_hat)) ]``; ``N_G = N`` at ``K_hat = 0``
    (exactly) and ``0`` when ``K_hat >= 1/2``. Broadcasts over arrays; nan ``k_hat`` gives nan.
    """
    k = np.asarray(k_hat, dtype=np.float64)
    nn = np.asarray(n, dtype=np.float64)
    b = nn / 3.0 - 0.5
    c = nn * (nn - 1.0) * (0.5 - k)
    disc = np.maximum(b * b + (2.0 / 3.0) * np.maximum(c, 0.0), 0.0)
    root = 3.0 * (-b + np.sqrt(disc))
    out = np.where(k >= 0.5, 0.0, np.clip(root, 0.0, nn))
    out = np.where(k == 0.0, nn, out)
    out = np.where(np.isnan(k), np.nan, out)
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------------------------------------------
# Overlap region omega* (Talker §4.3)
# --------------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _sweep_kendall(seq, lo, hi, bounds, out_k, out_n):  # pragma: no cover - numba
    """For every start block a and end bound c > a: inversions / count among ``seq[bounds[a]:bounds[c]]``
    restricted to values in ``[lo, hi)``; an inversion is an earlier element with a larger value."""
    g = bounds.shape[0] - 1
    m = seq.shape[0]
    size = hi - lo + 1
    tree = np.zeros(size, dtype=np.int64)
    for a in range(g):
        tree[:] = 0
        cnt = 0
        kk = 0
        c = a + 1
        for p in range(bounds[a], m):
            v = seq[p]
            if v >= lo and v < hi:
                cnt, kk = _kendall_step(tree, v, lo, size, cnt, kk)
            if p + 1 == bounds[c]:
                out_k[a, c] = kk
                out_n[a, c] = cnt
                c += 1
                if c > g:
                    break


@njit(cache=True)
def _window_kendall(sigma, i1l, i1h, i2l, i2h):  # pragma: no cover - numba
    """(K, n) of the matches with image-1 rank in [i1l, i1h) and image-2 rank in [i2l, i2h)."""
    size = i2h - i2l + 1
    if size < 2:
        return 0, 0
    tree = np.zeros(size, dtype=np.int64)
    cnt = 0
    kk = 0
    for i in range(i1l, i1h):
        v = sigma[i]
        if v >= i2l and v < i2h:
            cnt, kk = _kendall_step(tree, v, i2l, size, cnt, kk)
    return kk, cnt


@njit(cache=True)
def _ng_scalar(kk, cnt):  # pragma: no cover - numba
    """N_G (Talker Eq. 8/10) of a window with kk inversions among cnt matches; 0 when cnt < 2."""
    if cnt < 2:
        return 0.0
    kh = 2.0 * kk / (cnt * (cnt - 1.0))
    if kh >= 0.5:
        return 0.0
    if kh == 0.0:
        return float(cnt)
    b = cnt / 3.0 - 0.5
    c = cnt * (cnt - 1.0) * (0.5 - kh)
    r = 3.0 * (-b + math.sqrt(b * b + (2.0 / 3.0) * c))
    return min(max(r, 0.0), float(cnt))


@njit(cache=True)
def _profile(seq, lo, hi, start, stop, step):  # pragma: no cover - numba
    """N_G after each position of a sweep over ``seq[start], seq[start+step], ...`` (stop exclusive), counting only
    values in [lo, hi). step=+1: appending (inversion = earlier larger value); step=-1: prepending (smaller)."""
    size = hi - lo + 1
    m = (stop - start) * step
    ng = np.zeros(max(m, 0))
    cn = np.zeros(max(m, 0), dtype=np.int64)
    if size < 2 or m <= 0:
        return ng, cn
    tree = np.zeros(size, dtype=np.int64)
    cnt = 0
    kk = 0
    p = start
    for t in range(m):
        v = seq[p]
        if v >= lo and v < hi:
            q = v - lo + 1
            le = 0
            u = q
            while u > 0:
                le += tree[u]
                u -= u & (-u)
            if step > 0:
                kk += cnt - le
            else:
                kk += le
            u = q
            while u < size:
                tree[u] += 1
                u += u & (-u)
            cnt += 1
        ng[t] = _ng_scalar(kk, cnt)
        cn[t] = cnt
        p += step
    return ng, cn


@njit(cache=True)
def _refine_window_nb(sigma, inv, w0, span, step, max_passes):  # pragma: no cover - numba
    """Coordinate ascent of N_G over the 4 window ends (see _refine_window)."""
    n = sigma.shape[0]
    w = w0.copy()
    kk, cnt = _window_kendall(sigma, w[0], w[1], w[2], w[3])
    best = _ng_scalar(kk, cnt)
    bcnt = cnt
    for _ in range(max_passes):
        changed = False
        for j in range(4):
            if j == 0:  # i1_lo: prepend image-1 ranks w1-1, w1-2, ..., 0
                ng, cn = _profile(sigma, w[2], w[3], w[1] - 1, -1, -1)
            elif j == 1:  # i1_hi: append image-1 ranks w0, ..., n-1
                ng, cn = _profile(sigma, w[2], w[3], w[0], n, 1)
            elif j == 2:
                ng, cn = _profile(inv, w[0], w[1], w[3] - 1, -1, -1)
            else:
                ng, cn = _profile(inv, w[0], w[1], w[2], n, 1)
            bt = -1
            for t in range(1, ng.shape[0]):  # windows of >= 2 ranks
                if ng[t] > best or (ng[t] == best and cn[t] > bcnt):
                    best = ng[t]
                    bcnt = cn[t]
                    bt = t
            if bt >= 0:
                if j == 0:
                    w[0] = w[1] - 1 - bt
                elif j == 1:
                    w[1] = w[0] + bt + 1
                elif j == 2:
                    w[2] = w[3] - 1 - bt
                else:
                    w[3] = w[2] + bt + 1
                changed = True
        for pair in range(2):  # joint shifts of (i1_lo, i2_lo) or (i1_hi, i2_hi)
            a = 0 if pair == 0 else 1
            b = a + 2
            bd = 0
            for d in range(-span, span + 1, step):
                if d == 0:
                    continue
                t0, t1, t2, t3 = w[0], w[1], w[2], w[3]
                if pair == 0:
                    t0 += d
                    t2 += d
                else:
                    t1 += d
                    t3 += d
                if t0 < 0 or t2 < 0 or t1 > n or t3 > n or t1 - t0 < 2 or t3 - t2 < 2:
                    continue
                kk, cnt = _window_kendall(sigma, t0, t1, t2, t3)
                g = _ng_scalar(kk, cnt)
                if g > best or (g == best and cnt > bcnt):
                    best = g
                    bcnt = cnt
                    bd = d
            if bd != 0:
                w[a] += bd
                w[b] += bd
                changed = True
        if not changed:
            break
    return w


def _refine_window(sigma, w, q, passes=6):
    """Ascent of N_G from window w (our addition to Talker §4.3): exact line search (every rank, one O(N log N)
    sweep) over each end alone, and joint shifts of the two lower (resp. upper) ends within +-q in steps of q/8 --
    correct matches sit on the diagonal, so a corner that is off in both images needs a joint move."""
    sigma = np.ascontiguousarray(sigma, dtype=np.int64)
    inv = np.empty_like(sigma)
    inv[sigma] = np.arange(len(sigma))
    out = _refine_window_nb(sigma, inv, np.array(w, dtype=np.int64), int(max(q, 1)), int(max(q // 8, 1)),
                            int(passes))
    return tuple(int(v) for v in out)


def _grid(n: int, grid_fraction: float) -> np.ndarray:
    q = max(1, int(round(grid_fraction * n)))
    return np.unique(np.concatenate([np.arange(0, n, q), [n]])).astype(np.int64)


def _best_window(k, cnt, g):
    """Pick the (a, c) maximizing N_G (ties: larger window, then first)."""
    a_idx, c_idx = np.triu_indices(g + 1, k=1)
    a_idx, c_idx = a_idx[a_idx < g], c_idx[a_idx < g]
    nn = cnt[a_idx, c_idx].astype(np.float64)
    kk = k[a_idx, c_idx].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        kh = np.where(nn >= 2, 2.0 * kk / (nn * (nn - 1.0)), np.nan)
    ng = estimate_n_good(kh, nn)
    ng = np.where(np.isnan(ng), 0.0, ng)
    best = np.lexsort((-nn, -ng))[0]
    return int(a_idx[best]), int(c_idx[best]), float(ng[best])


def search_overlap(sigma, grid_fraction: float = 0.1, method: str = "k1d", refine: bool = True,
                   rounds: int = 3) -> tuple[int, int, int, int]:
    """Overlap region ``omega* = argmax_omega N_G(omega)`` (Talker §4.3, Eq. 10-11; Teng & Dong §III-B.2).

    Window ends lie on the grid ``0, q, 2q, ..., N`` with ``q = max(1, round(grid_fraction * N))``.
    ``N(omega)``, ``K_hat(omega)`` are those of the matches with image-1 rank in ``[i1_lo, i1_hi)`` and image-2 rank in
    ``[i2_lo, i2_hi)``. ``"k1d"``: first image-1 windows with image 2 = all, then image-2 windows with that image-1
    window fixed (O(G^2 N log N), G = N/q); with ``rounds > 1`` (our addition) the two stages alternate, the image-1
    stage then restricted to the current image-2 window, until the window stops changing (Talker's K1D is
    ``rounds=1``). ``"k2d"``: all window pairs jointly (O(G^3 N log N)). ``"none"``: full.
    ``refine`` (our addition, not in Talker): afterwards each of the 4 ends is moved within +-q of its grid value by
    coordinate ascent on N_G (step q/8, then 1), which removes most of the grid quantization error.

    Args:
        sigma: ``(N,) int64`` permutation (image-1 rank -> image-2 rank).

    Returns:
        ``(i1_lo, i1_hi, i2_lo, i2_hi)``: half-open rank windows.
    """
    sigma = np.ascontiguousarray(sigma, dtype=np.int64)
    n = len(sigma)
    if method == "none" or n < 2:
        return 0, n, 0, n
    if method not in ("k1d", "k2d"):
        raise ValueError(f"unknown overlap method {method!r}")
    bounds = _grid(n, grid_fraction)
    g = len(bounds) - 1
    inv = np.empty(n, dtype=np.int64)
    inv[sigma] = np.arange(n, dtype=np.int64)
    k = np.zeros((g + 1, g + 1), dtype=np.int64)
    cnt = np.zeros((g + 1, g + 1), dtype=np.int64)
    if method == "k1d":
        w = (0, n, 0, n)
        for _ in range(max(int(rounds), 1)):
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(sigma, w[2], w[3], bounds, k, cnt)
            a1, c1, _ = _best_window(k, cnt, g)
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(inv, int(bounds[a1]), int(bounds[c1]), bounds, k, cnt)
            a2, c2, _ = _best_window(k, cnt, g)
            new = (int(bounds[a1]), int(bounds[c1]), int(bounds[a2]), int(bounds[c2]))
            if new == w:
                break
            w = new
        return _refine_window(sigma, w, int(bounds[1] - bounds[0])) if refine else w
    best = (-1.0, -1, (0, n, 0, n))
    for a1 in range(g):
        for c1 in range(a1 + 1, g + 1):
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(inv, int(bounds[a1]), int(bounds[c1]), bounds, k, cnt)
            a2, c2, ng = _best_window(k, cnt, g)
            nw = int(cnt[a2, c2])
            if (ng, nw) > best[:2]:
                best = (ng, nw, (int(bounds[a1]), int(bounds[c1]), int(bounds[a2]), int(bounds[c2])))
    return _refine_window(sigma, best[2], int(bounds[1] - bounds[0])) if refine else best[2]


# --------------------------------------------------------------------------------------------------------------
# Probability that a match is correct (Talker §5, Eq. 12; Teng & Dong Eq. 6-9)
# --------------------------------------------------------------------------------------------------------------


def bad_inversion_range(left1, n_others, n_good_others):
    """Bounds ``[H_lo, H_hi]`` of the uniform model of ``P(H | B)`` (Talker §5; bounds derived here).

    Derivation. Normalize ranks: ``x = l1 / n_o`` (image 1), ``y`` (image 2). Under A1-A3 the ``G = n_good_others``
    correct matches lie on the monotone diagonal and the ``B = n_o - G`` incorrect ones are independent and uniform.
    A match at ``(x, y)`` then has on average

        ``H(y) = G |x - y| + B (x (1 - y) + (1 - x) y)``

    inversions (correct matches between x and y in rank, plus incorrect ones in the two off quadrants). An incorrect
    match has ``y ~ U[0, 1]`` independent of ``x``, so ``H`` sweeps the convex piecewise-linear ``H(y)``; the density is
    piecewise constant (1/|dH/dy| per branch), which Talker approximates as uniform between its extremes:
    ``H_hi = max(H(0), H(1)) = n_o max(x, 1 - x)`` (exact: at ``y = 0`` every left match is an inversion) and
    ``H_lo = min(H(x), H(0), H(1))`` with ``H(x) = 2 B x (1 - x)``, lowered by two standard deviations of the
    fluctuation at ``y = x`` (``H^l, H^r`` ~ Binomial(B, x(1-x)) each, Var ~ 2 B x (1 - x)) and by 1 (discreteness).
    ``H(x)`` is Talker's E[H | i in G]: a wrong match at the consistent place cannot be told apart by order.

    Args:
        left1: matches left of the match/gap in image 1 (scalar or array). n_others: other matches.
        n_good_others: correct ones among them (float).

    Returns:
        ``(H_lo, H_hi)`` float arrays (broadcast of ``left1``).
    """
    l1 = np.asarray(left1, dtype=np.float64)
    no = max(float(n_others), 1.0)
    g = min(max(float(n_good_others), 0.0), no)
    b = no - g
    x = np.clip(l1 / no, 0.0, 1.0)
    hx = 2.0 * b * x * (1.0 - x)
    h0 = no * x
    h1 = no * (1.0 - x)
    lo = np.minimum(np.minimum(hx, h0), h1) - 2.0 * np.sqrt(2.0 * b * x * (1.0 - x)) - 1.0
    return np.maximum(lo, 0.0), np.maximum(h0, h1)


@functools.lru_cache(maxsize=16)
def _hermite_nodes(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite (probabilists') nodes and normalized weights for k points (cached; read-only arrays)."""
    nodes, weights = np.polynomial.hermite_e.hermegauss(k)
    weights = weights / weights.sum()
    nodes.flags.writeable = False
    weights.flags.writeable = False
    return nodes, weights


def _beta_moments(left, n_others, n_bad, num_beta):
    """Mean and second moment of Talker's k node values of beta ~ Hyp(left draws; n_others, n_bad)."""
    left = np.asarray(left, dtype=np.float64)
    no = max(float(n_others), 1.0)
    nb = min(max(float(n_bad), 0.0), no)
    p = nb / no
    mean = left * p
    var = left * p * (1.0 - p) * (no - left) / max(no - 1.0, 1.0)
    sd = np.sqrt(np.maximum(var, 0.0))
    nodes, weights = _hermite_nodes(max(int(num_beta), 1))
    lo_s = np.maximum(0.0, left - (no - nb))[..., None]
    hi_s = np.minimum(left, nb)[..., None]
    b = np.clip(mean[..., None] + sd[..., None] * nodes, lo_s, np.maximum(hi_s, lo_s))
    return (b * weights).sum(-1), (b * b * weights).sum(-1)


def _cell_moments(m1, s1, m2, s2, nb, var_floor):
    """Mean and variance of H | G from the beta moments (broadcasting); see module docstring."""
    if nb < 1e-9:
        mu = np.zeros(np.broadcast(m1, m2).shape)
        return mu, mu + var_floor
    mu = m1 + m2 - 2.0 * m1 * m2 / nb
    e2 = s1 + s2 + 2.0 * m1 * m2 - 4.0 * (s1 * m2 + m1 * s2) / nb + 4.0 * s1 * s2 / (nb * nb)
    var_mu = np.maximum(e2 - mu * mu, 0.0)
    vh = 2.0 * (nb * m1 - s1) * (nb * m2 - s2) / (nb * nb * (nb - 1.0)) if nb > 1.0 else 0.0 * mu
    return mu, np.maximum(vh, 0.0) + var_mu + var_floor


def good_inversion_moments(left1, left2, n_others, n_good_others, num_beta=5, var_floor=1.0):
    """Mean and variance of ``H | G`` (Talker Eq. 7 averaged over his k beta values; "gaussian" model).

    Args:
        left1, left2: matches left of the match/gap in image 1 / image 2 (broadcastable arrays).
        n_others: number of other matches; n_good_others: correct ones among them (float).
    """
    nb = max(float(n_others) - float(n_good_others), 0.0)
    m1, s1 = _beta_moments(left1, n_others, nb, num_beta)
    m2, s2 = _beta_moments(left2, n_others, nb, num_beta)
    return _cell_moments(m1, s1, m2, s2, nb, var_floor)


def _posterior(log_pg_lik, h, left1, n_others, n_good_others, p_good):
    lo, hi = bad_inversion_range(left1, n_others, n_good_others)
    width = hi - lo + 1.0
    inside = (h >= lo) & (h <= hi)
    log_pb = np.log(1.0 - p_good) - np.log(width) + np.where(inside, 0.0, np.log(_OUT_OF_RANGE))
    log_a = np.log(p_good) + log_pg_lik
    return 1.0 / (1.0 + np.exp(np.clip(log_pb - log_a, -700.0, 700.0)))


def _gauss_loglik(h, mu, var):
    return -0.5 * np.log(2.0 * np.pi * var) - (h - mu) ** 2 / (2.0 * var)


@njit(cache=True)
def _logfact_table(n):  # pragma: no cover - numba
    t = np.zeros(n + 2)
    for i in range(1, n + 2):
        t[i] = t[i - 1] + math.log(i)
    return t


@njit(cache=True)
def _log_hyp(lf, n, k, pop, succ):  # pragma: no cover - numba
    """log Hyp(n draws, k successes; population pop with succ successes); -inf outside the support."""
    if k < 0 or k > n or k > succ or n - k > pop - succ or n > pop or succ < 0:
        return -np.inf
    return (lf[succ] - lf[k] - lf[succ - k] + lf[pop - succ] - lf[n - k] - lf[pop - succ - n + k]
            - (lf[pop] - lf[n] - lf[pop - n]))


@njit(cache=True)
def _exact_lik_good(left1, left2, h, n_others, n_bad, nsd):  # pragma: no cover - numba
    """Exact P(H = h | G) for each entry (hypergeometric sums, Teng & Dong Eq. 7-9), beta within nsd sd."""
    m = left1.shape[0]
    lf = _logfact_table(n_others + 2)
    out = np.zeros(m)
    nb = n_bad
    p = nb / max(n_others, 1)
    for e in range(m):
        l1 = left1[e]
        l2 = left2[e]
        hh = h[e]
        sd1 = math.sqrt(max(l1 * p * (1 - p) * (n_others - l1) / max(n_others - 1, 1), 0.0))
        sd2 = math.sqrt(max(l2 * p * (1 - p) * (n_others - l2) / max(n_others - 1, 1), 0.0))
        lo1 = max(0, l1 - (n_others - nb), int(math.floor(l1 * p - nsd * sd1 - 1)))
        hi1 = min(l1, nb, int(math.ceil(l1 * p + nsd * sd1 + 1)))
        lo2 = max(0, l2 - (n_others - nb), int(math.floor(l2 * p - nsd * sd2 - 1)))
        hi2 = min(l2, nb, int(math.ceil(l2 * p + nsd * sd2 + 1)))
        tot = 0.0
        for b1 in range(lo1, hi1 + 1):
            lp1 = _log_hyp(lf, l1, b1, n_others, nb)
            if lp1 == -np.inf:
                continue
            for b2 in range(lo2, hi2 + 1):
                lp2 = _log_hyp(lf, l2, b2, n_others, nb)
                if lp2 == -np.inf:
                    continue
                s = 0.0
                for a in range(max(0, hh - b2), min(hh, b1) + 1):
                    la = _log_hyp(lf, b1, a, nb, nb - b2)
                    if la == -np.inf:
                        continue
                    lb = _log_hyp(lf, b2, hh - a, nb, nb - b1)
                    if lb == -np.inf:
                        continue
                    s += math.exp(la + lb)
                tot += math.exp(lp1 + lp2) * s
        out[e] = tot
    return out


def probability_correct(left1, left2, h, n_others, n_good, n_total, *, method="gaussian", num_beta=5,
                        var_floor=1.0, new_feature=False, mean_shift=0.0):
    """``P(G | H)`` for matches (or hypothetical matches in gaps) with given left counts and inversions.

    Args:
        left1, left2, h: ``(M,)`` matches to the left in image 1 / image 2, and inversions ``H = H^l + H^r``.
        n_others: other matches (``n - 1`` for an existing match, ``n`` for a new feature in a gap).
        n_good: N_G of the model; n_total: n (for the prior ``P_G = N_G / n``).
        method: ``"gaussian"`` or ``"exact"`` (see module docstring).
        new_feature: gap of a new feature (others contain all N_G correct matches for both hypotheses) instead of
            an existing match (under G the others hold N_G - 1 correct ones, under B N_G).
        mean_shift: added to the mean of ``H | G`` ("gaussian" only; the order noise of :func:`order_noise`).
    """
    left1 = np.asarray(left1, dtype=np.int64).reshape(-1)
    left2 = np.asarray(left2, dtype=np.int64).reshape(-1)
    h = np.asarray(h, dtype=np.int64).reshape(-1)
    p_good = float(np.clip(n_good / max(n_total, 1), *_P_G_CLIP))
    g_under_g = float(n_good) if new_feature else max(float(n_good) - 1.0, 0.0)
    g_under_b = min(float(n_good), float(n_others))
    if method == "exact":
        if mean_shift:
            raise ValueError("mean_shift (order noise) is only defined for the gaussian model")
        nb = int(np.clip(round(n_others - g_under_g), 0, n_others))
        lik = _exact_lik_good(left1, left2, h, int(n_others), nb, _EXACT_NSD)
        with np.errstate(divide="ignore"):
            loglik = np.log(lik)
    elif method == "gaussian":
        mu, var = good_inversion_moments(left1, left2, n_others, g_under_g, num_beta, var_floor)
        loglik = _gauss_loglik(h, mu + mean_shift, var)
    else:
        raise ValueError(f"unknown probability method {method!r}")
    return _posterior(loglik, h, left1, n_others, g_under_b, p_good)


# --------------------------------------------------------------------------------------------------------------
# Search-range table (Teng & Dong §III-C)
# --------------------------------------------------------------------------------------------------------------


def gap_inversion_table(sigma) -> tuple[np.ndarray, np.ndarray]:
    """Inversions of a hypothetical match in every gap pair (Teng & Dong §III-C), vectorized 2-D prefix sums.

    Image-1 gap ``h`` (``i_h = h - 0.5`` in 0-based ranks, Teng & Dong's ``i + 0.5``) and image-2 gap ``k``:
    ``C[h, k] = #{m < h : sigma(m) < k}``, ``H^l = h - C``, ``H^r = k - C``.

    Returns:
        ``(H^l, H^r)``, each ``(N+1, N+1) int64`` (rows: image-1 gaps, columns: image-2 gaps). O(N^2) memory --
        for tests and diagnostics; :func:`fit_spatial_order` uses a fused Numba pass that never stores it.
    """
    sigma = np.asarray(sigma, dtype=np.int64)
    n = len(sigma)
    a = np.zeros((n + 1, n + 1), dtype=np.int64)
    a[np.arange(n) + 1, sigma + 1] = 1
    c = a.cumsum(0).cumsum(1)
    hh = np.arange(n + 1)[:, None]
    kk = np.arange(n + 1)[None, :]
    return hh - c, kk - c


def gap_probability_table(sigma, n_good, config: SpatialOrderConfig = SpatialOrderConfig(),
                          noise: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``(N+1, N+1)`` probability that a new feature in image-1 gap h matches correctly into image-2 gap k.

    Dense NumPy reference (O(N^2) memory) of what :func:`fit_spatial_order` thresholds; uses ``config.probability``
    ("exact" is slow: O(|S_beta| H) per cell). ``noise = (mean, var)`` is the order noise added to ``H | G``
    (``model.order_noise`` of a fitted model).
    """
    hl, hr = gap_inversion_table(sigma)
    n = len(sigma)
    hh, kk = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    p = probability_correct(hh.ravel(), kk.ravel(), (hl + hr).ravel(), n, n_good, n, method=config.probability,
                            num_beta=config.num_beta, var_floor=config.var_floor + noise[1], new_feature=True,
                            mean_shift=noise[0])
    return p.reshape(n + 1, n + 1)


@njit(inline="always", cache=True)
def _gap_cell_moments(m1h, s1h, m2k, s2k, nb, fm, ca, cb, cc, var_floor):  # pragma: no cover - numba
    """Mean (without order-noise shift) and variance of H | G in gap cell (h, k) from the per-row constants
    ``fm, ca, cb, cc`` of :func:`_gap_kernel` (the expressions of :func:`_cell_moments` expanded in m2, s2)."""
    mu = m1h + m2k * fm
    var_mu = s1h + ca * m2k + cb * s2k - mu * mu
    if var_mu < 0.0:
        var_mu = 0.0
    vh = cc * (nb * m2k - s2k)
    if vh < 0.0:
        vh = 0.0
    return mu, vh + var_mu + var_floor


@njit(cache=True, fastmath=True)
def _row_var_max(m1h, s1h, m2, s2, nb, fm, ca, cb, cc, var_floor):  # pragma: no cover - numba
    """max over k of the gap kernel's var(h, k) (vectorized; fast-math, so the caller adds a relative margin)."""
    v = var_floor
    for k in range(m2.shape[0]):
        v = max(v, _gap_cell_moments(m1h, s1h, m2[k], s2[k], nb, fm, ca, cb, cc, var_floor)[1])
    return v * (1.0 + 1e-6)


@njit(cache=True)
def _gap_kernel(sigma, m1, s1, m2, s2, blo, bhi, nb, log_pg, log_pb, log_odds_th, var_floor,
                log_out, mean_shift):  # pragma: no cover - numba
    """Fused pass over the (n+1)^2 gap table: C by incremental prefix sums, Gaussian P(H|G), threshold, runs."""
    n = sigma.shape[0]
    crow = np.zeros(n + 1, dtype=np.int64)
    gap_lo = np.full(n + 1, n + 1, dtype=np.int64)
    gap_hi = np.full(n + 1, -1, dtype=np.int64)
    count = np.zeros(n + 1, dtype=np.int64)
    ptr = np.zeros(n + 2, dtype=np.int64)
    cap = 2 * (n + 1)
    runs = np.empty((cap, 2), dtype=np.int64)
    nr = 0
    half_log_2pi = 0.5 * math.log(2.0 * math.pi)
    # skipping (exact): along a row, hv(k) = h + k - 2 C[h, k] moves by exactly +-1 per step and mu(k) by at most
    # |fm| * max|m2[k+1] - m2[k]|, so d = hv - mu is Lipschitz in k; a cell whose |d| exceeds the row's largest
    # admissible |d| (from an upper bound of var over the row) by x * L proves the next ceil(x) - 1 cells out too.
    dm2max = 0.0
    for k in range(n):
        dm2max = max(dm2max, abs(m2[k + 1] - m2[k]))
    for h in range(n + 1):
        if h > 0:
            s = sigma[h - 1]
            for k in range(s + 1, n + 1):
                crow[k] += 1
        width = bhi[h] - blo[h] + 1.0
        lpb_in = log_pb - math.log(width)
        lpb_out = lpb_in + log_out
        # a cell is surely out when the quadratic term alone exceeds this (uses var >= var_floor)
        bound = log_pg - half_log_2pi - 0.5 * math.log(var_floor) - lpb_out - log_odds_th
        if bound < 0.0:  # q >= 0 > bound: no cell of this row is admissible
            ptr[h + 1] = nr
            continue
        in_run = False
        # per-row constants of the cell moments (the expressions of _cell_moments expanded in m2[k], s2[k]):
        # mu = m1 + m2 - 2 m1 m2 / nb; E2 = s1 + A m2 + B s2; vh = C (nb m2 - s2)
        fm = ca = cb = cc = 0.0
        var_hi = var_floor
        lip = 1.0
        if nb >= 1e-9:
            inv_nb = 1.0 / nb
            fm = 1.0 - 2.0 * m1[h] * inv_nb
            ca = 2.0 * m1[h] - 4.0 * s1[h] * inv_nb
            cb = 1.0 - 4.0 * m1[h] * inv_nb + 4.0 * s1[h] * inv_nb * inv_nb
            cc = 2.0 * (nb * m1[h] - s1[h]) * inv_nb * inv_nb / (nb - 1.0) if nb > 1.0 else 0.0
            var_hi = _row_var_max(m1[h], s1[h], m2, s2, nb, fm, ca, cb, cc, var_floor)
            lip = 1.0 + abs(fm) * dm2max
        d_hi = math.sqrt(2.0 * var_hi * bound) * (1.0 + 1e-9) + 1e-9
        lip *= 1.0 + 1e-9
        k = 0
        while k <= n:
            hv = h + k - 2 * crow[k]
            if nb < 1e-9:
                mu = mean_shift
                var = var_floor
            else:
                mu, var = _gap_cell_moments(m1[h], s1[h], m2[k], s2[k], nb, fm, ca, cb, cc, var_floor)
                mu += mean_shift
            d = hv - mu
            # q = d^2 / (2 var) <= bound, tested without the division
            if d * d > 2.0 * var * bound:
                in_run = False
                ad = abs(d)
                if ad > d_hi:
                    k += int(math.ceil((ad - d_hi) / lip))  # the skipped cells are out as well
                else:
                    k += 1
                continue
            q = d * d / (2.0 * var)
            lpg = log_pg - half_log_2pi - 0.5 * math.log(var) - q
            lpb = lpb_in if (hv >= blo[h] and hv <= bhi[h]) else lpb_out
            if lpg - lpb >= log_odds_th:
                count[h] += 1
                if k < gap_lo[h]:
                    gap_lo[h] = k
                gap_hi[h] = k
                if not in_run:
                    if nr == cap:
                        cap *= 2
                        new = np.empty((cap, 2), dtype=np.int64)
                        for r in range(nr):  # element copy: a 2-D slice assignment costs ~4 s of first compile
                            new[r, 0] = runs[r, 0]  # (Numba's broadcast checks format shape strings)
                            new[r, 1] = runs[r, 1]
                        runs = new
                    runs[nr, 0] = k
                    nr += 1
                    in_run = True
                runs[nr - 1, 1] = k
            else:
                in_run = False
            k += 1
        ptr[h + 1] = nr
    return gap_lo, gap_hi, count, ptr, runs[:nr].copy()


def _build_gap_table(sigma_w, n_good, config, noise=(0.0, 0.0)):
    n = len(sigma_w)
    nb = max(float(n) - float(n_good), 0.0)
    gaps = np.arange(n + 1, dtype=np.float64)
    m1, s1 = _beta_moments(gaps, n, nb, config.num_beta)  # image-1 gaps: rows
    m2, s2 = m1, s1  # image-2 gaps: same left counts 0..n, same population
    blo, bhi = bad_inversion_range(gaps, n, n_good)
    p_good = float(np.clip(n_good / max(n, 1), *_P_G_CLIP))
    th = float(np.clip(config.threshold, 1e-300, 1.0 - 1e-16))
    return _gap_kernel(np.ascontiguousarray(sigma_w, dtype=np.int64), m1, s1, m2, s2, blo, bhi, nb,
                       math.log(p_good), math.log(1.0 - p_good), math.log(th / (1.0 - th)),
                       float(max(config.var_floor + noise[1], 1e-9)), math.log(_OUT_OF_RANGE), float(noise[0]))


# --------------------------------------------------------------------------------------------------------------
# Model fitting and lookup
# --------------------------------------------------------------------------------------------------------------


def _unusable(reason, n, config, sigma=None, rank1=None, rank2=None, k_hat=float("nan"), n_good=0.0,
              timings=None) -> SpatialOrderModel:
    z = np.zeros(0, dtype=np.int64)
    sigma = z if sigma is None else sigma
    return SpatialOrderModel(
        usable=False, reason=reason, n=int(n), n_window=0, n_good=float(n_good), k_hat=float(k_hat),
        window1_x=(-np.inf, np.inf), window2_x=(-np.inf, np.inf),
        x1_sorted=np.zeros(0), x2_sorted=np.zeros(0),
        gap_lo=np.zeros(1, dtype=np.int64), gap_hi=np.zeros(1, dtype=np.int64),
        gap_count=np.ones(1, dtype=np.int64), gap_contiguous=np.ones(1, dtype=bool),
        gap_runs_ptr=np.array([0, 1], dtype=np.int64), gap_runs=np.zeros((1, 2), dtype=np.int64),
        sigma=sigma, rank1=z if rank1 is None else rank1, rank2=z if rank2 is None else rank2,
        omega=(0, len(sigma), 0, len(sigma)), in_window=np.zeros(int(n), dtype=bool), sigma_window=z,
        probabilities=np.zeros(int(n)), config=config, timings=timings or {},
    )


def _window_fit(sigma, w, config, method):
    """Sub-permutation inside window w and its N_G, K_hat, inversions and per-match probabilities (None if < 2)."""
    n = len(sigma)
    i1l, i1h, i2l, i2h = w
    ranks_in = np.arange(i1l, i1h)
    sel_ranks = ranks_in[(sigma[ranks_in] >= i2l) & (sigma[ranks_in] < i2h)]  # image-1 ranks inside omega
    vals = sigma[sel_ranks]
    nw = len(vals)
    if nw < 2:
        return None
    mark = np.zeros(n, dtype=np.int64)
    mark[vals] = 1
    sigma_w = (np.cumsum(mark) - 1)[vals]
    hl, hr = inversions_per_match(sigma_w)
    k_hat = 2.0 * float(hl.sum()) / (nw * (nw - 1.0))
    n_good = float(estimate_n_good(k_hat, nw))
    prob = probability_correct(np.arange(nw), sigma_w, hl + hr, nw - 1, n_good, nw, method=method,
                               num_beta=config.num_beta, var_floor=config.var_floor)
    return sel_ranks, vals, sigma_w, hl, hr, k_hat, n_good, prob


def fit_spatial_order(x1, x2, config: SpatialOrderConfig = SpatialOrderConfig(), *, y1=None,
                      y2=None, likely_correct=None) -> SpatialOrderModel:
    """Fit the spatial-order model to matched coordinates (Talker §4-§5; Teng & Dong §III-B, §III-C).

    Args:
        x1, x2: ``(N,)`` x (pixels) of match m in image 1 / image 2 (e.g. image-2 coordinates after alignment).
        config: :class:`SpatialOrderConfig`.
        y1, y2: optional ``(N,)`` y, used only to break x ties (then match index).
        likely_correct: optional ``(N,) bool``, matches known to be (mostly) correct by other means, e.g. the
            RANSAC inliers of F; when given, the order noise (:func:`order_noise`) is measured on them instead of on
            the matches with ``P >= 1/2``.

    Returns:
        :class:`SpatialOrderModel`; ``usable=False`` with a reason (never an exception) when N < 2, coordinates are
        not finite, all x are equal in an image, lengths differ, or there is no significant order structure:
        ``K_hat(omega*) >= 1/2``, or ``z = (1/2 - K_hat) / sd_null < min(min_z, 1.5 + 0.6 ln N)`` with
        ``sd_null^2 = (2n + 5) / (18 n (n - 1))`` the variance of K_hat of a random permutation of the n window matches.
        The ``ln N`` term pays for the window search picking the best of many windows; it was calibrated on uniform
        random permutations (max z over 100 draws: 2.8, 3.8, 4.9, 5.2, 4.9 at N = 10, 50, 200, 600, 2000). So
        all-correct sets need N >= 8, and very weak structure (N_G ~ 10 % of N) is reported unusable.
    """
    import time

    t0 = time.perf_counter()
    try:
        x1 = np.asarray(x1, dtype=np.float64).reshape(-1)
        x2 = np.asarray(x2, dtype=np.float64).reshape(-1)
        y1 = None if y1 is None else np.asarray(y1, dtype=np.float64).reshape(-1)
        y2 = None if y2 is None else np.asarray(y2, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        return _unusable(f"coordinates not convertible to float arrays ({exc})", 0, config)
    n = len(x1)
    if len(x2) != n or (y1 is not None and len(y1) != n) or (y2 is not None and len(y2) != n):
        return _unusable(f"coordinate arrays differ in length ({len(x1)}, {len(x2)})", n, config)
    if n < 2:
        return _unusable(f"fewer than 2 matches ({n})", n, config)
    for name, arr in (("x1", x1), ("x2", x2), ("y1", y1), ("y2", y2)):
        if arr is not None and not np.all(np.isfinite(arr)):
            return _unusable(f"non-finite {name} coordinates ({int((~np.isfinite(arr)).sum())} of {n})", n, config)
    if np.ptp(x1) == 0.0 or np.ptp(x2) == 0.0:
        return _unusable("all x equal in one image: no order information", n, config)
    if config.overlap not in ("k1d", "k2d", "none") or config.probability not in ("gaussian", "exact"):
        raise ValueError(f"bad config {config}")

    sigma, r1, r2 = permutation_from_coordinates(x1, x2, y1, y2)
    t1 = time.perf_counter()
    w = search_overlap(sigma, config.grid_fraction, config.overlap, config.refine)
    fit = _window_fit(sigma, w, config, "gaussian")
    if config.overlap != "none" and fit is not None:
        # self-consistency pass (our addition): Talker's omega* spans the extreme correct matches, so re-window to
        # the extreme ranks of matches with P >= 1/2, re-refine, and keep the candidate with the largest sum of P
        # (the model's own expected number of correct matches; a window that wrongly includes non-overlapping
        # margins breaks A3 and makes the probabilities of the correct matches collapse). Windows whose sum of P
        # is >= 0.75 N_G count as consistent and are ranked by N_G (Talker's criterion); inconsistent ones only
        # win when no candidate is consistent (then by sum of P).
        def score(f):  # consistent windows (sum P >= 0.75 N_G) ranked by N_G, others by sum P below them
            sp_, ng_ = float(f[-1].sum()), float(f[6])
            return (1, ng_) if sp_ >= 0.75 * ng_ else (0, sp_)

        best_w, best_fit, best_score = w, fit, score(fit)
        cur = fit
        for _ in range(max(int(config.trim_rounds), 0)):
            sel_ranks_c, vals_c, p_c = cur[0], cur[1], cur[-1]
            hi_p = p_c >= 0.5
            if hi_p.sum() < 2:
                break
            t = (int(sel_ranks_c[hi_p].min()), int(sel_ranks_c[hi_p].max()) + 1,
                 int(vals_c[hi_p].min()), int(vals_c[hi_p].max()) + 1)
            cands = [t]
            if config.refine:
                cands.append(_refine_window(sigma, t, 2 * max(1, int(round(config.grid_fraction * n)))))
            cur = None
            for tc in cands:  # the trimmed window itself and its refinement
                fc = _window_fit(sigma, tc, config, "gaussian")
                if fc is None:
                    continue
                sc = score(fc)
                if sc > best_score:
                    best_w, best_fit, best_score = tc, fc, sc
                cur = fc
            if cur is None:
                break
        w, fit = best_w, best_fit
    i1l, i1h, i2l, i2h = w
    t2 = time.perf_counter()
    x1s_all = np.sort(x1)
    x2s_all = np.sort(x2)
    timings = {"ranks": t1 - t0, "overlap": t2 - t1}
    if fit is None:
        return _unusable("fewer than 2 matches inside the overlap window", n, config, sigma, r1, r2,
                         timings=timings)
    sel_ranks, vals, sigma_w, hl, hr, k_hat, n_good, prob_w = fit
    nw = len(sigma_w)
    in_window = (r1 >= i1l) & (r1 < i1h) & (r2 >= i2l) & (r2 < i2h)
    null_sd = math.sqrt((2.0 * nw + 5.0) / (18.0 * nw * (nw - 1.0)))
    z = (0.5 - k_hat) / null_sd
    z_crit = min(config.min_z, 1.5 + 0.6 * math.log(n))
    if k_hat >= 0.5 or z < z_crit:
        return _unusable(f"no significant order structure: K_hat={k_hat:.3f} over {nw} matches "
                         f"({z:.1f} null sd below 1/2 < {z_crit:.1f})", n, config, sigma, r1, r2, k_hat,
                         n_good, timings)
    if config.probability != "gaussian":
        idx = np.arange(nw)
        prob_w = probability_correct(idx, sigma_w, hl + hr, nw - 1, n_good, nw, method=config.probability,
                                     num_beta=config.num_beta, var_floor=config.var_floor)
    probs = np.zeros(n)
    # input match m with image-1 rank r1[m]; position of r1[m] in sel_ranks
    pos = np.full(n, -1, dtype=np.int64)
    pos[sel_ranks] = np.arange(nw)
    m_in = np.nonzero(in_window)[0]
    probs[m_in] = prob_w[pos[r1[m_in]]]
    noise = (0.0, 0.0)
    if config.order_noise:
        if likely_correct is not None and len(likely_correct) == n:
            lc = np.zeros(nw)
            lc[pos[r1[m_in]]] = np.asarray(likely_correct, bool)[m_in]
            noise = order_noise(sigma_w, lc)
        else:
            noise = order_noise(sigma_w, prob_w)
    t3 = time.perf_counter()
    if config.gap_table:
        gap_lo, gap_hi, count, ptr, runs = _build_gap_table(sigma_w, n_good, config, noise)
    else:  # no table: lookups refuse (see admissible_x_ranges)
        gap_lo = gap_hi = count = ptr = np.zeros(0, np.int64)
        runs = np.zeros((0, 2), np.int64)
    t4 = time.perf_counter()
    timings.update({"probabilities": t3 - t2, "gap_table": t4 - t3, "total": t4 - t0})
    return SpatialOrderModel(
        usable=True, reason="", n=n, n_window=nw, n_good=n_good, k_hat=k_hat,
        window1_x=(float(x1s_all[i1l]), float(x1s_all[i1h - 1])),
        window2_x=(float(x2s_all[i2l]), float(x2s_all[i2h - 1])),
        x1_sorted=x1s_all[sel_ranks], x2_sorted=x2s_all[np.sort(vals)],
        gap_lo=gap_lo, gap_hi=gap_hi, gap_count=count,
        gap_contiguous=(count == np.maximum(gap_hi - gap_lo + 1, 0)),
        gap_runs_ptr=ptr, gap_runs=runs, sigma=sigma, rank1=r1, rank2=r2, omega=(i1l, i1h, i2l, i2h),
        in_window=in_window, sigma_window=sigma_w, probabilities=probs, config=config, timings=timings,
        order_noise=noise,
    )


def order_noise(sigma_w, prob_w, min_matches: int = 8) -> tuple[float, float]:
    """Local order noise of the likely-correct matches: mean and variance of their inversions among themselves.

    Talker's A1 says correct matches never invert each other, so ``P(H|G)`` only counts inversions with incorrect
    matches. Real pairs break A1 locally: depth discontinuities ("poles"), perspective, residual roll and
    keypoint noise swap nearby correct matches. Among the matches with ``P >= 1/2`` (taken as correct) we count,
    for each, the inversions it takes part in with the others (``H_G``); a correct *new* feature at its true gap
    meets the same disorder, so the search-range table adds ``mean(H_G)`` to the mean of ``H | G`` and
    ``var(H_G)`` to its variance (an addition to Teng & Dong §III-C; ``order_noise=False`` restores the paper).
    The estimate is conservative on the low side: matches whose disorder already made ``P < 1/2`` are left out.
    Returns ``(0, 0)`` with fewer than ``min_matches`` likely-correct matches.
    """
    good = np.asarray(prob_w) >= 0.5
    if int(good.sum()) < min_matches:
        return (0.0, 0.0)
    sub = np.asarray(sigma_w)[good]
    dense = np.argsort(np.argsort(sub, kind="stable"), kind="stable")
    hl, hr = inversions_per_match(dense)
    hg = (hl + hr).astype(np.float64)
    return (float(hg.mean()), float(hg.var()))


def admissible_x_ranges(model: SpatialOrderModel, xq) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image-2 x search interval for new image-1 features (Teng & Dong §III-B.2 and §III-C).

    Args:
        model: a fitted :class:`SpatialOrderModel`.
        xq: ``(M,)`` image-1 x (pixels) of new features.

    Returns:
        ``(keep, lo, hi, contiguous)``. ``keep (M,) bool``: False when xq is outside ``window1_x``, not finite, or
        no gap is admissible. ``lo, hi (M,) float64``: the hull of the admissible image-2 gaps as an x interval;
        gap ``k`` spans ``(x2_sorted[k-1], x2_sorted[k])`` with ``x2_sorted[-1] := -inf``, ``x2_sorted[n] := +inf``;
        treat the interval as closed (features at the bounding matched positions included). ``lo = hi = nan``
        where ``keep`` is False. ``contiguous (M,) bool``: the admissible gap set equals its hull. The image-1 gap
        is ``np.searchsorted(model.x1_sorted, xq, side="left")``. Unusable model: keep all True, lo=-inf, hi=+inf.
    """
    xq = np.asarray(xq, dtype=np.float64).reshape(-1)
    m = len(xq)
    if not model.usable:
        return (np.ones(m, dtype=bool), np.full(m, -np.inf), np.full(m, np.inf), np.ones(m, dtype=bool))
    if len(model.gap_lo) != model.n_window + 1:
        raise ValueError("this model was fitted with gap_table=False: it has no search-range table")
    h = np.searchsorted(model.x1_sorted, xq, side="left")
    glo = model.gap_lo[h]
    ghi = model.gap_hi[h]
    keep = (xq >= model.window1_x[0]) & (xq <= model.window1_x[1]) & (glo <= ghi)
    x2lo = np.concatenate([[-np.inf], model.x2_sorted])  # lower bound of gap k: x2_sorted[k-1]
    x2hi = np.concatenate([model.x2_sorted, [np.inf]])  # upper bound of gap k: x2_sorted[k]
    nw = model.n_window
    lo = x2lo[np.clip(glo, 0, nw)]
    hi = x2hi[np.clip(ghi, 0, nw)]
    lo = np.where(keep, lo, np.nan)
    hi = np.where(keep, hi, np.nan)
    return keep, lo, hi, model.gap_contiguous[h].copy()


def match_probabilities(x1, x2, model_or_config=None) -> np.ndarray:
    """``P(i in G | H^l, H^r)`` per given match (Talker Eq. 12; Teng & Dong Eq. 6-9), 0 outside omega*.

    Args:
        x1, x2: ``(N,)`` matched x in image 1 / image 2 (pixels).
        model_or_config: a model fitted on exactly these matches (its stored probabilities are returned), or a
            :class:`SpatialOrderConfig` / None (a model is fitted first). Unusable model: all zeros.
    """
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1)
    if isinstance(model_or_config, SpatialOrderModel):
        model = model_or_config
        if model.n != len(x1):
            raise ValueError(f"model was fitted on {model.n} matches, got {len(x1)}")
    else:
        import dataclasses

        cfg = dataclasses.replace(model_or_config or SpatialOrderConfig(), gap_table=False)  # table not needed here
        model = fit_spatial_order(x1, x2, cfg)
    if not model.usable:
        return np.zeros(len(x1))
    return model.probabilities.copy()
