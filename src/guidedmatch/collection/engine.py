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
  both images) is at most ``inprocess_max_work`` (default 10,000,000 -- about 600 pairs of 8192 features), or
  when fewer than 2 cores are usable. Measured on the 2-core development machine, one run each, ``guidedmatch
  colmap DB`` at the defaults: Herz-Jesus-P8 at 11.4k features per image (W = 0.64 M) 2.4 s in threads vs 5.4 s on
  a 2-worker cluster (start-up ~1.2 s); Herz-Jesus-P25 (W = 7.3 M) 12.1 vs 12.2 s of first pass, equal; buddha's
  36-image subset (630 pairs, W = 5.6 M) 11.6 / 10.9 s in threads vs 10.0 / 10.2 s on workers; buddha (67 images,
  W ~ 19 M) 32.2 s in threads, one core a third idle (the unguided start of unrelated pairs is Python / NumPy work
  that holds the GIL), vs 24.6 s on 2 workers. Above the threshold the run pays the cluster's start-up for its
  parallelism and isolation (a pair that crashes its process costs a worker, not the run). Inside
  :func:`guidedmatch.sfm.stages.match_into_database` one cluster serves every stage of the run (first pass,
  expansion, second look: :func:`shared_cluster`).

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
resident blocks of images, so that each image is indexed once (:func:`~guidedmatch.collection.planning.plan_tasks`);
the cache evicts images whose approximate index is not built before those whose index is (a reload is a read, a
re-index ~1 s at 60k features). Features travel from the source to a worker once per cache miss (never with each
pair): the source object is picklable (paths only) and each worker opens it once per run.

Results stream back to ONE writer -- the caller's sink in this process -- in completion order; each
``sink.write`` is one transaction, so the sink always holds complete pairs only.

Start-up (in-process, threads >= 2)
-----------------------------------
Numba's CPU target is set up once per process (~0.13 s holding the GIL); the set-up would also import
``scipy.linalg`` (another 0.12-0.14 s) for a BLAS probe none of our kernels needs, which a process of ours skips
(``guidedmatch._runtime.without_numba_blas_probe``). One pool thread does that first
(:func:`~guidedmatch.collection.worker._load_numba`); meanwhile the other loads the images the queued pairs search,
in the order they are reached, and builds their approximate indexes (faiss releases the GIL), until the first pair
has finished; the report's ``prefetched_images`` / ``prefetched_indexes`` count them. Every index built this way is
one a queued pair needs, so it is work moved earlier, not added. Herz-Jesus-P8, 8192 SIFT, 28 pairs, 10 alternating fresh runs each of
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

One coarse quantizer (``shared_quantizer``, opt-in)
---------------------------------------------------
With ``"on"`` (or ``"auto"``, from 16 images), every image's approximate index shares one k-means quantizer trained
for the run (:mod:`~guidedmatch.collection.quantizer`, in a thread while a local cluster starts), so each image's
cells are computed once for all its pairs instead of once per pair (fox, 67 images: 0.52x -> 0.48x COLMAP's matching
time, but worse poses: docs/collections.md). A pair then gives the matches of ``match(prepare(a, quantizer=q),
prepare(b, quantizer=q))`` with the report's quantizer (``totals["quantizer"]``;
:func:`~guidedmatch.collection.quantizer.collection_quantizer` trains the same one again), not those of ``match(a,
b)`` alone; the default ``"off"`` gives those.

Where the code is
-----------------
This module is the flow of :func:`match_collection`: check the pairs, skip the done ones, choose the backend, plan
the tasks, run them, report. The rest of the package ``guidedmatch.collection``, one concern per module:

* ``config`` -- :class:`CollectionConfig`, :data:`COLLECTION_MATCHER_DEFAULTS`;
* ``report`` -- :class:`CollectionReport`, :class:`PairOutcome`;
* ``planning`` -- the backend rule, chunk sizes, :func:`plan_tasks` / :func:`resident_blocks` (sweeps), the task
  queue;
* ``cache`` -- the per-process image cache and the run's task spec;
* ``quantizer`` -- the run's shared IVF coarse quantizer;
* ``worker`` -- what runs where the pairs are matched: ``run_task``, the anchor token, the process set-up;
* ``inprocess`` -- the thread-pool backend with its start-up prefetch;
* ``dask_backend`` -- the local cluster and the Dask scheduling loop;
* ``writer`` -- the one writer (sink writes, retries, log lines, progress bar, totals).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import pickle
import sys
import time
import uuid

from ..errors import GuidedMatchError, InputError
from ..validation import config_from
from .cache import _has_prepared, _TaskSpec
from .config import COLLECTION_MATCHER_DEFAULTS, CollectionConfig, collection_matcher_config
from .dask_backend import SharedCluster, _run_dask, _start_local_cluster
from .inprocess import _run_inprocess
from .planning import (CACHE_BYTES_PER_FEATURE, INPROCESS_RULE, _choose_backend, _chunk_size, _Queue, _usable_cores,
                       plan_tasks)
from .planning import resident_blocks  # noqa: F401 - public, found here too
from .quantizer import collection_quantizer, train_meanwhile
from .report import CollectionReport, PairOutcome, _json_default
from .worker import run_task  # noqa: F401 - the task function, found here too (Dask sends worker.run_task)
from .writer import _NoBar, _Writer

__all__ = ["CollectionConfig", "CollectionReport", "PairOutcome", "match_collection", "plan_tasks",
           "COLLECTION_MATCHER_DEFAULTS", "collection_matcher_config",
           "INPROCESS_RULE"]


def _done_pairs(sink, candidates) -> set:
    """``sink.done_pairs(candidates)`` when the sink takes the pair list (an exact answer), else ``done_pairs()``."""
    import inspect

    try:
        takes = "candidates" in inspect.signature(sink.done_pairs).parameters
    except (TypeError, ValueError):
        takes = False
    return set(sink.done_pairs(candidates) if takes else sink.done_pairs())


def _todo(source, pairs: list, sink) -> tuple[list, dict, int]:
    """``(pairs not done yet, {image: features} of their images, work W = sum over them of n1 + n2)``."""
    done_before = _done_pairs(sink, pairs)
    todo = [p for p in pairs if frozenset(p) not in done_before]
    nfeat: dict = {}
    for a, b in todo:
        for n in (a, b):
            if n not in nfeat:
                nfeat[n] = int(source.num_features(n))
    return todo, nfeat, sum(nfeat[a] + nfeat[b] for a, b in todo)


def _check_picklable(source) -> None:
    """Refuse, before any cluster starts, a feature source that cannot be sent to worker processes."""
    try:
        pickle.dumps(source)
    except Exception as exc:  # noqa: BLE001 - checked before any cluster starts
        raise InputError(f"the feature source cannot be sent to worker processes (not picklable: {exc}); "
                         f"use workers=0") from None


@contextlib.contextmanager
def shared_cluster(source, pairs, sink, config: CollectionConfig | dict | None = None):
    """The :class:`~guidedmatch.collection.dask_backend.SharedCluster` for every stage of a run whose first pass
    (``pairs`` not yet in ``sink``) the backend rule sends to a local cluster (auto above ``inprocess_max_work``, or
    ``workers=N``), else ``None`` (in-process, a scheduler's address, nothing to do): pass it as ``client=`` to each
    stage; closed on exit."""
    from .pairs import normalize_pairs

    cfg = config_from(CollectionConfig, config)
    todo, _, work = _todo(source, list(normalize_pairs(getattr(pairs, "pairs", pairs), list(source.names())).pairs),
                          sink)
    backend, n, reason = _choose_backend(cfg, None, work) if todo else ("none", 0, "")
    if backend != "local-cluster":
        yield None
        return
    _check_picklable(source)
    with train_meanwhile(source, cfg.matcher, cfg.shared_quantizer):
        handle = SharedCluster(n, reason)
    with handle:
        yield handle


def match_collection(source, pairs, sink, config: CollectionConfig | dict | None = None, *,
                     client=None, first: dict | None = None, start_memos=None) -> CollectionReport:
    """Match every pair of ``pairs`` with features from ``source`` and write them into ``sink``.

    Args:
        source: a :class:`~guidedmatch.collection.sources.FeatureSource` (``names()``, ``num_features(name)``,
            ``load(name)``; picklable when the pairs run on worker processes).
        pairs: a :class:`~guidedmatch.collection.pairs.PairList` or an iterable of ``(name1, name2)``; names must
            be in ``source.names()``; repeated pairs (either order) are matched once.
        sink: an open :class:`~guidedmatch.collection.sinks.MatchSink` (``done_pairs()``, ``write(...)``); only
            this process writes to it.
        config: :class:`CollectionConfig` or a dict of its fields.
        client: a :class:`distributed.Client` of a running cluster to use, or the
            :class:`~guidedmatch.collection.dask_backend.SharedCluster` of the run (:func:`shared_cluster`); not
            closed by this call.
        first: ``{(name1, name2): prior}``, the matcher's prior draw order of some pairs (``first`` of
            :func:`guidedmatch.matcher.match`: image-1 feature indices drawn first, as the pair is oriented in
            ``pairs``), e.g. the chained keypoints of :mod:`~guidedmatch.collection.second_look`; sent with the task
            of the pair only.
        start_memos: a :class:`~guidedmatch.collection.memos.StartMemos`: the memos it holds of these pairs go with
            their tasks (the unguided starts do not search those features again), and while ``start_memos.recording``
            the pairs left rejected or weak return theirs into it. The matches are the same with or without.

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
    todo, nfeat, work = _todo(source, todo_all, sink)
    skipped = len(todo_all) - len(todo)
    shared = isinstance(client, SharedCluster)  # the run's cluster: started once, closed by its owner
    if not todo:
        backend, n_workers, reason = "none", 0, "nothing to do"
    elif shared:
        backend, n_workers, reason = "local-cluster", client.n_workers, client.reason
    else:
        backend, n_workers, reason = _choose_backend(cfg, client, work)
    spec = _TaskSpec(uuid.uuid4().hex[:12], cfg.mode, cfg.matcher, int(cfg.cache_mb * 2**20),
                     single_thread=backend == "local-cluster")
    if backend in ("local-cluster", "scheduler", "client"):
        _check_picklable(source)
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
            if shared:
                use = client.client
            elif backend == "local-cluster":
                with train_meanwhile(source, cfg.matcher, cfg.shared_quantizer):  # while the workers start
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
            startup_s = client.take_startup() if shared else time.perf_counter() - t0
        quantizer, quantizer_info = (collection_quantizer(source, cfg.matcher, cfg.shared_quantizer) if todo
                                     else (None, dict(used=False, why="nothing to do")))
        spec = dataclasses.replace(spec, quantizer=quantizer,
                                   cache_key=client.cache_key(source, quantizer, spec.cache_bytes) if shared else "",
                                   memo_below=start_memos.keep_below if start_memos is not None
                                   and start_memos.recording else -1)
        log = open(cfg.log_path, "a", encoding="utf-8") if cfg.log_path else None  # noqa: SIM115 - closed below
        if cfg.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(todo), unit="pair", desc="matching pairs", file=sys.stderr, dynamic_ncols=True,
                       smoothing=0.05)
        else:  # no bar: tqdm is not even imported (~30 ms of a short run's start-up)
            bar = _NoBar()
        if use is not None:
            bar.set_postfix_str(backend, refresh=False)
        writer = _Writer(sink, cfg, queue, bar, log, start_memos)
        if backend == "in-process":
            facts = _run_inprocess(source, spec, queue, writer, threads=cfg.threads or _usable_cores(), firsts=first,
                                   memos=start_memos)
        elif backend == "none":
            facts = dict(cache_hits=0, image_loads=0, workers=0)
        else:
            facts = _run_dask(use, source, spec, queue, writer, cfg.tasks_per_worker, firsts=first,
                              memos=start_memos)
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
                  cache_mb=cfg.cache_mb, prepared=_has_prepared(), quantizer=quantizer_info,
                  start_memos=start_memos.summary() if start_memos is not None else None,
                  retried=sum(1 for k, v in writer.attempts.items() if v > 1))
    report = CollectionReport(writer.done, skipped, writer.failed, writer.per_pair, totals, wall)
    if log is not None:
        with contextlib.suppress(Exception):
            log.write(json.dumps(dict(event="summary", done=report.done, skipped=skipped,
                                      failed=[[list(p), r] for p, r in report.failed], wall_s=wall, **totals),
                                 default=_json_default) + "\n")
        log.close()
    return report
