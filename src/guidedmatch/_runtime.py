"""Process-level settings of the command line and of collection worker processes (never of a library call).

>>> freeze_gc_at_exit(); freeze_gc_at_exit()   # registers once
>>> len(_REGISTERED)
1
"""
from __future__ import annotations

import atexit
import gc

_REGISTERED: list = []


def freeze_gc_at_exit() -> None:
    """Make this process's interpreter shutdown cheap: ``gc.freeze()`` as an exit handler (registered once).

    At shutdown CPython runs its cyclic garbage collector over every object still alive, several times while it
    clears the modules. Once Numba has loaded the kernels that is ~110,000 objects (its type registries) and costs
    0.15-0.25 s per process: 10 % of ``guidedmatch colmap`` on the 28-pair Herz-Jesus database (2.13 -> 1.86 s,
    docs/collections.md). Frozen objects are skipped by those passes, and the operating system takes the memory
    back anyway. Every file and database is closed explicitly before exit; no output relies on a finalizer.
    Exit handlers run last-in first-out, so handlers registered later (Dask's cluster shutdown, ...) run first.
    """
    if not _REGISTERED:
        atexit.register(gc.freeze)
        _REGISTERED.append(True)


def byte_compile_package() -> dict:
    """Write the ``.pyc`` files of every guidedmatch module, as ``pip install`` does for a regular (non-editable)
    install; the benchmarks call it before timing fresh processes. An editable install writes them on first import,
    except where ``PYTHONDONTWRITEBYTECODE`` is set (as in the development sandbox): there every process would compile
    every module from source again, ~60 ms per ``guidedmatch colmap`` process that a user's installed copy does not
    pay. Returns ``{"package": path, "ok": bool, "seconds": float}`` for the benchmark's metadata."""
    import compileall
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parent
    t0 = time.perf_counter()
    ok = bool(compileall.compile_dir(str(root), quiet=1))
    return {"package": str(root), "ok": ok, "seconds": round(time.perf_counter() - t0, 3)}
