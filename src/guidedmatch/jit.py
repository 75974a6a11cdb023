"""Numba compilation kept out of reported timings.

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
#: features per image used to warm up: enough for the progressive phase, the model fits and the final pass to run
#: (a guided run's warm-up is guided too, see :func:`warm_up`); the SIFT demo's warm-ups load all 9 kernels at 2048
WARM_UP_FEATURES = 2048

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
    and length, hence the same kernel specializations); when the full run is guided, so is the warm-up (its
    ``auto_bf`` is turned off: the subset may be below the brute-force threshold). Prints
    :data:`NOTE` on stderr when something is actually compiled. Returns the seconds spent compiling (0.0 when
    everything was cached). Any kernel the warm-up run did not reach is still compiled by the timed run; callers
    measure that with :func:`compile_monitor` and report it separately.
    """
    from .config import MatcherConfig, Mode
    from .matcher.run import _bf_wins, match
    from .validation import config_from

    a, b = _strongest(f1, max_features), _strongest(f2, max_features)
    if len(a) == 0 or len(b) == 0:
        return 0.0
    with compile_monitor(note=note) as cm:
        try:
            cfg = config_from(MatcherConfig, config)
            binary = np.asarray(f1.descriptors).dtype == np.uint8
            if Mode.parse(mode).guided and (len(a), len(b)) != (len(f1), len(f2)) and \
                    _bf_wins(cfg, len(f1), len(f2), binary) is None:
                cfg = cfg.replace(auto_bf=False)  # the full run is guided (not auto-bf): its smaller warm-up too
            match(a, b, mode=mode, config=cfg)
        except Exception:  # the real run reports errors; a warm-up never hides or raises them
            pass
    return cm.seconds


# --------------------------------------------------------------------------- first run: compile on both cores
#: "0": compile in the foreground only; "1": always use the helper processes on a cold cache; unset: when a core is idle
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


#: kernel groups of a first run, each compiled by a helper process (one per core): ``"guided"`` (~2.8 CPU-seconds
#: for SIFT) and ``"order"`` (~3.2 s)
HELPER_GROUPS = ("guided", "order")


def _precompile(detector: str, group: str) -> None:
    """Compile (into the on-disk cache) one group of the kernels a run of ``detector`` features needs, by direct
    calls on small arrays of the exact argument types the matcher passes:

    * ``"guided"``: first the brute-force top-2 (mode ``bf`` and the guided modes' unguided phase) and, for SIFT,
      the exact-uint8 descriptor check; then the guided candidate kernel of ``detector``'s descriptor kind and the
      strip index's counting sort (every guided mode);
    * ``"order"``: the spatial-order kernels (modes with ``so``), through :func:`~guidedmatch.spatial_order.
      fit_spatial_order` and a lookup on a synthetic monotone match set with outliers, and the search-region kernel.

    A group that misses a specialization costs nothing but time: the caller's warm-up compiles whatever is not in
    the cache (and reports it).
    """
    from . import kernels

    rng = np.random.default_rng(0)
    n = 64
    sift = detector == "sift"
    desc = rng.integers(0, 256, (n, 128)).astype(np.float32)
    if group == "guided":
        if sift:
            d = kernels.as_exact_uint8(desc)
            kernels.top2_gemm_serial(desc @ desc.T, np.ones(n, np.float32), np.ones(n, np.float32), False)
            kernels.topk_gemm_serial(desc @ desc.T, np.ones(n, np.float32), np.ones(n, np.float32), 4)  # IVF coarse
        else:
            d = kernels.pack_bits_u64(desc[:, :32].astype(np.uint8))
            kernels.hamming_top2(d, d)
            kernels.hamming_col_best(d, d)
        pts = rng.uniform(0, 100, (n, 2))
        cols, rows = kernels.build_strips(pts, 16.0, 0), kernels.build_strips(pts, 16.0, 1)
        lines = np.tile([0.0, 1.0, -50.0], (n, 1))
        kernels.guided_top2(np.arange(n), d, d, lines, True, 5.0, np.full(n, -np.inf), np.full(n, np.inf), cols, rows)
    elif group == "order":
        from .spatial_order import admissible_x_ranges, fit_spatial_order

        m = 300
        x1 = rng.uniform(0, 1000, m)
        x2 = 0.9 * x1 + 40 + rng.normal(0, 2, m)
        x2[:30] = rng.uniform(0, 1000, 30)  # wrong matches
        y = rng.uniform(0, 800, m)
        model = fit_spatial_order(x1, x2, y1=y, y2=y, likely_correct=np.arange(m) >= 30)
        admissible_x_ranges(model, x1[:8] + 0.5)
        from .matcher import search_regions

        search_regions(np.c_[x1[:8], y[:8]], model, np.eye(3), (0.0, 1000.0), "band")  # the region kernel
    else:
        raise ValueError(f"unknown kernel group {group!r}")


def _helper_main(detector: str, group: str, seconds=None) -> None:  # pragma: no cover - a forked helper
    import os
    import warnings

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    warnings.simplefilter("ignore")
    t0 = time.process_time()
    try:
        _precompile(detector, group)
    except BaseException:  # the caller's warm-up compiles (and reports) whatever a helper did not
        os._exit(1)
    if seconds is not None:
        seconds.value = time.process_time() - t0


class _Forked:
    """A forked helper (:mod:`multiprocessing` "fork" context) with the ``subprocess.Popen`` methods used here;
    ``seconds``: its compilation time (CPU seconds) once it has finished (None before, or when it failed)."""

    def __init__(self, proc, seconds):
        self.proc = proc
        self._seconds = seconds

    @property
    def seconds(self) -> float | None:
        v = self._seconds.value
        return v if self.proc.exitcode == 0 and v >= 0 else None

    def wait(self, timeout=None):
        import subprocess

        self.proc.join(timeout)
        if self.proc.exitcode is None:
            raise subprocess.TimeoutExpired("guidedmatch.jit helper", timeout)
        return self.proc.exitcode

    def poll(self):
        return self.proc.exitcode

    @property
    def returncode(self):
        return self.proc.exitcode

    def kill(self):
        self.proc.kill()


def _can_fork() -> bool:
    """Helpers are forked (Linux): they then cost only their compilation, nothing the caller would not do itself."""
    import multiprocessing

    return (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon)  # a daemonic process may not have children


def _start_helper(detector: str, group: str):
    """Start the helper process compiling kernel ``group``: forked on Linux, once this process has imported the
    matcher and initialised Numba's compiler (both ~0.7 CPU-seconds that every fresh interpreter pays again, and
    that this process needs anyway), else ``python -m guidedmatch.jit DETECTOR GROUP``."""
    import multiprocessing
    import subprocess

    if _can_fork():
        _init_compiler()
        ctx = multiprocessing.get_context("fork")
        seconds = ctx.Value("d", -1.0, lock=False)
        proc = ctx.Process(target=_helper_main, args=(detector, group, seconds), name=f"guidedmatch-jit-{group}",
                           daemon=True)
        proc.start()
        return _Forked(proc, seconds)
    return subprocess.Popen([sys.executable, "-m", "guidedmatch.jit", detector, group],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


_compiler_ready = False


def _init_compiler() -> None:
    """Import what the helpers compile and compile one trivial function (Numba's one-off compiler set-up)."""
    global _compiler_ready
    if _compiler_ready:
        return
    from numba import njit

    from . import kernels, matcher, spatial_order  # noqa: F401 - imported for the forked helpers

    njit(cache=False)(lambda x: x + 1)(1)
    _compiler_ready = True


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
    """Helper processes compiling the kernels of a first run while the caller reads and detects
    (:func:`background_compile`): ``procs`` maps a group of :data:`HELPER_GROUPS` to its process. ``wait(group)``
    waits for one group's helper (all by default) and returns the seconds waited (first-run compilation); a helper
    still running after ``timeout`` seconds is killed (the caller's warm-up then compiles what it left out)."""

    def __init__(self, procs: dict):
        self.procs = dict(procs)
        self.helpers = len(self.procs)
        #: CPU seconds the finished helpers spent compiling (forked helpers report it; None when one did not)
        self.helper_seconds: float | None = 0.0

    def __bool__(self) -> bool:
        return bool(self.procs)

    def wait(self, group: str | None = None, timeout: float = 180.0) -> float:
        import subprocess

        if not self.procs:
            return 0.0
        t0 = time.perf_counter()
        for g in [group] if group is not None else list(self.procs):
            p = self.procs.pop(g, None)
            if p is None:
                continue
            try:
                p.wait(timeout=max(1.0, timeout - (time.perf_counter() - t0)))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            sec = getattr(p, "seconds", None)
            self.helper_seconds = None if sec is None or self.helper_seconds is None else self.helper_seconds + sec
        return time.perf_counter() - t0

    def stop(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        self.procs = {}

    def cancel(self) -> None:
        """Stop the helpers: the run turned out not to need their kernels (:func:`guided_kernels_needed`); the
        foreground compiles what it does need. Numba writes a cache entry's data before its index entry, atomically,
        so a killed helper leaves no broken entry."""
        self.stop()
        self.helpers, self.helper_seconds = 0, 0.0


def guided_kernels_needed(f1, f2, modes, config=None) -> bool:
    """Whether matching ``f1`` with ``f2`` in any of ``modes`` runs the guided matcher, i.e. a guided mode that
    ``auto_bf`` does not replace by brute force at these feature counts (e.g. ORB below 12000 features: every
    mode is brute force, so the guided and spatial-order kernels the helpers compile would never be used)."""
    from .config import MatcherConfig, Mode
    from .matcher.run import _bf_wins
    from .validation import config_from

    cfg = config_from(MatcherConfig, config)
    binary = np.asarray(f1.descriptors).dtype == np.uint8
    return any(Mode.parse(m).guided and _bf_wins(cfg, len(f1), len(f2), binary) is None for m in modes)


def _background_wanted() -> bool:
    """``GUIDEDMATCH_BACKGROUND_COMPILE``: ``0`` never, ``1`` always, unset (or ``auto``): always where helpers are
    forked (:func:`_can_fork`: they duplicate no work, and the 1-minute load average right after a ``pip install``
    would wrongly say "busy"), else when a core is idle by the load average (a fresh interpreter per helper costs
    ~0.7 CPU-seconds of imports, wasted on a saturated machine)."""
    import os

    value = os.environ.get(BACKGROUND_ENV, "auto").strip().lower()
    if value == "0":
        return False
    if value == "1":
        return True
    return _can_fork() or _idle_cores() >= 1


@contextmanager
def background_compile(detector: str, modes=("so+epi+ia",), *, stream=None):
    """On a first run (:func:`cache_is_cold`) of guided ``modes``, compile the kernels they need for ``detector``
    features in helper processes -- one per group of :data:`HELPER_GROUPS` the modes use (``"order"`` only for
    ``so`` modes) -- while the block runs (image reading, detection); yields a :class:`BackgroundCompile` (falsy
    when nothing was started: warm cache, ``bf`` alone, no idle core by the load average, or
    ``GUIDEDMATCH_BACKGROUND_COMPILE=0``; ``=1`` starts them whatever the load).
    Call ``wait()`` before matching (or ``wait(group)`` before warming up the modes that group serves); on leaving
    the block the helpers are waited for (or killed on an error), never left running. The caller's warm-up then loads
    the kernels from the cache, and compiles whatever is missing.
    """
    global _note_printed
    procs = {}
    modes = [str(m) for m in modes]
    guided = any(m != "bf" for m in modes)  # bf alone needs one small kernel: compiled in the foreground
    if guided and _background_wanted() and cache_is_cold(detector):
        with _note_lock:
            if not _note_printed:
                _note_printed = True
                print(NOTE, file=stream or sys.stderr, flush=True)
        groups = [g for g in HELPER_GROUPS if g != "order" or any("so" in m for m in modes)]
        for group in groups:
            try:
                procs[group] = _start_helper(detector, group)
            except Exception:  # cannot start one (no fork, no resources): the foreground compiles instead
                break
    bg = BackgroundCompile(procs)
    try:
        yield bg
    except BaseException:
        bg.stop()
        raise
    bg.wait()


if __name__ == "__main__":  # helper process of background_compile: python -m guidedmatch.jit DETECTOR GROUP
    _precompile(sys.argv[1], sys.argv[2])
