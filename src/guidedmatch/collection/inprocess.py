"""The in-process backend: the pairs of a collection run in this process, one after the other or ``threads`` pairs at
once on a thread pool sharing one image cache, with the start-up overlap (Numba's set-up on one pool thread while
another prefetches the first images and builds their indexes) described in :mod:`guidedmatch.collection.engine`.
"""
from __future__ import annotations

import collections
import contextlib
import threading

from .cache import _ImageCache, _TaskSpec
from .planning import _Queue
from .report import PairOutcome
from .worker import _load_numba, _match_one
from .writer import _Writer


def _run_inprocess(source, spec: _TaskSpec, queue: _Queue, writer: _Writer, threads: int = 1,
                   firsts: dict | None = None, memos=None) -> dict:
    """The pairs in this process: one after the other (``threads=1``), or ``threads`` pairs at once on a thread pool
    (each pool thread runs Numba's kernels single-threaded, faiss runs single-threaded for the run; the image cache
    and the prepared images' index builds are locked). The caller's thread is the one writer either way, results
    are written in completion order, and the matches are the same as one after the other. ``firsts``: the prior
    draw order of some pairs (:func:`~guidedmatch.collection.engine.match_collection`); ``memos``: the run's
    :class:`~guidedmatch.collection.memos.StartMemos` (each pair's memo taken when the pair starts)."""
    cache = _ImageCache(source, spec)
    firsts = firsts or {}

    def memo(a: str, b: str):
        return memos.take((a, b)) if memos is not None else None

    if threads <= 1:
        while queue:
            anchor, task = queue.take()
            outs = [_match_one(cache, a, b, spec, "in-process", firsts.get((a, b)), memo(a, b)) for a, b in task]
            queue.finished(anchor)
            for out in outs:
                writer.handle(out)
        hits, loads, load_s = cache.counters()
        return dict(cache_hits=hits, image_loads=loads, workers=1, threads=1)

    import concurrent.futures as cf

    from .. import kernels
    from ..prepared import _faiss_threads

    def one(a: str, b: str, m) -> PairOutcome:
        kernels.limit_threads_here(1)  # this pool thread's kernel calls stay in it: the concurrency is across pairs
        return _match_one(cache, a, b, spec, "in-process", firsts.get((a, b)), m)

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
        # finished, the other sets Numba up (~0.13 s holding the GIL) before any pair needs it (engine doc, "Start-up")
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
                inflight[pool.submit(one, a, b, memo(a, b))] = (entry, a, b)

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
