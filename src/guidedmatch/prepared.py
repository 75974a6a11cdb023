"""Per-image state reused across every pair an image takes part in (a cheap unguided start, above all on low-overlap
pairs).

Matching one image against many (an SfM collection) repeats per-image work on every pair: descriptor conversion to
the kernels' form (exact uint8 copies of byte-valued SIFT, packed 64-bit words of binary descriptors), squared norms
for the GEMM, and -- the expensive part -- an approximate index of the image for the unguided start of the matcher.
:func:`prepare` does it once; :func:`guidedmatch.matcher.match` accepts the :class:`PreparedImage` on either side
(or plain :class:`~guidedmatch.features.Features`, which it prepares itself) and returns the same matches either way.

The approximate index (float descriptors only) is a faiss ``IndexIVFFlat`` (exact L2 inside the probed lists; for
byte-valued descriptors such as OpenCV's or COLMAP's SIFT an ``IndexIVFScalarQuantizer`` with ``QT_8bit_direct`` codes
and no residual, which stores the same values in a quarter of the memory and gives the same exact distances):
``nlist = nlist_factor * sqrt(N)`` k-means cells trained on at most ``train_per_list * nlist`` descriptors with a fixed
seed, so it is deterministic; ``nprobe`` cells are searched per query. It is built lazily the first time the image is
the second image of a pair whose unguided phase uses it, then kept. Measured on Herz-Jesus-P8 (8192 SIFT per image,
2 cores, one run): IVF (2 sqrt N = 181 cells, nprobe 4) searches all 8192 queries of a
pair with 4.5-4.8 % of the N1*N2 distance evaluations (coarse + fine) in 0.06-0.15 s against 0.6-1.3 s for the
exact GEMM top-2 in 64-query batches (0.10-0.12 of it), its nearest neighbour agrees with the exact one on 98.8-100 %
of the ratio-test matches, and it builds in 0.09-0.19 s; HNSW (M = 32, efSearch 32) needs 0.54-1.16 of the GEMM
time and builds in 0.4-1.1 s, IVF with nprobe 8 (362 cells) 0.14-0.21. The coarse step of a search (which cells)
is NumPy's GEMM + our fused top-k (:func:`guidedmatch.kernels.topk_gemm`, the same cells as faiss's flat quantizer,
as fast as faiss on the CPU's own BLAS kernels and 3x faster where faiss's bundled OpenBLAS falls back to generic ones:
:func:`guidedmatch._runtime.pin_faiss_blas`); faiss then searches the chosen lists (``search_preassigned``). The
index build (k-means + adding every descriptor) is faiss's GEMMs: 0.19 s for 61.6k SIFT on the CPU's kernels, 0.86-1.1
s on the generic ones.

In a collection the images can share one coarse quantizer (``prepare(features, quantizer=q)``,
:mod:`guidedmatch.collection.quantizer`): no k-means per image, and a search looks up its queries' cells
(:meth:`PreparedImage.query_cells`, computed once per image) instead of computing them against image 2's centroids.

Pickling drops the index and the cells (rebuilt on first use in the receiving process); everything else is plain
arrays.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from . import exact, kernels
from .errors import InputError
from .features import Features
from .validation import check_choice, check_number

__all__ = ["PreparedConfig", "PreparedImage", "prepare", "as_prepared"]

#: an image uses a collection's shared quantizer when its own index would have at least this share of the shared
#: one's cells (nlist ~ sqrt(N): at least 0.64x the median number of features the quantizer was sized for)
SHARED_MIN_NLIST_SHARE = 0.8


@dataclass(frozen=True)
class PreparedConfig:
    """How :func:`prepare` indexes an image for the unguided phase."""

    index: str = "ivf"                # approximate index of float descriptors: "ivf" (faiss IVF; 8-bit codes when byte-valued) or "none"
    nlist_factor: float = 2.0         # IVF cells = nlist_factor * sqrt(N) (COLMAP: 4; 2 as fast, same verdicts)
    nprobe: int = 4                   # IVF cells searched per query
    train_per_list: int = 20          # k-means trained on at most this many descriptors per cell (40: builds 1.6x
                                      # slower, same verdicts and GT inliers within 0.3 %: docs/pairs.md)
    kmeans_iters: int = 8             # k-means iterations of the IVF training (4 builds 40 % faster, loses pairs: docs/pairs.md)
    min_features: int = 1024          # smaller images get no index (exact search is cheaper than building one)
    seed: int = 0                     # seeds the training subsample and k-means

    def __post_init__(self) -> None:
        o = "PreparedConfig"
        check_choice(o, "index", self.index, ("ivf", "none"))
        check_number(o, "nlist_factor", self.nlist_factor, lo=0.0, lo_open=True, hi=64.0)
        check_number(o, "nprobe", self.nprobe, lo=1, integer=True)
        check_number(o, "train_per_list", self.train_per_list, lo=1, integer=True)
        check_number(o, "kmeans_iters", self.kmeans_iters, lo=1, integer=True)
        check_number(o, "min_features", self.min_features, lo=0, integer=True)
        check_number(o, "seed", self.seed, lo=0, integer=True)


class PreparedImage:
    """One image's features plus the reusable per-image matching state (build with :func:`prepare`).

    Attributes:
        features: the :class:`~guidedmatch.features.Features`.
        binary: descriptors are packed bits (Hamming).
        kdesc: descriptors in the candidate kernel's form: ``(N, W) uint64`` words (binary), ``(N, D) uint8`` exact
            copies of byte-valued float descriptors (OpenCV SIFT), else ``(N, D) float32``.
        byte_exact: ``kdesc`` is the exact uint8 copy.
        sqnorms: ``(N,) float32`` squared L2 norms of float descriptors (None for binary).
        finite: every descriptor value is known to be finite (binary, or all ``sqnorms`` finite).
        config: the :class:`PreparedConfig`.
        quantizer: the collection's :class:`~guidedmatch.collection.quantizer.SharedQuantizer` this image's index
            uses, or None (its own k-means: no quantizer given, binary descriptors, or an image under 0.64x the size
            the quantizer was made for).
    """

    def __init__(self, features: Features, config: PreparedConfig | None = None,
                 quantizer=None):
        if not isinstance(features, Features):
            raise InputError(f"prepare() needs guidedmatch.features.Features, got {type(features).__name__}")
        self.features = features
        self.config = config or PreparedConfig()
        d = features.descriptors
        if quantizer is not None and d.dtype != np.uint8 and quantizer.dim != d.shape[1]:
            raise InputError(f"the shared quantizer has {quantizer.dim}-D centroids; these descriptors are "
                             f"{d.shape[1]}-D")
        self.quantizer = quantizer if d.dtype != np.uint8 else None  # binary descriptors have no index
        if self.quantizer is not None and self._own_nlist < SHARED_MIN_NLIST_SHARE * self.quantizer.nlist:
            # an image far below the collection's median size keeps its own k-means: the shared cells hold too few
            # of its descriptors (buddha's 2,365-feature image, 17 per cell instead of 24, lost the weak first-pass
            # pairs that let the second look register it)
            self.quantizer = None
        self.binary = bool(d.dtype == np.uint8)
        self.byte_exact = False
        if self.binary:
            self.kdesc = kernels.pack_bits_u64(d)
            self.sqnorms = None
        else:
            u8 = kernels.as_exact_uint8(d)
            self.byte_exact = u8 is not None
            self.kdesc = u8 if u8 is not None else d
            self.sqnorms = np.einsum("ij,ij->i", d, d).astype(np.float32)
        # finite squared norms imply finite values (a NaN/inf value makes its row's sum NaN/inf); match() then skips
        # its NaN/inf scan of these descriptors (False only costs that scan, e.g. values too large to square)
        self.finite = True if self.binary else bool(np.isfinite(self.sqnorms).all())
        self._index = None
        self._coarse = None  # (centroids, their squared norms, the index they came from): search2's coarse step
        self._list_ids = None  # each IVF list's descriptor indices (search2's rare exact fallback)
        self._cells = {}  # nprobe -> (cells, distances) of every descriptor in the shared quantizer (query_cells)
        self._lock = threading.Lock()
        self.index_build_s = 0.0

    def __len__(self) -> int:
        return len(self.features)

    @property
    def descriptors(self) -> np.ndarray:
        return self.features.descriptors

    # ------------------------------------------------------------------ pickling: the index is rebuilt lazily
    def __getstate__(self):
        state = dict(self.__dict__)
        state["_index"] = None
        state["_coarse"] = None
        state["_list_ids"] = None
        state["_cells"] = {}
        state.pop("_lock", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ approximate index
    @property
    def has_index(self) -> bool:
        """Whether the approximate index is (or would be) used for this image."""
        c = self.config
        return c.index == "ivf" and not self.binary and len(self) >= max(c.min_features, 2)

    @property
    def nlist(self) -> int:
        if self.quantizer is not None:
            return self.quantizer.nlist
        return self._own_nlist

    @property
    def _own_nlist(self) -> int:
        return max(1, int(round(self.config.nlist_factor * math.sqrt(len(self)))))

    @property
    def nprobe(self) -> int:
        """Cells a search of this image probes: ``config.nprobe``; with a shared quantizer, as many as cover at least
        the share of this image its own index would (``nprobe * nlist / own nlist``, rounded, at least ``nprobe``):
        an image with fewer features than the collection's median has fewer per cell, so it probes more cells
        (buddha, 137 shared cells: a 3,000-feature image 5 of them instead of 4 of its own 110)."""
        c = self.config
        if self.quantizer is None:
            return min(int(c.nprobe), self.nlist)
        return int(min(self.nlist, max(c.nprobe, round(c.nprobe * self.nlist / self._own_nlist))))

    @property
    def build_comparisons(self) -> int:
        """Distance evaluations of building the index (0 without one): k-means assigns the training sample to the
        ``nlist`` centroids ``kmeans_iters`` times, then every descriptor is assigned once -- the price the unguided
        start's ski-rental compares with exact search (Herz-Jesus ~40k SIFT: 45 M with the defaults, 67 M with 40 per cell
        = 1700 exact queries of 40k comparisons)."""
        if not self.has_index:
            return 0
        c, n, nlist = self.config, len(self), self.nlist
        if self.quantizer is not None:  # no k-means of its own: every descriptor is assigned once
            return int(n * nlist)
        return int(min(n, c.train_per_list * nlist) * nlist * c.kmeans_iters + n * nlist)

    def index(self):
        """The faiss IVF index of the descriptors (IVF-Flat, or IVF-SQ8-direct when byte-exact), built on first call (thread-safe), or None."""
        if not self.has_index:
            return None
        with self._lock:
            if self._index is None:
                self._index = self._build_index()
        return self._index

    def _build_index(self):
        import time

        import faiss

        t0 = time.perf_counter()
        c = self.config
        d = np.ascontiguousarray(self.features.descriptors, np.float32)
        n, dim = d.shape
        nlist = self.nlist
        quantizer = faiss.IndexFlatL2(dim)
        if self.quantizer is not None:  # the collection's cells: nothing to train
            quantizer.add(self.quantizer.centroids)
            train = d[:min(n, 256)]  # only the 8-bit codes' (no-op) training reads it; k-means is skipped
        else:
            ntrain = min(n, c.train_per_list * nlist)
            rng = np.random.default_rng(c.seed)
            train = d if ntrain >= n else d[np.sort(rng.choice(n, ntrain, replace=False))]
        if self.byte_exact:
            # byte-valued descriptors (OpenCV / COLMAP SIFT): stored as 8-bit codes, no residual -- the same exact L2
            # distances from a quarter of the memory traffic (Herz-Jesus ~40k: search 30 % faster, same neighbours)
            index = faiss.IndexIVFScalarQuantizer(quantizer, dim, nlist, faiss.ScalarQuantizer.QT_8bit_direct,
                                                  faiss.METRIC_L2, False)
        else:
            index = faiss.IndexIVFFlat(quantizer, dim, nlist)
        index.cp.niter = int(c.kmeans_iters)
        index.cp.seed = int(c.seed)
        index.cp.min_points_per_centroid = 1  # silence faiss's "please provide more points" warning
        index.cp.max_points_per_centroid = max(int(c.train_per_list), 1)
        with _faiss_threads(1):
            index.train(train)
            index.add(d)
        index.nprobe = self.nprobe
        self._list_sizes = np.array([index.invlists.list_size(i) for i in range(nlist)], np.int64)
        self._list_ids = None  # each list's descriptor indices, read on first need (exact_top's rare fallback)
        self.index_build_s = time.perf_counter() - t0
        return index

    def _centroids(self) -> tuple[np.ndarray, np.ndarray]:
        """The index's coarse centroids ``(nlist, D) float32`` and their squared norms (cached with the index)."""
        if self.quantizer is not None:
            return self.quantizer.centroids, self.quantizer.sqnorms
        c = self._coarse
        if c is None or c[2] is not self._index:
            index = self.index()
            cent = np.ascontiguousarray(index.quantizer.reconstruct_n(0, index.nlist), np.float32)
            c = self._coarse = (cent, np.einsum("ij,ij->i", cent, cent), index)
        return c[0], c[1]

    def _list_members(self, lists) -> np.ndarray:
        """Descriptor indices stored in the index's ``lists`` (the domain of a query that probed them)."""
        import faiss

        if self._list_ids is None:
            inv = self.index().invlists
            self._list_ids = [faiss.rev_swig_ptr(inv.get_ids(i), int(n)).astype(np.int64) if n else
                              np.zeros(0, np.int64) for i, n in enumerate(self._list_sizes)]
        lists = [int(x) for x in np.asarray(lists).ravel() if x >= 0]
        return np.concatenate([self._list_ids[x] for x in lists]) if lists else np.zeros(0, np.int64)

    def query_cells(self, nprobe: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``nprobe`` cells of every descriptor of this image in its shared quantizer, as a search of this image's
        features in another image of the collection (whose :attr:`nprobe` it is) probes them: ``(cells (N, nprobe)
        int64, sq (N, nprobe) float32)``, each row in cell order (:func:`coarse_cells`); computed on first call for
        each ``nprobe`` (thread-safe), then kept."""
        if self.quantizer is None:
            raise InputError("query_cells() needs an image prepared with a shared quantizer")
        k = int(min(max(int(nprobe), 1), self.quantizer.nlist))
        with self._lock:
            if k not in self._cells:
                q = np.ascontiguousarray(self.features.descriptors, np.float32)
                self._cells[k] = coarse_cells(q, self.quantizer.centroids, self.quantizer.sqnorms, k,
                                              kernels.num_threads())
            return self._cells[k]

    def search2(self, queries: np.ndarray, byte_exact: bool = False, cells=None, per_row: bool = False):
        """Approximate 2-NN of float ``queries (Q, D)`` in this image: ``(i1, s1, i2, s2, comparisons)``.

        The probed cells: the ``nprobe`` centroids nearest each query, exactly (the set of the GEMM's ``nprobe``
        nearest, certified by the gap to the next one against the GEMM's error bound, else recomputed exactly,
        :mod:`guidedmatch.exact`), scanned in index order; then the :data:`~guidedmatch.exact.K` nearest
        descriptors in those cells by faiss, recomputed and certified the same way (a near-tie at the K-th: every
        descriptor of the probed cells exactly). ``s1``, ``s2`` are the exact squared L2 distances (float64) to the
        two nearest descriptors in the probed cells (``-1`` / ``inf`` when fewer than two were found), the same on
        every CPU and thread count given the index (``byte_exact``: the queries are byte-valued too, and this image's
        8-bit codes give exact integer distances: faiss's K are only sorted, not recomputed); ``comparisons`` = the number of distance evaluations of the
        search: ``nlist`` centroid distances per query plus the size of every probed cell (the exact recompute of
        a few of them is not counted again). ``cells``: the queries' cells ``(Iq, Dq)`` in the shared quantizer
        (rows of :meth:`query_cells` of the queries' image) instead of the coarse step here. With a shared quantizer the
        coarse step is counted at this image's own-index ``nlist`` per query (what its own index would cost, the price
        the unguided start's budget is set in), though the cells are computed once per image. ``per_row``:
        ``comparisons`` as an ``(Q,) int64`` array, each query's share (their sum is the total).
        """
        index = self.index()
        if index is None:
            raise InputError("this image has no approximate index (binary descriptors, too few, or index='none')")
        q = np.ascontiguousarray(queries, np.float32)
        # the calling thread's kernel thread count (1 in a collection's pair threads): a batch of >= 64 queries keeps
        # faiss's OpenMP team busy (Herz-Jesus ~40k unrelated pair: unguided start 0.6 -> 0.35 s on 2 cores)
        threads = kernels.num_threads() if len(q) >= 64 else 1
        # the coarse step (nearest nprobe of nlist centroids, coarse_cells): ours, not faiss's, so it does not depend
        # on how faiss's BLAS was loaded (docs/pairs.md)
        nprobe = self.nprobe
        if cells is None:
            cent, cn = self._centroids()
            Iq, Dq = coarse_cells(q, cent, cn, nprobe, threads)
        else:  # the queries' cells in the collection's shared quantizer, computed once per image (query_cells)
            Iq, Dq = cells
        k = exact.K
        with _faiss_threads(threads):
            D, I = index.search_preassigned(q, k, Iq, Dq)
        # a shared quantizer's coarse step is charged at this image's own nlist: the unguided start's budget then buys
        # as many queries as with the image's own index (at the shared nlist a small image's budget bought fewer:
        # buddha's 2,365-feature image lost the first-pass pairs that let the second look register it)
        rows = self._own_nlist + np.where(Iq >= 0, self._list_sizes[np.maximum(Iq, 0)], 0).sum(axis=1, dtype=np.int64)
        comparisons = rows if per_row else int(rows.sum())
        I = I.astype(np.int64)
        D = np.where(I >= 0, D, np.inf).astype(np.float32)
        if byte_exact and self.byte_exact:
            top, sq = exact.top_of_exact(I, D, 2)
        else:
            top, sq = exact.exact_top(q, self.features.descriptors, I, D, 2, gamma=exact.sum_gamma(q.shape[1]),
                                      domain=lambda i: self._list_members(Iq[i]))
        return top[:, 0], sq[:, 0], top[:, 1], sq[:, 1], comparisons


def coarse_cells(q: np.ndarray, cent: np.ndarray, cn: np.ndarray, nprobe: int, threads: int):
    """The ``nprobe`` nearest of the centroids ``cent (C, D)`` (squared norms ``cn``) of each float32 row of ``q``,
    exactly: ``(cells (Q, nprobe) int64, sq (Q, nprobe) float32)``, each row in cell (index) order.

    NumPy's GEMM + a fused top-k per row (:func:`guidedmatch.kernels.topk_gemm`, the same cells as faiss's flat
    quantizer: 68k queries vs 637 centroids 0.16-0.22 s, one thread; faiss took 0.57-0.64 s while its bundled OpenBLAS
    ran generic kernels, :func:`guidedmatch._runtime.pin_faiss_blas`); the set is certified by the gap to the next
    centroid against the GEMM's error bound, else recomputed exactly (:mod:`guidedmatch.exact`), so which cells does
    not depend on the GEMM's rounding. Cell order fixes the scan order, hence faiss's order among equal distances,
    on every CPU (faiss ignores the coarse distances of these non-residual indexes)."""
    nlist = len(cent)
    Ic, Dc = kernels.topk_gemm(q, cent, cn, min(nprobe + 1, nlist), threads)
    Iq, Dq = Ic[:, :nprobe], Dc[:, :nprobe]
    if Ic.shape[1] > nprobe:  # certify the set
        qn = np.einsum("ij,ij->i", q, q)
        delta = exact.gemm_delta(qn, float(cn.max()), q.shape[1])
        bad = np.flatnonzero(~(Dc[:, nprobe].astype(np.float64) - delta > Dc[:, nprobe - 1] + delta))
        if len(bad):  # a near-tie at the nprobe-th cell: those queries' cells exactly, among every centroid the
            # bound cannot rule out (approximate distance within 2 delta of the nprobe-th)
            Iq, Dq = Iq.copy(), Dq.copy()
            Iq[bad], sq = _exact_cells(q[bad], cent, (qn[bad, None] + cn[None, :]) - 2.0 * (q[bad] @ cent.T),
                                       delta[bad], nprobe)
            Dq[bad] = sq.astype(np.float32)
    o = np.argsort(Iq, axis=1, kind="stable")
    r = np.arange(len(q))[:, None]
    return np.ascontiguousarray(Iq[r, o]), np.ascontiguousarray(Dq[r, o], np.float32)


def _exact_cells(q: np.ndarray, cent: np.ndarray, approx: np.ndarray, delta: np.ndarray, nprobe: int):
    """Exact nearest ``nprobe`` centroids of each query row ``q (R, D)`` among the centroids its approximate
    distances ``approx (R, C)`` cannot rule out (within ``2 delta`` of its ``nprobe``-th): ``(idx (R, nprobe),
    sq (R, nprobe) float64)``, equal distances by the lower index (:func:`guidedmatch.exact.exact_top_among_rows`)."""
    near = approx <= (np.sort(approx, axis=1)[:, nprobe - 1] + 2.0 * delta)[:, None]
    return exact.exact_top_among_rows(q, cent, near, nprobe)


class _faiss_threads:
    """Limit faiss's OpenMP threads inside the block (small batches: a thread team costs more than it saves)."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self):
        import faiss

        self.old = faiss.omp_get_max_threads()
        faiss.omp_set_num_threads(self.n)

    def __exit__(self, *exc):
        import faiss

        faiss.omp_set_num_threads(self.old)


def prepare(features: Features, config: PreparedConfig | None = None,
            quantizer=None) -> PreparedImage:
    """Prepare ``features`` for matching against many images (see the module doc); ``quantizer``: the collection's
    :class:`~guidedmatch.collection.quantizer.SharedQuantizer` (its images' indexes share the cells; searches look up
    the queries' cells).

    >>> import numpy as np
    >>> from guidedmatch.features import Features
    >>> rng = np.random.default_rng(0)
    >>> f = Features(rng.uniform(0, 100, (2000, 2)), rng.integers(0, 255, (2000, 128)).astype(np.float32), (100, 100))
    >>> p = prepare(f)
    >>> p.byte_exact, p.has_index, p.nlist
    (True, True, 89)
    >>> i1, s1, i2, s2, comparisons = p.search2(f.descriptors[:3])
    >>> i1.tolist(), s1.tolist()
    ([0, 1, 2], [0.0, 0.0, 0.0])
    """
    return PreparedImage(features, config, quantizer)


def as_prepared(x, config: PreparedConfig | None = None) -> PreparedImage:
    """``x`` itself when it is a :class:`PreparedImage`, else :func:`prepare` of it."""
    return x if isinstance(x, PreparedImage) else prepare(x, config)


class StartMemo:
    """What the unguided start of one oriented pair found, per image-1 feature and search path ("gemm", "ivf",
    "popcount"): the 2-NN ``(i1, s1, i2, s2)`` and the comparisons each query cost. Given to
    :func:`guidedmatch.matcher.match` (``start_memo``) again for the same pair -- the same image 1, the same image 2
    and its index -- the start takes the results of the features it holds instead of searching them: the matches are
    bit-identical (a query's search result depends on the query and image 2 alone, :meth:`PreparedImage.search2`),
    only the time changes. A collection's second look matches again pairs its first pass matched
    (:mod:`guidedmatch.collection.second_look`), most of whose drawn features the first pass searched already.

    Pickled compactly: only the features held, integers and distances narrowed where that is exact.
    """

    def __init__(self, n1: int, n2: int):
        self.n1, self.n2 = int(n1), int(n2)
        self.parts: dict = {}   # path -> [have (n1,) bool, i1, s1, i2, s2, comparisons (n1,)]
        self._pending: list = []  # (path, queries, results) put since the last flush: a start that keeps no
        # memo (most pairs) pays a list append per search, not the scatter

    def fits(self, n1: int, n2: int) -> bool:
        return self.n1 == int(n1) and self.n2 == int(n2)

    def has(self, path: str, queries: np.ndarray) -> np.ndarray:
        """Which ``queries`` the memo held when this start began (a start searches each feature once: what it put
        itself is never asked again)."""
        part = self.parts.get(path)
        return np.zeros(len(queries), bool) if part is None else part[0][queries]

    def put(self, path: str, queries: np.ndarray, *results) -> None:
        self._pending.append((path, queries, results))

    def get(self, path: str, queries: np.ndarray):
        self._flush()
        part = self.parts[path]
        return tuple(a[queries] for a in part[1:])

    def _flush(self) -> None:
        for path, queries, results in self._pending:
            part = self.parts.get(path)
            if part is None:
                part = self.parts[path] = [np.zeros(self.n1, bool)] + [np.zeros(self.n1, np.asarray(r).dtype)
                                                                        for r in results]
            part[0][queries] = True
            for a, r in zip(part[1:], results):
                a[queries] = r
        self._pending.clear()

    @property
    def held(self) -> int:
        """Features held, over the paths."""
        self._flush()
        return int(sum(int(p[0].sum()) for p in self.parts.values()))

    def __getstate__(self):
        self._flush()
        parts = {}
        for path, p in self.parts.items():
            idx = np.flatnonzero(p[0])
            parts[path] = (_narrow(idx), [(a.dtype.str, _narrow(a[idx])) for a in p[1:]])
        return dict(n1=self.n1, n2=self.n2, parts=parts)

    def __setstate__(self, state) -> None:
        self.n1, self.n2, self.parts, self._pending = state["n1"], state["n2"], {}, []
        for path, (idx, arrays) in state["parts"].items():
            self.put(path, idx.astype(np.int64), *[a.astype(np.dtype(dt)) for dt, a in arrays])
        self._flush()


def _narrow(a: np.ndarray) -> np.ndarray:
    """``a`` as int32 / float32 when that holds every value exactly (restored by ``astype`` of the original dtype),
    else ``a``: a memo's indices, comparisons and integer-valued distances of byte descriptors."""
    if a.dtype == np.int64 and (not len(a) or (int(a.min()) >= -2**31 and int(a.max()) < 2**31)):
        return a.astype(np.int32)
    if a.dtype == np.float64:
        with np.errstate(over="ignore"):
            b = a.astype(np.float32)
        if np.array_equal(b.astype(np.float64), a, equal_nan=True):
            return b
    return a


class UnguidedSearch:
    """2-NN of image-1 query batches over all of image 2 for the matcher's unguided start (a context manager).

    ``kind`` (chosen by :meth:`choose`): ``"ivf"`` -- the approximate index of image 2 (:meth:`PreparedImage.search2`),
    ``"gemm"`` -- exact float GEMM top-2 (:class:`~guidedmatch.bruteforce.DenseKnn2`), ``"popcount"`` -- exact
    Hamming top-2 of binary descriptors. With ``kind="ivf"`` and ``exact_budget > 0`` the first queries are searched
    exactly (GEMM) until ``exact_budget`` comparisons are spent, the index only after (built then when image 2 was not
    prepared; the build time is in ``index_build_s``): ski-rental, the same searches whether or not the index exists.
    :meth:`query` returns ``(i1, s1, i2, s2, comparisons)`` with exact squared L2 distances (float64,
    :mod:`guidedmatch.exact`) or Hamming bit counts (binary).
    """

    KINDS = ("ivf", "gemm", "popcount")

    def __init__(self, p1: PreparedImage, p2: PreparedImage, kind: str, exact_budget: float = 0.0,
                 memo: "StartMemo | None" = None):
        if kind not in self.KINDS:
            raise ValueError(f"kind must be one of {self.KINDS}; got {kind!r}")
        self.p1, self.p2, self.kind = p1, p2, kind
        self.memo = memo if memo is not None and memo.fits(len(p1), len(p2)) else None
        self.memo_hits = 0
        self.exact_budget = float(exact_budget) if kind == "ivf" else 0.0
        self.exact_comparisons = 0
        self.ivf_queries = self.ivf_comparisons = 0
        self.index_build_s = 0.0
        self._dense = None
        self._blas = None

    @staticmethod
    def choose(p2: PreparedImage, use_index: bool = True) -> str:
        if p2.binary:
            return "popcount"
        return "ivf" if use_index and p2.has_index else "gemm"

    @property
    def exact(self) -> bool:
        """The next query is searched exactly."""
        return self.kind != "ivf" or self.exact_comparisons < self.exact_budget

    @property
    def used(self) -> str:
        """What searched so far: ``"gemm"``, ``"popcount"``, ``"ivf"`` or ``"gemm+ivf"`` (ski-rental switched)."""
        if self.kind != "ivf":
            return self.kind
        return "+".join(k for k, n in (("gemm", self.exact_comparisons), ("ivf", self.ivf_queries)) if n) or "gemm"

    def per_query(self) -> float:
        """Comparisons one more query is expected to cost (index: the mean so far, else nlist + nprobe cells)."""
        n2 = len(self.p2)
        if self.exact:
            return float(n2)
        if self.ivf_queries:
            return self.ivf_comparisons / self.ivf_queries
        nlist = self.p2.nlist
        return float(nlist + self.p2.nprobe * n2 / nlist)

    def __enter__(self) -> "UnguidedSearch":
        if self.kind == "gemm" or (self.kind == "ivf" and self.exact_budget > 0):
            from .bruteforce import DenseKnn2

            self._dense = DenseKnn2(self.p2.descriptors, self.p2.sqnorms, byte_exact=self.p2.byte_exact).__enter__()
        if self.kind == "ivf":
            # the index's coarse GEMMs (search2) run one per kernel thread: BLAS single-threaded meanwhile, as in
            # DenseKnn2 (two collection threads' unrelated 68k pairs: 1.3-1.6 s with BLAS's own threads on top,
            # 0.84-0.95 s without)
            from .bruteforce import blas_one_thread

            self._blas = blas_one_thread(load_scipy=False)
        return self

    def __exit__(self, *exc) -> None:
        if self._dense is not None:
            self._dense.__exit__(*exc)
            self._dense = None
        if self._blas is not None:
            self._blas.restore_original_limits()
            self._blas = None

    def query(self, queries: np.ndarray):
        """``(i1, s1, i2, s2, comparisons)`` of the image-1 features ``queries``: exact (GEMM / popcount) while
        :attr:`exact`, else the index. With a :class:`StartMemo` the queries it holds for this path are not searched
        again (their results and comparisons are the memo's: the same as searching, every query's result depends
        on the query and image 2 alone); the others are searched and added to it."""
        queries = np.asarray(queries, np.int64)
        path = self.kind if self.kind != "ivf" else ("gemm" if self.exact else "ivf")
        if self.memo is None:
            i1, s1, i2, s2, rows = self._search(path, queries)
        else:
            have = self.memo.has(path, queries)
            if not have.any():
                i1, s1, i2, s2, rows = out = self._search(path, queries)
                self.memo.put(path, queries, *out)
            else:
                if not have.all():
                    new = queries[~have]
                    self.memo.put(path, new, *self._search(path, new))
                self.memo_hits += int(have.sum())
                i1, s1, i2, s2, rows = self.memo.get(path, queries)
        comparisons = int(rows.sum()) if isinstance(rows, np.ndarray) else int(rows)
        if path == "ivf":
            self.ivf_queries += len(queries)
            self.ivf_comparisons += comparisons
        elif path == "gemm":
            self.exact_comparisons += comparisons
        return i1, s1, i2, s2, comparisons

    def _search(self, path: str, queries: np.ndarray):
        """The search of ``queries`` on ``path`` ("popcount", "gemm" or "ivf"): ``(i1, s1, i2, s2, comparisons of
        each query (Q,) int64)``."""
        n2 = len(self.p2)
        per_query = np.full(len(queries), n2, np.int64)
        if path == "popcount":
            i1, s1, i2, s2 = kernels.hamming_top2(self.p1.kdesc[queries], self.p2.kdesc)
        elif path == "gemm":
            i1, s1, i2, s2 = self._dense.query(self.p1.descriptors[queries], byte_exact=self.p1.byte_exact)
        else:
            if self.p2._index is None:
                import time

                t0 = time.perf_counter()
                self.p2.index()
                self.index_build_s += time.perf_counter() - t0
            cells = None
            q1, q2 = self.p1.quantizer, self.p2.quantizer
            if q1 is not None and q2 is not None and q1.token == q2.token:  # the collection's quantizer: image 1's
                Iq, Dq = self.p1.query_cells(self.p2.nprobe)                 # cells, computed once for all its pairs
                cells = (Iq[queries], Dq[queries])
            return self.p2.search2(self.p1.descriptors[queries], byte_exact=self.p1.byte_exact, cells=cells,
                                   per_row=True)
        return i1, s1, i2, s2, per_query
