"""Peer matchers for the benchmark, run in the same process on the *same* features as guidedmatch.

Every peer takes two ``Features`` (or, except GMS, two descriptor arrays: ``float32`` -> L2,
``uint8`` packed bits -> Hamming) and returns :class:`guidedmatch.results.MatchResult` with
:class:`~guidedmatch.results.MatchStats` (``method``, ``comparisons``, ``time_s``; settings in ``details``):

=================  ===================================================  =============================
peer               what                                                 ``comparisons``
=================  ===================================================  =============================
``opencv_bf``      ``cv2.BFMatcher.knnMatch(k=2)`` + Lowe ratio         ``N1 * N2`` (exact)
``opencv_flann``   ``cv2.FlannBasedMatcher`` (KD-tree for float, LSH    ``None``: approximate search,
                   for binary) ``knnMatch(k=2)`` + ratio                FLANN does not report how many
                                                                        distances it evaluated
``faiss_flat``     faiss ``IndexFlatL2`` / ``IndexBinaryFlat`` exact     ``N1 * N2`` (exact)
                   2-NN + ratio (needs the ``bench`` extra)
``faiss_ivf``      COLMAP-style cached index: faiss                     exact count: coarse-quantizer
                   ``IndexIVFScalarQuantizer`` (``QT_8bit_direct``,     distances (``nlist`` per query)
                   ``nlist = 4 sqrt(N)``, ``nprobe = 8``), one index    + codes scanned in the probed
                   per image (:func:`build_ivf_index`), 2-NN both ways, lists (faiss ``indexIVF_stats``),
                   ratio + max distance + cross-check                   both directions
``gms``            1-NN (``BFMatcher.match``) filtered by               ``N1 * N2`` (the 1-NN pass)
                   ``cv2.xfeatures2d.matchGMS`` (Bian et al. 2017)
=================  ===================================================  =============================

Ratio test as in :mod:`guidedmatch.bruteforce`: keep ``(i, j1)`` iff ``d1 < ratio * d2`` (strict,
Euclidean -- not squared -- distances, Hamming bit counts); with a single image-2 descriptor ``d2 = inf``
(kept); a query that gets no neighbour back (FLANN LSH can return none) is dropped.
``time_s`` covers index building + search + ratio test (descriptors already computed), measured with
``time.perf_counter``; thread counts of the library used are in ``stats.details["threads"]``.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..results import MatchResult, MatchStats, empty_pairs

DEFAULT_RATIO = 0.8  # Lowe ratio used by all ratio-test peers

FAISS_MISSING = (
    "faiss is not installed; install the benchmark extra: pip install 'guidedmatch[bench]' "
    "(or pip install faiss-cpu)"
)


def _descriptors(f: Any) -> tuple[np.ndarray, bool]:
    """``(descriptors, binary)`` of a Features-like object or an array (uint8 array -> binary)."""
    d = getattr(f, "descriptors", f)
    d = np.asarray(d)
    binary = bool(getattr(f, "binary", d.dtype == np.uint8))
    if d.ndim != 2:
        d = d.reshape(len(d), -1) if d.size else d.reshape(0, 32 if binary else 128)
    d = np.ascontiguousarray(d, dtype=np.uint8 if binary else np.float32)
    return d, binary


def _pair_descriptors(f1: Any, f2: Any) -> tuple[np.ndarray, np.ndarray, bool]:
    d1, b1 = _descriptors(f1)
    d2, b2 = _descriptors(f2)
    if b1 != b2:
        raise ValueError("cannot match binary against float descriptors")
    if len(d1) and len(d2) and d1.shape[1] != d2.shape[1]:
        raise ValueError(f"descriptor lengths differ: {d1.shape[1]} vs {d2.shape[1]}")
    return d1, d2, b1


def _ratio_select(query: np.ndarray, nn: np.ndarray, dist1: np.ndarray, dist2: np.ndarray,
                  ratio: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(query, nn)`` passing ``dist1 < ratio * dist2`` (all if ``ratio`` is None)."""
    keep = np.isfinite(dist1) & (nn >= 0)
    if ratio is not None:
        keep &= dist1 < ratio * dist2
    if not keep.any():
        return empty_pairs(), np.zeros(0, np.float32)
    pairs = np.stack([query[keep], nn[keep]], axis=1).astype(np.int64)
    return pairs, dist1[keep].astype(np.float32)


def _knn_lists_to_arrays(knn: list, n1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV ``knnMatch`` output -> ``(query, nn, d1, d2)`` arrays (``d2 = inf`` when one neighbour,
    ``nn = -1``/``d1 = inf`` when none)."""
    q = np.arange(n1, dtype=np.int64)
    nn = np.full(n1, -1, np.int64)
    d1 = np.full(n1, np.inf)
    d2 = np.full(n1, np.inf)
    for ms in knn:
        if not ms:
            continue
        i = ms[0].queryIdx
        nn[i] = ms[0].trainIdx
        d1[i] = ms[0].distance
        if len(ms) > 1:
            d2[i] = ms[1].distance
    return q, nn, d1, d2


def _result(method: str, pairs, dist, comparisons: int | None, time_s: float, n1: int, n2: int, *, metric: str,
            **details) -> MatchResult:
    """A peer's MatchResult: :class:`~guidedmatch.results.MatchStats` with the peer's settings in ``details``."""
    stats = MatchStats(method=method, comparisons=comparisons, time_s=time_s, num_features=(n1, n2), metric=metric,
                       details=details)
    return MatchResult(pairs, dist, stats)


def _empty(method: str, n1: int, n2: int, t0: float, comparisons: int | None, **extra) -> MatchResult:
    return _result(method, empty_pairs(), np.zeros(0, np.float32), comparisons, time.perf_counter() - t0, n1, n2,
                   **extra)


def match_opencv_bf(f1: Any, f2: Any, ratio: float | None = DEFAULT_RATIO) -> MatchResult:
    """Exact 2-NN with ``cv2.BFMatcher`` (``NORM_L2`` / ``NORM_HAMMING``) + Lowe ratio."""
    import cv2

    d1, d2, binary = _pair_descriptors(f1, f2)
    n1, n2 = len(d1), len(d2)
    extra = {"metric": "hamming" if binary else "l2", "ratio": ratio, "threads": cv2.getNumThreads()}
    t0 = time.perf_counter()
    if n1 == 0 or n2 == 0:
        return _empty("opencv_bf", n1, n2, t0, n1 * n2, **extra)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2, crossCheck=False)
    knn = bf.knnMatch(d1, d2, k=min(2, n2))
    pairs, dist = _ratio_select(*_knn_lists_to_arrays(knn, n1), ratio)
    dt = time.perf_counter() - t0
    return _result("opencv_bf", pairs, dist, n1 * n2, dt, n1, n2, **extra)


def match_opencv_flann(f1: Any, f2: Any, ratio: float | None = DEFAULT_RATIO, *, trees: int = 5,
                       checks: int = 50, lsh_tables: int = 6, lsh_key_size: int = 12,
                       lsh_multi_probe: int = 1) -> MatchResult:
    """Approximate 2-NN with ``cv2.FlannBasedMatcher`` + Lowe ratio.

    Float descriptors: randomized KD-trees (``trees``, ``checks`` leaves visited per query). Binary: LSH
    (``lsh_tables`` tables, ``lsh_key_size``-bit keys, ``lsh_multi_probe`` probe level). The number of
    descriptor distances FLANN evaluates is not exposed, so ``stats.comparisons`` is ``None``
    (unknown) -- never an estimate.
    """
    import cv2

    d1, d2, binary = _pair_descriptors(f1, f2)
    n1, n2 = len(d1), len(d2)
    if binary:
        index_params = {"algorithm": 6, "table_number": lsh_tables, "key_size": lsh_key_size,
                        "multi_probe_level": lsh_multi_probe}  # FLANN_INDEX_LSH
    else:
        index_params = {"algorithm": 1, "trees": trees}  # FLANN_INDEX_KDTREE
    extra = {"metric": "hamming" if binary else "l2", "ratio": ratio, "index": "lsh" if binary else "kdtree",
             "index_params": index_params, "checks": checks, "threads": cv2.getNumThreads(),
             "comparisons_note": "unknown: approximate search, FLANN does not report distance evaluations"}
    t0 = time.perf_counter()
    if n1 == 0 or n2 == 0:
        return _empty("opencv_flann", n1, n2, t0, None, **extra)
    fl = cv2.FlannBasedMatcher(index_params, {"checks": int(checks)})
    knn = fl.knnMatch(d1, d2, k=min(2, n2))
    pairs, dist = _ratio_select(*_knn_lists_to_arrays(knn, n1), ratio)
    dt = time.perf_counter() - t0
    return _result("opencv_flann", pairs, dist, None, dt, n1, n2, **extra)


def _import_faiss():
    try:
        import faiss  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(FAISS_MISSING) from exc
    return faiss


def faiss_available() -> bool:
    """True when faiss can be imported (callers skip the faiss peer otherwise)."""
    try:
        _import_faiss()
    except ImportError:
        return False
    return True


def match_faiss(f1: Any, f2: Any, ratio: float | None = DEFAULT_RATIO) -> MatchResult:
    """Exact 2-NN with faiss (``IndexFlatL2`` for float, ``IndexBinaryFlat`` for binary) + Lowe ratio.

    ``IndexFlatL2`` returns squared L2 distances; they are clamped at 0 and square-rooted before the ratio
    test. Raises ``ImportError`` naming the ``bench`` extra when faiss is missing.
    """
    faiss = _import_faiss()
    d1, d2, binary = _pair_descriptors(f1, f2)
    n1, n2 = len(d1), len(d2)
    extra = {"metric": "hamming" if binary else "l2", "ratio": ratio, "threads": faiss.omp_get_max_threads(),
             "index": "IndexBinaryFlat" if binary else "IndexFlatL2"}
    t0 = time.perf_counter()
    if n1 == 0 or n2 == 0:
        return _empty("faiss_flat", n1, n2, t0, n1 * n2, **extra)
    k = min(2, n2)
    if binary:
        index = faiss.IndexBinaryFlat(d2.shape[1] * 8)
        index.add(d2)
        D, I = index.search(d1, k)
        D = D.astype(np.float64)
    else:
        index = faiss.IndexFlatL2(d2.shape[1])
        index.add(d2)
        D, I = index.search(d1, k)
        D = np.sqrt(np.maximum(D.astype(np.float64), 0.0))
    I = I.astype(np.int64)
    D[I < 0] = np.inf
    nn = I[:, 0]
    dist1 = D[:, 0]
    dist2 = D[:, 1] if k == 2 else np.full(n1, np.inf)
    pairs, dist = _ratio_select(np.arange(n1, dtype=np.int64), nn, dist1, dist2, ratio)
    dt = time.perf_counter() - t0
    return _result("faiss_flat", pairs, dist, n1 * n2, dt, n1, n2, **extra)


COLMAP_MAX_DISTANCE = 0.7 * 512.0  # COLMAP SiftMatchingOptions.max_distance (0.7) on descriptors of norm 512 (L2)
COLMAP_NPROBE = 8  # inverted lists probed per query (COLMAP's CPU matcher)
COLMAP_MIN_INDEXED = 512  # COLMAP indexes fewer descriptors with a flat (exact) index


class IVFIndex:
    """A cached per-image faiss index, as COLMAP's CPU matcher keeps one per image (:func:`build_ivf_index`).

    Attributes:
        index: the faiss index (``IndexIVFScalarQuantizer`` with ``QT_8bit_direct``, or ``IndexFlatL2`` below
            ``COLMAP_MIN_INDEXED`` descriptors). descriptors: ``(N, 128) float32`` the indexed descriptors.
        nlist: number of inverted lists (0 for a flat index). nprobe: lists probed per query.
        build_s: seconds spent training + adding (``time.perf_counter``).
    """

    def __init__(self, index, descriptors: np.ndarray, nlist: int, nprobe: int, build_s: float):
        self.index, self.descriptors, self.nlist, self.nprobe, self.build_s = index, descriptors, nlist, nprobe, build_s

    def __len__(self) -> int:
        return len(self.descriptors)

    def search(self, queries: np.ndarray, k: int = 2) -> tuple[np.ndarray, np.ndarray, int]:
        """``(D (Q,k) Euclidean distances, I (Q,k) int64, comparisons)``; missing neighbours get ``I = -1``,
        ``D = inf``. ``comparisons`` = descriptor distances evaluated: ``Q * nlist`` (coarse quantizer) + the codes
        scanned in the probed lists (faiss ``indexIVF_stats.ndis``); ``Q * N`` for a flat index."""
        faiss = _import_faiss()
        q = np.ascontiguousarray(queries, np.float32)
        k = min(k, len(self))
        if self.nlist:
            faiss.cvar.indexIVF_stats.reset()
            D, I = self.index.search(q, k)
            comparisons = len(q) * self.nlist + int(faiss.cvar.indexIVF_stats.ndis)
        else:
            D, I = self.index.search(q, k)
            comparisons = len(q) * len(self)
        I = I.astype(np.int64)
        D = np.sqrt(np.maximum(D.astype(np.float64), 0.0))
        D[I < 0] = np.inf
        return D, I, comparisons


def build_ivf_index(f: Any, *, nprobe: int = COLMAP_NPROBE, seed: int = 1234) -> IVFIndex:
    """Build COLMAP's cached CPU-matcher index of one image's float descriptors (once per image, reused per pair).

    ``IndexIVFScalarQuantizer(IndexFlatL2, d, nlist = int(4 sqrt(N)), QT_8bit_direct, L2)``, trained (k-means
    of the coarse quantizer, ``min_points_per_centroid = 1`` as COLMAP, seeded) and filled with all ``N``
    descriptors; ``nprobe`` lists probed per query. ``QT_8bit_direct`` stores each component as ``uint8``
    unchanged, so the distances are exact for byte-valued descriptors (OpenCV / COLMAP SIFT, values 0..255):
    only the inverted-list probing is approximate. Fewer than ``COLMAP_MIN_INDEXED`` descriptors: a flat index.
    """
    faiss = _import_faiss()
    d, binary = _descriptors(f)
    if binary:
        raise ValueError("build_ivf_index needs float descriptors (the IVF-SQ8 index is for SIFT-like vectors)")
    t0 = time.perf_counter()
    n, dim = d.shape
    if n >= COLMAP_MIN_INDEXED:
        nlist = int(4 * np.sqrt(n))
        quantizer = faiss.IndexFlatL2(dim)
        # encode_residual=False: QT_8bit_direct stores the raw byte values (residuals to the centroid would be
        # negative and clipped -- wrong distances)
        index = faiss.IndexIVFScalarQuantizer(quantizer, dim, nlist, faiss.ScalarQuantizer.QT_8bit_direct,
                                              faiss.METRIC_L2, False)
        index.cp.min_points_per_centroid = 1
        index.cp.seed = int(seed)
        index.train(d)
        index.add(d)
        index.nprobe = int(nprobe)
    else:
        nlist, quantizer = 0, None
        index = faiss.IndexFlatL2(dim)
        if n:
            index.add(d)
    out = IVFIndex(index, d, nlist, int(nprobe) if nlist else 0, time.perf_counter() - t0)
    out.quantizer = quantizer  # the coarse quantizer must live as long as the index
    return out


def _one_way(D: np.ndarray, I: np.ndarray, ratio: float | None, max_distance: float | None) -> np.ndarray:
    """Best neighbour per query passing the ratio and max-distance tests, else -1 (COLMAP's one-way rule)."""
    nn = I[:, 0].copy() if I.shape[1] else np.full(len(I), -1, np.int64)
    d1 = D[:, 0] if D.shape[1] else np.full(len(I), np.inf)
    d2 = D[:, 1] if D.shape[1] > 1 else np.full(len(I), np.inf)
    ok = np.isfinite(d1) & (nn >= 0)
    if max_distance is not None:
        ok &= d1 <= max_distance
    if ratio is not None:
        ok &= d1 < ratio * d2
    nn[~ok] = -1
    return nn


def match_faiss_ivf(f1: Any, f2: Any, ratio: float | None = DEFAULT_RATIO, *, index1: IVFIndex | None = None,
                    index2: IVFIndex | None = None, cross_check: bool = True,
                    max_distance: float | None = COLMAP_MAX_DISTANCE, nprobe: int = COLMAP_NPROBE) -> MatchResult:
    """Match as COLMAP's CPU matcher does with its cached faiss IVF-SQ8 indexes: 2-NN of image 1 in image 2's index;
    keep ``i -> j`` when ``d1 <= max_distance`` and ``d1 < ratio * d2`` (Euclidean); with ``cross_check`` also
    search image 2 in image 1's index and keep only mutual pairs.

    ``index1`` / ``index2``: prebuilt :func:`build_ivf_index` of each image (the cached case; ``time_s`` then is
    search + selection only). Missing ones are built here and their build time is added to ``time_s`` and reported
    in ``stats.details["build_s"]`` (``search_s`` = the rest). ``max_distance`` = COLMAP's 0.7 on unit descriptors, times 512 (OpenCV and COLMAP SIFT
    descriptors have norm ~512). Returns pairs sorted by image-1 index.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> d = rng.integers(0, 60, (600, 128)).astype(np.float32)
    >>> r = match_faiss_ivf(d, d[::-1].copy())
    >>> bool(np.all(r.pairs[:, 1] == 599 - r.pairs[:, 0])), len(r) > 550
    (True, True)
    """
    d1, d2, binary = _pair_descriptors(f1, f2)
    if binary:
        raise ValueError("match_faiss_ivf needs float descriptors")
    n1, n2 = len(d1), len(d2)
    extra = {"metric": "l2", "ratio": ratio, "max_distance": max_distance, "cross_check": bool(cross_check),
             "index": "IndexIVFScalarQuantizer(QT_8bit_direct)"}
    build_s = 0.0
    if index2 is None and n2:
        index2 = build_ivf_index(d2, nprobe=nprobe)
        build_s += index2.build_s
    if cross_check and index1 is None and n1:
        index1 = build_ivf_index(d1, nprobe=nprobe)
        build_s += index1.build_s
    faiss = _import_faiss()
    extra["threads"] = faiss.omp_get_max_threads()
    t0 = time.perf_counter()
    if n1 == 0 or n2 == 0:
        return _empty("faiss_ivf", n1, n2, t0 - build_s, 0, build_s=build_s, search_s=0.0, nlist=0, nprobe=0, **extra)
    for idx, n in ((index2, n2), (index1, n1)):
        if idx is not None and len(idx) != n:
            raise ValueError(f"a prebuilt index holds {len(idx)} descriptors, the features {n}")
    D, I, comp = index2.search(d1, 2)
    fwd = _one_way(D, I, ratio, max_distance)
    if cross_check:
        Db, Ib, comp_b = index1.search(d2, 2)
        comp += comp_b
        bwd = _one_way(Db, Ib, ratio, max_distance)
        q = np.flatnonzero(fwd >= 0)
        q = q[bwd[fwd[q]] == q]
    else:
        q = np.flatnonzero(fwd >= 0)
    pairs = np.stack([q, fwd[q]], axis=1).astype(np.int64) if len(q) else empty_pairs()
    dist = D[q, 0].astype(np.float32)
    search_s = time.perf_counter() - t0
    return _result("faiss_ivf", pairs, dist, int(comp), search_s + build_s, n1, n2, search_s=search_s, build_s=build_s,
                   nlist=index2.nlist, nprobe=index2.nprobe, **extra)


def match_gms(f1: Any, f2: Any, *, with_rotation: bool = False, with_scale: bool = False,
              threshold_factor: float = 6.0) -> MatchResult:
    """GMS (grid-based motion statistics, Bian et al. CVPR 2017) on exact 1-NN matches.

    1-NN from ``cv2.BFMatcher.match`` (no ratio test, no cross-check), then
    ``cv2.xfeatures2d.matchGMS(size1, size2, kp1, kp2, matches, withRotation, withScale, thresholdFactor)``.
    Needs ``Features`` (keypoints and ``image_size``), not bare descriptor arrays.
    ``stats.details["num_nn_matches"]`` is the number of 1-NN matches fed to GMS; ``time_s`` excludes the
    conversion of keypoints to ``cv2.KeyPoint``.
    """
    import cv2

    for f in (f1, f2):
        if not (hasattr(f, "keypoints") and hasattr(f, "image_size")):
            raise TypeError("match_gms needs Features (keypoints + image_size), not bare descriptor arrays")
    if not hasattr(cv2, "xfeatures2d") or not hasattr(cv2.xfeatures2d, "matchGMS"):
        raise ImportError("cv2.xfeatures2d.matchGMS is missing: install opencv-contrib-python(-headless)")
    d1, d2, binary = _pair_descriptors(f1, f2)
    n1, n2 = len(d1), len(d2)
    extra = {"metric": "hamming" if binary else "l2", "with_rotation": bool(with_rotation),
             "with_scale": bool(with_scale), "threshold_factor": float(threshold_factor),
             "threads": cv2.getNumThreads()}
    kp1 = _cv_keypoints(f1)  # conversion to cv2.KeyPoint is data marshalling, kept out of time_s
    kp2 = _cv_keypoints(f2)
    t0 = time.perf_counter()
    if n1 == 0 or n2 == 0:
        return _empty("gms", n1, n2, t0, n1 * n2, num_nn_matches=0, **extra)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2, crossCheck=False)
    nn = bf.match(d1, d2)
    good = cv2.xfeatures2d.matchGMS(tuple(int(v) for v in f1.image_size), tuple(int(v) for v in f2.image_size),
                                    kp1, kp2, nn, withRotation=bool(with_rotation), withScale=bool(with_scale),
                                    thresholdFactor=float(threshold_factor))
    if len(good):
        pairs = np.array([(m.queryIdx, m.trainIdx) for m in good], dtype=np.int64)
        dist = np.array([m.distance for m in good], dtype=np.float32)
        order = np.argsort(pairs[:, 0], kind="stable")
        pairs, dist = pairs[order], dist[order]
    else:
        pairs, dist = empty_pairs(), np.zeros(0, np.float32)
    dt = time.perf_counter() - t0
    return _result("gms", pairs, dist, n1 * n2, dt, n1, n2, num_nn_matches=len(nn), **extra)


def _cv_keypoints(f: Any) -> list:
    """``cv2.KeyPoint`` list from Features (size from ``scales`` or 1 px, angle from ``angles`` or -1)."""
    import cv2

    if hasattr(f, "to_cv_keypoints"):
        return list(f.to_cv_keypoints())
    kp = np.asarray(f.keypoints, dtype=np.float64).reshape(-1, 2)
    sc = getattr(f, "scales", None)
    an = getattr(f, "angles", None)
    return [cv2.KeyPoint(float(x), float(y), float(sc[i]) if sc is not None else 1.0,
                         float(an[i]) if an is not None else -1.0) for i, (x, y) in enumerate(kp)]


#: Peer name -> matcher ``fn(f1, f2) -> MatchResult`` with default settings. ``match_faiss_ivf`` is not listed: its
#: point is the per-image index cached across pairs (:func:`build_ivf_index`), which a per-pair loop would rebuild.
PEERS: dict[str, Callable[..., MatchResult]] = {
    "opencv_bf": match_opencv_bf,
    "opencv_flann": match_opencv_flann,
    "faiss_flat": match_faiss,
    "gms": match_gms,
}


def available_peers() -> list[str]:
    """Names in :data:`PEERS` whose dependencies are importable (faiss is optional)."""
    names = list(PEERS)
    if not faiss_available():
        names.remove("faiss_flat")
    return names
