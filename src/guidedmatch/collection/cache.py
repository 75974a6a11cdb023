"""The image cache of a collection run: loaded (prepared) images, one LRU per process, bounded in bytes.

Each process that matches pairs (a worker process of a Dask cluster, or this process for an in-process run) keeps
one :class:`_ImageCache` per run: an image is loaded from the feature source and prepared
(:func:`guidedmatch.prepared.prepare`) on a miss, reused by every later pair of that image, and evicted least
recently used first -- but images without a built approximate index before those with one (a reload is a read, a
re-index ~1 s at 60k features). The two images of the pair being matched are never evicted. :class:`_TaskSpec` is
what every task of the run carries besides its pairs (the cache's bound among it).
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import MatcherConfig


@dataclass(frozen=True)
class _TaskSpec:
    """What every task needs besides its pairs (small; pickled with each task)."""

    run_id: str
    mode: str
    matcher: MatcherConfig
    cache_bytes: int
    single_thread: bool
    quantizer: Any = None  # the run's guidedmatch.collection.quantizer.SharedQuantizer, or None
    cache_key: str = ""    # the process's image cache to use: "" -- the run's own (run_id); else one shared by the
                           # stages of a SharedCluster that load the same images the same way (dask_backend)
    memo_below: int = -1   # >= 0: pairs not verified or with fewer inliers return their start memo (memos.py)

    @property
    def cache_id(self) -> str:
        """The key of this run's image cache in a process."""
        return self.cache_key or self.run_id


@dataclass
class _CachedImage:
    features: Any          # guidedmatch.features.Features
    prepared: Any          # what is passed to the matcher (PreparedImage when available, else the Features)
    nbytes: int


def _prepare_fn():
    """``guidedmatch.prepared.prepare`` when that module exists, else None (Features are matched directly)."""
    try:
        from ..prepared import prepare
    except ImportError:
        return None
    return prepare


def _has_prepared() -> bool:
    """Whether ``guidedmatch.prepared`` exists, without importing it: importing it imports Numba (~0.15 s), which a
    client that only schedules and writes never needs (that import had been 0.15 s of the end of every cluster run).
    """
    import importlib.util

    return importlib.util.find_spec("guidedmatch.prepared") is not None


def _nbytes(obj) -> int:
    n = getattr(obj, "nbytes", None)
    if isinstance(n, (int, np.integer)):
        return int(n)
    total = 0
    for name in ("keypoints", "descriptors", "scales", "angles", "responses"):
        a = getattr(obj, name, None)
        if isinstance(a, np.ndarray):
            total += a.nbytes
    return total


def _prepared_nbytes(prep) -> int:
    """Estimated bytes of a prepared image beyond its features: its own arrays (kernel-form descriptors, norms) plus
    a float32 copy of the descriptors for the approximate index it may build (faiss IVF-Flat stores the vectors)."""
    total = sum(v.nbytes for k, v in vars(prep).items() if isinstance(v, np.ndarray))
    f = getattr(prep, "features", None)
    if f is not None and f.descriptors.dtype != np.uint8:
        total += 4 * f.descriptors.size
    return total


class _ImageCache:
    """Per-process LRU of loaded (prepared) images of one run, bounded by ``cache_bytes`` (the memory bound of
    :mod:`guidedmatch.collection.engine`)."""

    def __init__(self, source, spec: _TaskSpec):
        self.source = source
        self.spec = spec
        self.items: collections.OrderedDict[str, _CachedImage] = collections.OrderedDict()
        self.bytes = 0
        self.hits = 0
        self.loads = 0
        self.prefetch_loads = 0  # loads made by _prefetch_indexes (not by a pair)
        self.load_s = 0.0
        self.lock = threading.Lock()
        self.prepare = _prepare_fn()

    def get(self, name: str, pinned: tuple[str, ...], count_hit: bool = True) -> _CachedImage:
        """The cached image (loaded and prepared on a miss); ``count_hit=False``: a hit is not counted (a prefetch
        reaching an image a pair already loaded is not a reuse)."""
        with self.lock:
            item = self.items.get(name)
            if item is not None:
                self.items.move_to_end(name)
                self.hits += count_hit
                return item
            t0 = time.perf_counter()
            feats = self.source.load(name)
            prepared = feats if self.prepare is None else self.prepare(feats, quantizer=self.spec.quantizer)
            extra = 0 if prepared is feats else _prepared_nbytes(prepared)
            item = _CachedImage(feats, prepared, _nbytes(feats) + extra)
            self.load_s += time.perf_counter() - t0
            self.loads += 1
            self.prefetch_loads += not count_hit
            self.items[name] = item
            self.bytes += item.nbytes
            self._evict(pinned)
            return item

    def _evict(self, pinned) -> None:
        """Least recently used first, but images without a built approximate index first of all: reloading one
        is a read (~0.05 s at 60k features), re-indexing one ~1 s (see
        :func:`~guidedmatch.collection.planning.plan_tasks` on sweeps)."""
        for cheap_only in (True, False):
            for key in list(self.items):
                if self.bytes <= self.spec.cache_bytes:
                    return
                if key in pinned or (cheap_only and getattr(self.items[key].prepared, "_index", None) is not None):
                    continue
                self.bytes -= self.items.pop(key).nbytes

    def counters(self) -> tuple[int, int, float]:
        with self.lock:
            return self.hits, self.loads, self.load_s
