"""Exact brute-force matching (the paper's BF baseline, Teng & Dong §IV).

Every image-1 descriptor is compared with every image-2 descriptor: exactly ``N1 * N2`` distance
evaluations, reported in ``stats.comparisons``.

* Float descriptors: the ``K`` (:data:`guidedmatch.exact.K`) nearest by the squared L2 distance through blocked
  GEMM, ``||a||^2 + ||b||^2 - 2 a.b`` clamped at 0, in float32 (:func:`~guidedmatch.kernels.topk_block`), then
  their distances recomputed exactly in a fixed order and the top 2 taken on those, the candidate set certified
  against the GEMM's error bound (:mod:`guidedmatch.exact`): neighbours and distances are the same on every CPU,
  BLAS and thread count. :func:`knn2` and the match result report L2 (Euclidean, **not** squared), the float32
  square root of the exact float64 squared distance.
  Query rows are processed in blocks sized so the block's distance matrix stays under
  ``memory_budget_mb`` (default 256 MB; at 150k x 150k that is 447 query rows per block).
* Binary descriptors: Hamming distance (bits, as float32) by 64-bit popcount in a Numba kernel (no extra memory).

Ratio test (Lowe), on these L2 (not squared) or Hamming distances: a match ``(i, j1)`` is kept when
``d1 < ratio * d2`` (strict), where ``d2`` is the distance to the second-nearest neighbour; with a single
image-2 descriptor ``d2 = inf`` and the test passes. Ties (``d1 == d2``) therefore fail the ratio test.
Among equal distances the lowest image-2 index is the nearest neighbour.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import exact, kernels
from .errors import InputError
from .results import MatchResult, MatchStats, empty_pairs

DEFAULT_MEMORY_BUDGET_MB = 256.0


def check_descriptors(d1: np.ndarray, d2: np.ndarray, *, known_finite: bool = False) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validate two descriptor arrays; returns them contiguous plus ``binary`` (uint8 = Hamming).

    Raises :class:`~guidedmatch.errors.InputError` on dimension or dtype mismatch, wrong rank, or NaN/inf.
    ``known_finite``: the caller has already established that every value is finite (prepared images: their squared
    norms are finite), so the NaN/inf scan is skipped.
    """
    d1 = np.asarray(d1)
    d2 = np.asarray(d2)
    if d1.ndim != 2 or d2.ndim != 2:
        raise InputError(f"descriptors must be 2-D (N, D); got shapes {d1.shape} and {d2.shape}")
    if d1.shape[1] != d2.shape[1]:
        raise InputError(f"descriptor lengths differ: {d1.shape[1]} (image 1) vs {d2.shape[1]} (image 2)")
    b1, b2 = d1.dtype == np.uint8, d2.dtype == np.uint8
    if b1 != b2:
        raise InputError(f"descriptor types differ: {d1.dtype} (image 1) vs {d2.dtype} (image 2); "
                         "binary (uint8) and float descriptors cannot be matched with each other")
    if not b1:
        d1 = np.ascontiguousarray(d1, dtype=np.float32)
        d2 = np.ascontiguousarray(d2, dtype=np.float32)
        if not known_finite and not (np.all(np.isfinite(d1)) and np.all(np.isfinite(d2))):
            raise InputError("descriptors contain NaN/inf")
    return np.ascontiguousarray(d1), np.ascontiguousarray(d2), b1


def block_rows(n2: int, memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB) -> int:
    """Query rows per GEMM block so one ``(rows, n2) float32`` block stays under the budget."""
    return int(max(1, min(1 << 16, (memory_budget_mb * 2**20) // (4 * max(n2, 1)))))


def knn2(d1: np.ndarray, d2: np.ndarray, *, memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
         want_column_best: bool = False, d2_sqnorms: np.ndarray | None = None, checked: bool = False):
    """Exact 2-NN of each ``d1`` row among ``d2`` rows.

    Returns ``(i1, dist1, i2, dist2)`` arrays of length N1 (index -1 / distance inf when missing) and,
    when ``want_column_best``, ``(col_i, col_d)``: for each ``d2`` row its nearest ``d1`` row (for float descriptors
    the same exact search the other way round). Distances are ``float32`` L2 (square root of the exact squared
    distance, :mod:`guidedmatch.exact`) for float descriptors, Hamming bits for binary ones; equal distances: the
    lower index first.
    ``d2_sqnorms`` (float descriptors: ``(N2,)`` squared norms of ``d2``) and ``checked=True`` (inputs already
    validated by :func:`check_descriptors`) let a caller that queries the same ``d2`` repeatedly skip that work.
    """
    if checked:
        binary = d1.dtype == np.uint8
    else:
        d1, d2, binary = check_descriptors(d1, d2)
    if binary:
        q, t = kernels.pack_bits_u64(d1), kernels.pack_bits_u64(d2)
        out = kernels.hamming_top2(q, t)
        col = kernels.hamming_col_best(q, t) if want_column_best else None
        return out, col
    i1, s1, i2, s2 = _knn2_exact_sq(d1, d2, memory_budget_mb, d2_sqnorms)
    out = (i1, exact.l2(s1), i2, exact.l2(s2))
    col = None
    if want_column_best:
        (ci, cd, _, _), _ = knn2(d2, d1, memory_budget_mb=memory_budget_mb, checked=True)
        col = (ci, cd)
    return out, col


def _knn2_exact_sq(d1: np.ndarray, d2: np.ndarray, memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB,
                   d2_sqnorms: np.ndarray | None = None):
    """Float descriptors: exact 2-NN ``(i1, s1, i2, s2)`` of each ``d1`` row among ``d2`` rows, **squared** float64
    distances: the :data:`~guidedmatch.exact.K` nearest of blocked float32 GEMMs, recomputed exactly and certified
    (:func:`guidedmatch.exact.exact_top`)."""
    n1, n2 = len(d1), len(d2)
    i1 = np.full(n1, -1, np.int64)
    i2 = np.full(n1, -1, np.int64)
    s1 = np.full(n1, np.inf, np.float64)
    s2 = np.full(n1, np.inf, np.float64)
    if n1 and n2:
        nn2 = np.einsum("ij,ij->i", d2, d2) if d2_sqnorms is None else d2_sqnorms
        tn_max = float(np.max(nn2))
        rows = block_rows(n2, memory_budget_mb)
        buf = np.empty((min(rows, n1), n2), np.float32)
        k = min(exact.K, n2)
        for a in range(0, n1, rows):
            b = min(n1, a + rows)
            blk = buf[: b - a]
            q = d1[a:b]
            np.matmul(q, d2.T, out=blk)
            qn = np.einsum("ij,ij->i", q, q)
            # the K nearest by max(-2 q.t + |t|^2 + |q|^2, 0) in float32 (one pass), then exact and certified
            cand, approx = kernels.topk_block(blk, nn2, qn, k)
            idx, sq = exact.exact_top(q, d2, cand, approx, 2, delta=exact.gemm_delta(qn, tn_max, d1.shape[1]))
            i1[a:b], s1[a:b], i2[a:b], s2[a:b] = idx[:, 0], sq[:, 0], idx[:, 1], sq[:, 1]
    return i1, s1, i2, s2


_CONTROLLER: list = [None, -1]  # [ThreadpoolController, len(sys.modules) when it was built]


def _blas_controller(load_scipy: bool = True):
    """A ``threadpoolctl.ThreadpoolController`` of the BLAS libraries loaded now (inspecting them takes ~2 ms).

    Rebuilt only when modules were imported since the last call (a new extension module -- faiss, another SciPy
    -- may bring its own BLAS, which a stale controller would leave multi-threaded). With ``load_scipy`` SciPy's
    BLAS is loaded first (Numba's linear algebra and our geometry use it), so it is limited as well; without, only
    what is loaded now (NumPy's BLAS, for NumPy GEMMs: importing ``scipy.linalg`` costs 0.13 s, which a collection
    run otherwise never pays).
    """
    import importlib
    import sys

    if load_scipy:
        importlib.import_module("scipy.linalg")  # loads SciPy's OpenBLAS before the libraries are listed
    if _CONTROLLER[0] is None or _CONTROLLER[1] != len(sys.modules):
        from threadpoolctl import ThreadpoolController

        _CONTROLLER[0] = ThreadpoolController()
        _CONTROLLER[1] = len(sys.modules)
    return _CONTROLLER[0]


def blas_one_thread(load_scipy: bool = True):
    """Limit the BLAS libraries loaded now (and SciPy's, with ``load_scipy``: :func:`_blas_controller`) to one thread;
    a ``threadpoolctl`` limiter: a context manager, or ``restore_original_limits()`` to undo it."""
    return _blas_controller(load_scipy).limit(limits=1, user_api="blas")


class DenseKnn2:
    """Exact 2-NN of successive small query batches against one fixed float descriptor set (``(N2, D)``).

    For the progressive matcher's unguided phase (a few batches of 64 queries). The image-2 columns are split
    into one chunk per Numba thread; each chunk's GEMM (BLAS limited to one thread) and fused top-2 run in
    their own Python thread and the chunk results are merged exactly (ties keep the lower index). Why not one
    multi-threaded GEMM: OpenBLAS's worker threads keep spinning for tens of milliseconds after every call and
    then slow the next Numba parallel kernel by up to 2x (measured on 2 cores: guided final pass 23 -> 45 ms);
    single-threaded BLAS calls leave no spinning workers behind.

    Use as a context manager: while it is open, BLAS libraries loaded by the process are limited to one thread
    (``threadpoolctl``; process-wide, restored on exit). ``query(q)`` returns ``(i1, s1, i2, s2)`` with exact
    squared L2 distances (float64): each chunk hands over its :data:`~guidedmatch.exact.K` nearest by its GEMM, the
    best K of all chunks are recomputed exactly and certified (:func:`guidedmatch.exact.exact_top`; a candidate left
    out by a chunk is no nearer than that chunk's K-th, hence than the merged K-th), so the result is :func:`knn2`'s,
    bit for bit, whatever the number of chunks (threads) or the BLAS.
    """

    def __init__(self, d2: np.ndarray, d2_sqnorms: np.ndarray | None = None, threads: int | None = None,
                 byte_exact: bool = False):
        self.d2 = np.ascontiguousarray(d2, np.float32)
        n2 = len(self.d2)
        nn2 = np.einsum("ij,ij->i", self.d2, self.d2) if d2_sqnorms is None else np.asarray(d2_sqnorms, np.float32)
        k = max(1, min(int(threads or kernels.num_threads()), max(1, n2 // 1024)))
        cuts = np.linspace(0, n2, k + 1).astype(np.int64)
        self.chunks = [(self.d2[a:b], nn2[a:b], int(a)) for a, b in zip(cuts[:-1], cuts[1:])]
        self.tn_max = float(np.max(nn2)) if n2 else 0.0
        self.byte_exact = bool(byte_exact)  # d2 holds integers 0..255 (query(..., byte_exact=True) may skip work)
        self._pool = None
        self._limit = None

    def __enter__(self) -> "DenseKnn2":
        self._limit = blas_one_thread()
        if len(self.chunks) > 1:
            self._pool = ThreadPoolExecutor(len(self.chunks), thread_name_prefix="guidedmatch-knn2")
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._limit is not None:
            self._limit.restore_original_limits()
            self._limit = None

    @staticmethod
    def _chunk(q, qn, chunk):
        t, tn, off = chunk
        idx, dist = kernels.topk_gemm_serial(q @ t.T, tn, qn, min(exact.K, len(t)))
        return np.where(idx >= 0, idx + off, -1), dist

    def query(self, q: np.ndarray, byte_exact: bool = False):
        """``byte_exact``: the queries hold integers 0..255 too; with byte-valued targets and squared norms below
        2^24 every GEMM distance is then an exact integer and the best K are only sorted, not recomputed."""
        q = np.ascontiguousarray(q, np.float32)
        nq = len(q)
        if nq == 0 or len(self.d2) == 0:
            e = np.full(nq, -1, np.int64), np.full(nq, np.inf, np.float64)
            return e[0], e[1], e[0].copy(), e[1].copy()
        qn = np.einsum("ij,ij->i", q, q)
        if self._pool is None:
            parts = [self._chunk(q, qn, c) for c in self.chunks]
        else:
            parts = list(self._pool.map(lambda c: self._chunk(q, qn, c), self.chunks))
        idx = np.concatenate([p[0] for p in parts], axis=1)
        dist = np.concatenate([p[1] for p in parts], axis=1)
        if len(parts) > 1:  # the best K of all chunks' best K, by distance then index
            big = np.where(idx >= 0, idx, np.iinfo(np.int64).max)
            o = np.lexsort((big, dist), axis=-1)[:, :exact.K]
            r = np.arange(nq)[:, None]
            idx, dist = idx[r, o], dist[r, o]
        if byte_exact and self.byte_exact and float(qn.max()) + self.tn_max < exact.EXACT_INT:
            top, sq = exact.top_of_exact(idx, dist, 2)
        else:
            top, sq = exact.exact_top(q, self.d2, idx, dist, 2, delta=exact.gemm_delta(qn, self.tn_max, q.shape[1]))
        return top[:, 0], sq[:, 0], top[:, 1], sq[:, 1]


def select_matches(i1, dist1, dist2, *, ratio: float | None = 0.8, max_distance: float | None = None,
                   mutual_best: np.ndarray | None = None, query_index: np.ndarray | None = None):
    """Apply ratio / max-distance / mutual tests to 2-NN results; returns ``(pairs, distances, keep)``.

    ``query_index`` maps row k to the image-1 feature index (default ``arange``); ``mutual_best[j]``
    is the image-1 index nearest to image-2 feature ``j`` (for the mutual check).
    """
    i1 = np.asarray(i1)
    q = np.arange(len(i1)) if query_index is None else np.asarray(query_index)
    keep = i1 >= 0
    if ratio is not None:
        keep &= dist1 < np.float32(ratio) * dist2
    if max_distance is not None:
        keep &= dist1 <= max_distance
    if mutual_best is not None:
        ok = np.zeros_like(keep)
        ok[keep] = mutual_best[i1[keep]] == q[keep]
        keep = ok
    pairs = np.stack([q[keep], i1[keep]], axis=1).astype(np.int64) if keep.any() else empty_pairs()
    return pairs, np.asarray(dist1[keep], np.float32), keep


def match_bruteforce(d1, d2, *, ratio: float | None = 0.8, mutual: bool = False,
                     max_distance: float | None = None,
                     memory_budget_mb: float = DEFAULT_MEMORY_BUDGET_MB) -> MatchResult:
    """Brute-force match descriptor sets (or :class:`~guidedmatch.features.Features`).

    Args:
        d1: ``(N1, D)`` image-1 descriptors (float32 -> L2, uint8 packed bits -> Hamming), or Features.
        d2: ``(N2, D)`` image-2 descriptors of the same kind, or Features.
        ratio: Lowe ratio (keep when ``d1 < ratio * d2``); ``None`` disables it.
        mutual: also require image-1 feature to be the nearest neighbour of its match.
        max_distance: drop matches farther than this (L2, not squared, or Hamming bits).
        memory_budget_mb: bound on the temporary distance block for float descriptors.

    Returns:
        :class:`MatchResult`: ``stats`` a :class:`~guidedmatch.results.MatchStats` (``comparisons = N1*N2``,
        ``time_s``, ``method = "bf"``; ``details``: ``ratio``, ``mutual``, ``max_distance``, ``block_rows``);
        ``pairs`` is ``(0, 2)`` when nothing matches.

    >>> import numpy as np
    >>> d1 = np.array([[0, 0], [10, 0], [5, 0]], np.float32)    # the 3rd is equally far from two image-2 rows:
    >>> d2 = np.array([[0, 1], [10, 1], [5, 9]], np.float32)     # the ratio test drops it
    >>> r = match_bruteforce(d1, d2)
    >>> r.pairs.tolist(), r.distances.tolist(), r.stats.comparisons
    ([[0, 0], [1, 1]], [1.0, 1.0], 9)
    """
    d1 = getattr(d1, "descriptors", d1)
    d2 = getattr(d2, "descriptors", d2)
    t0 = time.perf_counter()
    d1c, d2c, binary = check_descriptors(d1, d2)
    n1, n2 = len(d1c), len(d2c)
    (i1, s1, _i2, s2), col = knn2(d1c, d2c, memory_budget_mb=memory_budget_mb, want_column_best=mutual,
                                  checked=True)
    pairs, dist, keep = select_matches(i1, s1, s2, ratio=ratio, max_distance=max_distance,
                                       mutual_best=col[0] if mutual else None)
    dropped_mutual = int(select_matches(i1, s1, s2, ratio=ratio, max_distance=max_distance)[2].sum() - keep.sum()) \
        if mutual else 0
    dt = time.perf_counter() - t0
    stats = MatchStats(method="bf", comparisons=int(n1) * int(n2), time_s=dt, num_features=(n1, n2),
                       metric="hamming" if binary else "l2", dropped_by_mutual=dropped_mutual,
                       details=dict(ratio=ratio, mutual=mutual, max_distance=max_distance,
                                    block_rows=None if binary else block_rows(n2, memory_budget_mb)))
    return MatchResult(pairs, dist, stats)
