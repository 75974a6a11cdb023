"""The strip index of the guided matcher: image-2 points bucketed in strips cut into cells, which the guided
candidate kernel (:func:`guidedmatch.kernels.guided_top2`) walks along each query's epipolar band.

* :class:`StripIndex` -- the index (a NamedTuple, so Numba kernels take it as an argument);
* :func:`build_strips` -- builds it (one ``nogil`` Numba pass, :func:`_strip_layout`);
* :func:`counting_order` -- the stable counting sort behind it (the matcher's start and the collection workers use it
  too);
* :func:`first_nonempty` -- the strip-skipping table the candidate kernel jumps over empty strips with;
* :func:`sorted_join` -- a merge of two sorted key arrays (the second look's chained correspondences use it).

The Numba code here calls no kernel of another module: Numba's on-disk cache (``cache=True``) checks only the
defining file of a cached function, so a kernel that calls or inlines another one must live in the same file
(the distance primitives and the kernels using them stay together in :mod:`guidedmatch.kernels`).
Every name is also importable from :mod:`guidedmatch.kernels`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["StripIndex", "build_strips", "counting_order", "first_nonempty"]


class StripIndex(NamedTuple):
    """Points indexed in strips cut into cells (:func:`build_strips`); a NamedTuple so the Numba kernels take it.

    Strip ``s``, cell ``k`` (strip coordinate ``u`` in ``[u0 + s*width, u0 + (s+1)*width)``, other coordinate in
    ``[k0 + k*cell, k0 + (k+1)*cell)``) holds rows ``offsets[s*ncells + k] : offsets[s*ncells + k + 1]`` of
    ``pts_sorted``, which are the input points ``items[...]``.
    """

    u0: float                # strip origin along the strip axis, px
    nstrips: int             # number of strips
    width: float             # strip width, px
    k0: float                # cell origin along the other axis, px
    ncells: int              # cells per strip
    cell: float              # cell height, px
    offsets: np.ndarray      # (nstrips * ncells + 1,) int64 CSR offsets into items / pts_sorted
    items: np.ndarray        # (N,) int64 input index of each sorted point
    pts_sorted: np.ndarray   # (N, 2) float64 the points, strip by strip, cell by cell


def build_strips(pts: np.ndarray, width: float, axis: int = 0, cell: float | None = None):
    """Index points ``(N, 2)`` in strips of ``width`` px along ``axis``, bucketed in cells along the other axis.

    ``axis=0``: vertical strips (x intervals) cut into cells of ``cell`` px in y -- for near-horizontal epipolar
    lines; ``axis=1``: horizontal strips (y intervals) cut along x -- for near-vertical lines. Points are stored
    strip by strip, cell by cell, so the points of any run of cells of one strip are contiguous: a band query
    visits each strip it crosses once, looks up the cells spanned by the band's extent over the strip (two table
    reads, no search) and scans them, i.e. a superset of the band by about ``1 + (|slope| * width + cell) / band``.

    ``cell`` defaults to ``width / 6``. Both sizes are enlarged when needed so the offset table has at most
    ``4 N + 4096`` cells (aligned coordinates can spread far out).

    Returns a :class:`StripIndex`. ``build_strips(pts, w, axis=1, cell=w).items`` is also a row-major cell order
    of the points (the matcher processes queries in it).
    """
    pts = np.ascontiguousarray(np.asarray(pts, np.float64).reshape(-1, 2))
    width = float(width)
    cell = float(cell) if cell else width / 6.0
    if len(pts) == 0:
        return StripIndex(0.0, 1, width, 0.0, 1, cell, np.zeros(2, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    # one nogil kernel (it runs once per model update of every pair: in a collection's pair threads the NumPy
    # version's dozen array passes held the GIL, ~1.7 ms of 43 ms a pair at 11k points)
    u0, ns, width, k0, nk, cell, offsets, items, ps = _strip_layout(pts, int(axis), width, cell)
    return StripIndex(u0, ns, width, k0, nk, cell, offsets, items, ps)

@njit(cache=True, nogil=True)
def _strip_layout(pts, axis, width, cell):
    """:func:`build_strips` of ``n >= 1`` points: the table sizes (strips * cells <= ``4 n + 4096``), each point's
    strip and cell (floor divisions, clipped to the last strip / cell), the stable counting sort by cell."""
    n = pts.shape[0]
    other = 1 - axis
    umin = umax = pts[0, axis]
    vmin = vmax = pts[0, other]
    for i in range(1, n):
        u = pts[i, axis]
        v = pts[i, other]
        umin = min(umin, u)
        umax = max(umax, u)
        vmin = min(vmin, v)
        vmax = max(vmax, v)
    su = umax - umin
    sv = vmax - vmin
    budget = 4 * n + 4096  # strips * cells <= budget
    width = max(width, su / (budget // 4) * (1.0 + 1e-12))  # ns <= budget / 4 + 1, so budget // ns >= 3
    ns = int(su // width) + 1
    kmax = budget // ns
    cell = max(cell, sv / (kmax - 1) * (1.0 + 1e-12))  # nk <= kmax
    nk = int(sv // cell) + 1
    key = np.empty(n, np.int64)
    for i in range(n):
        sid = min(int((pts[i, axis] - umin) // width), ns - 1)
        kid = min(int((pts[i, other] - vmin) // cell), nk - 1)
        key[i] = sid * nk + kid
    items, offsets = counting_order(key, ns * nk)
    ps = np.empty((n, 2), np.float64)
    for r in range(n):
        ps[r, 0] = pts[items[r], 0]
        ps[r, 1] = pts[items[r], 1]
    return umin, ns, width, vmin, nk, cell, offsets, items, ps


@njit(cache=True, nogil=True)
def counting_order(key, nbins):
    """Stable counting sort of ``key (N,)`` ints in ``[0, nbins)``: ``(order (N,), offsets (nbins+1,))``.

    ``order`` lists indices by key, ties in index order; bin ``b`` is ``order[offsets[b]:offsets[b+1]]``. O(N + nbins).
    """
    n = key.shape[0]
    offsets = np.zeros(nbins + 1, np.int64)
    for i in range(n):
        offsets[key[i] + 1] += 1
    for b in range(nbins):
        offsets[b + 1] += offsets[b]
    pos = offsets[:nbins].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[pos[key[i]]] = i
        pos[key[i]] += 1
    return order, offsets


@njit(cache=True, nogil=True)
def sorted_join(a, b):
    """For ascending int64 keys ``a (N,)`` and ``b (M,)``: ``(lo, cnt)``, the first position of ``a[i]`` in ``b`` and
    how many times it occurs there (0: absent; ``lo`` is then where it would go) -- ``searchsorted`` left and right
    of every ``a[i]`` as one two-pointer merge, O(N + M).

    >>> [x.tolist() for x in sorted_join(np.array([1, 3, 3, 7]), np.array([0, 3, 3, 5, 7]))]
    [[1, 1, 1, 4], [0, 2, 2, 1]]
    """
    n, m = a.shape[0], b.shape[0]
    lo = np.empty(n, np.int64)
    cnt = np.zeros(n, np.int64)
    p = 0
    for i in range(n):
        x = a[i]
        while p < m and b[p] < x:
            p += 1
        lo[i] = p
        q = p
        while q < m and b[q] == x:
            q += 1
        cnt[i] = q - p
    return lo, cnt


def first_nonempty(S):
    """``first[s]`` = the first strip ``>= s`` of strip index ``S`` (:func:`build_strips`) holding a point
    (``ns`` when none): ``(ns + 1,) int64``. The candidate kernel jumps over empty strips with it, so its walk
    costs at most one step per occupied strip, however far a transformed frame spreads the points.
    (NumPy, O(ns): a reversed running minimum -- one Numba kernel less to compile on a first run.)"""
    ns, nk = int(S.nstrips), int(S.ncells)
    starts = S.offsets[0: ns * nk + 1: nk]  # offsets[s * nk] for s = 0 .. ns
    idx = np.where(starts[1:] > starts[:-1], np.arange(ns, dtype=np.int64), ns)
    first = np.empty(ns + 1, np.int64)
    first[ns] = ns
    first[:ns] = np.minimum.accumulate(idx[::-1])[::-1]
    return first
