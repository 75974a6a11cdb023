"""Numba kernels for descriptor distances: top-2 search over dense blocks, Hamming brute force,
and the guided candidate kernel of the progressive matcher.

All kernels return, per query, the best and second-best candidate (index and distance) and count the
exact number of descriptor distances they evaluated (the paper's "# matches" column, Teng & Dong §IV-A).
Distances are L2 (Euclidean, not squared) for float descriptors and Hamming bit counts for binary ones.
Index ``-1`` and distance ``+inf`` mean "no such candidate".
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

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


@njit(inline="always", cache=True)
def _l2sq(a, b):
    s = np.float32(0.0)
    for k in range(a.shape[0]):
        d = a[k] - b[k]
        s += d * d
    return s


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
            v = row[j]
            if v < b2:
                if v < b1:
                    b2 = b1
                    j2 = j1
                    b1 = v
                    j1 = j
                else:
                    b2 = v
                    j2 = j
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
            v = _hamming(q[i], t[j])
            if v < b2:
                if v < b1:
                    b2 = b1
                    j2 = j1
                    b1 = v
                    j1 = j
                else:
                    b2 = v
                    j2 = j
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
