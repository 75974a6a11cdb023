"""Exact, order-fixed descriptor distances: the reported distance of every match and every ratio-test decision.

The fast searches (BLAS GEMM, the vectorized Numba L2 sum of the guided kernel, faiss) add up a float distance in an
order set by the CPU's vector width, the BLAS kernel and how the work is cut between threads, so their values can
differ in the last bits between an Intel AVX-512 and an AMD AVX2 machine, between 1 and 2 BLAS or Numba threads,
between a direct call and a collection's worker. Here each such search hands over its ``K`` approximately nearest
candidates per query; their distances are recomputed by :func:`sqdist_rows` -- float64 differences squared and added
in an order the code spells out (dimension ``k`` into running sum ``k % 4``, in index order, then ``(s0 + s1) + (s2 +
s3)``), in a Numba kernel compiled *without* fast-math, so LLVM may neither reassociate the sums (vectorizing a float
reduction needs that) nor contract them into FMAs: the same IEEE-754 operations in the same order on every x86-64
CPU, whatever its vector width or thread count -- and the nearest ``m``
(the top 2 of a ratio test) are taken on these values, equal distances by the lower index. Integer distances (uint8
descriptors summed in int/float32 below 2^24, Hamming popcounts) are exact already and are not recomputed.

**The candidate set is certified, not hoped for.** A fast search's distance ``~d`` of a true distance ``d`` obeys
``|~d - d| <= delta + gamma d`` for a known bound (:func:`sum_gamma`: a float32 sum of D non-negative squares, any
order; :func:`gemm_delta`: ``|q|^2 + |t|^2 - 2 q.t`` from a float32 GEMM, any order, FMA or not). Every candidate the
search did not return has ``~d >= ~d_K`` (the K-th returned), and the m returned first have true distances
``<= (~d_m + delta) / (1 - gamma)``; so when ``(~d_K - delta) / (1 + gamma) > (~d_m + delta) / (1 - gamma)`` no
unreturned candidate can be among the true nearest m, ties included, and the exact top m of the K returned is the
exact top m of the whole search domain, on any CPU. A search that returned fewer than K candidates returned its whole
domain. Otherwise (a near-tie at the K-th candidate; rare, and counted in :data:`FALLBACKS`) that query's whole domain
is recomputed exactly. The cost is ``Q * K * D`` operations besides the search (``Q * N * D`` for the rare fallback).
"""
from __future__ import annotations

import numpy as np
from numba import njit

#: approximate candidates a fast search hands over per query for an exact top 2 (2 + a margin of 2)
K = 4
#: unit roundoff of float32
U32 = 2.0 ** -24
#: queries whose candidate set could not be certified and were recomputed over their whole domain (since import)
FALLBACKS = [0]


def sum_gamma(dim: int) -> float:
    """Relative error bound of a float32 sum of ``dim`` squared float32 differences, in any order (with or without
    FMA): ``gamma_{dim+2}`` (each term: a rounded difference and a rounded square; the sum: dim - 1 roundings, no
    cancellation since every term is >= 0), doubled for safety."""
    n = int(dim) + 3
    return 2.0 * n * U32 / (1.0 - n * U32)


def gemm_delta(qn: np.ndarray, tn_max: float, dim: int) -> np.ndarray:
    """Absolute error bound ``(Q,)`` float64 of the squared L2 distances formed from a float32 GEMM,
    ``max(|q|^2 + |t|^2 - 2 q.t, 0)`` with float32 norms, for queries of squared norms ``qn`` against targets of
    squared norm at most ``tn_max``: ``|fl(q.t) - q.t| <= gamma_D |q||t| <= gamma_D (|q|^2 + |t|^2) / 2`` for any
    summation order, the norms within ``gamma_D`` relative, the two additions one rounding each of a value below
    ``3 (|q|^2 + |t|^2)``: in all below ``2 gamma_{D+3} (|q|^2 + |t|^2)``; doubled for safety."""
    n = int(dim) + 3
    g = n * U32 / (1.0 - n * U32)
    return 4.0 * g * (np.asarray(qn, np.float64) + float(tn_max))


@njit(cache=True, nogil=True)
def _sqdist(a, b):
    # float64 differences squared into four running sums, dimension k into sum k % 4 in index order, then
    # (s0 + s1) + (s2 + s3): an order written here, not chosen by the compiler (no fast-math: no reassociation, no
    # contraction; LLVM may put the four sums in one vector register, which changes nothing lane by lane). Four
    # independent chains run ~4x faster than one.
    n = a.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    k = 0
    while k + 4 <= n:
        d0 = np.float64(a[k]) - np.float64(b[k])
        d1 = np.float64(a[k + 1]) - np.float64(b[k + 1])
        d2 = np.float64(a[k + 2]) - np.float64(b[k + 2])
        d3 = np.float64(a[k + 3]) - np.float64(b[k + 3])
        s0 += d0 * d0
        s1 += d1 * d1
        s2 += d2 * d2
        s3 += d3 * d3
        k += 4
    if k < n:
        d0 = np.float64(a[k]) - np.float64(b[k])
        s0 += d0 * d0
    if k + 1 < n:
        d1 = np.float64(a[k + 1]) - np.float64(b[k + 1])
        s1 += d1 * d1
    if k + 2 < n:
        d2 = np.float64(a[k + 2]) - np.float64(b[k + 2])
        s2 += d2 * d2
    return (s0 + s1) + (s2 + s3)


@njit(cache=True, nogil=True)
def sqdist_rows(q, t, cand):
    """Exact squared L2 distances ``(Q, C) float64`` of query rows ``q (Q, D)`` to target rows ``t[cand[i, c]]``
    (``inf`` where ``cand < 0``), each summed in float64 in the fixed order of the module doc."""
    nq, nc = cand.shape
    out = np.empty((nq, nc), np.float64)
    for i in range(nq):
        for c in range(nc):
            j = cand[i, c]
            out[i, c] = _sqdist(q[i], t[j]) if j >= 0 else np.inf
    return out


@njit(cache=True, nogil=True)
def _refine(q, t, cand, approx, m, delta, gamma):
    """Exact top ``m`` of each row's candidates and whether the row's candidate set is certified."""
    nq, nk = cand.shape
    idx = np.full((nq, m), -1, np.int64)
    dist = np.full((nq, m), np.inf, np.float64)
    ok = np.ones(nq, np.bool_)
    for i in range(nq):
        nvalid = 0
        for c in range(nk):
            j = cand[i, c]
            if j < 0:
                continue
            nvalid += 1
            v = _sqdist(q[i], t[j])
            # insertion into the row's top m by (distance, index)
            p = m
            while p > 0 and (dist[i, p - 1] > v or (dist[i, p - 1] == v and (idx[i, p - 1] > j or idx[i, p - 1] < 0))):
                p -= 1
            if p < m:
                for r in range(m - 1, p, -1):
                    dist[i, r] = dist[i, r - 1]
                    idx[i, r] = idx[i, r - 1]
                dist[i, p] = v
                idx[i, p] = j
        if nvalid >= nk and nk > m:  # fewer than K returned: the whole domain was returned
            am = np.float64(approx[i, m - 1])
            ak = np.float64(approx[i, nk - 1])
            ok[i] = (ak - delta[i]) / (1.0 + gamma) > (am + delta[i]) / (1.0 - gamma)
        elif nvalid >= nk:
            ok[i] = False
    return idx, dist, ok


def exact_top(q: np.ndarray, t: np.ndarray, cand: np.ndarray, approx: np.ndarray, m: int = 2, *,
              delta: np.ndarray | float = 0.0, gamma: float = 0.0, domain=None):
    """Exact top ``m`` of each query among its fast search's candidates, certified (see the module doc).

    Args:
        q: ``(Q, D)`` query descriptors; t: ``(N, D)`` target descriptors (float32 or any numeric dtype).
        cand: ``(Q, K) int64`` target indices a fast search returned, nearest first by its own distances ``approx
            (Q, K)`` (ascending; ``-1`` / ``inf`` past the number found). A row with fewer than K found means the
            search returned its whole domain.
        m: how many nearest to return (< K for a certificate).
        delta, gamma: the search's error bound ``|~d - d| <= delta + gamma d`` (``delta`` scalar or ``(Q,)``).
        domain: ``domain(i) -> (n,) int64`` target indices of query ``i``'s whole search domain (default: all of
            ``t``), recomputed exactly for a row whose candidates are not certified.

    Returns:
        ``(idx (Q, m) int64, sq (Q, m) float64)``: exact squared L2 distances, ascending, equal ones by index.
    """
    q = np.ascontiguousarray(q)
    nq = len(q)
    cand = np.ascontiguousarray(cand, np.int64).reshape(nq, -1)
    approx = np.ascontiguousarray(approx, np.float64).reshape(nq, -1)
    d = np.broadcast_to(np.asarray(delta, np.float64), (nq,)).copy()
    idx, sq, ok = _refine(q, t, cand, approx, int(m), d, float(gamma))
    for i in np.flatnonzero(~ok):
        FALLBACKS[0] += 1
        js = np.arange(len(t), dtype=np.int64) if domain is None else np.asarray(domain(int(i)), np.int64)
        idx[i], sq[i] = exact_top_among(q[i], t, js, m)
    return idx, sq


def exact_top_among(qrow: np.ndarray, t: np.ndarray, js: np.ndarray, m: int = 2):
    """Exact top ``m`` of one query row among targets ``js``: ``(idx (m,), sq (m,) float64)`` (``-1`` / ``inf``
    past ``len(js)``), equal distances by the lower index."""
    js = np.unique(np.asarray(js, np.int64))  # ascending: a stable sort by distance keeps equal ones by index
    out_i = np.full(m, -1, np.int64)
    out_d = np.full(m, np.inf, np.float64)
    if len(js):
        dd = sqdist_rows(np.ascontiguousarray(qrow)[None], t, js[None])[0]
        o = np.argsort(dd, kind="stable")[:m]
        out_i[:len(o)], out_d[:len(o)] = js[o], dd[o]
    return out_i, out_d


def exact_top_among_rows(q: np.ndarray, t: np.ndarray, among: np.ndarray, m: int = 2):
    """:func:`exact_top_among` for every query row at once: the exact top ``m`` of row ``i`` of ``q (R, D)`` among the
    targets ``t[j]`` with ``among[i, j]`` (a boolean ``(R, len(t))`` mask): ``(idx (R, m), sq (R, m) float64)``, equal
    distances by the lower index, ``-1`` / ``inf`` past a row's count. One padded candidate matrix through
    :func:`sqdist_rows`: the same sums, so the same values as the row-by-row call."""
    count = among.sum(axis=1)
    width = max(int(count.max()) if len(count) else 0, m)
    cand = np.argsort(~among, axis=1, kind="stable")[:, :width]  # each row's targets first, in index order
    cand[np.arange(cand.shape[1])[None, :] >= count[:, None]] = -1  # padding: distance inf
    dd = sqdist_rows(np.ascontiguousarray(q), t, np.ascontiguousarray(cand, np.int64))
    o = np.argsort(dd, axis=1, kind="stable")[:, :m]  # stable: equal distances keep the lower index
    r = np.arange(len(q))[:, None]
    sq = dd[r, o]
    return np.where(np.isfinite(sq), cand[r, o], -1), sq


def top_of_exact(cand: np.ndarray, dist: np.ndarray, m: int = 2):
    """Top ``m`` of candidates whose distances are exact already (integers below 2^24 in float32: byte-valued
    descriptors through a GEMM or faiss's 8-bit codes): ``(idx (Q, m), sq (Q, m) float64)`` by distance, then the
    lower index. No recompute: such a sum is exact in any order, on any CPU."""
    cand = np.asarray(cand, np.int64)
    dist = np.where(cand >= 0, np.asarray(dist, np.float64), np.inf)
    big = np.where(cand >= 0, cand, np.iinfo(np.int64).max)
    o = np.lexsort((big, dist), axis=-1)[:, :m]
    r = np.arange(len(cand))[:, None]
    idx, sq = cand[r, o], dist[r, o]
    if idx.shape[1] < m:
        pad = m - idx.shape[1]
        idx = np.pad(idx, ((0, 0), (0, pad)), constant_values=-1)
        sq = np.pad(sq, ((0, 0), (0, pad)), constant_values=np.inf)
    return np.where(np.isfinite(sq), idx, -1), sq


#: largest squared norm sum for which a float32 GEMM distance of byte-valued descriptors is an exact integer
EXACT_INT = float(2 ** 24)


def l2(sq: np.ndarray) -> np.ndarray:
    """Reported L2 distances: ``float32(sqrt(sq))`` of float64 squared distances (``inf`` stays ``inf``). For an
    integer ``sq`` below 2^24 this equals float32's own square root of it (rounding a float64 square root to float32
    is correctly rounded), so byte-valued descriptors report what they always did."""
    return np.sqrt(np.asarray(sq, np.float64)).astype(np.float32)
