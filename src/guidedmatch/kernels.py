"""Numba kernels for descriptor distances: top-2 search over dense blocks, Hamming brute force,
and the guided candidate kernel of the progressive matcher.

All kernels return, per query, the best and second-best candidate (index and distance) and count the
exact number of descriptor distances they evaluated (the paper's "# matches" column, Teng & Dong §IV-A).
Distances are L2 (Euclidean, not squared) for float descriptors and Hamming bit counts for binary ones.
Index ``-1`` and distance ``+inf`` mean "no such candidate".
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

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


@njit(inline="always", cache=True)
def _hamming(a, b):
    s = np.uint64(0)
    for k in range(a.shape[0]):
        s += _popcount64(a[k] ^ b[k])
    return np.float32(s)


@njit(inline="always", cache=True, fastmath=True)
def _l2sq(a, b):
    s = np.float32(0.0)
    for k in range(a.shape[0]):
        d = a[k] - b[k]
        s += d * d
    return s


@njit(inline="always", cache=True)
def _l2sq_u8(a, b):
    # exact squared L2 of byte-valued descriptors (e.g. SIFT, integers 0..255): int32 accumulation
    s = np.int32(0)
    for k in range(a.shape[0]):
        d = np.int32(a[k]) - np.int32(b[k])
        s += d * d
    return np.float32(s)


def as_exact_uint8(desc: np.ndarray) -> np.ndarray | None:
    """``desc`` as uint8 when every value is an integer in 0..255 (OpenCV SIFT), else None.

    Squared L2 of such descriptors is computed exactly in int32 on a quarter of the memory traffic.
    """
    if desc.dtype != np.float32 or desc.size == 0:
        return None
    u = desc.astype(np.uint8)
    return u if np.array_equal(u, desc) else None


def desc_dist(a, b):  # pragma: no cover - replaced by the Numba overload below inside jitted code
    """Descriptor distance: squared L2 for float or byte-valued rows, Hamming for uint64 word rows."""
    raise NotImplementedError


@overload(desc_dist)
def _desc_dist_overload(a, b):
    # resolved at compile time from the array dtype, so one cached kernel per descriptor kind
    if isinstance(a, types.Array) and isinstance(a.dtype, types.Float):
        return lambda a, b: _l2sq(a, b)
    if isinstance(a, types.Array) and a.dtype == types.uint64:
        return lambda a, b: _hamming(a, b)
    if isinstance(a, types.Array) and a.dtype == types.uint8:
        return lambda a, b: _l2sq_u8(a, b)
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


# --------------------------------------------------------------------------- dense top-2
@njit(parallel=True, cache=True)
def top2_rows(dist_sq):
    """Per row of a ``(R, C) float32`` squared-distance block: best/second index and squared distance.

    Ties keep the lowest column index as best (like ``np.argmin``).
    """
    r, c = dist_sq.shape
    i1 = np.full(r, -1, np.int64)
    i2 = np.full(r, -1, np.int64)
    d1 = np.full(r, np.inf, np.float32)
    d2 = np.full(r, np.inf, np.float32)
    for i in prange(r):
        b1 = np.float32(np.inf)
        b2 = np.float32(np.inf)
        j1 = -1
        j2 = -1
        row = dist_sq[i]
        for j in range(c):
            b1, j1, b2, j2 = _push(row[j], j, b1, j1, b2, j2)
        i1[i] = j1
        i2[i] = j2
        d1[i] = b1
        d2[i] = b2
    return i1, d1, i2, d2


@njit(parallel=True, cache=True)
def hamming_top2(q, t):
    """Brute-force Hamming top-2 of every query word row ``q (N1, W) uint64`` among ``t (N2, W)``."""
    n1 = q.shape[0]
    n2 = t.shape[0]
    i1 = np.full(n1, -1, np.int64)
    i2 = np.full(n1, -1, np.int64)
    d1 = np.full(n1, np.inf, np.float32)
    d2 = np.full(n1, np.inf, np.float32)
    for i in prange(n1):
        b1 = np.float32(np.inf)
        b2 = np.float32(np.inf)
        j1 = -1
        j2 = -1
        for j in range(n2):
            b1, j1, b2, j2 = _push(_hamming(q[i], t[j]), j, b1, j1, b2, j2)
        i1[i] = j1
        i2[i] = j2
        d1[i] = b1
        d2[i] = b2
    return i1, d1, i2, d2


@njit(parallel=True, cache=True)
def hamming_col_best(q, t):
    """For every target row of ``t``: index of and distance to its nearest query row (mutual check)."""
    n2 = t.shape[0]
    n1 = q.shape[0]
    best = np.full(n2, -1, np.int64)
    bd = np.full(n2, np.inf, np.float32)
    for j in prange(n2):
        b = np.float32(np.inf)
        k = -1
        for i in range(n1):
            v = _hamming(q[i], t[j])
            if v < b:
                b = v
                k = i
        best[j] = k
        bd[j] = b
    return best, bd


# --------------------------------------------------------------------------- guided candidates
def build_grid(pts: np.ndarray, cell: float):
    """Bucket points ``(N, 2)`` into square cells of side ``cell`` px (CSR layout).

    Returns ``(origin (2,), ncx, ncy, cell_start (ncx*ncy+1,) int64, cell_items (N,) int64)``; points of
    cell ``cy * ncx + cx`` are ``cell_items[cell_start[c]:cell_start[c+1]]`` (ascending index).
    """
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(2), 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int64)
    origin = pts.min(axis=0)
    span = pts.max(axis=0) - origin
    ncx = int(span[0] // cell) + 1
    ncy = int(span[1] // cell) + 1
    cx = np.minimum(((pts[:, 0] - origin[0]) // cell).astype(np.int64), ncx - 1)
    cy = np.minimum(((pts[:, 1] - origin[1]) // cell).astype(np.int64), ncy - 1)
    cid = cy * ncx + cx
    items = np.argsort(cid, kind="stable").astype(np.int64)
    start = np.zeros(ncx * ncy + 1, np.int64)
    np.cumsum(np.bincount(cid, minlength=ncx * ncy), out=start[1:])
    return origin, ncx, ncy, start, items


@njit(inline="always", cache=True)
def _scan_cell(c, qd, desc2, pts2, lines_q, use_band, band, lo, hi, start, items, b1, j1, b2, j2, cnt):
    # desc2 / pts2 are stored in cell order (row p belongs to feature items[p]) so a cell is contiguous in memory
    a = lines_q[0]
    b = lines_q[1]
    cc = lines_q[2]
    for p in range(start[c], start[c + 1]):
        x = pts2[p, 0]
        if x < lo or x > hi:
            continue
        if use_band and abs(a * x + b * pts2[p, 1] + cc) > band:
            continue
        j = items[p]
        d = desc_dist(qd, desc2[p])
        cnt += 1
        b1, j1, b2, j2 = _push(d, j, b1, j1, b2, j2)
    return b1, j1, b2, j2, cnt


def guided_top2(queries, desc1, desc2, pts2, lines, use_band, band, xlo, xhi,
                origin, cell, ncx, ncy, start, items):
    """Best two candidates of each query among image-2 features in its search region.

    ``desc2`` and ``pts2`` must be in cell order (``desc2[p]`` is feature ``items[p]``, see :func:`build_grid`);
    returned indices are original feature indices. The region of query ``q`` is ``{j : xlo[q] <= pts2[j,0] <= xhi[q]}`` (spatial-order x-range) and, when
    ``use_band``, ``|lines[q] . (pts2[j], 1)| <= band`` (epipolar band; lines normalized so a^2+b^2=1).
    All coordinates are the (aligned) image-2 coordinates the grid was built on. Only grid cells the
    region can touch are visited: columns when the line is closer to horizontal, rows otherwise.

    Returns ``(i1, d1, i2, d2, ncand)``; ``d`` are raw ``desc_dist`` values (squared L2 or Hamming) and
    ``ncand[q]`` is the exact number of descriptor distances evaluated for query ``q``.
    """
    nq = queries.shape[0]
    i1 = np.full(nq, -1, np.int64)
    i2 = np.full(nq, -1, np.int64)
    d1 = np.full(nq, np.inf, np.float32)
    d2 = np.full(nq, np.inf, np.float32)
    ncand = np.zeros(nq, np.int64)
    gx0 = origin[0]
    gy0 = origin[1]
    gx1 = gx0 + ncx * cell
    gy1 = gy0 + ncy * cell
    eps = 1e-9
    for q in prange(nq):
        qd = desc1[queries[q]]
        lo = xlo[q]
        hi = xhi[q]
        a = lines[q, 0]
        b = lines[q, 1]
        c = lines[q, 2]
        b1 = np.float32(np.inf)
        b2 = np.float32(np.inf)
        j1 = -1
        j2 = -1
        cnt = 0
        xa = max(lo, gx0)
        xb = min(hi, gx1)
        if xa > xb:
            continue
        cx_lo = int((xa - gx0) // cell)
        cx_hi = min(int((xb - gx0) // cell), ncx - 1)
        if not use_band:
            for cx in range(cx_lo, cx_hi + 1):
                for cy in range(ncy):
                    b1, j1, b2, j2, cnt = _scan_cell(cy * ncx + cx, qd, desc2, pts2, lines[q], False, band, lo, hi,
                                                     start, items, b1, j1, b2, j2, cnt)
        elif abs(b) >= abs(a):
            # mostly horizontal line: walk columns, rows limited to the band around the line
            m = band / abs(b) + eps
            for cx in range(cx_lo, cx_hi + 1):
                u0 = gx0 + cx * cell
                u1 = u0 + cell
                ya = -(a * u0 + c) / b
                yb = -(a * u1 + c) / b
                ymin = min(ya, yb) - m
                ymax = max(ya, yb) + m
                if ymax < gy0 or ymin > gy1:
                    continue
                cy_lo = max(0, int((ymin - gy0) // cell))
                cy_hi = min(ncy - 1, int((ymax - gy0) // cell))
                for cy in range(cy_lo, cy_hi + 1):
                    b1, j1, b2, j2, cnt = _scan_cell(cy * ncx + cx, qd, desc2, pts2, lines[q], True, band, lo, hi,
                                                     start, items, b1, j1, b2, j2, cnt)
        else:
            # mostly vertical line: walk rows, columns limited to the band and the x-range
            m = band / abs(a) + eps
            ry0 = gy0
            ry1 = gy1
            if abs(b) > 1e-12 and np.isfinite(lo) and np.isfinite(hi):
                # rows where the band can meet x in [lo, hi]
                t1 = (-a * lo - c - band) / b
                t2 = (-a * lo - c + band) / b
                t3 = (-a * hi - c - band) / b
                t4 = (-a * hi - c + band) / b
                ry0 = max(gy0, min(min(t1, t2), min(t3, t4)) - eps)
                ry1 = min(gy1, max(max(t1, t2), max(t3, t4)) + eps)
            if ry0 > ry1:
                continue
            cy_lo = max(0, int((ry0 - gy0) // cell))
            cy_hi = min(ncy - 1, int((ry1 - gy0) // cell))
            for cy in range(cy_lo, cy_hi + 1):
                v0 = gy0 + cy * cell
                v1 = v0 + cell
                xa2 = -(b * v0 + c) / a
                xb2 = -(b * v1 + c) / a
                xmin = max(min(xa2, xb2) - m, xa)
                xmax = min(max(xa2, xb2) + m, xb)
                if xmin > xmax:
                    continue
                c_lo = max(0, int((xmin - gx0) // cell))
                c_hi = min(ncx - 1, int((xmax - gx0) // cell))
                for cx in range(c_lo, c_hi + 1):
                    b1, j1, b2, j2, cnt = _scan_cell(cy * ncx + cx, qd, desc2, pts2, lines[q], True, band, lo, hi,
                                                     start, items, b1, j1, b2, j2, cnt)
        i1[q] = j1
        i2[q] = j2
        d1[q] = b1
        d2[q] = b2
        ncand[q] = cnt
    return i1, d1, i2, d2, ncand


def _renamed(fn, name):
    import types as _pytypes

    code = fn.__code__.replace(co_name=name, co_qualname=name)
    return _pytypes.FunctionType(code, fn.__globals__, name, fn.__defaults__, fn.__closure__)


_FASTMATH = {"contract", "reassoc", "arcp", "nsz"}
_guided_py = guided_top2
#: parallel over queries (final pass)
guided_top2 = njit(parallel=True, cache=True, fastmath=_FASTMATH)(_guided_py)
#: the same kernel single-threaded, for small batches: waking a thread pool per 64-query batch between BLAS
#: calls costs more than it saves on 2 cores (the BLAS and Numba pools contend)
guided_top2_serial = njit(parallel=False, cache=True, fastmath=_FASTMATH)(_renamed(_guided_py, "guided_top2_serial"))
