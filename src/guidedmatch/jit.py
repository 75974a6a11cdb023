"""Numba compilation kept out of reported timings.

The kernels (:mod:`guidedmatch.kernels`, :mod:`guidedmatch.strip_index`, :mod:`guidedmatch.spatial_order`) are
compiled by Numba the first time they see a descriptor kind (``cache=True`` stores the machine code next to the
sources, or in ``NUMBA_CACHE_DIR``, so later processes only load it). A first call therefore costs seconds of
compilation that are not matching time. This module

* measures compilation through Numba's ``"numba:compile"`` event, which fires only on a cache miss
  (:class:`CompileMonitor`, :func:`compile_monitor`);
* prints one line on stderr when a kernel is compiled for the first time (:data:`NOTE`);
* warms up exactly the kernels a run needs -- the same mode on subsets of the same descriptors
  (:func:`warm_up`) -- so that the timed run that follows only executes machine code;
* compiles a first run's kernels in helper processes while the caller reads and detects (:func:`background_compile`).

What to run for a warm-up is a registry (:func:`register_warmup`) that the matcher fills when it is imported
(``guidedmatch.matcher.warmup``): this module imports neither the matcher nor the kernels it serves.

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

from numba.core import event

__all__ = ["CompileMonitor", "compile_monitor", "warm_up", "exclude_compile_time", "NOTE", "WARM_UP_FEATURES",
           "register_warmup", "registered_warmup", "WARMUP_NAMES"]

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


#: name -> function, filled by the modules whose kernels need warming up (:func:`register_warmup`); this module
#: imports none of them
_WARMUPS: dict = {}
#: what each registered name does (the registry's contract; a registration under another name is refused)
WARMUP_NAMES = {
    "match": "fn(f1, f2, mode, config, max_features) -> None: run the matcher on subsets of the features",
    "guided_kernels_needed": "fn(f1, f2, modes, config) -> bool: a run in any of modes is guided",
    "cache_index": "fn() -> iterable: the keys of the on-disk cache index of the guided candidate kernel",
    "guided": "fn(detector) -> None: compile the brute-force / guided candidate kernels (helper group)",
    "order": "fn(detector) -> None: compile the spatial-order and search-region kernels (helper group)",
}


def register_warmup(name: str, fn) -> None:
    """Register ``fn`` under ``name`` (one of :data:`WARMUP_NAMES`): the matcher (``guidedmatch.matcher.warmup``)
    registers its warm-ups when it is imported, so this module never imports the matcher or its kernels. A later
    registration under the same name replaces the earlier one."""
    if name not in WARMUP_NAMES:
        raise ValueError(f"unknown warm-up name {name!r}; expected one of {sorted(WARMUP_NAMES)}")
    _WARMUPS[name] = fn


def registered_warmup(name: str):
    """The function registered under ``name``; a clear error when nothing registered it (the matcher registers every
    name when ``guidedmatch.matcher`` is imported: import it first)."""
    fn = _WARMUPS.get(name)
    if fn is None:
        raise RuntimeError(f"no warm-up registered under {name!r}: import guidedmatch.matcher first (it registers the "
                           "matcher's kernel warm-ups with guidedmatch.jit)")
    return fn


def warm_up(f1, f2, mode: str, config=None, *, note: bool = True, max_features: int = WARM_UP_FEATURES) -> float:
    """Compile (or load from the cache) every kernel ``match(f1, f2, mode, config)`` needs, untimed.

    Runs the registered ``"match"`` warm-up: the same mode and config on the ``max_features`` strongest features of
    each image (same descriptor dtype and length, hence the same kernel specializations); when the full run is guided,
    so is the warm-up (its ``auto_bf`` is turned off: the subset may be below the brute-force threshold). Prints
    :data:`NOTE` on stderr when something is actually compiled. Returns the seconds spent compiling (0.0 when
    everything was cached). Any kernel the warm-up run did not reach is still compiled by the timed run; callers
    measure that with :func:`compile_monitor` and report it separately.
    """
    run = registered_warmup("match")
    if len(f1) == 0 or len(f2) == 0:
        return 0.0
    with compile_monitor(note=note) as cm:
        try:
            run(f1, f2, mode, config, max_features)
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

    Reads the cache index of the guided candidate kernel (the registered ``"cache_index"``; Numba internals, so any
    failure -- caching disabled, another Numba version -- answers False: no background work, the foreground compiles
    as usual).
    """
    probe = registered_warmup("cache_index")
    try:
        index = probe()
        tag = f"Array({_kernel_dtype(detector)}, 2"
        return not any(tag in str(key) for key in index)
    except Exception:
        return False


#: kernel groups of a first run, each compiled by a helper process (one per core): ``"guided"`` (~2.8 CPU-seconds
#: for SIFT) and ``"order"`` (~3.2 s)
HELPER_GROUPS = ("guided", "order")


def _precompile(detector: str, group: str) -> None:
    """Compile (into the on-disk cache) one group of :data:`HELPER_GROUPS` for ``detector`` features: the function
    registered under the group's name (``guidedmatch.matcher.warmup``: direct calls of the kernels on small arrays of
    the exact argument types the matcher passes). A group that misses a specialization costs nothing but time: the
    caller's warm-up compiles whatever is not in the cache (and reports it)."""
    if group not in HELPER_GROUPS:
        raise ValueError(f"unknown kernel group {group!r}")
    registered_warmup(group)(detector)


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
    """Start the helper process compiling kernel ``group``: forked on Linux, once this process has initialised Numba's
    compiler (~0.7 CPU-seconds, with the matcher's imports, that every fresh interpreter pays again, and that this
    process needs anyway), else a fresh interpreter that imports the modules which registered the warm-ups."""
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
    # a fresh interpreter: import the modules that registered the warm-ups, then compile the group
    modules = sorted({getattr(fn, "__module__", None) for fn in _WARMUPS.values()} - {None, __name__})
    code = ("import importlib, sys\nfor m in sys.argv[3:]:\n    importlib.import_module(m)\n"
            f"importlib.import_module({__name__!r})._precompile(sys.argv[1], sys.argv[2])\n")
    return subprocess.Popen([sys.executable, "-c", code, detector, group, *modules],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


_compiler_ready = False


def _init_compiler() -> None:
    """Compile one trivial function (Numba's one-off compiler set-up) before forking helpers; the kernels' modules are
    already imported by whoever registered the warm-ups (the matcher)."""
    global _compiler_ready
    if _compiler_ready:
        return
    from numba import njit

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
    mode is brute force, so the guided and spatial-order kernels the helpers compile would never be used); the
    registered ``"guided_kernels_needed"``."""
    return bool(registered_warmup("guided_kernels_needed")(f1, f2, modes, config))


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
