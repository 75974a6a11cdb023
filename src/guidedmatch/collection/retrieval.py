"""Retrieval pairs from the collection itself: a bag of visual words over the collection's own descriptors.

No pretrained vocabulary and no download. :func:`retrieval_pairs` (``--pairs retrieval[:K]``):

1. **Vocabulary** -- a two-level k-means quantizer (``coarse`` x ``fine`` words, default 64 x 64 = 4096) trained with
   faiss on a seeded sample of the collection's descriptors (``sample`` rows in all, the same number from each of at
   most ``train_images`` evenly spaced images: a constant cost however large the collection). Descriptors are
   L2-normalised first (COLMAP's SIFT rows are RootSIFT already; binary descriptors are unpacked to 0/1 bits).
   Two levels keep the assignment at ``coarse + fine`` distances per descriptor.
2. **Bag of words** -- every descriptor of every image is assigned to its word (linear in the total number of
   features, one image in memory at a time); per image ``sqrt(tf) * idf``, L2-normalised: a sparse
   ``images x words`` matrix (``scipy.sparse``).
3. **Shortlist** -- cosine similarities by blocks of rows of the sparse product ``V V^T``, corrected for hubs
   (CSLS: ``2 cos - r_i - r_j``, :func:`shortlist`); each image keeps its ``K`` most similar images; the union of
   both directions (symmetric), each unordered pair once, in exhaustive order (``retrieval:K`` with ``K >= n - 1``
   is exactly the exhaustive list).

Resumable: the vocabulary, the bag-of-words matrix and the shortlist are saved (atomically) in one ``.npz``
(default: next to the feature file, ``<source>.retrieval.npz``) with a key of the image names, their feature counts,
the vocabulary settings and the seed; a run with the same key reuses the vocabulary and the bag of words (and the
shortlist when K is the same too). Memory: the training sample (``sample x dim x 4`` bytes, 13 MB at the default)
plus one image's descriptors plus the sparse matrix (at most ``words`` entries per image).
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError
from ..validation import check_bool, check_number, config_from

__all__ = ["RetrievalConfig", "RetrievalResult", "retrieval_pairs", "parse_retrieval_spec", "bag_of_words",
           "shortlist", "retrieval_cache_path", "most_similar"]

DEFAULT_K = 20  # images kept per image by ``retrieval`` without ``:K`` (chosen on the 220-image collection)


@dataclass(frozen=True)
class RetrievalConfig:
    """Settings of :func:`retrieval_pairs`."""

    k: int = DEFAULT_K            # most similar images kept per image (the shortlist is the symmetric union)
    coarse: int = 64              # first-level k-means centroids
    fine: int = 64                # second-level centroids per first-level cell (words = coarse x fine)
    sample: int = 25_000          # descriptors sampled (seeded, evenly over the images) to train the vocabulary
    train_images: int = 64        # images the sample is drawn from at most (evenly spaced in name order)
    seed: int = 0                 # seed of the sample and of k-means
    niter: int = 20               # k-means iterations per level
    hub_k: int = 10               # rank by CSLS with each image's mean similarity to its hub_k nearest (0: cosine)
    block: int = 512              # rows of the similarity matrix computed at once (memory: block x images floats)
    progress: bool = True         # tqdm bars (images/s, ETA) on stderr

    def __post_init__(self) -> None:
        own = "RetrievalConfig"
        check_number(own, "k", self.k, lo=1, integer=True)
        check_number(own, "coarse", self.coarse, lo=1, integer=True)
        check_number(own, "fine", self.fine, lo=1, integer=True)
        check_number(own, "sample", self.sample, lo=1, integer=True)
        check_number(own, "train_images", self.train_images, lo=1, integer=True)
        check_number(own, "seed", self.seed, lo=0, integer=True)
        check_number(own, "niter", self.niter, lo=1, integer=True)
        check_number(own, "hub_k", self.hub_k, lo=0, integer=True)
        check_number(own, "block", self.block, lo=1, integer=True)
        check_bool(own, "progress", self.progress)

    @property
    def words(self) -> int:
        return self.coarse * self.fine


@dataclass(frozen=True)
class RetrievalResult:
    """What :func:`retrieval_pairs` computed: the pairs and the stage's facts (``info``: time, vocabulary size,
    reused or not, cache path, ...)."""

    pairs: tuple
    info: dict


def parse_retrieval_spec(spec: str) -> int:
    """K of ``"retrieval"`` (:data:`DEFAULT_K`) or ``"retrieval:K"`` (an integer >= 1); ConfigError otherwise.

    >>> parse_retrieval_spec("retrieval"), parse_retrieval_spec("retrieval:5")
    (20, 5)
    """
    parts = str(spec).strip().split(":")
    if parts[0] != "retrieval" or len(parts) > 2:
        raise ConfigError(f"pairs spec {spec!r}: expected retrieval[:K] with an integer K >= 1")
    if len(parts) == 1:
        return DEFAULT_K
    try:
        k = int(parts[1])
    except ValueError:
        k = 0
    if k < 1 or str(k) != parts[1].strip().lstrip("+"):
        raise ConfigError(f"pairs spec {spec!r}: expected retrieval[:K] with an integer K >= 1 "
                          f"(images kept per image), got {parts[1]!r}")
    return k


def retrieval_cache_path(source) -> Path | None:
    """Default cache file of a source: ``<feature file>.retrieval.npz`` (None when the source has no path)."""
    p = getattr(source, "path", None)
    return None if p is None else Path(str(p) + ".retrieval.npz")


# ---------------------------------------------------------------------------------------------------- descriptors
def _rows(desc: np.ndarray) -> np.ndarray:
    """Float32, L2-normalised rows (uint8 binary descriptors are unpacked to bits first)."""
    d = np.asarray(desc)
    if d.dtype == np.uint8 and d.ndim == 2 and d.shape[1] <= 64:  # packed binary (ORB / AKAZE ...)
        d = np.unpackbits(d, axis=1)
    d = np.array(d, dtype=np.float32, copy=True).reshape(len(d), -1)
    n = np.sqrt(np.einsum("ij,ij->i", d, d))
    d *= (1.0 / np.maximum(n, 1e-12))[:, None]
    return d


def _descriptors(source, name: str) -> np.ndarray:
    """The image's descriptors as L2-normalised float32 rows; from a COLMAP database only the descriptor blob is read
    (8x faster than ``source.load``, which also converts the keypoints)."""
    from .colmap_source import ColmapSource, _descriptor_rows

    if isinstance(source, ColmapSource):
        db = source._db()
        desc = source._retry(lambda: db.read_descriptors(source.image_id(name)))
        data = np.asarray(desc.data)
        if data.ndim == 2 and len(data):
            return _rows(_descriptor_rows(desc, int(data.shape[1]))[1])
    return _rows(source.load(name).descriptors)


def _bar(total: int, desc: str, on: bool):
    if not on:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="image", desc=desc, file=sys.stderr, dynamic_ncols=True, smoothing=0.1)


def _kmeans(x: np.ndarray, k: int, niter: int, seed: int) -> np.ndarray:
    """faiss k-means centroids (k <= len(x); fewer points than k: the points themselves, padded by repeats)."""
    import faiss

    k = int(k)
    if len(x) <= k:
        reps = np.resize(np.arange(len(x)), k) if len(x) else np.zeros(k, int)
        return np.ascontiguousarray(x[reps] if len(x) else np.zeros((k, x.shape[1]), np.float32))
    km = faiss.Kmeans(x.shape[1], k, niter=niter, seed=int(seed) + 1, verbose=False, min_points_per_centroid=1,
                      max_points_per_centroid=max(256, len(x) // k + 1))
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)  # small problems: OpenMP threads cost more than they give (15x on a busy machine)
    try:
        km.train(np.ascontiguousarray(x, dtype=np.float32))
    finally:
        faiss.omp_set_num_threads(before)
    return np.asarray(km.centroids, np.float32)


def _nearest(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Index of the nearest centroid of every row (squared L2 via one matrix product)."""
    d = (c * c).sum(1)[None, :] - 2.0 * (x @ c.T)
    return np.argmin(d, axis=1)


def train_vocabulary(source, names, cfg: RetrievalConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(coarse (C, D), fine (C, F, D))`` centroids trained on a seeded sample of the collection's descriptors."""
    if len(names) > cfg.train_images:
        names = [names[int(i)] for i in np.unique(np.linspace(0, len(names) - 1, cfg.train_images).round())]
    per = max(1, -(-cfg.sample // max(1, len(names))))
    parts = []
    bar = _bar(len(names), "retrieval: vocabulary sample", cfg.progress)
    for i, n in enumerate(names):
        d = _descriptors(source, n)
        if len(d) > per:
            rng = np.random.default_rng([cfg.seed, i])
            d = d[np.sort(rng.choice(len(d), per, replace=False))]
        parts.append(d)
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    x = np.concatenate(parts) if parts else np.zeros((0, 128), np.float32)
    if len(x) == 0:
        raise InputError("retrieval: the images have no descriptors")
    coarse = _kmeans(x, cfg.coarse, cfg.niter, cfg.seed)
    cell = _nearest(x, coarse)
    fine = np.empty((cfg.coarse, cfg.fine, x.shape[1]), np.float32)
    for c in range(cfg.coarse):
        members = x[cell == c]
        fine[c] = _kmeans(members, cfg.fine, cfg.niter, cfg.seed + c + 1) if len(members) else coarse[c]
    return coarse, fine


def assign_words(d: np.ndarray, coarse: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """Word id (``cell * fine + sub``) of every row of ``d`` (L2-normalised float32)."""
    cell = _nearest(d, coarse)
    words = np.empty(len(d), np.int64)
    order = np.argsort(cell, kind="stable")
    bounds = np.searchsorted(cell[order], np.arange(len(coarse) + 1))
    for c in range(len(coarse)):
        idx = order[bounds[c]:bounds[c + 1]]
        if len(idx):
            words[idx] = c * fine.shape[1] + _nearest(d[idx], fine[c])
    return words


def bag_of_words(counts, n_words: int):
    """The L2-normalised ``sqrt(tf) * idf`` matrix (``scipy.sparse.csr_matrix``, images x words) of per-image
    word-count dicts / arrays ``(words, counts)``.

    >>> m = bag_of_words([(np.array([0, 1]), np.array([1, 1])), (np.array([1]), np.array([4]))], 3)
    >>> np.round(m.toarray(), 3).tolist()
    [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    """
    import scipy.sparse as sp

    rows, cols, vals = [], [], []
    for i, (w, c) in enumerate(counts):
        rows.append(np.full(len(w), i, np.int64))
        cols.append(np.asarray(w, np.int64))
        vals.append(np.asarray(c, np.float64))
    n = len(counts)
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    cidx = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    v = np.concatenate(vals) if vals else np.zeros(0)
    m = sp.csr_matrix((v, (r, cidx)), shape=(n, n_words))
    df = np.bincount(m.indices, minlength=n_words)
    idf = np.log(max(n, 1) / np.maximum(df, 1))
    totals = np.asarray(m.sum(axis=1)).reshape(-1)
    m = sp.diags(1.0 / np.maximum(totals, 1)) @ m
    m.data = np.sqrt(m.data)
    m = m @ sp.diags(idf)
    norms = np.sqrt(np.asarray(m.multiply(m).sum(axis=1)).reshape(-1))
    m = sp.diags(1.0 / np.maximum(norms, 1e-12)) @ m
    m = m.tocsr()
    m.eliminate_zeros()
    return m.astype(np.float32)


def _similarity(bow, bt, rows: np.ndarray) -> np.ndarray:
    """``(len(rows), n) float64``: cosine of each image of ``rows`` with every image (``bt`` = ``bow.T`` as CSC),
    ``-inf`` with itself."""
    sim = np.asarray((bow[rows] @ bt).todense(), np.float64)
    sim[np.arange(len(rows)), rows] = -np.inf
    return sim


def _similarity_blocks(bow, block: int):
    """``(s, e, cosine (e - s, n) float64 with -inf on the diagonal)`` by blocks of rows."""
    n = bow.shape[0]
    bt = bow.T.tocsc()
    for s in range(0, n, block):
        e = min(n, s + block)
        yield s, e, _similarity(bow, bt, np.arange(s, e))


def hub_scores(bow, hub_k: int, block: int = 512) -> np.ndarray:
    """Per image, the mean cosine of its ``hub_k`` most similar other images (how much of a "hub" it is)."""
    n = bow.shape[0]
    kk = int(min(hub_k, n - 1))
    r = np.zeros(n)
    if kk < 1:
        return r
    for s, e, sim in _similarity_blocks(bow, block):
        r[s:e] = -np.mean(np.partition(-sim, kk - 1, axis=1)[:, :kk], axis=1)
    return r


def shortlist(bow, k: int, block: int = 512, hub_k: int = 0) -> np.ndarray:
    """``(P, 2)`` index pairs ``i < j``, sorted: the union over images of their ``k`` most similar other images
    (cosine of the rows of ``bow``; ties broken by the smaller index). ``k >= n - 1`` gives every pair.

    ``hub_k > 0``: images are ranked by ``2 cos(i, j) - r_i - r_j`` instead (cross-domain similarity local
    scaling, CSLS), ``r`` = :func:`hub_scores`: an image similar to everything (many generic words: textured
    photos, repetitive texture) stops crowding every other image's list. On the 220-image collection the share of
    same-scene images among the top 20 of the scene images went from 0.76 (cosine) to 0.96 (``hub_k=10``).

    >>> import scipy.sparse as sp
    >>> v = sp.csr_matrix(np.array([[1, 0], [0.9, 0.1], [0, 1], [0.1, 0.9]], np.float32))
    >>> shortlist(v, 1).tolist()
    [[0, 1], [2, 3]]
    """
    n = bow.shape[0]
    k = int(min(k, n - 1))
    if n < 2 or k < 1:
        return np.zeros((0, 2), np.int64)
    r = hub_scores(bow, hub_k, block) if hub_k > 0 else None
    keep = np.zeros((n, n), bool) if n <= 4096 else None
    bt = bow.T.tocsc()
    sel_i, sel_j = [], []
    for s in range(0, n, block):
        e = min(n, s + block)
        order = _top(bow, bt, np.arange(s, e), k, r)
        ii = np.repeat(np.arange(s, e), k)
        jj = order.reshape(-1)
        sel_i.append(ii)
        sel_j.append(jj)
    i = np.concatenate(sel_i)
    j = np.concatenate(sel_j)
    a, b = np.minimum(i, j), np.maximum(i, j)
    if keep is not None:
        keep[a, b] = True
        out = np.argwhere(keep)
    else:
        out = np.unique(np.stack([a, b], 1), axis=0)
    return out.astype(np.int64)


def _top(bow, bt, rows: np.ndarray, k: int, r: np.ndarray | None) -> np.ndarray:
    """``(len(rows), k)``: for each image of ``rows``, its ``k`` most similar other images, best first -- cosine of
    the rows of ``bow`` (``bt`` = ``bow.T`` as CSC), or CSLS ``2 cos - r_i - r_j`` with the hub scores ``r``; ties go
    to the smaller index (stable sort). :func:`shortlist` and :func:`most_similar` rank with it."""
    sim = _similarity(bow, bt, rows)
    if r is not None:
        sim = 2.0 * sim - r[rows, None] - r[None, :]
    return np.argsort(-sim, axis=1, kind="stable")[:, :k]


# ---------------------------------------------------------------------------------------------------- the stage
def _key(source, names, cfg: RetrievalConfig) -> str:
    h = hashlib.sha256()
    nf = [int(source.num_features(n)) for n in names]
    vocab = {k: v for k, v in asdict(cfg).items()
             if k in ("coarse", "fine", "sample", "seed", "niter", "train_images")}
    h.update(json.dumps([list(map(str, names)), nf, vocab, 1]).encode())
    return h.hexdigest()[:32]


def _load_cache(path: Path | None, key: str) -> dict | None:
    if path is None or not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            return {k: z[k] for k in z.files}
    except Exception:  # noqa: BLE001 - an unreadable cache is rebuilt (and reported as not reused)
        return None


def retrieval_pairs(source, names=None, config: RetrievalConfig | dict | None = None, *,
                    cache: str | os.PathLike | None | bool = True) -> RetrievalResult:
    """The retrieval shortlist of ``source``'s images (module doc).

    Args:
        source: a feature source (``names()``, ``num_features(name)``, ``load(name).descriptors``).
        names: the images to pair (default: ``source.names()``).
        config: :class:`RetrievalConfig` or a dict of its fields.
        cache: ``True``: :func:`retrieval_cache_path` of the source; a path; ``None`` / ``False``: no file.

    Returns:
        :class:`RetrievalResult` with ``pairs`` (name pairs, exhaustive order of ``names``) and ``info``:
        ``k, images, pairs, words, sample, reused ("none" | "vocabulary" | "all"), time_s, vocabulary_s,
        assign_s, shortlist_s, cache``.
    """
    from threadpoolctl import threadpool_limits

    cfg = config_from(RetrievalConfig, config)
    with threadpool_limits(1):  # small matrix products: BLAS threads cost more than they give (3.4x on a busy box)
        return _retrieval_pairs(source, names, cfg, cache)


def _retrieval_pairs(source, names, cfg: RetrievalConfig, cache) -> RetrievalResult:
    names = list(source.names() if names is None else names)
    path = retrieval_cache_path(source) if cache is True else (Path(cache) if cache else None)
    t0 = time.perf_counter()
    key = _key(source, names, cfg)
    cached = _load_cache(path, key)
    info = dict(k=cfg.k, images=len(names), words=cfg.words, coarse=cfg.coarse, fine=cfg.fine, sample=cfg.sample,
                seed=cfg.seed, cache=str(path) if path else None, vocabulary_s=0.0, assign_s=0.0, shortlist_s=0.0)
    if cached is not None and int(cached["k"]) == cfg.k and int(cached.get("hub_k", -1)) == cfg.hub_k:
        idx = cached["pairs"]
        info.update(reused="all")
    else:
        coarse, fine, bow = _bag(source, names, cfg, cached, info)
        t = time.perf_counter()
        idx = shortlist(bow, cfg.k, cfg.block, cfg.hub_k)
        info["shortlist_s"] = time.perf_counter() - t
        _save(path, key, cfg.k, cfg.hub_k, coarse, fine, idx, bow, names)
    pairs = tuple((names[int(i)], names[int(j)]) for i, j in idx)
    info.update(pairs=len(pairs), time_s=time.perf_counter() - t0)
    return RetrievalResult(pairs, info)


def _bag(source, names, cfg: RetrievalConfig, cached: dict | None, info: dict):
    """``(coarse, fine, bow)``: from the cache when it holds them (``info["reused"] = "vocabulary"``), else the
    vocabulary trained and every image's words assigned (``"none"``; the stage times into ``info``)."""
    if cached is not None:
        import scipy.sparse as sp

        bow = sp.csr_matrix((cached["bow_data"], cached["bow_indices"], cached["bow_indptr"]),
                            shape=tuple(cached["bow_shape"]))
        info.update(reused="vocabulary")
        return cached["coarse"], cached["fine"], bow
    t = time.perf_counter()
    coarse, fine = train_vocabulary(source, names, cfg)
    info["vocabulary_s"] = time.perf_counter() - t
    t = time.perf_counter()
    counts = []
    bar = _bar(len(names), "retrieval: visual words", cfg.progress)
    for n in names:
        w = assign_words(_descriptors(source, n), coarse, fine)
        u, c = np.unique(w, return_counts=True)
        counts.append((u, c))
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    bow = bag_of_words(counts, cfg.words)
    info["assign_s"] = time.perf_counter() - t
    info.update(reused="none")
    return coarse, fine, bow


def _save(path: Path | None, key: str, k: int, hub_k: int, coarse, fine, idx, bow, names) -> None:
    if path is not None:
        from ..features import atomic_savez

        atomic_savez(path, key=np.array(key), k=np.array(k), hub_k=np.array(hub_k), coarse=coarse, fine=fine,
                     pairs=idx, bow_data=bow.data, bow_indices=bow.indices, bow_indptr=bow.indptr,
                     bow_shape=np.array(bow.shape), names=np.array(names, dtype=str))


def most_similar(source, queries, k: int, names=None, config: RetrievalConfig | dict | None = None, *,
                 cache: str | os.PathLike | None | bool = True) -> dict:
    """``{query: [the k images most similar to it, best first]}`` for the images ``queries`` among ``names``
    (default ``source.names()``), ranked as :func:`shortlist` ranks them (CSLS with ``hub_k``, ties to the smaller
    index). The bag of words comes from the retrieval cache when its key matches (the ``retrieval`` pairs of the
    same collection computed it), else it is computed -- and saved there, so a later ``retrieval`` run reuses it.
    Used by the second look's orphan round (:mod:`guidedmatch.collection.second_look`).
    """
    from threadpoolctl import threadpool_limits

    cfg = config_from(RetrievalConfig, config)
    names = list(source.names() if names is None else names)
    index = {n: i for i, n in enumerate(names)}
    unknown = [q for q in queries if q not in index]
    if unknown:
        raise InputError(f"most_similar: {len(unknown)} query image(s) not among the names, e.g. {unknown[0]!r}")
    path = retrieval_cache_path(source) if cache is True else (Path(cache) if cache else None)
    key = _key(source, names, cfg)
    cached = _load_cache(path, key)
    with threadpool_limits(1):
        coarse, fine, bow = _bag(source, names, cfg, cached, {})
        if cached is None:  # no shortlist yet: k = 0 (a retrieval run computes its own and keeps the vocabulary)
            _save(path, key, 0, -1, coarse, fine, np.zeros((0, 2), np.int64), bow, names)
        r = hub_scores(bow, cfg.hub_k, cfg.block) if cfg.hub_k > 0 else None
        rows = np.array([index[q] for q in queries], np.int64)
        order = _top(bow, bow.T.tocsc(), rows, max(0, min(int(k), len(names) - 1)), r)
    return {q: [names[int(j)] for j in o] for q, o in zip(queries, order)}
