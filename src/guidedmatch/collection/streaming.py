"""Pairs matched as they become ready: :class:`PairStream`, the in-process engine of a collection whose images are
still being written (``guidedmatch sfm`` matching pairs while its extraction runs, :mod:`guidedmatch.sfm.overlap`).

:func:`~guidedmatch.collection.engine.match_collection` takes a whole pair list and runs it; a :class:`PairStream`
takes pairs a few at a time (:meth:`PairStream.add`) and leaves the thread pool and the loop to its caller, which
shares them with other work: the caller submits a pair when it has a free thread (:meth:`PairStream.submit`), waits
on its futures together with its own, and hands each finished one back (:meth:`PairStream.finish`), in the one thread
that writes. Everything else is the in-process engine's: the image cache (one per run, bounded by ``cache_mb``), the
per-pair function (:func:`~guidedmatch.collection.worker._match_one`), the writer with its retries, log lines and
totals, and the single-threaded libraries inside each pool thread (:meth:`PairStream.thread_limits`) -- so a pair
gives the same matches as in :func:`~guidedmatch.collection.engine.match_collection` with
``shared_quantizer="off"`` (a stream's images are not all known when its first pairs start: each image keeps its own
k-means, :mod:`~guidedmatch.collection.quantizer`).
"""
from __future__ import annotations

import collections
import contextlib
import time
import uuid

from ..validation import config_from
from .cache import _has_prepared, _ImageCache, _TaskSpec
from .config import CollectionConfig
from .planning import _Queue
from .report import CollectionReport, PairOutcome
from .worker import _match_one
from .writer import _NoBar, _Writer

__all__ = ["PairStream"]


class PairStream:
    """Match pairs of ``source`` into ``sink`` in this process as the caller adds them.

    Args:
        source: a feature source that knows every image of a pair by the time the pair is added (a
            :class:`~guidedmatch.collection.sources.ColmapSource` grows with ``add_image``).
        sink: an open sink (``write``); only the caller's thread writes (:meth:`finish`).
        config: :class:`CollectionConfig` (``mode``, ``matcher``, ``cache_mb``, ``retries``, ``log_path``,
            ``report_max_pairs``, ``tasks_per_worker``); ``workers`` / ``scheduler`` do not apply (always in this
            process).

    Pairs are de-duplicated (either order: the first added is kept) and queued by anchor image (the first image of
    the pair); a failed pair is retried ``retries`` times, then reported in :meth:`report`'s ``failed``.
    """

    def __init__(self, source, sink, config: CollectionConfig | dict | None = None) -> None:
        self.cfg = cfg = config_from(CollectionConfig, config)
        self.spec = _TaskSpec(uuid.uuid4().hex[:12], cfg.mode, cfg.matcher, int(cfg.cache_mb * 2**20),
                              single_thread=False)
        self.cache = _ImageCache(source, self.spec)
        self.queue = _Queue(collections.OrderedDict(), cfg.tasks_per_worker)
        self.log = open(cfg.log_path, "a", encoding="utf-8") if cfg.log_path else None  # noqa: SIM115 - close()
        self.writer = _Writer(sink, cfg, self.queue, _NoBar(), self.log)
        self.sink = sink
        self.added: set[frozenset] = set()
        self.pairs: list[tuple[str, str]] = []   # every pair added, as oriented
        self.skipped = 0                  # pairs added that the sink already held (a resumed run)
        self.inflight: dict = {}          # future -> (anchor, name1, name2)
        self.max_inflight = 0
        self.t_start = time.perf_counter()
        self.t_first = self.t_last = None  # first submission, last finish (perf_counter)

    def add(self, pairs) -> int:
        """Queue ``pairs`` (``(name1, name2)``, oriented as they will be matched) not added before; those the sink
        already holds (``sink.done_pairs``: a resumed run) are counted as skipped, not matched. Returns how many
        were queued."""
        from .engine import _done_pairs

        fresh = []
        for a, b in pairs:
            key = frozenset((a, b))
            if key not in self.added:
                self.added.add(key)
                self.pairs.append((a, b))
                fresh.append((a, b))
        # (a sink without a candidates argument lists every pair it holds: only the fresh ones count)
        done = (_done_pairs(self.sink, fresh) & {frozenset(p) for p in fresh}) if fresh else set()
        self.skipped += len(done)
        queued = 0
        for a, b in fresh:
            if frozenset((a, b)) not in done:
                self.queue.plan.setdefault(a, collections.deque()).append([(a, b)])
                queued += 1
        return queued

    @property
    def waiting(self) -> bool:
        """Whether a pair is queued (not yet submitted)."""
        return bool(self.queue)

    def submit(self, pool):
        """Submit the next queued pair to ``pool`` (a ``concurrent.futures`` executor); returns its future (None
        when nothing is queued)."""
        took = self.queue.take() if self.queue else None
        if took is None:
            return None
        anchor, task = took
        (a, b), = task
        fut = pool.submit(self._one, a, b)
        self.inflight[fut] = (anchor, a, b)
        self.max_inflight = max(self.max_inflight, len(self.inflight))
        if self.t_first is None:
            self.t_first = time.perf_counter()
        return fut

    def _one(self, a: str, b: str) -> PairOutcome:
        from .. import kernels

        kernels.limit_threads_here(1)  # this pool thread's kernel calls stay in it: the concurrency is across tasks
        return _match_one(self.cache, a, b, self.spec, "in-process")

    def finish(self, fut) -> None:
        """Write (or requeue, or report as failed) the pair of a finished future; in the caller's (writing) thread."""
        anchor, a, b = self.inflight.pop(fut)
        exc = fut.exception()
        out = fut.result() if exc is None else PairOutcome(a, b, False, f"{type(exc).__name__}: {exc}",
                                                            stats=dict(worker="in-process"))
        self.queue.finished(anchor)
        self.writer.handle(out)
        self.t_last = time.perf_counter()

    @staticmethod
    def thread_limits() -> contextlib.ExitStack:
        """The in-process engine's limits for the whole run (:func:`guidedmatch.collection.inprocess._run_inprocess`):
        faiss, OpenCV and BLAS single-threaded, the concurrency being across the pool's tasks. Entering it imports
        the matcher's libraries (faiss, Numba): a caller may enter it once its other work has started."""
        from ..bruteforce import blas_one_thread
        from ..prepared import _faiss_threads
        from .inprocess import _opencv_threads

        stack = contextlib.ExitStack()
        stack.enter_context(_faiss_threads(1))
        stack.enter_context(_opencv_threads(1))
        stack.enter_context(blas_one_thread(load_scipy=False))
        return stack

    def report(self, threads: int, reason: str) -> CollectionReport:
        """What the stream did (``totals`` as :func:`~guidedmatch.collection.engine.match_collection`'s, backend
        ``in-process``, ``backend_reason`` = ``reason``)."""
        wall = time.perf_counter() - self.t_start
        w = self.writer
        s = w.sums
        hits, loads, _ = self.cache.counters()
        totals = dict(pairs=len(self.added), dropped={}, work=None, backend="in-process", backend_reason=reason,
                      backend_rule="pipelined with the extraction: always in this process",
                      inprocess_max_work=self.cfg.inprocess_max_work, workers=1, threads=threads, mode=self.cfg.mode,
                      matches=int(s["matches"]), inliers=int(s["inliers"]), verified_pairs=int(s["verified_pairs"]),
                      verdicts=dict(w.verdicts), load_s=float(s["load_s"]), match_s=float(s["match_s"]),
                      cache_hits=hits, sweeps=0, image_loads=loads, prefetched_indexes=0, prefetched_images=0,
                      images=len(self.cache.items), startup_s=0.0, shutdown_s=0.0,
                      pairs_per_s=w.done / wall if wall > 0 else 0.0, chunk_pairs=1,
                      max_tasks_in_flight=self.max_inflight, cache_mb=self.cfg.cache_mb, prepared=_has_prepared(),
                      retried=sum(1 for v in w.attempts.values() if v > 1))
        return CollectionReport(w.done, self.skipped, w.failed, w.per_pair, totals, wall)

    def close(self) -> None:
        log, self.log = self.log, None
        if log is not None:
            log.close()
