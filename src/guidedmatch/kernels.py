"""Numba kernels for descriptor distances: top-k search over dense GEMM blocks, Hamming brute force,
and the guided candidate kernel of the progressive matcher.

The kernels return, per query, the best few candidates (index and distance) and count the exact number of
descriptor distances they evaluated (the paper's "# matches" column, Teng & Dong §IV-A). Distances returned by
these kernels are **squared** L2 for float32 and byte-valued (uint8) descriptors (``topk_gemm_serial``:
``max(|q|^2 + |t|^2 - 2 q.t, 0)`` in float32; ``guided_top2``: the sum of squared differences, exact integers for
byte-valued rows) and Hamming bit counts for binary ones (uint64 words; not squared), all as float32. Integer ones
are exact; float ones depend on the summation order (the CPU's vector width, the BLAS, the thread split), so the
callers recompute the best few exactly (:mod:`guidedmatch.exact`) and report L2 (Euclidean, not squared): the
float32 square root of the exact squared distance. ``MatchResult.distances`` are L2 or Hamming bits.
Index ``-1`` and distance ``+inf`` mean "no such candidate".

What lives where:

* here -- the distance primitives (``desc_dist``: float / byte-valued L2, Hamming), the dense kernels (GEMM top-k,
  Hamming brute force), the search-region kernel and the guided candidate kernel, with their Python entry points
  (:func:`topk_block`, :func:`topk_gemm`, :func:`hamming_top2`, :func:`hamming_col_best`, :func:`guided_top2`).
  They stay in one file on purpose: Numba's on-disk cache (``cache=True``) checks only the defining file of a
  cached kernel, so an edit of a kernel that others call or inline (the distance primitives, the top-2 / top-3
  updates) recompiles them only when they share its file;
* :mod:`guidedmatch.strip_index` -- the strip index the guided kernel walks (:class:`StripIndex`,
  :func:`build_strips`, :func:`first_nonempty`) and :func:`counting_order`;
* :mod:`guidedmatch.kernel_threads` -- the thread schedule of large calls (:func:`num_threads`,
  :func:`limit_threads_here`).

The names of both are importable from here too (``kernels.build_strips``, ``kernels.num_threads``, ...).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numba.extending import overload

from .kernel_threads import _chunked_rows, _join_rows
from .kernel_threads import limit_threads_here, num_threads  # noqa: F401 -- re-exported
from .strip_index import StripIndex, build_strips, counting_order, first_nonempty  # noqa: F401 -- re-exported

INF = np.float32(np.inf)


# --------------------------------------------------------------------------- helpers
def pack_bits_u64(desc: np.ndarray) -> np.ndarray:
    """``(N, B) uint8`` packed bits -> ``(N, ceil(B/8)) uint64`` words (zero padded) for popcount."""
    desc = np.ascontiguousarray(desc, dtype=np.uint8)
    n, b = desc.shape
    w = (b + 7) // 8
    if w * 8 != b:
        pad = np.zeros((n, w * 8), np.uint8)
        pad[:, :b] = desc
        desc = pad
    return np.ascontiguousarray(desc).view(np.uint64).reshape(n, w)


@njit(inline="always", cache=True)
def _popcount64(x):
    # SWAR popcount; LLVM turns this into a popcnt instruction where available
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


# The distance primitives take the two descriptor arrays and the row of each (``A[i]`` vs ``B[j]``), never row views:
# inside a kernel's loop a view (``A[i]``), and every array argument of a function inlined at Numba-IR level, is a new
# reference, counted by two atomic updates of Numba's NRT -- the guided kernel spent a third of its time on them.
# Neither are they inlined at Numba-IR level (LLVM inlines them): the fast-math flags of the L2 sums stay on their
# own instructions, and the calling kernels' band test stays IEEE on every CPU.
@njit(cache=True)
def _hamming(A, i, B, j):
    # Hamming bits between packed-word rows A[i] and B[j] (uint64)
    s = np.uint64(0)
    for k in range(A.shape[1]):
        s += _popcount64(A[i, k] ^ B[j, k])
    return np.float32(s)


@njit(cache=True, fastmath={"reassoc", "contract"})
def _l2sq(A, i, B, j):
    # approximate squared L2 of float32 rows: 'reassoc' lets LLVM vectorize the sum, in an order set by the CPU's
    # vector width, so the value may differ in the last bits between CPUs; the matcher takes the kernel's best three
    # and recomputes them exactly (guidedmatch.exact).
    s = np.float32(0.0)
    for k in range(A.shape[1]):
        d = A[i, k] - B[j, k]
        s += d * d
    return s


@njit(cache=True, fastmath={"reassoc", "contract"})
def _l2sq_u8(A, i, B, j):
    # exact squared L2 of byte-valued descriptors (e.g. SIFT, integers 0..255), summed in float32: every term and
    # partial sum is an integer below 2^24 (at most 255^2 * 256 = 16,646,400 for up to 256 dimensions), so any order
    # of summation -- the vectorized one 'reassoc' allows -- gives the exact value. Numba promotes int32 arithmetic to
    # int64 lanes (4 per AVX2 register): 16 ns per 128-D distance vs 11 ns here.
    s = np.float32(0.0)
    for k in range(A.shape[1]):
        d = np.float32(A[i, k]) - np.float32(B[j, k])
        s += d * d
    return s


def as_exact_uint8(desc: np.ndarray, block: int = 8192) -> np.ndarray | None:
    """``desc`` as uint8 when every value is an integer in 0..255 (OpenCV SIFT), else None.

    Squared L2 of such descriptors is computed exactly (float32 sums of integers < 2^24) on a quarter of the memory
    traffic.
    Plain NumPy in blocks of ``block`` rows, stopping at the first block with a value that does not fit: a collection
    prepares images with it before Numba has loaded any kernel, so that the first images' indexes are built while
    another thread loads them (``collection.engine``). Any value outside 0..255, fractional or NaN casts to a uint8
    that compares unequal to it, whatever value the cast gives (hence ``invalid="ignore"``). ~10 ms at 68k x 128.
    """
    if desc.dtype != np.float32 or desc.size == 0 or desc.ndim != 2 or desc.shape[1] > 256:
        return None  # > 256 dimensions: the float32 sum of _l2sq_u8 could exceed 2^24 and round
    out = np.empty(desc.shape, np.uint8)
    for s in range(0, len(desc), block):
        b = desc[s:s + block]
        with np.errstate(invalid="ignore"):
            out[s:s + block] = b  # the cast (unsafe for values that do not fit; checked next)
        if not np.array_equal(out[s:s + block], b):
            return None
    return out


def desc_dist(A, i, B, j):  # pragma: no cover - replaced by the Numba overload below inside jitted code
    """Descriptor distance between rows ``A[i]`` and ``B[j]``: squared L2 (float32) for float or byte-valued rows,
    Hamming bits for uint64 word rows."""
    raise NotImplementedError


@overload(desc_dist)
def _desc_dist_overload(A, i, B, j):
    # resolved at compile time from the array dtype, so one cached kernel per descriptor kind
    if isinstance(A, types.Array) and isinstance(A.dtype, types.Float):
        return lambda A, i, B, j: _l2sq(A, i, B, j)
    if isinstance(A, types.Array) and A.dtype == types.uint64:
        return lambda A, i, B, j: _hamming(A, i, B, j)
    if isinstance(A, types.Array) and A.dtype == types.uint8:
        return lambda A, i, B, j: _l2sq_u8(A, i, B, j)
    return None


@njit(inline="always", cache=True)
def _push(d, j, b1, j1, b2, j2):
    # top-2 update; equal distances prefer the lower index (deterministic, like argmin).
    # Fast path first: almost every value is not among the best two, which costs one comparison.
    if d > b2 or (d == b2 and j >= j2 >= 0):
        return b1, j1, b2, j2
    if d < b1 or (d == b1 and j < j1):
        return d, j, b1, j1
    return b1, j1, d, j


@njit(inline="always", cache=True)
def _push3(d, j, b1, j1, b2, j2, b3, j3):
    # top-3 update, equal distances by the lower index (the guided kernel keeps a third for the exact recompute)
    if d > b3 or (d == b3 and j >= j3 >= 0):
        return b1, j1, b2, j2, b3, j3
    if d < b2 or (d == b2 and j < j2):
        if d < b1 or (d == b1 and j < j1):
            return d, j, b1, j1, b2, j2
        return b1, j1, d, j, b2, j2
    return b1, j1, b2, j2, d, j


# --------------------------------------------------------------------------- dense top-2
def _topk_gemm_py(dot, nn2, qn, k):
    """The ``k`` smallest squared L2 distances of every row of a GEMM block, ascending: ``(idx (R, k) int64,
    dist (R, k) float32)`` (``-1`` / ``inf`` past the number of columns).

    ``dot (R, C) float32`` = query·targetᵀ, ``nn2 (C,)`` and ``qn (R,)`` squared norms; the distance is
    ``max((qn + nn2) - 2 dot, 0)`` in float32, in that order (faiss's ``exhaustive_L2sqr_blas``). Equal distances
    keep the lower column index. ``k`` is a few (the IVF coarse step's nprobe + 1, brute force's
    :data:`guidedmatch.exact.K`): one comparison per column, an insertion only when the column beats the current
    ``k``-th. The values are approximate (float32 GEMM); the callers recompute the winners exactly
    (:mod:`guidedmatch.exact`).
    """
    r, c = dot.shape
    idx = np.full((r, k), -1, np.int64)
    dist = np.full((r, k), np.inf, np.float32)
    m2 = np.float32(-2.0)
    zero = np.float32(0.0)
    bd = np.empty(k, np.float32)
    bi = np.empty(k, np.int64)
    for i in range(r):
        for t in range(k):
            bd[t] = np.inf
            bi[t] = -1
        row = dot[i]
        q = qn[i]
        worst = np.float32(np.inf)
        for j in range(c):
            v = max((q + nn2[j]) + row[j] * m2, zero)
            if v >= worst:
                continue
            t = k - 1
            while t > 0 and bd[t - 1] > v:
                bd[t] = bd[t - 1]
                bi[t] = bi[t - 1]
                t -= 1
            bd[t] = v
            bi[t] = j
            worst = bd[k - 1]
        for t in range(k):
            idx[i, t] = bi[t]
            dist[i, t] = bd[t]
    return idx, dist


@njit(cache=True, nogil=True)
def _hamming_top2(q, t):
    """Brute-force Hamming top-2 of every query word row ``q (N1, W) uint64`` among ``t (N2, W)``: ``(i1, d1, i2,
    d2)``, distances in bits as float32 (not squared)."""
    n1 = q.shape[0]
    n2 = t.shape[0]
    i1 = np.full(n1, -1, np.int64)
    i2 = np.full(n1, -1, np.int64)
    d1 = np.full(n1, np.inf, np.float32)
    d2 = np.full(n1, np.inf, np.float32)
    for i in range(n1):
        b1 = np.float32(np.inf)
        b2 = np.float32(np.inf)
        j1 = -1
        j2 = -1
        for j in range(n2):
            b1, j1, b2, j2 = _push(_hamming(q, i, t, j), j, b1, j1, b2, j2)
        i1[i] = j1
        i2[i] = j2
        d1[i] = b1
        d2[i] = b2
    return i1, d1, i2, d2


@njit(cache=True, nogil=True)
def _hamming_col_best(q, t):
    """For every target row of ``t``: index of and Hamming distance (bits, float32) to its nearest query row
    (mutual check)."""
    n2 = t.shape[0]
    n1 = q.shape[0]
    best = np.full(n2, -1, np.int64)
    bd = np.full(n2, np.inf, np.float32)
    for j in range(n2):
        b = np.float32(np.inf)
        k = -1
        for i in range(n1):
            v = _hamming(q, i, t, j)
            if v < b:
                b = v
                k = i
        best[j] = k
        bd[j] = b
    return best, bd


# --------------------------------------------------------------------------- guided candidates
@njit(cache=True, nogil=True)
def search_regions_kernel(p, use_so, x1_sorted, gap_lo, gap_hi, x1_lo, x1_hi, x2_sorted, nw, rescue, r_lo, r_hi,
                          use_F, F):  # pragma: no cover - numba
    """:func:`guidedmatch.matcher.search_regions` for ``p (Q, 2)`` aligned image-1 points: ``(keep, lo, hi, lines,
    rescued)``. Spatial order (``use_so``): the image-1 gap ``h`` (searchsorted left in ``x1_sorted``), kept when
    ``x1_lo <= x <= x1_hi`` and ``gap_lo[h] <= gap_hi[h]``, x-range ``[x2(gap_lo - 1), x2(gap_hi)]`` with
    ``x2(-1) = -inf``, ``x2(nw) = +inf`` (NaN when not kept); ``rescue``: not kept but ``r_lo <= x <= r_hi`` -> kept,
    unbounded. Epipolar (``use_F``): the line ``F (x, y, 1)`` scaled to a unit normal, ``(0, 0, inf)`` when
    degenerate. Same arithmetic as the NumPy formulation."""
    q = p.shape[0]
    keep = np.ones(q, np.bool_)
    lo = np.full(q, -np.inf)
    hi = np.full(q, np.inf)
    rescued = np.zeros(q, np.bool_)
    lines = np.empty((q if use_F else 0, 3))
    n1 = x1_sorted.shape[0]
    for i in range(q):
        x = p[i, 0]
        if use_so:
            a, b = 0, n1  # searchsorted(x1_sorted, x, side="left")
            while a < b:
                m = (a + b) >> 1
                if x1_sorted[m] < x:
                    a = m + 1
                else:
                    b = m
            glo = gap_lo[a]
            ghi = gap_hi[a]
            k = x >= x1_lo and x <= x1_hi and glo <= ghi
            if k:
                c0 = min(max(glo, 0), nw)
                c1 = min(max(ghi, 0), nw)
                lo[i] = -np.inf if c0 == 0 else x2_sorted[c0 - 1]
                hi[i] = np.inf if c1 == nw else x2_sorted[c1]
            elif rescue and x >= r_lo and x <= r_hi:
                rescued[i] = True
                k = True
            else:
                lo[i] = np.nan
                hi[i] = np.nan
            keep[i] = k
        if use_F:
            y = p[i, 1]
            la = F[0, 0] * x + F[0, 1] * y + F[0, 2]
            lb = F[1, 0] * x + F[1, 1] * y + F[1, 2]
            lc = F[2, 0] * x + F[2, 1] * y + F[2, 2]
            nrm = math.hypot(la, lb)
            if nrm > 1e-12:
                lines[i, 0] = la / nrm
                lines[i, 1] = lb / nrm
                lines[i, 2] = lc / nrm
            else:
                lines[i, 0] = 0.0
                lines[i, 1] = 0.0
                lines[i, 2] = np.inf
    return keep, lo, hi, lines, rescued


@njit(inline="always", cache=True)
def _cells(k0, nk, h, ih, kmin, kmax):
    # the cells of a strip (``nk`` cells of ``h`` px from ``k0``) overlapping [kmin, kmax]: (c0, c1), empty when
    # c0 > c1. Scalars only: an array argument of an inlined function costs Numba an atomic reference-count
    # increment and decrement per call, i.e. per strip the guided kernel visits (a third of its time)
    # int(t / h) of t >= 0 instead of t // h (a libm fmod call, 8 % of the kernel): the rounded quotient is at most
    # one cell above the floor, and only where [kmin, kmax] -- padded by the caller by 1e-7 relative -- ends within
    # rounding of a cell boundary: no point of the band lies there
    # ``ih`` = 1 / h: a product instead of a division per visited strip (the quotient is then within a few ulps of
    # t / h: the same argument holds)
    if kmax < k0 or kmin > k0 + nk * h:
        return 1, 0
    c0 = 0 if kmin <= k0 else min(int((kmin - k0) * ih), nk - 1)
    c1 = nk - 1 if kmax >= k0 + nk * h else min(int((kmax - k0) * ih), nk - 1)
    return c0, c1


def _guided_py(queries, desc1, desc2, lines, use_band, band, xlo, xhi, cols, rows, fcols, frows):
    """Best two candidates of each query among the image-2 features of its search region.

    The region of query ``q`` (image-1 feature ``queries[q]``) is ``{j : xlo[q] <= x_j <= xhi[q]}`` (the
    spatial-order x-range) and, when ``use_band``, ``|lines[q] . (x_j, y_j, 1)| <= band`` (the epipolar band;
    lines scaled to a^2+b^2 = 1); ``(x_j, y_j)`` are the (aligned) image-2 coordinates the strip structures were
    built on (:func:`build_strips`): ``cols`` (``axis=0``) serves queries whose line is closer to horizontal and
    queries without band, ``rows`` (``axis=1``) the others (it may be a dummy ``build_strips(empty)`` when no
    such query exists). Only strips the region can touch are visited, and in each only the cells spanned by the
    band's extent; the predicate above is then tested exactly per scanned point.

    ``desc1``/``desc2``: float32 rows (squared L2, approximate: a vectorized sum), uint8 byte-valued rows (exact
    squared L2) or uint64 words (Hamming). Returns ``(i1, d1, i2, d2, ncand, nvisit, i3, d3)`` with original
    image-2 indices, raw ``desc_dist`` values (``i3, d3``: the third best), ``ncand[q]`` = the exact number of descriptor distances evaluated for query ``q`` and ``nvisit[q]`` =
    the strips it visited.

    Work bound: each query's walk is clipped to the part of its band inside the bounding box of the
    indexed points and jumps over empty strips (``fcols``/``frows`` = :func:`first_nonempty` of ``cols``/``rows``),
    so a query visits at most the occupied strips its band crosses -- never a number of strips set by the
    coordinate range of a (badly) transformed frame.
    """
    nq = queries.shape[0]
    i1 = np.full(nq, -1, np.int64)
    i2 = np.full(nq, -1, np.int64)
    d1 = np.full(nq, np.inf, np.float32)
    d2 = np.full(nq, np.inf, np.float32)
    i3 = np.full(nq, -1, np.int64)
    d3 = np.full(nq, np.inf, np.float32)
    ncand = np.zeros(nq, np.int64)
    nvisit = np.zeros(nq, np.int64)
    w = cols.width
    gx0 = cols.u0
    gx1 = gx0 + cols.nstrips * w
    wr = rows.width
    gy0 = rows.u0
    gy1 = gy0 + rows.nstrips * wr
    eps = 1e-7
    c_off, c_items, c_ps, c_k0, c_nk, c_h = cols.offsets, cols.items, cols.pts_sorted, cols.k0, cols.ncells, cols.cell
    r_off, r_items, r_ps, r_k0, r_nk, r_h = rows.offsets, rows.items, rows.pts_sorted, rows.k0, rows.ncells, rows.cell
    ns_c = cols.nstrips
    ns_r = rows.nstrips
    buf = np.empty(max(c_items.shape[0], r_items.shape[0]), np.int64)  # positions of one strip's candidates
    c_ih = 1.0 / c_h if c_h > 0 else 0.0
    r_ih = 1.0 / r_h if r_h > 0 else 0.0
    for q in range(nq):
        qi = queries[q]
        lo = xlo[q]
        hi = xhi[q]
        a = lines[q, 0]
        b = lines[q, 1]
        c = lines[q, 2]
        b1 = np.float32(np.inf)
        b2 = np.float32(np.inf)
        b3 = np.float32(np.inf)
        j1 = -1
        j2 = -1
        j3 = -1
        cnt = 0
        vis = 0
        xa = max(lo, gx0)
        xb = min(hi, gx1)
        if xa > xb or c_items.shape[0] == 0 or (use_band and a == 0.0 and b == 0.0):
            continue  # empty x-range, no image-2 points, or undefined epipolar line (query at the epipole)
        if not use_band or abs(b) >= abs(a):
            # vertical strips sorted by y; the band's y-extent over the strip's x-interval bounds the scan
            m = band / abs(b) if use_band else 0.0
            if use_band and abs(a) > 1e-300:
                # x where the band meets the points' y-extent [ky0, ky1]: a x + c in [-b y - band, -b y + band]
                ky0 = c_k0
                ky1 = ky0 + c_nk * c_h
                e1 = -b * ky0
                e2 = -b * ky1
                t1 = (min(e1, e2) - band - c) / a
                t2 = (max(e1, e2) + band - c) / a
                pad = eps * (1.0 + abs(t1) + abs(t2))
                xa = max(xa, min(t1, t2) - pad)
                xb = min(xb, max(t1, t2) + pad)
                if xa > xb:
                    continue
            nib = -1.0 / b if use_band else 0.0   # |b| >= 1/sqrt(2) here: y = -(a u + c) / b as a product
            s_lo = int((xa - gx0) // w)
            s_hi = min(int((xb - gx0) // w), ns_c - 1)
            s = fcols[s_lo]
            while s <= s_hi:
                vis += 1
                if use_band:
                    u0 = max(gx0 + s * w, xa)
                    u1 = min(gx0 + (s + 1) * w, xb)
                    ya = (a * u0 + c) * nib
                    yb = (a * u1 + c) * nib
                    kmin = min(ya, yb) - m
                    kmax = max(ya, yb) + m
                    kmin -= eps * (1.0 + abs(kmin))
                    kmax += eps * (1.0 + abs(kmax))
                else:
                    kmin = -np.inf
                    kmax = np.inf
                # the points of strip s in the cells overlapping [kmin, kmax]; a candidate must satisfy exactly the
                # region predicate lo <= x <= hi and |a x + b y + c| <= band ([kmin, kmax] only limits the scan)
                c0, c1 = _cells(c_k0, c_nk, c_h, c_ih, kmin, kmax)
                # two passes: the scanned points that satisfy the predicate, written branch-free into buf, then
                # their distances in the same order (a branch per scanned point instead: fox's final passes 0.89 s
                # vs 0.68 s, tools/kernel_probe.py)
                nb = 0
                for p in range(c_off[s * c_nk + c0], c_off[s * c_nk + c1 + 1] if c0 <= c1 else 0):
                    x = c_ps[p, 0]
                    buf[nb] = p
                    nb += np.int64((x >= lo) & (x <= hi) & ((not use_band) | (abs(a * x + b * c_ps[p, 1] + c) <= band)))
                for t in range(nb):
                    j = c_items[buf[t]]
                    b1, j1, b2, j2, b3, j3 = _push3(desc_dist(desc1, qi, desc2, j), j, b1, j1, b2, j2, b3, j3)
                cnt += nb
                s = fcols[s + 1]
        else:
            # horizontal strips sorted by x; rows limited to where the band can meet x in [lo, hi]
            m = band / abs(a)
            ry0 = gy0
            ry1 = gy1
            # rows where the band can meet x in [lo, hi] clipped to the points' x-extent [kx0, kx1]
            xl = max(lo, r_k0)
            xr = min(hi, r_k0 + r_nk * r_h)
            if xl > xr:
                continue
            if abs(b) > 1e-12:
                t1 = (-a * xl - c - band) / b
                t2 = (-a * xl - c + band) / b
                t3 = (-a * xr - c - band) / b
                t4 = (-a * xr - c + band) / b
                ry0 = max(gy0, min(min(t1, t2), min(t3, t4)) - eps * (1.0 + abs(gy0) + abs(gy1)))
                ry1 = min(gy1, max(max(t1, t2), max(t3, t4)) + eps * (1.0 + abs(gy0) + abs(gy1)))
            if ry0 > ry1:
                continue
            nia = -1.0 / a   # |a| > 1/sqrt(2) here: x = -(b v + c) / a as a product
            r_lo = max(0, int((ry0 - gy0) // wr))
            r_hi = min(ns_r - 1, int((ry1 - gy0) // wr))
            r = frows[r_lo]
            while r <= r_hi:
                vis += 1
                v0 = gy0 + r * wr
                v1 = v0 + wr
                xa2 = (b * v0 + c) * nia
                xb2 = (b * v1 + c) * nia
                kmin = max(min(xa2, xb2) - m, lo)
                kmax = min(max(xa2, xb2) + m, hi)
                kmin -= eps * (1.0 + abs(kmin))
                kmax += eps * (1.0 + abs(kmax))
                if kmin <= kmax:
                    c0, c1 = _cells(r_k0, r_nk, r_h, r_ih, kmin, kmax)  # as for the column strips above
                    nb = 0
                    for p in range(r_off[r * r_nk + c0], r_off[r * r_nk + c1 + 1] if c0 <= c1 else 0):
                        x = r_ps[p, 0]
                        buf[nb] = p
                        nb += np.int64((x >= lo) & (x <= hi)
                                       & ((not use_band) | (abs(a * x + b * r_ps[p, 1] + c) <= band)))
                    for t in range(nb):
                        j = r_items[buf[t]]
                        b1, j1, b2, j2, b3, j3 = _push3(desc_dist(desc1, qi, desc2, j), j, b1, j1, b2, j2, b3, j3)
                    cnt += nb
                r = frows[r + 1]
        i1[q] = j1
        i2[q] = j2
        d1[q] = b1
        d2[q] = b2
        i3[q] = j3
        d3[q] = b3
        ncand[q] = cnt
        nvisit[q] = vis
    return i1, d1, i2, d2, ncand, nvisit, i3, d3


def _renamed(fn, name):
    import types as _pytypes

    code = fn.__code__.replace(co_name=name, co_qualname=name)
    return _pytypes.FunctionType(code, fn.__globals__, name, fn.__defaults__, fn.__closure__)


_FASTMATH = {"contract", "reassoc", "arcp", "nsz"}
# Every kernel below is compiled single-threaded (``parallel=False``) and releases the GIL (``nogil=True``); large
# inputs run as one contiguous chunk per Numba thread in Python threads (:mod:`guidedmatch.kernel_threads`).
#: fused GEMM post-processing + the k smallest of a block of rows (the k nearest centroids of the IVF coarse step,
#: the k nearest candidates of brute force: :func:`topk_gemm`, :func:`topk_block` run it on row chunks in threads)
topk_gemm_serial = njit(parallel=False, cache=True, nogil=True)(_renamed(_topk_gemm_py, "topk_gemm_serial"))
# The guided kernel is compiled without fast-math for every descriptor kind: its band test |a x + b y + c| <= band is
# evaluated with plain IEEE rounding, bit for bit as NumPy does, on every CPU (fast-math would let LLVM contract it
# into FMAs as it sees fit and move points lying exactly on the band edge). The float L2 sum carries its own fast-math
# flags (_l2sq, vectorized): its distances are approximate, and the matcher recomputes the best three exactly.
_guided_ser = njit(parallel=False, cache=True, nogil=True)(_renamed(_guided_py, "guided_top2_serial"))
#: fewer queries run in the calling thread: for small batches (the progressive phase's 64 queries between BLAS
#: calls) waking threads costs more than it saves on 2 cores
PARALLEL_MIN_QUERIES = 2048


def topk_block(dot, nn2, qn, k):
    """:func:`topk_gemm_serial` of a GEMM block ``dot (R, C)`` on one chunk of rows per thread (blocks of >= 256
    rows): ``(idx (R, k), dist (R, k))``, the ``k`` smallest approximate squared distances of each row, ascending."""
    return _chunked_rows(lambda a, b: topk_gemm_serial(dot[a:b], nn2, qn[a:b], int(k)), dot.shape[0], 256)


def topk_gemm(q, centroids, cn, k, threads: int | None = None):
    """``(idx (Q, k), dist (Q, k))``: the ``k`` nearest ``centroids (C, D)`` (squared norms ``cn``) of each float32
    row of ``q``, nearest first (:func:`topk_gemm_serial`); one chunk of rows per thread (``threads``, default
    :func:`num_threads`), each chunk a GEMM (BLAS) and a pass of the kernel per block of ``_TOPK_BLOCK`` rows."""
    q = np.ascontiguousarray(q, np.float32)
    qn = np.einsum("ij,ij->i", q, q)
    ct = np.ascontiguousarray(np.asarray(centroids, np.float32).T)
    cn = np.ascontiguousarray(cn, np.float32)

    def chunk(a, b):
        return _join_rows([topk_gemm_serial(q[s:min(s + _TOPK_BLOCK, b)] @ ct, cn, qn[s:min(s + _TOPK_BLOCK, b)],
                                            int(k)) for s in range(a, b, _TOPK_BLOCK)]
                          or [topk_gemm_serial(q[a:b] @ ct, cn, qn[a:b], int(k))])

    return _chunked_rows(chunk, len(q), 256, threads)


# rows per GEMM block of topk_gemm: its (rows, nlist) float32 distances stay in a core's L2 (1024 x 637 = 2.6 MB);
# 68k queries vs 637 centroids, one thread: 0.15 s in blocks of 512-2048 rows, 0.18-0.22 s as one block
_TOPK_BLOCK = 1024


def guided_top2(queries, desc1, desc2, lines, use_band, band, xlo, xhi, cols, rows, *, return_visits: bool = False,
                return_third: bool = False):
    queries = np.ascontiguousarray(queries, np.int64)
    lines = np.ascontiguousarray(lines, np.float64).reshape(-1, 3)
    xlo = np.ascontiguousarray(xlo, np.float64)
    xhi = np.ascontiguousarray(xhi, np.float64)
    if len(lines) != len(queries) or len(xlo) != len(queries) or len(xhi) != len(queries):
        raise ValueError("queries, lines, xlo and xhi must have the same length")
    if use_band and len(cols.items) and not len(rows.items):
        if np.any(np.abs(lines[:, 0]) > np.abs(lines[:, 1])):
            raise ValueError("near-vertical epipolar lines need the row strips (build_strips(pts, width, axis=1))")
    kernel = _guided_ser
    use_band, band = bool(use_band), float(band)
    fc, fr = first_nonempty(cols), first_nonempty(rows)
    out = _chunked_rows(lambda a, b: kernel(queries[a:b], desc1, desc2, lines[a:b], use_band, band, xlo[a:b],
                                            xhi[a:b], cols, rows, fc, fr), len(queries), PARALLEL_MIN_QUERIES)
    res = tuple(out[:6]) if return_visits else tuple(out[:5])
    return res + tuple(out[6:]) if return_third else res


def hamming_top2(q, t):
    """Brute-force Hamming top-2 of every query word row ``q (N1, W) uint64`` among ``t (N2, W)``: ``(i1, d1, i2,
    d2)``, distances in bits as float32 (not squared); one chunk of query rows per thread."""
    return _chunked_rows(lambda a, b: _hamming_top2(q[a:b], t), q.shape[0], 256)


def hamming_col_best(q, t):
    """For every target row of ``t``: index of and Hamming distance (bits, float32) to its nearest query row
    (mutual check); one chunk of target rows per thread."""
    return _chunked_rows(lambda a, b: _hamming_col_best(q, t[a:b]), t.shape[0], 256)


guided_top2.__doc__ = (_guided_py.__doc__ or "") + """
    ``guided_top2(..., return_visits=True)`` also returns ``nvisit``; without it the first five arrays.
    ``return_third=True`` appends ``(i3, d3)``, the third-best candidate (for the exact recompute of float
    descriptors, :mod:`guidedmatch.exact`)."""
