"""One IVF coarse quantizer for every image of a collection (``CollectionConfig.shared_quantizer``; opt-in).

The unguided start of every pair searches an approximate index of image 2 (:mod:`guidedmatch.prepared`): first the
coarse step -- which ``nprobe`` of image 2's k-means cells each image-1 query probes, a GEMM of the queries against
image 2's centroids -- then faiss scans those cells. With a k-means per image, that coarse step is paid again in every
pair. With one quantizer for the collection, each image's cells are computed once, for all its pairs
(:meth:`~guidedmatch.prepared.PreparedImage.query_cells`), and no image trains a k-means of its own: fox (67 images,
COLMAP's SIFT, 200 random pairs in one thread) 5.7-5.8 -> 5.2-5.3 s, inliers -0.2 %, the same number of verified
pairs; whole runs 0.52x -> 0.48x COLMAP's matching time. It is not the default: fox's poses came out worse with it
(median 0.496 deg / AUC@1 0.467 over three mapper seeds, against 0.478 / 0.494 with per-image k-means and COLMAP's
0.481 / 0.490; docs/collections.md).

The quantizer is trained once per run in the calling process: k-means (faiss, seed 0, one thread, so the same
centroids whatever the thread count) of ``PER_LIST`` descriptors per cell, ``ITERS`` iterations, sampled evenly from
at most ``SAMPLE_IMAGES`` images spread over the source's sorted names -- all the source's images, not only the pairs
still to match, so a resumed run and the second look get the same quantizer; ``nlist`` is the per-image rule
(``PreparedConfig.nlist_factor * sqrt(N)``) at the sampled images' median ``N``. ``"auto"`` uses it from
``MIN_IMAGES`` images on (below, the per-image k-means of a few images costs less than training one for them); it is
never used for binary descriptors, images under ``PreparedConfig.min_features``, or a matcher that does not search
an index (``start="paper"``, ``unguided_index=False``). The report says which (``totals["quantizer"]``).
"""
from __future__ import annotations

import contextlib
import math
import threading
import time
import weakref

import numpy as np

from ..errors import InputError

__all__ = ["SharedQuantizer", "train_quantizer", "collection_quantizer", "train_meanwhile", "MIN_IMAGES", "SAMPLE_IMAGES",
           "PER_LIST", "ITERS"]

MIN_IMAGES = 16      # "auto": a shared quantizer from this many images in the source on
SAMPLE_IMAGES = 32   # images the training sample is drawn from (evenly spread over the sorted names)
PER_LIST = 100       # training descriptors per cell (fox: 20 -> inliers -0.8 %, 100 -> -0.2 % against per-image)
ITERS = 25           # k-means iterations (fox: 0.24 s for 171 cells, one thread)

_LAST: list = []     # [(weakref to the source, key, quantizer, info)]: the second look reuses the first pass's


class SharedQuantizer:
    """One IVF coarse quantizer for every image of a collection (:func:`train_quantizer`).

    With their own k-means per image, the coarse step of every search (which ``nprobe`` of image 2's cells each
    image-1 query probes) is a GEMM of the queries against image 2's centroids, once per pair. With one quantizer
    for all images, each image's cells are computed once (:meth:`PreparedImage.query_cells`) and every pair looks them
    up; no image trains its own k-means. Plain arrays: pickled with each task of a collection run.

    Attributes:
        centroids: ``(nlist, D) float32``. sqnorms: their squared norms. token: a digest of the centroids (two
        images share the quantizer when their tokens are equal, also after pickling).
    """

    def __init__(self, centroids: np.ndarray):
        import hashlib

        c = np.ascontiguousarray(centroids, np.float32)
        if c.ndim != 2 or not len(c) or not np.isfinite(c).all():
            raise InputError(f"a shared quantizer needs finite (nlist, D) centroids, got shape {c.shape}")
        self.centroids = c
        self.sqnorms = np.einsum("ij,ij->i", c, c)
        self.token = hashlib.sha1(c.tobytes()).hexdigest()[:16]

    @property
    def nlist(self) -> int:
        return len(self.centroids)

    @property
    def dim(self) -> int:
        return self.centroids.shape[1]

    def __repr__(self) -> str:
        return f"SharedQuantizer(nlist={self.nlist}, dim={self.dim}, token={self.token!r})"


def train_quantizer(sample: np.ndarray, nlist: int, seed: int = 0, iters: int = 25) -> SharedQuantizer:
    """k-means (faiss, seeded: the same centroids for the same sample) of float descriptors ``sample (S, D)`` into
    ``nlist`` cells: the :class:`SharedQuantizer` of a collection. faiss subsamples to 256 points per cell."""
    import faiss

    x = np.ascontiguousarray(sample, np.float32)
    nlist = int(nlist)
    if x.ndim != 2 or len(x) < nlist or nlist < 1:
        raise InputError(f"train_quantizer needs at least nlist = {nlist} descriptors, got shape {x.shape}")
    km = faiss.Kmeans(x.shape[1], nlist, niter=int(iters), seed=int(seed), min_points_per_centroid=1,
                      max_points_per_centroid=256)
    km.train(x)
    return SharedQuantizer(km.centroids)


def collection_quantizer(source, matcher, mode: str = "auto"):
    """``(SharedQuantizer or None, info)`` for a run over ``source`` with ``matcher`` (a
    :class:`~guidedmatch.config.MatcherConfig`); ``info`` says what was trained, or why none was."""
    if mode == "off":
        return None, dict(used=False, why="shared_quantizer='off'")
    if matcher.start == "paper" or not matcher.unguided_index:
        return None, dict(used=False, why="the matcher searches no index (start='paper' or unguided_index=False)")
    names = sorted(source.names())
    if mode == "auto" and len(names) < MIN_IMAGES:
        return None, dict(used=False, why=f"{len(names)} images, fewer than {MIN_IMAGES} (shared_quantizer='auto')")
    if not names:
        return None, dict(used=False, why="no images")
    pick = [names[i] for i in sorted(set(np.linspace(0, len(names) - 1, min(SAMPLE_IMAGES, len(names)))
                                         .round().astype(int).tolist()))]
    key = (tuple(pick), tuple(int(source.num_features(n)) for n in pick), PER_LIST, ITERS)
    for ref, k, q, info in _LAST:
        if ref() is source and k == key:
            return q, dict(info, reused=True)
    return _train(source, pick, key)


def _train(source, pick, key):
    from ..prepared import PreparedConfig, _faiss_threads

    t0 = time.perf_counter()
    descs = [source.load(n).descriptors for n in pick]
    if any(d.dtype == np.uint8 for d in descs):
        return None, dict(used=False, why="binary descriptors (no approximate index)")
    if len({d.shape[1] for d in descs}) > 1:
        return None, dict(used=False, why="descriptors of different lengths")
    pc = PreparedConfig()
    median_n = float(np.median([len(d) for d in descs]))
    if median_n < max(pc.min_features, 2):
        return None, dict(used=False, why=f"median {median_n:.0f} features per image, fewer than "
                                          f"min_features = {pc.min_features} (no approximate index)")
    nlist = max(1, int(round(pc.nlist_factor * math.sqrt(median_n))))
    per = int(math.ceil(PER_LIST * nlist / len(descs)))
    rng = np.random.default_rng(0)
    sample = np.concatenate([d if len(d) <= per else d[np.sort(rng.choice(len(d), per, replace=False))]
                             for d in descs]).astype(np.float32)
    if len(sample) < nlist:
        return None, dict(used=False, why=f"{len(sample)} descriptors sampled, fewer than {nlist} cells")
    with _faiss_threads(1):
        q = train_quantizer(sample, nlist, seed=0, iters=ITERS)
    info = dict(used=True, nlist=nlist, images=len(pick), samples=int(len(sample)), token=q.token,
                train_s=round(time.perf_counter() - t0, 3))
    try:
        _LAST[:] = [(weakref.ref(source), key, q, info)]
    except TypeError:  # a source that takes no weak reference: trained again next time
        _LAST[:] = []
    return q, info


@contextlib.contextmanager
def train_meanwhile(source, matcher, mode: str = "auto"):
    """Train the run's quantizer (:func:`collection_quantizer`) in a thread while the block runs -- a local cluster
    starting, whose worker processes the client only waits for -- and wait for it at the end; the run's own call
    then finds it trained. An error is left for that call to raise (it is only a head start). ``"off"``: no thread."""
    if mode == "off":
        yield
        return

    def work():
        with contextlib.suppress(Exception):
            collection_quantizer(source, matcher, mode)

    t = threading.Thread(target=work, name="guidedmatch-quantizer", daemon=True)
    t.start()
    try:
        yield
    finally:
        t.join()
