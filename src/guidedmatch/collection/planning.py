"""Planning a collection run: where the pairs run (:func:`_choose_backend`, the auto rule :data:`INPROCESS_RULE`),
how many pairs a task takes (:func:`_chunk_size`), which pairs share a task and in which order the tasks come
(:func:`plan_tasks`; :func:`resident_blocks` for collections larger than the image cache), and how the tasks are
handed out (:class:`_Queue`: retries first, anchors spread over the workers). The reasons and measurements behind
each rule: :mod:`guidedmatch.collection.engine`.
"""
from __future__ import annotations

import collections
import os

from .config import CollectionConfig

__all__ = ["INPROCESS_RULE", "CACHE_BYTES_PER_FEATURE", "resident_blocks", "plan_tasks"]


#: the auto rule, as reported in ``CollectionReport.totals["backend_rule"]``
INPROCESS_RULE = "in-process (threads) when sum over pairs of (n1 + n2) <= inprocess_max_work or < 2 usable cores"


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
    anchors; an anchor's later tasks follow it to the worker holding it, see
    :func:`~guidedmatch.collection.dask_backend._run_dask`)."""

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
