"""How a large kernel call is spread over threads: one contiguous chunk of rows per thread, in a shared pool.

The Numba kernels of :mod:`guidedmatch.kernels` are compiled single-threaded (``parallel=False``) and release the GIL
(``nogil=True``); a large input is cut into one contiguous chunk per Numba thread and the chunks run in Python
threads (:func:`_chunked`). That is the same schedule as a ``prange`` loop (Numba's default: one equal chunk per
thread), with identical results, but compiles 2-3x faster: the parfor lowering of the guided kernel alone took
6 s of a first run's compilation, more than the single-threaded kernel it wraps (2.6 s).

* :func:`num_threads` -- threads a large kernel call uses; :func:`limit_threads_here` caps it for one thread (a
  collection's pair threads run their kernels unchunked);
* :func:`_chunked` / :func:`_chunked_rows` -- run a kernel on the chunks and join the per-row results in row order.

Plain Python (no Numba code); :func:`num_threads` and :func:`limit_threads_here` are also importable from
:mod:`guidedmatch.kernels`.
"""
from __future__ import annotations

import os
import threading

import numpy as np

__all__ = ["limit_threads_here", "num_threads"]

_POOL: list = [None, 0, 0]  # [ThreadPoolExecutor, its number of threads, the process id that started it]
_POOL_LOCK = threading.Lock()
_LOCAL = threading.local()  # per-thread cap of num_threads() (limit_threads_here)


def limit_threads_here(n: int) -> None:
    """Cap :func:`num_threads` at ``n`` for the calling thread only (a pool thread matching one pair of a collection
    while other threads match others: its kernel calls then run in that thread, unchunked)."""
    _LOCAL.cap = max(1, int(n))


def num_threads() -> int:
    """Threads a large kernel call uses: the calling thread's cap (:func:`limit_threads_here`), else Numba's thread
    count (``NUMBA_NUM_THREADS`` / ``numba.set_num_threads``; read without starting Numba's own thread pool when
    nothing else started it)."""
    cap = getattr(_LOCAL, "cap", None)
    if cap is not None:
        return cap
    import numba
    from numba.np.ufunc import parallel

    if getattr(parallel, "_is_initialized", False):
        return int(numba.get_num_threads())
    return int(numba.config.NUMBA_NUM_THREADS)


def _chunked(fn, n: int, min_rows: int, threads: int | None = None):
    """``[fn(a, b) for a, b in chunks]`` over one contiguous chunk ``[a, b)`` of ``range(n)`` per thread, run in a
    shared thread pool (``fn`` calls a ``nogil`` kernel); in the calling thread when ``n < min_rows``."""
    k = max(1, min(int(threads or num_threads()), n // max(1, min_rows // 2) if n >= min_rows else 1))
    if k == 1:
        return [fn(0, n)]
    cuts = [n * i // k for i in range(k + 1)]
    pid = os.getpid()
    with _POOL_LOCK:  # callers may be concurrent (the collection's in-process pair threads)
        if _POOL[0] is None or _POOL[1] < k or _POOL[2] != pid:  # a forked child has none of its parent's threads
            from concurrent.futures import ThreadPoolExecutor

            if _POOL[0] is not None and _POOL[2] == pid:
                _POOL[0].shutdown(wait=False)  # work already submitted to it still runs
            _POOL[:] = [ThreadPoolExecutor(k, thread_name_prefix="guidedmatch-kernel"), k, pid]
        pool = _POOL[0]
    futures = [pool.submit(fn, a, b) for a, b in zip(cuts[1:-1], cuts[2:])]
    first = fn(cuts[0], cuts[1])  # the calling thread takes the first chunk
    return [first] + [f.result() for f in futures]


def _join_rows(parts: list):
    """Tuples of per-row arrays, one per chunk of rows, joined in row order (one chunk: returned as it is)."""
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(arrays) for arrays in zip(*parts))


def _chunked_rows(fn, n: int, min_rows: int, threads: int | None = None):
    """:func:`_chunked` for a kernel returning a tuple of per-row arrays: the chunks' arrays joined in row order."""
    return _join_rows(_chunked(fn, n, min_rows, threads))
