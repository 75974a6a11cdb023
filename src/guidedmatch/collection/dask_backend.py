"""The Dask backend: the tasks of a collection run on a Dask cluster -- a local cluster of single-threaded worker
processes started for the run (:func:`_start_local_cluster`), a running scheduler or a given client -- with
anchor-token locality, bounded tasks in flight, retries and the quarantine of pairs whose worker died
(:func:`_run_dask`). The results come back to this process's one writer.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import time
import uuid

from ..errors import GuidedMatchError
from .cache import _TaskSpec
from .planning import _Queue
from .report import PairOutcome
from .worker import _anchor_token, _cache_counters, _forget_run, _load_numba, run_task
from .writer import _Writer


#: environment of the worker processes of a local cluster: one thread per process for every library
_SINGLE_THREAD_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                      "MKL_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


def _start_local_cluster(n: int):
    import dask
    from distributed import Client, LocalCluster

    from .._runtime import hugepages_off_for_children

    # the command line's huge pages (set for the extraction) are not passed on: they cost the matching workers
    hugepages_off_for_children()

    # allowed-failures 0: a task whose worker dies fails at once; our own retry (the pair alone) takes over.
    # MALLOC_TRIM_THRESHOLD_ unset: Dask sets it to 64 kB in every worker it spawns, and an explicit glibc trim
    # threshold switches off glibc's adaptive mmap threshold, so each large NumPy temporary of a pair is a fresh
    # mmap + page faults: a 68k-feature pair took 0.35 s in a worker vs 0.295 s in-process (0003-0005, 1 thread),
    # and the 50k set's 28 pairs 13.6 s vs 9.0 s of matching with 1 worker. (Dask's profiler and GIL monitor,
    # also tried, cost nothing measurable.)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.worker.daemon": True,
                          "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        # logs up to ERROR silenced: a pair's failure comes back to the writer as the task's exception (reported
        # by name); what the workers would print is a CommClosedError traceback from orphans whose parent was
        # killed (seen under load in the kill -9 trials), after the run has already stopped
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.CRITICAL, env=dict(_SINGLE_THREAD_ENV))
        return cluster, Client(cluster, set_as_default=False)


class SharedCluster:
    """A local cluster started once for every stage of one matching run -- the first pass, the verified expansion's
    rounds, the second look's rounds (:func:`guidedmatch.sfm.stages.match_into_database`) -- instead of one per
    stage (each ~1.2 s to start, and a stage the auto rule found small ran in threads, where the GIL serializes the
    unguided start of unrelated pairs: buddha's second look 14.2 s in threads, 11.5 s on the first pass's workers).
    Give it as ``client=`` to :func:`~guidedmatch.collection.engine.match_collection`: the run reports the backend
    ``local-cluster`` with this object's reason, and the start-up with its first stage. Closed by :meth:`close` (or
    the ``with`` block), not by the stages."""

    def __init__(self, n_workers: int, reason: str):
        t0 = time.perf_counter()
        self.n_workers, self.reason = int(n_workers), f"{reason}; one cluster for every stage of the run"
        self.cache_prefix = f"shared-{uuid.uuid4().hex[:12]}"
        self.cluster, self.client = _start_local_cluster(self.n_workers)
        self._startup_s = time.perf_counter() - t0
        self._caches: dict = {}  # cache key -> the source it loads from (kept alive: its id is part of the key)

    def cache_key(self, source, quantizer, cache_bytes: int) -> str:
        """The key of the image cache that the stages loading ``source`` with ``quantizer`` (a SharedQuantizer or
        None) share in each worker process: a later stage -- the expansion's or the second look's rounds -- finds the
        images the first pass loaded and indexed (fox: 124 loads and k-means of the second look, ~3 s of the
        workers' time). The same source object, the same quantizer token and memory bound give the same key; the
        images themselves do not depend on the stage's matcher settings (:func:`guidedmatch.prepared.prepare`)."""
        token = getattr(quantizer, "token", None) if quantizer is not None else None
        key = f"{self.cache_prefix}-{id(source):x}-{token}-{int(cache_bytes)}"
        self._caches.setdefault(key, source)
        return key

    def take_startup(self) -> float:
        """The start-up time, once (the first stage reports it; 0 afterwards)."""
        t, self._startup_s = self._startup_s, 0.0
        return t

    def close(self) -> None:
        for obj in (self.client, self.cluster):
            with contextlib.suppress(Exception):
                obj.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _run_dask(client, source, spec: _TaskSpec, queue: _Queue, writer: _Writer, tasks_per_worker: int,
              firsts: dict | None = None, memos=None) -> dict:
    """Run the queue on a Dask cluster; at most ``tasks_per_worker`` tasks per worker in flight.

    Locality without placement restrictions: each anchor image gets a tiny *token* task that loads it into a
    worker's cache; the anchor's pair tasks depend on the token, so Dask's scheduler runs them on the worker
    holding it (work stealing still balances an idle worker). If that worker dies, the token is recomputed
    elsewhere. (Hard ``workers=[...]`` restrictions were tried first: a finished task whose worker died before its
    result was gathered was then never recomputed, and the run hung.) ``memos``: the run's
    :class:`~guidedmatch.collection.memos.StartMemos`, whose memos of a task's pairs go with the task.
    """
    from distributed import as_completed

    def live_workers() -> list[str]:
        return sorted(client.scheduler_info(n_workers=-1)["workers"])

    workers = live_workers()
    # a cache shared with earlier stages (spec.cache_key): this stage's loads and hits are the counters' growth
    before = _counters(client, spec.cache_id) if spec.cache_key else {}
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
            mine = {(a, b): firsts[(a, b)] for a, b in task if (a, b) in firsts} if firsts else None
            fut = client.submit(run_task, source, spec, task, *deps, pure=False, firsts=mine,
                                memos=memos.for_task(task) if memos is not None else None,
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
            if spec.cache_key and not queue:  # a shared cluster's stage: later stages come, see _warm_numba_here
                _warm_numba_here()
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
    counters = _counters(client, spec.cache_id)
    if not spec.cache_key:  # the run's own cache; a shared one lives as long as the cluster's workers
        with contextlib.suppress(Exception):
            client.run(_forget_run, spec.run_id)
    hits = sum(c[0] - (before.get(w) or (0, 0))[0] for w, c in counters.items() if c)
    loads = sum(c[1] - (before.get(w) or (0, 0))[1] for w, c in counters.items() if c)
    return dict(cache_hits=hits, image_loads=loads, workers=len(seen_workers))


_WARMED = threading.Event()


def _warm_numba_here() -> None:
    """Set Numba up in this process (the client's) in a thread, once, while a stage's last tasks run: the stages after
    the first pass use compiled kernels here -- the second look's chains (:func:`~guidedmatch.strip_index.sorted_join`),
    the 1.5 px selection's angles -- and the first of them pays Numba's start (0.3-0.5 s holding this process; fox:
    ~1 s of wall time between the first pass and the second look, both workers idle) unless it is done by then."""
    if _WARMED.is_set():
        return
    _WARMED.set()

    def warm() -> None:
        with contextlib.suppress(Exception):  # only a head start: a failure shows where the kernel is used
            _load_numba()

    threading.Thread(target=warm, name="guidedmatch-numba-warm", daemon=True).start()


def _counters(client, key: str) -> dict:
    """``{worker: (hits, loads, load_s) or None}`` of the image cache ``key`` in each worker process."""
    try:
        return client.run(_cache_counters, key)
    except Exception:  # noqa: BLE001 - a worker restarting: the counters are only statistics
        return {}
