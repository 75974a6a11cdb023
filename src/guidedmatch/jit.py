"""Numba compilation kept out of reported timings (issue 14).

The kernels (:mod:`guidedmatch.kernels`, :mod:`guidedmatch.spatial_order`) are compiled by Numba the first time
they see a descriptor kind (``cache=True`` stores the machine code next to the sources, or in
``NUMBA_CACHE_DIR``, so later processes only load it). A first call therefore costs seconds of compilation that
are not matching time. This module

* measures compilation through Numba's ``"numba:compile"`` event, which fires only on a cache miss
  (:class:`CompileMonitor`, :func:`compile_monitor`);
* prints one line on stderr when a kernel is compiled for the first time (:data:`NOTE`);
* warms up exactly the kernels a run needs -- the same mode on subsets of the same descriptors
  (:func:`warm_up`) -- so that the timed run that follows only executes machine code.

>>> with compile_monitor(note=False) as cm:
...     pass
>>> cm.seconds, cm.count
(0.0, 0)
"""
from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager

import numpy as np
from numba.core import event

__all__ = ["CompileMonitor", "compile_monitor", "warm_up", "exclude_compile_time", "NOTE", "WARM_UP_FEATURES"]

NOTE = ("guidedmatch: compiling Numba kernels for this descriptor type (first run only; cached for later runs, "
        "and not counted in the reported times) ...")
#: features per image used to warm up (enough for the progressive phase and a parallel final pass)
WARM_UP_FEATURES = 4096

_note_lock = threading.Lock()
_note_printed = False


class CompileMonitor(event.Listener):
    """Numba listener for ``"numba:compile"``: total seconds of (outermost) compilations, their count, and a one-line
    note on stderr at the first compilation of the process (``note=True``)."""

    def __init__(self, note: bool = True, stream=None):
        self.note = note
        self.stream = stream
        self.seconds = 0.0
        self.count = 0
        self._depth = 0
        self._t0 = 0.0

    def on_start(self, ev) -> None:
        global _note_printed
        if self._depth == 0:
            self._t0 = time.perf_counter()
            if self.note:
                with _note_lock:
                    if not _note_printed:
                        _note_printed = True
                        print(NOTE, file=self.stream or sys.stderr, flush=True)
        self._depth += 1

    def on_end(self, ev) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._t0
            self.count += 1


@contextmanager
def compile_monitor(note: bool = True, stream=None):
    """Context manager yielding a :class:`CompileMonitor` active inside the block."""
    mon = CompileMonitor(note, stream)
    with event.install_listener("numba:compile", mon):
        yield mon


def exclude_compile_time(result, seconds: float):
    """``result`` with ``stats.time_s`` reduced by ``seconds`` of compilation that happened during the run, which
    is reported as ``stats.details["jit_compile_s"]`` instead (unchanged when ``seconds`` is 0)."""
    if not seconds:
        return result
    import dataclasses

    st = result.stats
    details = {**st.details, "jit_compile_s": float(seconds)}
    stats = dataclasses.replace(st, time_s=max(0.0, st.time_s - seconds), details=details)
    return dataclasses.replace(result, stats=stats)


def _strongest(f, n: int):
    """The ``n`` strongest features of ``f`` (by response; the first ``n`` without responses), in index order."""
    if len(f) <= n:
        return f
    if f.responses is not None:
        idx = np.sort(np.argsort(-f.responses, kind="stable")[:n])
    else:
        idx = np.arange(n)
    return f.subset(idx)


def warm_up(f1, f2, mode: str, config=None, *, note: bool = True, max_features: int = WARM_UP_FEATURES) -> float:
    """Compile (or load from the cache) every kernel ``match(f1, f2, mode, config)`` needs, untimed.

    Runs the same mode and config on the ``max_features`` strongest features of each image (same descriptor dtype
    and length, hence the same kernel specializations; enough queries for the parallel final pass). Prints
    :data:`NOTE` on stderr when something is actually compiled. Returns the seconds spent compiling (0.0 when
    everything was cached). Any kernel the warm-up run did not reach is still compiled by the timed run; callers
    measure that with :func:`compile_monitor` and report it separately.
    """
    from .matcher import match

    a, b = _strongest(f1, max_features), _strongest(f2, max_features)
    if len(a) == 0 or len(b) == 0:
        return 0.0
    with compile_monitor(note=note) as cm:
        try:
            match(a, b, mode=mode, config=config)
        except Exception:  # the real run reports errors; a warm-up never hides or raises them
            pass
    return cm.seconds
