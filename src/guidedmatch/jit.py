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


# --------------------------------------------------------------------------- first run: compile on both cores
#: set to "0" to compile in the foreground only (the CLI otherwise uses two helper processes on a cold cache)
BACKGROUND_ENV = "GUIDEDMATCH_BACKGROUND_COMPILE"


def _kernel_dtype(detector: str) -> str:
    """dtype of the guided kernel's descriptor arrays for a detector: byte-valued SIFT runs as uint8, binary as
    uint64 words (:func:`~guidedmatch.kernels.pack_bits_u64`)."""
    return "uint8" if detector == "sift" else "uint64"


def cache_is_cold(detector: str) -> bool:
    """True when Numba's on-disk cache holds no guided kernel for ``detector``'s descriptor type (a first run).

    Reads the cache index of :data:`guidedmatch.kernels._guided_ser` (Numba internals, so any failure -- caching
    disabled, another Numba version -- answers False: no background work, the foreground compiles as usual).
    """
    try:
        from . import kernels

        index = kernels._guided_ser._cache._cache_file._load_index()
        tag = f"Array({_kernel_dtype(detector)}, 2"
        return not any(tag in str(key) for key in index)
    except Exception:
        return False


def _precompile(detector: str, part: str, with_bf: bool = False) -> None:
    """Compile one half of the kernels a run of ``detector`` features needs (in a helper process; they land in the
    on-disk cache). ``part="parallel"``: the multi-threaded guided kernel, and with ``with_bf`` the brute-force
    top-2 of mode ``bf`` (direct calls on small arrays of the exact argument types); ``"serial"``: everything a
    ``so+epi+ia`` run of <= 1500 features reaches (single-threaded guided kernel, spatial-order and alignment
    kernels) on a small rendered scene."""
    rng = np.random.default_rng(0)
    if part == "parallel":
        from . import kernels

        n = kernels.PARALLEL_MIN_QUERIES
        pts = rng.uniform(0, 100, (n, 2))
        if detector == "sift":
            d = rng.integers(0, 256, (n, 128)).astype(np.uint8)
        else:
            d = kernels.pack_bits_u64(rng.integers(0, 256, (n, 32), dtype=np.uint8))
        cols, rows = kernels.build_strips(pts, 16.0, 0), kernels.build_strips(pts, 16.0, 1)
        lines = np.tile([0.0, 1.0, -50.0], (n, 1))
        kernels.guided_top2(np.arange(n), d, d, lines, True, 5.0, np.full(n, -np.inf), np.full(n, np.inf), cols, rows)
        if not with_bf:
            return
        if detector == "sift":
            kernels.top2_gemm(np.zeros((256, 64), np.float32), np.zeros(64, np.float32), np.zeros(256, np.float32),
                              False)
        else:
            kernels.hamming_top2(d[:8], d[:8])
    else:
        from .features import detect
        from .matcher import match
        from .testing.scenes import make_scene

        scene = make_scene((640, 480), roll_deg=20.0, seed=1)
        match(detect(scene.image1, detector, 1500), detect(scene.image2, detector, 1500), "so+epi+ia")


def _idle_cores() -> float:
    """Usable cores minus the 1-minute load average (helpers only pay off when a core is idle; on a saturated
    machine they add ~3 CPU-seconds of imports for nothing)."""
    import os

    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    try:
        return n - os.getloadavg()[0]
    except (AttributeError, OSError):
        return float(n)


class BackgroundCompile:
    """Two helper processes compiling the kernels of a first run while the caller reads and detects
    (:func:`background_compile`). ``wait()`` returns the seconds spent waiting for them."""

    def __init__(self, procs):
        self.procs = procs

    def __bool__(self) -> bool:
        return bool(self.procs)

    def wait(self, timeout: float = 600.0) -> float:
        import subprocess

        if not self.procs:
            return 0.0
        t0 = time.perf_counter()
        for p in self.procs:
            try:
                p.wait(timeout=max(1.0, timeout - (time.perf_counter() - t0)))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = []
        return time.perf_counter() - t0

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        self.procs = []


@contextmanager
def background_compile(detector: str, modes=("so+epi+ia",), *, stream=None):
    """On a first run (:func:`cache_is_cold`) of guided ``modes``, compile the kernels they need for ``detector``
    features in two helper processes -- one per core -- while the block runs (image reading, detection); yields a
    :class:`BackgroundCompile` (falsy when nothing was started: warm cache, no idle core (load average), or
    ``GUIDEDMATCH_BACKGROUND_COMPILE=0``).
    Call ``wait()`` before matching; on leaving the block the helpers are waited for (or killed on an error), never
    left running. The caller's warm-up then loads the kernels from the cache, and compiles whatever is missing.
    """
    import os
    import subprocess

    global _note_printed
    procs = []
    modes = [str(m) for m in modes]
    guided = any(m != "bf" for m in modes)  # bf alone needs one small kernel: compiled in the foreground
    if guided and os.environ.get(BACKGROUND_ENV, "1") != "0" and _idle_cores() >= 1 and cache_is_cold(detector):
        with _note_lock:
            if not _note_printed:
                _note_printed = True
                print(NOTE, file=stream or sys.stderr, flush=True)
        for part in ("parallel", "serial"):
            try:
                procs.append(subprocess.Popen([sys.executable, "-m", "guidedmatch.jit", detector, part,
                                               "bf" if "bf" in modes else "-"],
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            except OSError:
                break
    bg = BackgroundCompile(procs)
    try:
        yield bg
    except BaseException:
        bg.stop()
        raise
    bg.wait()


if __name__ == "__main__":  # helper process of background_compile: python -m guidedmatch.jit DETECTOR PART
    _precompile(sys.argv[1], sys.argv[2], sys.argv[3] == "bf")
