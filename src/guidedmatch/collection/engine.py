"""Collection engine: match every pair of a pair list from a feature source into a sink, locally or on Dask.

:func:`match_collection` is the scheduler behind ``guidedmatch colmap`` / ``guidedmatch hloc``. A
:class:`~guidedmatch.collection.sources.FeatureSource` gives the images' features (a COLMAP database, an hloc
``features.h5``), a pair list says which pairs to match and a
:class:`~guidedmatch.collection.sinks.MatchSink` stores each pair's matches and two-view geometry.

Where the pairs run (``CollectionConfig.workers`` / ``scheduler`` / the ``client`` argument)
-------------------------------------------------------------------------------------------
* ``client=`` a :class:`distributed.Client` (or ``scheduler="tcp://host:8786"``): the running Dask cluster; the
  workers read the features themselves from the source (a path: shared storage) and need ``guidedmatch``
  installed.
* ``workers=N`` (N >= 1): a :class:`distributed.LocalCluster` of N single-threaded worker processes
  (``threads_per_worker=1, processes=True``; NumPy / Numba / OpenCV limited to one thread each), started and
  stopped by the call.
* ``workers=0``: in this process, ``threads`` pairs at once (default one per usable core) on a thread pool; each
  pair's Numba kernels and faiss run single-threaded, the pairs share the loaded images (one copy, one cache).
* ``workers=None`` (default, "auto"): in this process when the job is not huge, else a local cluster with one worker
  per usable core. **Rule**: in-process when the work ``W = sum over the pairs to do of (n1 + n2)`` (features of
  both images) is at most ``inprocess_max_work`` (default 20,000,000 -- about 1,200 pairs of 8192 features), or
  when fewer than 2 cores are usable. Measured on the 2-core development machine (Herz-Jesus-P8, 28 pairs, one
  run each, `guidedmatch colmap DB --pairs exhaustive`): at 68k features per image (W = 3.8 M) 2 threads in-process
  took 11.1 s, a local cluster of 2 worker processes 17.7 s (its start / stop ~2 s, and the two processes' pairs
  ran slower side by side than two threads sharing one copy of the images: 25.3 s vs 19.4 s of matching summed
  over pairs); at 11.4k (W = 0.64 M) 2 threads 2.5 s vs 3.0 s for one thread. Above the threshold the run is
  long enough to pay the cluster's start-up for its isolation (a pair that crashes its process costs a worker,
  not the run).

Scheduling (locality)
---------------------
Pairs are grouped by an *anchor* image (of the two images of a pair, the one first in source order) and cut into
tasks of at most ``chunk_pairs`` pairs sharing the anchor. Each worker process keeps an LRU cache of loaded
(prepared) images; a task loads its anchor once and reuses it for all its pairs. Each anchor also gets a tiny
*token* task that loads the anchor into some worker's cache; the anchor's pair tasks depend on that token, so
Dask's scheduler runs them on the worker holding it (data locality; work stealing still feeds an idle worker) and
an image's prepared state is reused across that image's pairs. The client submits tasks in anchor order, spread
over the first anchors (at most ``tasks_per_worker`` tasks of one anchor in flight), with at most
``workers * tasks_per_worker`` tasks in flight in total. With exhaustive pairs and a cache holding the collection,
every worker loads every image at most once. A collection larger than an in-process cache runs in *sweeps* over
resident blocks of images, so that each image is indexed once (:func:`plan_tasks`); the cache evicts images whose
approximate index is not built before those whose index is (a reload is a read, a re-index ~1 s at 60k features). Features travel from the source to a worker once per cache miss (never
with each pair): the source object is picklable (paths only) and each worker opens it once per run.

Results stream back to ONE writer -- the caller's sink in this process -- in completion order; each
``sink.write`` is one transaction, so the sink always holds complete pairs only.

Start-up (in-process, threads >= 2)
-----------------------------------
Numba's CPU target is set up once per process (~0.13 s holding the GIL); the set-up would also import
``scipy.linalg`` (another 0.12-0.14 s) for a BLAS probe none of our kernels needs, which a process of ours skips
(``guidedmatch._runtime.without_numba_blas_probe``). One pool thread does that first (:func:`_load_numba`);
meanwhile the other loads the images the queued pairs search, in the order they are reached, and builds their
approximate indexes (faiss releases the GIL), until the first pair has finished; the report's
``prefetched_images`` / ``prefetched_indexes`` count them. Every index built this way is one a queued pair needs,
so it is work moved earlier, not added. Herz-Jesus-P8, 8192 SIFT, 28 pairs, 10 alternating fresh runs each of
``guidedmatch colmap DB --pairs exhaustive`` (``tools/ab_collection.py``): the prefetch 1.99 -> 1.86 s, the Numba
set-up first 1.61 -> 1.54 s, the set-up without SciPy's probe 1.61 -> 1.49 s (medians; docs/collections.md).

Memory bound
------------
* Client: the tasks in flight, at most ``workers * tasks_per_worker * chunk_pairs`` pair results, each
  ``M * 21`` bytes (``(M, 2) int64`` matches + ``(M,) float32`` scores + ``(M,)`` inlier mask, ``M <= min(n1,
  n2)``): with 2 workers, 2 tasks each, 16 pairs per task and 8192 features, <= 11 MB, whatever the collection
  size. Plus the pair list itself (names, ~200 bytes per pair), the sink's done-pair set and at most
  ``report_max_pairs`` per-pair dicts kept in the report (all of them go to ``log_path``). In-process with
  ``threads`` threads: at most ``2 * threads`` pairs in flight (their matcher working memory and results).
* Each worker process (and this process when in-process): the image cache, at most ``cache_mb`` MB of loaded
  images (estimated as their array bytes: keypoints 16 B + descriptors 4 B x D per feature, plus, with
  ``guidedmatch.prepared``, the prepared image's arrays and 4 B x D for its approximate index: ~1.2 KB per SIFT
  feature in all, ~10 MB per 8192-feature image, so the 1024 MB default holds ~100 such images),
  but never fewer than the two images of the pair being matched; plus the matcher's
  working memory for one pair.

Resume and failures
-------------------
Pairs in ``sink.done_pairs()`` are skipped (reported as ``skipped``). A pair whose task raises or whose worker
dies is retried ``retries`` times (alone, as a one-pair task), then reported in ``failed`` with the reason -- it is
not written, so a rerun tries it again. Matching is deterministic (seeded), so a run interrupted at any moment and
rerun gives the same matches as an uninterrupted run.

Each pair: :func:`guidedmatch.matcher.match` (``mode``, ``matcher`` config), then the two-view verdict: the
matcher's own ``result.geometry`` (every matcher result carries one; its time is part of ``match_s``).
"""
from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import pickle
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._runtime import freeze_gc_at_exit, mark_own_process, without_numba_blas_probe
from ..config import MODES, MatcherConfig
from ..errors import ConfigError, GuidedMatchError, InputError
from ..geometry import TwoViewGeometry
from ..validation import check_bool, check_choice, check_number, config_from

__all__ = ["CollectionConfig", "CollectionReport", "PairOutcome", "match_collection", "plan_tasks",
           "COLLECTION_MATCHER_DEFAULTS", "collection_matcher_config",
           "INPROCESS_RULE"]

#: the auto rule, as reported in ``CollectionReport.totals["backend_rule"]``
INPROCESS_RULE = "in-process (threads) when sum over pairs of (n1 + n2) <= inprocess_max_work or < 2 usable cores"

#: environment of the worker processes of a local cluster: one thread per process for every library
_SINGLE_THREAD_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                      "MKL_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


#: matcher settings a collection changes from :class:`~guidedmatch.config.MatcherConfig`'s one-off defaults (a dict
#: given as ``CollectionConfig.matcher`` is applied on top of these; a ``MatcherConfig`` instance is taken as it is).
#: ``exact_rent=0``: every image of a collection is indexed once for all its pairs (its ``PreparedImage`` is cached),
#: so the unguided start searches the index from its first query instead of renting exact search first -- the rent
#: only pays off for one-off pairs. Herz-Jesus-P8 ~40k SIFT, 28 pairs with prepared images: 4.05 -> 3.61 s, GT
#: inliers 186,104 -> 188,491, same verdicts; the 50k COLMAP database: ~0.1 s CPU less per pair (docs/collections.md).
COLLECTION_MATCHER_DEFAULTS = {"exact_rent": 0.0}


def collection_matcher_config(value=None) -> MatcherConfig:
    """The matcher settings of a collection: ``value`` (None, a dict of :class:`MatcherConfig` fields, or an
    instance, taken as it is) over :data:`COLLECTION_MATCHER_DEFAULTS`."""
    if isinstance(value, MatcherConfig):
        return value
    if value is None or isinstance(value, dict):
        return config_from(MatcherConfig, {**COLLECTION_MATCHER_DEFAULTS, **(value or {})})
    return config_from(MatcherConfig, value)  # raises the usual ConfigError


# ============================================================================================ config / report
@dataclass(frozen=True)
class CollectionConfig:
    """Settings of :func:`match_collection` (see the module doc for the scheduling and the memory bound).

    ``matcher`` accepts a dict of its fields.
    """

    mode: str = "so+epi+ia"                    # matcher mode for every pair (guidedmatch.matcher.MODES)
    matcher: MatcherConfig = field(default_factory=lambda: collection_matcher_config())  # matcher settings: a dict
                                               # of fields is applied over COLLECTION_MATCHER_DEFAULTS
    workers: int | None = None                 # None: auto (module doc); 0: in-process; N: local cluster of N processes
    threads: int | None = None                 # in-process: pairs matched at once by this many threads (None: 1 per core)
    scheduler: str | None = None               # address of a running Dask scheduler, e.g. "tcp://10.0.0.1:8786"
    retries: int = 1                           # extra attempts of a failed pair before it is reported failed
    progress: bool = True                      # tqdm progress bar (pairs/s, ETA) on stderr
    log_path: str | None = None                # JSON lines: one line per pair, then one summary line (appended)
    chunk_pairs: int = 16                      # pairs per task; a task's pairs share one anchor image
    tasks_per_worker: int = 2                  # tasks in flight per worker (one running, one queued): bounds memory
    cache_mb: float = 1024.0                   # per worker process: LRU bound on cached images, MB (module doc)
    inprocess_max_work: int = 20_000_000       # auto: in-process when sum over pairs of (n1 + n2) is at most this
    report_max_pairs: int = 100_000            # per-pair dicts kept in the report (the log gets all of them)

    def __post_init__(self) -> None:
        own = "CollectionConfig"
        check_choice(own, "mode", self.mode, MODES)
        object.__setattr__(self, "matcher", collection_matcher_config(self.matcher))
        check_number(own, "workers", self.workers, lo=0, integer=True, allow_none=True)
        check_number(own, "threads", self.threads, lo=1, integer=True, allow_none=True)
        if self.scheduler is not None and (not isinstance(self.scheduler, str) or not self.scheduler.strip()):
            raise ConfigError(f"{own}.scheduler must be an address like 'tcp://host:8786' or None; "
                              f"got {self.scheduler!r}")
        if self.scheduler is not None and self.workers is not None:
            raise ConfigError(f"{own}: give workers (a local cluster) or scheduler (a running one), not both")
        check_number(own, "retries", self.retries, lo=0, integer=True)
        check_bool(own, "progress", self.progress)
        if self.log_path is not None and not isinstance(self.log_path, (str, os.PathLike)):
            raise ConfigError(f"{own}.log_path must be a path or None; got {self.log_path!r}")
        check_number(own, "chunk_pairs", self.chunk_pairs, lo=1, integer=True)
        check_number(own, "tasks_per_worker", self.tasks_per_worker, lo=1, integer=True)
        check_number(own, "cache_mb", self.cache_mb, lo=0)
        check_number(own, "inprocess_max_work", self.inprocess_max_work, lo=0, integer=True)
        check_number(own, "report_max_pairs", self.report_max_pairs, lo=0, integer=True)


@dataclass(frozen=True)
class CollectionReport:
    """What :func:`match_collection` did.

    Attributes:
        done: pairs matched and written in this run.
        skipped: pairs already in the sink (``sink.done_pairs()``), not matched again.
        failed: ``[((name1, name2), reason), ...]`` pairs that failed after ``retries`` retries (not written).
        per_pair: one dict per finished pair (done or failed; the first ``report_max_pairs``): names, features,
            matches, verdict, model, inliers, geometry source, times, worker, attempts, errors.
        totals: sums and run facts (backend and its rule, workers, work, matches, verified pairs, inliers, cache
            hits / loads, pairs/s, in-flight bound, ...).
        wall_s: wall time of the call, seconds (cluster start / stop included).
    """

    done: int
    skipped: int
    failed: list
    per_pair: list
    totals: dict
    wall_s: float

    @property
    def ok(self) -> bool:
        """True when no pair failed."""
        return not self.failed

    def to_dict(self) -> dict:
        """JSON-ready dict (pairs as lists)."""
        return dict(done=self.done, skipped=self.skipped,
                    failed=[dict(pair=list(p), reason=r) for p, r in self.failed],
                    per_pair=self.per_pair, totals=self.totals, wall_s=self.wall_s)

    def summary(self) -> str:
        """A few human-readable lines."""
        t = self.totals
        lines = [f"pairs      : {t.get('pairs', 0)} ({self.done} matched, {self.skipped} skipped as already done, "
                 f"{len(self.failed)} failed)",
                 f"backend    : {t.get('backend')} ({_workers_text(t)}); {t.get('backend_reason')}",
                 f"matches    : {t.get('matches', 0)}; verified pairs {t.get('verified_pairs', 0)} of {self.done}, "
                 f"inlier matches {t.get('inliers', 0)}",
                 f"time       : {self.wall_s:.2f} s wall ({t.get('pairs_per_s', 0.0):.2f} pairs/s matched), "
                 f"matching (verdicts included) {t.get('match_s', 0.0):.2f} s summed over pairs"]
        if t.get("sweeps"):
            lines.append(f"cache      : the images exceed cache_mb {t.get('cache_mb')}: {t['sweeps']} sweeps over "
                         f"resident blocks, {t.get('image_loads', 0)} image loads (a larger cache_mb / --cache-mb: "
                         "fewer)")
        if t.get("startup_s"):
            lines.append(f"cluster    : start {t['startup_s']:.2f} s, stop {t.get('shutdown_s', 0.0):.2f} s")
        for (a, b), reason in self.failed[:5]:
            lines.append(f"failed     : {a} {b}: {reason}")
        if len(self.failed) > 5:
            lines.append(f"failed     : ... and {len(self.failed) - 5} more (see the log)")
        return "\n".join(lines)


# ============================================================================================ worker side
@dataclass(frozen=True)
class _TaskSpec:
    """What every task needs besides its pairs (small; pickled with each task)."""

    run_id: str
    mode: str
    matcher: MatcherConfig
    cache_bytes: int
    single_thread: bool


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
    """Per-process LRU of loaded (prepared) images of one run, bounded by ``cache_bytes`` (module doc)."""

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
            prepared = feats if self.prepare is None else self.prepare(feats)
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
        is a read (~0.05 s at 60k features), re-indexing one ~1 s (see :func:`plan_tasks` on sweeps)."""
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


_RUNS: dict[str, _ImageCache] = {}
_RUNS_LOCK = threading.Lock()


def _worker_cache(source, spec: _TaskSpec) -> _ImageCache:
    """The image cache of run ``spec.run_id`` in this worker process (created, with the source, on first use)."""
    with _RUNS_LOCK:
        cache = _RUNS.get(spec.run_id)
        if cache is None:
            if spec.single_thread:
                _limit_threads()
                freeze_gc_at_exit()  # a worker process of ours: its shutdown is part of the run's wall time
                mark_own_process()
                _load_numba()        # Numba's set-up without SciPy (guidedmatch._runtime), before the first pair
            cache = _RUNS[spec.run_id] = _ImageCache(source, spec)
        return cache


def _forget_run(run_id: str) -> bool:
    """Drop a run's cache in this process (called on every worker at the end of a run)."""
    with _RUNS_LOCK:
        cache = _RUNS.pop(run_id, None)
    if cache is not None:
        with contextlib.suppress(Exception):
            cache.source.close()
    return cache is not None


def _workers_text(t: dict) -> str:
    if t.get("backend") == "in-process":
        n = t.get("threads", 1)
        return f"{n} thread{'s' if n != 1 else ''}"
    return f"{t.get('workers')} worker(s)"


def _limit_threads() -> None:
    """One thread for OpenCV and faiss in a single-threaded worker process (Numba/BLAS: via the environment)."""
    with contextlib.suppress(Exception):
        import cv2

        cv2.setNumThreads(1)
    if "faiss" in sys.modules:
        with contextlib.suppress(Exception):
            sys.modules["faiss"].omp_set_num_threads(1)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "in-process"


@dataclass
class PairOutcome:
    """One pair's result as it travels from a worker to the writer.

    ``pairs (M, 2) int64`` / ``scores (M,) float32`` (the matcher's descriptor distances) and ``geometry`` are set
    when ``ok``; ``reason`` says why not otherwise. ``stats`` is the JSON-ready per-pair record.
    """

    name1: str
    name2: str
    ok: bool
    reason: str = ""
    pairs: np.ndarray | None = None
    scores: np.ndarray | None = None
    geometry: TwoViewGeometry | None = None
    stats: dict = field(default_factory=dict)


def _fallback_text(f) -> str:
    """A matcher :class:`~guidedmatch.results.Fallback` as one log string; the model update it happened at is named
    (the same step can degrade at several updates, e.g. an unusable Bougnoux focal at updates 1 and 2).

    >>> from guidedmatch.results import Fallback
    >>> _fallback_text(Fallback("focal1", "f = w + h used", 2)), _fallback_text(Fallback("early_exit", "budget"))
    ('focal1 (model update 2): f = w + h used', 'early_exit: budget')
    """
    at = getattr(f, "at_update", 0)
    return f"{f.what}{f' (model update {at})' if at else ''}: {f.reason}"


def _match_one(cache: _ImageCache, a: str, b: str, spec: _TaskSpec, worker: str) -> PairOutcome:
    from ..matcher import match

    t0 = time.perf_counter()
    wall0 = time.time()
    try:
        A = cache.get(a, (a, b))
        B = cache.get(b, (a, b))
        t1 = time.perf_counter()
        res = match(A.prepared, B.prepared, spec.mode, spec.matcher)
        t2 = time.perf_counter()
        geom = res.geometry
    except Exception as exc:  # noqa: BLE001 - reported per pair, retried by the client, never silently lost
        return PairOutcome(a, b, False, f"{type(exc).__name__}: {exc}",
                           stats=dict(worker=worker, time_s=time.perf_counter() - t0))
    st = res.stats
    stats = dict(n1=len(A.features), n2=len(B.features), matches=len(res), verdict=geom.verdict, model=geom.model,
                 inliers=int(geom.num_inliers), comparisons=getattr(st, "comparisons", None),
                 fallbacks=[_fallback_text(f) for f in getattr(st, "fallbacks", ())],
                 load_s=t1 - t0, match_s=t2 - t1, worker=worker, t_start=wall0, t_end=wall0 + (t2 - t0))
    return PairOutcome(a, b, True, "", res.pairs, res.distances, geom, stats)


def run_task(source, spec: _TaskSpec, pairs: list, *anchor_token) -> list[PairOutcome]:
    """A task: match ``pairs`` (list of ``(name1, name2)``) with the run's image cache of this process
    (``anchor_token``: the result of :func:`_anchor_token`, only there to place the task)."""
    cache = _worker_cache(source, spec)
    worker = _worker_name()
    return [_match_one(cache, a, b, spec, worker) for a, b in pairs]


def _cache_counters(run_id: str):
    cache = _RUNS.get(run_id)
    return None if cache is None else cache.counters()


# ============================================================================================ planning
#: estimated bytes one feature takes in a worker's image cache (keypoints, descriptors, the prepared image's arrays and
#: its approximate index): 1,180 B measured for a 61,615-feature COLMAP SIFT image (72.7 MB); used to plan the order
#: of the pairs before any image is loaded (:func:`resident_blocks`)
CACHE_BYTES_PER_FEATURE = 1200


def resident_blocks(order: list[str], sizes: dict, cache_bytes: float, streamed: int = 3) -> dict | None:
    """Split the images ``order`` (source order) into consecutive *resident blocks* when they do not all fit in a
    cache of ``cache_bytes``; ``None`` when they fit (then any order reuses every loaded image).

    Each block, plus ``streamed`` images of the largest size (the images streamed past it, in flight), fits in the
    cache; a block holds at least one image. Returns ``{name: block index}``.

    >>> resident_blocks(["a", "b", "c"], {"a": 10, "b": 10, "c": 10}, 100)    # all fit: no blocks
    >>> resident_blocks(list("abcdef"), dict.fromkeys("abcdef", 10), 50)      # 50 - 3 x 10: two images a block
    {'a': 0, 'b': 0, 'c': 1, 'd': 1, 'e': 2, 'f': 2}
    """
    if sum(sizes[n] for n in order) <= cache_bytes:
        return None
    budget = cache_bytes - streamed * max(sizes[n] for n in order)
    blocks, k, used = {}, 0, 0
    for n in order:
        if used and used + sizes[n] > budget:
            k, used = k + 1, 0
        blocks[n] = k
        used += sizes[n]
    return blocks


def plan_tasks(pairs: list[tuple[str, str]], names: list[str], chunk_pairs: int,
               anchor: str = "first", sizes: dict | None = None,
               cache_bytes: float | None = None) -> "collections.OrderedDict":
    """Group pairs by anchor image into tasks of <= ``chunk_pairs`` pairs.

    ``anchor="first"`` (in-process runs): the pair's image first in ``names`` order; anchors in source order.
    ``anchor="second"`` (worker processes): the pair's second image, whose approximate index the matcher's unguided
    start searches, so that each image's index is built by the one worker its tasks go to (anchoring on the first
    image made both workers index nearly every image: 50k set, 2 workers, 15 of 16 image loads), and anchors with
    the most pairs first (then source order): the last tasks are the small ones, so the workers finish together.
    In-process, the threads share one cache, and two threads on one anchor would wait for one index build: there
    "first" measured faster (50k set, 2 threads: 7.3 vs 8.0 s).

    Returns ``OrderedDict anchor -> deque of tasks`` (a task = list of pairs, in their given orientation).

    **Collections larger than the cache**, ``anchor="first"`` (``sizes``: estimated bytes per image,
    ``cache_bytes``: the image cache; see :func:`resident_blocks`): grouped by their first image, an anchor's pairs
    cycle through the other images, whose indexes the matcher searches, and an LRU cache smaller than the
    collection reloads -- and re-indexes -- an image for nearly every pair (the 50k set with a 300 MB cache, one
    thread: 31 loads for 28 pairs, 38.2 s instead of 19.7 s). Then the pairs run in *sweeps* instead: the images are
    cut into resident blocks that fit in the cache; sweep ``k`` runs every pair whose **second** image (the one whose
    approximate index is searched) lies in block ``k``, grouped by the pair's first image, which is *streamed* past
    the resident block (a load, no index). Each index is built once, each resident block loaded once, and a first
    image loaded once per sweep that needs it (same set: 32 loads, 22.4 s). The anchor key is then ``(k, first
    image)``, in sweep order, then source order; the pairs and their orientation are unchanged. ``anchor="second"``
    (worker processes) already keeps each task's searched image resident and streams the first images past it, in
    every worker; sweeps there would make each worker index every resident of the sweep (2 workers, same set:
    20.7 s with sweeps vs 16.0 s without), so worker plans are never swept.

    >>> pairs = [("a", "b"), ("a", "c"), ("b", "c"), ("a", "e"), ("d", "f"), ("f", "c"), ("a", "d")]
    >>> plan = plan_tasks(pairs, list("abcdef"), 4, sizes=dict.fromkeys("abcdef", 10), cache_bytes=50)
    >>> for key, tasks in plan.items():                           # resident blocks {a, b}, {c, d}, {e, f}
    ...     print(key, list(tasks))
    (0, 'a') [[('a', 'b')]]
    (1, 'a') [[('a', 'c'), ('a', 'd')]]
    (1, 'b') [[('b', 'c')]]
    (1, 'f') [[('f', 'c')]]
    (2, 'a') [[('a', 'e')]]
    (2, 'd') [[('d', 'f')]]

    >>> plan = plan_tasks([("a", "b"), ("a", "c"), ("b", "c"), ("c", "a")], ["a", "b", "c"], 2)
    >>> {k: [t for t in v] for k, v in plan.items()}
    {'a': [[('a', 'b'), ('a', 'c')], [('c', 'a')]], 'b': [[('b', 'c')]]}
    >>> plan = plan_tasks([("a", "b"), ("a", "c"), ("b", "c"), ("c", "a")], ["a", "b", "c"], 2, anchor="second")
    >>> {k: [t for t in v] for k, v in plan.items()}
    {'c': [[('a', 'c'), ('b', 'c')]], 'a': [[('c', 'a')]], 'b': [[('a', 'b')]]}
    """
    if anchor not in ("first", "second"):
        raise ValueError(f"anchor must be 'first' or 'second', got {anchor!r}")
    pos = {n: i for i, n in enumerate(names)}
    if anchor == "first" and sizes is not None and cache_bytes is not None and pairs:
        order = sorted({n for p in pairs for n in p}, key=pos.__getitem__)
        blocks = resident_blocks(order, sizes, cache_bytes)
        if blocks is not None:
            swept: dict[tuple, list] = collections.defaultdict(list)
            for a, b in pairs:
                swept[(blocks[b], a)].append((a, b))
            plan = collections.OrderedDict()
            for key in sorted(swept, key=lambda ka: (ka[0], pos[ka[1]])):
                g = sorted(swept[key], key=lambda p: pos[p[1]])
                plan[key] = collections.deque(g[i:i + chunk_pairs] for i in range(0, len(g), chunk_pairs))
            return plan
    groups: dict[str, list] = collections.defaultdict(list)
    for a, b in pairs:
        groups[b if anchor == "second" else (a if pos[a] <= pos[b] else b)].append((a, b))
    key = (lambda a: (-len(groups[a]), pos[a])) if anchor == "second" else pos.__getitem__
    plan = collections.OrderedDict()
    for a in sorted(groups, key=key):
        g = groups[a]
        plan[a] = collections.deque(g[i:i + chunk_pairs] for i in range(0, len(g), chunk_pairs))
    return plan


class _Queue:
    """Tasks waiting to run: one-pair retries first, then the planned tasks in anchor order, spread over the first
    anchors so that each anchor has at most ``per_anchor`` tasks in flight (the workers start on different
    anchors; an anchor's later tasks follow it to the worker holding it, see :func:`_run_dask`)."""

    def __init__(self, plan, per_anchor: int = 2):
        self.plan = plan                                   # anchor -> deque of tasks
        self.retry: collections.deque = collections.deque()  # one-pair retry tasks
        self.suspects: collections.deque = collections.deque()  # one-pair tasks to run alone on the cluster
        self.per_anchor = per_anchor
        self.inflight: collections.Counter = collections.Counter()  # anchor -> tasks in flight

    def __bool__(self) -> bool:
        return bool(self.retry) or bool(self.plan) or bool(self.suspects)

    def take(self, *, idle: bool = True) -> tuple[str | None, list] | None:
        """``(anchor, task)`` (anchor None for a retry task), or None when only suspects wait and the cluster is not
        ``idle`` (a suspect runs alone). Call :meth:`finished` with the anchor when the task is done."""
        if self.retry:
            return None, self.retry.popleft()
        if not self.plan:
            return (None, self.suspects.popleft()) if idle and self.suspects else None
        anchor = next((a for a in self.plan if self.inflight[a] < self.per_anchor), None)
        if anchor is None:
            anchor = next(iter(self.plan))
        tasks = self.plan[anchor]
        task = tasks.popleft()
        if not tasks:
            del self.plan[anchor]
        self.inflight[anchor] += 1
        return anchor, task

    def finished(self, anchor: str | None) -> bool:
        """Count a task of ``anchor`` done; True when the anchor has nothing left (queued or in flight)."""
        if anchor is None:
            return False
        self.inflight[anchor] -= 1
        if self.inflight[anchor] <= 0 and anchor not in self.plan:
            del self.inflight[anchor]
            return True
        return False


# ============================================================================================ writer
class _Writer:
    """The one writer: sink writes, retries, the failed list, per-pair log lines, progress and totals."""

    def __init__(self, sink, cfg: CollectionConfig, queue: _Queue, bar, log):
        self.sink, self.cfg, self.queue, self.bar, self.log = sink, cfg, queue, bar, log
        self.attempts: collections.Counter = collections.Counter()
        self.errors: dict[frozenset, list] = {}
        self.done = 0
        self.failed: list = []
        self.per_pair: list = []
        self.sums = collections.Counter()
        self.verdicts = collections.Counter()
        self.quarantined: set = set()

    def handle(self, out: PairOutcome, *, task_failed: bool = False, alone: bool = True) -> None:
        """Write a done pair; requeue or report a failed one.

        ``task_failed``: the whole task failed (its worker died, ...), not the pair's own code. When that task ran
        next to others (``alone=False``) the pair may be a bystander of another pair that killed the worker: it is
        put in quarantine (run later alone, one task on the whole cluster) without counting an attempt.
        """
        key = frozenset((out.name1, out.name2))
        if not out.ok:
            self.errors.setdefault(key, []).append(out.reason)
            if task_failed and not alone and key not in self.quarantined:
                self.quarantined.add(key)
                self.queue.suspects.append([(out.name1, out.name2)])
                return
            self.attempts[key] += 1
            if self.attempts[key] <= self.cfg.retries:
                (self.queue.suspects if task_failed else self.queue.retry).append([(out.name1, out.name2)])
                return
            self.failed.append(((out.name1, out.name2), out.reason))
            self._record(out, dict(status="failed", reason=out.reason))
            return
        self.attempts[key] += 1
        self.sink.write(out.name1, out.name2, out.pairs, out.scores, out.geometry)
        self.done += 1
        st = out.stats
        self.sums.update(matches=st["matches"], inliers=st["inliers"] if out.geometry else 0,
                         verified_pairs=int(bool(out.geometry)))
        for k in ("load_s", "match_s"):
            self.sums[k] += st[k]
        self.verdicts[st["verdict"]] += 1
        self._record(out, dict(status="done"))

    def _record(self, out: PairOutcome, extra: dict) -> None:
        key = frozenset((out.name1, out.name2))
        rec = dict(pair=[out.name1, out.name2], **extra, attempts=self.attempts[key], **out.stats)
        if self.errors.get(key):
            rec["errors"] = self.errors[key]
        if len(self.per_pair) < self.cfg.report_max_pairs:
            self.per_pair.append(rec)
        if self.log is not None:
            self.log.write(json.dumps(dict(event="pair", **rec), default=_json_default) + "\n")
            self.log.flush()
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=len(self.failed), refresh=False)


class _NoBar:
    """The progress bar's interface, doing nothing (``progress=False``)."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def set_postfix_str(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ============================================================================================ backends
def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _chunk_size(chunk_pairs: int, pairs: int, workers: int | None) -> int:
    """Pairs per task: ``chunk_pairs``, cut so that each of ``workers`` known workers gets >= 4 tasks (a short
    run split into a few big tasks leaves a worker idle at the end: 28 pairs in tasks of 16 ran 16 / 12 on 2 workers).

    >>> _chunk_size(16, 28, 2), _chunk_size(16, 10_000, 2), _chunk_size(16, 28, None)
    (4, 16, 16)
    """
    if not workers:
        return chunk_pairs
    return max(1, min(chunk_pairs, -(-pairs // (4 * workers))))


def _choose_backend(cfg: CollectionConfig, client, work: int) -> tuple[str, int | None, str]:
    """``(backend, n_workers, reason)`` with backend in-process | local-cluster | scheduler | client."""
    if client is not None:
        return "client", None, "attached to the given dask client"
    if cfg.scheduler is not None:
        return "scheduler", None, f"attached to the dask scheduler at {cfg.scheduler}"
    if cfg.workers == 0:
        return "in-process", 0, "workers=0"
    if cfg.workers is not None:
        return "local-cluster", cfg.workers, f"workers={cfg.workers}"
    cores = _usable_cores()
    if cores < 2:
        return "in-process", 0, f"auto: {cores} usable core"
    if work <= cfg.inprocess_max_work:
        return "in-process", 0, (f"auto: work {work:,} <= inprocess_max_work {cfg.inprocess_max_work:,} "
                                 f"({INPROCESS_RULE})")
    return "local-cluster", cores, (f"auto: work {work:,} > inprocess_max_work {cfg.inprocess_max_work:,}: "
                                    f"one single-threaded worker per usable core ({cores})")


def _run_inprocess(source, spec: _TaskSpec, queue: _Queue, writer: _Writer, threads: int = 1) -> dict:
    """The pairs in this process: one after the other (``threads=1``), or ``threads`` pairs at once on a thread pool
    (each pool thread runs Numba's kernels single-threaded, faiss runs single-threaded for the run; the image cache
    and the prepared images' index builds are locked). The caller's thread is the one writer either way, results
    are written in completion order, and the matches are the same as one after the other."""
    cache = _ImageCache(source, spec)
    if threads <= 1:
        while queue:
            anchor, task = queue.take()
            outs = [_match_one(cache, a, b, spec, "in-process") for a, b in task]
            queue.finished(anchor)
            for out in outs:
                writer.handle(out)
        hits, loads, load_s = cache.counters()
        return dict(cache_hits=hits, image_loads=loads, workers=1, threads=1)

    import concurrent.futures as cf

    from .. import kernels
    from ..prepared import _faiss_threads

    def one(a: str, b: str) -> PairOutcome:
        kernels.limit_threads_here(1)  # this pool thread's kernel calls stay in it: the concurrency is across pairs
        return _match_one(cache, a, b, spec, "in-process")

    pending: collections.deque = collections.deque()  # (anchor, remaining pairs of its task)
    inflight: dict = {}
    first_done = threading.Event()
    # faiss and OpenCV single-threaded for the whole run: the concurrency is across pairs (and the per-search save /
    # set / restore of faiss's global thread count, prepared._faiss_threads, then only ever writes 1, so concurrent
    # searches cannot race on it)
    from ..bruteforce import blas_one_thread

    # BLAS single-threaded for the whole run too (the IVF coarse GEMMs, prepared.PreparedImage.search2): per-search
    # limits set and restored by concurrent pair threads would race each other back to BLAS's own threads
    with _faiss_threads(1), _opencv_threads(1), blas_one_thread(load_scipy=False), \
            cf.ThreadPoolExecutor(threads, thread_name_prefix="guidedmatch-pair") as pool:
        # one pool thread builds the indexes the first pairs will search (faiss releases the GIL) until a pair has
        # finished, the other sets Numba up (~0.13 s holding the GIL) before any pair needs it (module doc, "Start-up")
        prefetch = pool.submit(_prefetch_indexes, cache, _index_order(queue), first_done)
        pool.submit(_load_numba)

        def fill() -> None:
            while len(inflight) < 2 * threads:
                if not pending:
                    if not queue:
                        return
                    anchor, task = queue.take()
                    pending.append([anchor, collections.deque(task), len(task)])  # anchor, to submit, unfinished
                entry = pending[0]
                a, b = entry[1].popleft()
                if not entry[1]:
                    pending.popleft()
                inflight[pool.submit(one, a, b)] = (entry, a, b)

        try:
            fill()
            while inflight:
                finished, _ = cf.wait(list(inflight), return_when=cf.FIRST_COMPLETED)
                for fut in finished:
                    entry, a, b = inflight.pop(fut)
                    exc = fut.exception()
                    out = fut.result() if exc is None else PairOutcome(
                        a, b, False, f"{type(exc).__name__}: {exc}", stats=dict(worker="in-process"))
                    entry[2] -= 1
                    if entry[2] == 0:  # the task's last pair
                        queue.finished(entry[0])
                    first_done.set()
                    writer.handle(out)
                fill()
        finally:
            first_done.set()  # also when the loop raises: the prefetch stops before the pool shuts down
        prefetched = prefetch.result()
    hits, loads, load_s = cache.counters()
    return dict(cache_hits=hits, image_loads=loads, workers=1, threads=threads, prefetched=prefetched,
                prefetch_loads=cache.prefetch_loads)


def _load_numba() -> None:
    """Set Numba's CPU target up (~0.13 s holding the GIL, once per process; 0.12-0.14 s more where SciPy's BLAS
    probe is not skipped) by loading its smallest cached kernel: the first pair then starts with it done, while the
    other pool thread builds indexes."""
    from .. import kernels

    try:
        with without_numba_blas_probe():
            kernels.counting_order(np.zeros(1, np.int64), 1)
    except ImportError:
        # a Numba whose set-up needs SciPy beyond the BLAS probe: set up again with SciPy visible (the registries
        # loaded before the failure are kept, the others load now); only the start-up saving is lost
        kernels.counting_order(np.zeros(1, np.int64), 1)


def _index_order(queue: _Queue) -> list[str]:
    """The images whose approximate index the queued pairs search (each pair's second image), in the order the
    in-process runner reaches them."""
    order: dict[str, None] = {}
    for tasks in queue.plan.values():
        for task in tasks:
            for _, b in task:
                order.setdefault(b, None)
    return list(order)


def _prefetch_indexes(cache: _ImageCache, names: list[str], stop: threading.Event) -> int:
    """Load (prepare) ``names`` in order and build their approximate indexes until ``stop`` is set or the cache is
    full; returns how many were built. Every one is needed later (the pairs that search it are queued), so nothing
    is wasted unless the cache evicts it first; a failing load is left to the pair that needs it (reported there)."""
    built = 0
    for name in names:
        if stop.is_set() or cache.bytes >= cache.spec.cache_bytes:
            break
        try:
            prepared = cache.get(name, (name,), count_hit=False).prepared
            if getattr(prepared, "has_index", False):
                prepared.index()
                built += 1
        except Exception:  # noqa: BLE001 - the pair's own load reports it
            break
    return built


class _opencv_threads:
    """OpenCV's thread count inside the block (restored after; a no-op without OpenCV)."""

    def __init__(self, n: int):
        self.n, self.old = n, None

    def __enter__(self):
        with contextlib.suppress(Exception):
            import cv2

            self.old = cv2.getNumThreads()
            cv2.setNumThreads(self.n)
        return self

    def __exit__(self, *exc) -> None:
        if self.old is not None:
            import cv2

            cv2.setNumThreads(self.old)


def _start_local_cluster(n: int):
    import dask
    from distributed import Client, LocalCluster

    # allowed-failures 0: a task whose worker dies fails at once; our own retry (the pair alone) takes over.
    # MALLOC_TRIM_THRESHOLD_ unset: Dask sets it to 64 kB in every worker it spawns, and an explicit glibc trim
    # threshold switches off glibc's adaptive mmap threshold, so each large NumPy temporary of a pair is a fresh
    # mmap + page faults: a 68k-feature pair took 0.35 s in a worker vs 0.295 s in-process (0003-0005, 1 thread),
    # and the 50k set's 28 pairs 13.6 s vs 9.0 s of matching with 1 worker. (Dask's profiler and GIL monitor,
    # also tried, cost nothing measurable.)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.worker.daemon": True,
                          "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR, env=dict(_SINGLE_THREAD_ENV))
        return cluster, Client(cluster, set_as_default=False)


def _anchor_token(source, spec: _TaskSpec, anchor: str) -> str:
    """Load (prepare) ``anchor`` into this worker's cache; the tiny result is what the anchor's tasks depend on."""
    with contextlib.suppress(Exception):  # a failing load is reported per pair by the tasks themselves
        _worker_cache(source, spec).get(anchor, (anchor,))
    return anchor


def _run_dask(client, source, spec: _TaskSpec, queue: _Queue, writer: _Writer, tasks_per_worker: int) -> dict:
    """Run the queue on a Dask cluster; at most ``tasks_per_worker`` tasks per worker in flight.

    Locality without placement restrictions: each anchor image gets a tiny *token* task that loads it into a
    worker's cache; the anchor's pair tasks depend on the token, so Dask's scheduler runs them on the worker
    holding it (work stealing still balances an idle worker). If that worker dies, the token is recomputed
    elsewhere. (Hard ``workers=[...]`` restrictions were tried first: a finished task whose worker died before its
    result was gathered was then never recomputed, and the run hung.)
    """
    from distributed import as_completed

    def live_workers() -> list[str]:
        return sorted(client.scheduler_info(n_workers=-1)["workers"])

    workers = live_workers()
    deadline = time.monotonic() + 60.0
    while not workers and time.monotonic() < deadline:  # an attached cluster may still be starting its workers
        time.sleep(0.5)
        workers = live_workers()
    if not workers:
        raise GuidedMatchError("the dask cluster has no workers (waited 60 s); start some with `dask worker ADDRESS`")
    seen_workers = set(workers)
    inflight: dict = {}
    tokens: dict = {}
    ac = as_completed(loop=client.loop)
    seq = 0
    last_refresh = time.monotonic()

    def fill() -> None:
        nonlocal seq
        while len(inflight) < tasks_per_worker * max(1, len(workers)) and queue:
            got = queue.take(idle=not inflight)
            if got is None:  # only suspects left: one at a time, alone on the cluster
                return
            anchor, task = got
            seq += 1
            deps = ()
            if anchor is not None:
                if anchor not in tokens:  # an anchor key is an image name, or (sweep, image) (plan_tasks)
                    name = anchor[1] if isinstance(anchor, tuple) else anchor
                    tokens[anchor] = client.submit(_anchor_token, source, spec, name, pure=False,
                                                   key=f"guidedmatch-anchor-{spec.run_id}-{seq}")
                deps = (tokens[anchor],)
            fut = client.submit(run_task, source, spec, task, *deps, pure=False,
                                key=f"guidedmatch-pairs-{spec.run_id}-{seq}")
            inflight[fut] = (anchor, task, seq if not inflight else None)
            ac.add(fut)

    try:
        fill()
        while inflight:
            fut = next(ac)
            anchor, task, alone_seq = inflight.pop(fut)
            alone = alone_seq == seq and not inflight  # nothing else ran on the cluster meanwhile
            failed = False
            try:
                outs = fut.result()
            except Exception as exc:  # noqa: BLE001 - worker died (KilledWorker), lost connection, ...
                failed = True
                reason = f"task failed: {type(exc).__name__}: {exc}"
                outs = [PairOutcome(a, b, False, reason, stats=dict(worker="?")) for a, b in task]
            fut.release()
            if queue.finished(anchor):
                tokens.pop(anchor).release()
            for out in outs:
                writer.handle(out, task_failed=failed, alone=alone and len(task) == 1)
            if time.monotonic() - last_refresh > 1.0:
                last_refresh = time.monotonic()
                workers = live_workers()
                seen_workers.update(workers)
            fill()
            if not inflight and queue:  # every worker gone: wait a little for replacements, then give up
                for _ in range(40):
                    workers = live_workers()
                    if workers:
                        break
                    time.sleep(0.5)
                if not workers:
                    while queue:
                        anchor, task = queue.take()
                        queue.finished(anchor)
                        for a, b in task:
                            writer.handle(PairOutcome(a, b, False, "no dask workers left"))
                fill()
    finally:
        for fut in list(inflight) + list(tokens.values()):
            fut.cancel()
    try:
        counters = client.run(_cache_counters, spec.run_id)
    except Exception:  # noqa: BLE001 - a worker restarting: the counters are only statistics
        counters = {}
    with contextlib.suppress(Exception):
        client.run(_forget_run, spec.run_id)
    hits = sum(c[0] for c in counters.values() if c)
    loads = sum(c[1] for c in counters.values() if c)
    return dict(cache_hits=hits, image_loads=loads, workers=len(seen_workers))


# ============================================================================================ entry point
def _done_pairs(sink, candidates) -> set:
    """``sink.done_pairs(candidates)`` when the sink takes the pair list (an exact answer), else ``done_pairs()``."""
    import inspect

    try:
        takes = "candidates" in inspect.signature(sink.done_pairs).parameters
    except (TypeError, ValueError):
        takes = False
    return set(sink.done_pairs(candidates) if takes else sink.done_pairs())


def match_collection(source, pairs, sink, config: CollectionConfig | dict | None = None, *,
                     client=None) -> CollectionReport:
    """Match every pair of ``pairs`` with features from ``source`` and write them into ``sink``.

    Args:
        source: a :class:`~guidedmatch.collection.sources.FeatureSource` (``names()``, ``num_features(name)``,
            ``load(name)``; picklable when the pairs run on worker processes).
        pairs: a :class:`~guidedmatch.collection.pairs.PairList` or an iterable of ``(name1, name2)``; names must
            be in ``source.names()``; repeated pairs (either order) are matched once.
        sink: an open :class:`~guidedmatch.collection.sinks.MatchSink` (``done_pairs()``, ``write(...)``); only
            this process writes to it.
        config: :class:`CollectionConfig` or a dict of its fields.
        client: a :class:`distributed.Client` of a running cluster to use (not closed by this call).

    Returns:
        :class:`CollectionReport`. Pairs that failed after their retries are listed in ``report.failed``;
        errors of the sink (a write failing) and bad input (unknown names) raise.

    >>> import numpy as np
    >>> from guidedmatch.features import Features
    >>> rng = np.random.default_rng(0)
    >>> class Src:                                  # any object with names / num_features / load
    ...     feats = {n: Features(rng.uniform(0, 500, (300, 2)), rng.random((300, 16), np.float32), (500, 500))
    ...              for n in "abc"}
    ...     def names(self): return list(self.feats)
    ...     def num_features(self, n): return len(self.feats[n])
    ...     def load(self, n): return self.feats[n]
    ...     def close(self): pass
    >>> class Sink:
    ...     written = []
    ...     def done_pairs(self): return {frozenset(("a", "b"))}
    ...     def write(self, a, b, pairs, scores, geometry): self.written.append((a, b, geometry.verdict))
    >>> rep = match_collection(Src(), [("a", "b"), ("a", "c"), ("b", "c")], Sink(), dict(progress=False))
    >>> rep.done, rep.skipped, rep.failed, rep.totals["backend"]
    (2, 1, [], 'in-process')
    """
    cfg = config_from(CollectionConfig, config)
    t_start = time.perf_counter()
    from .pairs import PairList, normalize_pairs

    names = list(source.names())
    checked = normalize_pairs(getattr(pairs, "pairs", pairs), names)  # InputError naming unknown images
    if isinstance(pairs, PairList):  # keep the report of the normalization done when the list was made
        checked = PairList(checked.pairs, pairs.report)
    pairs = checked
    todo_all = list(pairs.pairs)
    dropped = {k: v.get("count", 0) for k, v in pairs.report.items() if isinstance(v, dict) and "count" in v}
    done_before = _done_pairs(sink, todo_all)
    todo = [p for p in todo_all if frozenset(p) not in done_before]
    skipped = len(todo_all) - len(todo)
    nfeat = {}
    for a, b in todo:
        for n in (a, b):
            if n not in nfeat:
                nfeat[n] = int(source.num_features(n))
    work = sum(nfeat[a] + nfeat[b] for a, b in todo)
    backend, n_workers, reason = _choose_backend(cfg, client, work) if todo else ("none", 0, "nothing to do")
    spec = _TaskSpec(uuid.uuid4().hex[:12], cfg.mode, cfg.matcher, int(cfg.cache_mb * 2**20),
                     single_thread=backend == "local-cluster")
    if backend in ("local-cluster", "scheduler", "client"):
        try:
            pickle.dumps(source)
        except Exception as exc:  # noqa: BLE001 - checked before any cluster starts
            raise InputError(f"the feature source cannot be sent to worker processes (not picklable: {exc}); "
                             f"use workers=0") from None
    chunk = _chunk_size(cfg.chunk_pairs, len(todo), n_workers if backend == "local-cluster" else None)
    plan = plan_tasks(todo, names, chunk, anchor="first" if backend == "in-process" else "second",
                      sizes={n: k * CACHE_BYTES_PER_FEATURE for n, k in nfeat.items()}, cache_bytes=spec.cache_bytes)
    sweeps = len({k[0] for k in plan if isinstance(k, tuple)})
    queue = _Queue(plan, cfg.tasks_per_worker)
    startup_s = shutdown_s = 0.0
    cluster = own_client = use = None
    log = bar = None
    try:
        if backend in ("local-cluster", "scheduler", "client"):  # before the progress bar and the log
            t0 = time.perf_counter()
            if backend == "local-cluster":
                cluster, own_client = _start_local_cluster(n_workers)
                use = own_client
            elif backend == "scheduler":
                from distributed import Client

                try:
                    own_client = use = Client(cfg.scheduler, timeout="10s", set_as_default=False)
                except (OSError, TimeoutError) as exc:
                    raise GuidedMatchError(f"cannot connect to the dask scheduler at {cfg.scheduler}: {exc}") from None
            else:
                use = client
            startup_s = time.perf_counter() - t0
        log = open(cfg.log_path, "a", encoding="utf-8") if cfg.log_path else None  # noqa: SIM115 - closed below
        if cfg.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(todo), unit="pair", desc="matching pairs", file=sys.stderr, dynamic_ncols=True,
                       smoothing=0.05)
        else:  # no bar: tqdm is not even imported (~30 ms of a short run's start-up)
            bar = _NoBar()
        if use is not None:
            bar.set_postfix_str(backend, refresh=False)
        writer = _Writer(sink, cfg, queue, bar, log)
        if backend == "in-process":
            facts = _run_inprocess(source, spec, queue, writer, threads=cfg.threads or _usable_cores())
        elif backend == "none":
            facts = dict(cache_hits=0, image_loads=0, workers=0)
        else:
            facts = _run_dask(use, source, spec, queue, writer, cfg.tasks_per_worker)
    except BaseException:
        if log is not None:
            log.close()
        raise
    finally:
        if bar is not None:
            bar.close()
        t0 = time.perf_counter()
        if own_client is not None:
            with contextlib.suppress(Exception):
                own_client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
        shutdown_s = time.perf_counter() - t0
    wall = time.perf_counter() - t_start
    s = writer.sums
    totals = dict(pairs=len(todo_all), dropped=dropped, work=work, backend=backend,
                  backend_reason=reason, backend_rule=INPROCESS_RULE, inprocess_max_work=cfg.inprocess_max_work,
                  workers=facts["workers"], threads=facts.get("threads", 1), mode=cfg.mode,
                  matches=int(s["matches"]), inliers=int(s["inliers"]),
                  verified_pairs=int(s["verified_pairs"]), verdicts=dict(writer.verdicts),
                  load_s=float(s["load_s"]),
                  match_s=float(s["match_s"]), cache_hits=facts["cache_hits"], sweeps=sweeps,
                  image_loads=facts["image_loads"], prefetched_indexes=facts.get("prefetched", 0),
                  prefetched_images=facts.get("prefetch_loads", 0), images=len(nfeat),
                  startup_s=startup_s, shutdown_s=shutdown_s,
                  pairs_per_s=writer.done / wall if wall > 0 else 0.0, chunk_pairs=chunk,
                  max_tasks_in_flight=(cfg.tasks_per_worker * facts["workers"]) if backend != "in-process"
                  else (1 if facts.get("threads", 1) <= 1 else 2 * facts["threads"]),
                  cache_mb=cfg.cache_mb, prepared=_has_prepared(),
                  retried=sum(1 for k, v in writer.attempts.items() if v > 1))
    report = CollectionReport(writer.done, skipped, writer.failed, writer.per_pair, totals, wall)
    if log is not None:
        with contextlib.suppress(Exception):
            log.write(json.dumps(dict(event="summary", done=report.done, skipped=skipped,
                                      failed=[[list(p), r] for p, r in report.failed], wall_s=wall, **totals),
                                 default=_json_default) + "\n")
        log.close()
    return report
