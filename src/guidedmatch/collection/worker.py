"""What runs where the pairs are matched (a Dask worker process, or this process for an in-process run).

:func:`run_task` matches a task's pairs with the run's image cache of the process (:func:`_worker_cache`: created on
the first task of a run, with the process set up for single-threaded libraries when it is a worker process of a
local cluster); :func:`_anchor_token` loads an anchor image into a worker's cache (the task that places an anchor's
pair tasks, see :mod:`guidedmatch.collection.dask_backend`); :func:`_cache_counters` / :func:`_forget_run` are run
on every worker at the end of a run. Dask sends these functions by reference: a worker imports this module.
"""
from __future__ import annotations

import contextlib
import sys
import threading
import time

import numpy as np

from .._runtime import freeze_gc_at_exit, mark_own_process, without_numba_blas_probe
from .cache import _ImageCache, _TaskSpec
from .report import PairOutcome

__all__ = ["run_task"]


_RUNS: dict[str, _ImageCache] = {}
_RUNS_LOCK = threading.Lock()


def _worker_cache(source, spec: _TaskSpec) -> _ImageCache:
    """The image cache of run ``spec`` in this worker process (created, with the source, on first use): the run's own,
    or the one the stages of a shared cluster share (``spec.cache_key``)."""
    with _RUNS_LOCK:
        cache = _RUNS.get(spec.cache_id)
        if cache is None:
            if spec.single_thread:
                _limit_threads()
                freeze_gc_at_exit()  # a worker process of ours: its shutdown is part of the run's wall time
                mark_own_process()
                _load_numba()        # Numba's set-up without SciPy (guidedmatch._runtime), before the first pair
            cache = _RUNS[spec.cache_id] = _ImageCache(source, spec)
        return cache


def _forget_run(run_id: str) -> bool:
    """Drop a run's cache in this process (called on every worker at the end of a run; a cache the stages of a
    shared cluster share lives as long as the cluster's workers)."""
    with _RUNS_LOCK:
        cache = _RUNS.pop(run_id, None)
    if cache is not None:
        with contextlib.suppress(Exception):
            cache.source.close()
    return cache is not None


def _cache_counters(run_id: str):
    cache = _RUNS.get(run_id)
    return None if cache is None else cache.counters()


def _limit_threads() -> None:
    """One thread for OpenCV and faiss in a single-threaded worker process (Numba/BLAS: via the environment)."""
    with contextlib.suppress(Exception):
        import cv2

        cv2.setNumThreads(1)
    if "faiss" in sys.modules:
        with contextlib.suppress(Exception):
            sys.modules["faiss"].omp_set_num_threads(1)


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


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "in-process"


def _fallback_text(f) -> str:
    """A matcher :class:`~guidedmatch.results.Fallback` as one log string; the model update it happened at is named
    (the same step can degrade at several updates, e.g. an unusable Bougnoux focal at updates 1 and 2).

    >>> from guidedmatch.results import Fallback
    >>> _fallback_text(Fallback("focal1", "f = w + h used", 2)), _fallback_text(Fallback("early_exit", "budget"))
    ('focal1 (model update 2): f = w + h used', 'early_exit: budget')
    """
    at = getattr(f, "at_update", 0)
    return f"{f.what}{f' (model update {at})' if at else ''}: {f.reason}"


def _match_one(cache: _ImageCache, a: str, b: str, spec: _TaskSpec, worker: str, first=None,
               memo=None) -> PairOutcome:
    """Match one pair (``first``: the matcher's prior draw order for it, :func:`guidedmatch.matcher.match`;
    ``memo``: a :class:`~guidedmatch.prepared.StartMemo` of it from an earlier stage); any error is the pair's
    outcome, never raised. With ``spec.memo_below >= 0`` the outcome carries the pair's start memo when its verdict
    is not "verified" or it has fewer inliers (a pair the second look may match again)."""
    from ..matcher import match

    t0 = time.perf_counter()
    wall0 = time.time()
    try:
        A = cache.get(a, (a, b))
        B = cache.get(b, (a, b))
        t1 = time.perf_counter()
        given = memo is not None
        if given:
            from .memos import load

            memo = load(memo)
        elif spec.memo_below >= 0:  # record this pair's start for a later stage
            from ..prepared import StartMemo

            memo = StartMemo(len(A.features), len(B.features))
        res = match(A.prepared, B.prepared, spec.mode, spec.matcher, first=first, start_memo=memo)
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
    if given:
        stats["start_memo_hits"] = int(st.details.get("start_memo_hits", 0))
    # the verdict first: held() assembles the memo, which only the pairs that keep it should pay for
    keep = (not given and memo is not None
            and (geom.verdict != "verified" or int(geom.num_inliers) < spec.memo_below) and memo.held)
    if keep:
        from .memos import dump

        memo = dump(memo)
    return PairOutcome(a, b, True, "", res.pairs, res.distances, geom, stats, memo=memo if keep else None)


def run_task(source, spec: _TaskSpec, pairs: list, *anchor_token, firsts: dict | None = None,
             memos: dict | None = None) -> list[PairOutcome]:
    """A task: match ``pairs`` (list of ``(name1, name2)``) with the run's image cache of this process
    (``anchor_token``: the result of :func:`_anchor_token`, only there to place the task; ``firsts``: the prior draw
    order of some of the pairs, ``{(name1, name2): first}``, sent with the task that needs it; ``memos``: their
    start memos from an earlier stage, likewise)."""
    cache = _worker_cache(source, spec)
    worker = _worker_name()
    firsts, memos = firsts or {}, memos or {}
    return [_match_one(cache, a, b, spec, worker, firsts.get((a, b)), memos.get((a, b))) for a, b in pairs]


def _anchor_token(source, spec: _TaskSpec, anchor: str) -> str:
    """Load (prepare) ``anchor`` into this worker's cache; the tiny result is what the anchor's tasks depend on."""
    with contextlib.suppress(Exception):  # a failing load is reported per pair by the tasks themselves
        _worker_cache(source, spec).get(anchor, (anchor,))
    return anchor
