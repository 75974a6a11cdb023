"""Process-level settings of the command line and of collection worker processes (never of a library call), and
two process-level checks that library calls use too (:func:`zlib_shadowed`: pycolmap's exported zlib;
:func:`faiss_blas`: the kernel of faiss's own OpenBLAS, chosen by :func:`pin_faiss_blas` at ``import guidedmatch``).

>>> freeze_gc_at_exit(); freeze_gc_at_exit()   # registers once
>>> len(_REGISTERED)
1
"""
from __future__ import annotations

import atexit
import contextlib
import gc
import os
import sys
import threading

_REGISTERED: list = []
_OWN_PROCESS: list = []
_ZLIB_VERDICT: list = []
_FAISS_PIN: list = []  # what pin_faiss_blas did in this process: [(core or None, why)]

#: CPU flags (``/proc/cpuinfo``) -> the OpenBLAS kernel family they allow, best first; names OpenBLAS 0.3.15 knows
_OPENBLAS_CORES = (("SkylakeX", frozenset({"avx512f", "avx512dq", "avx512cd", "avx512bw", "avx512vl"})),
                   ("Haswell", frozenset({"avx2", "fma"})))
_GENERIC_CORES = frozenset({"prescott", "core2", "katmai", "coppermine", "northwood", "banias", "atom", "nehalem",
                            "dunnington", "penryn", "opteron", "barcelona", "athlon", "sandybridge", "bulldozer",
                            "piledriver", "steamroller", "excavator", "unknown"})


def mark_own_process() -> None:
    """Declare this process guidedmatch's own (the command line, a worker process of a local cluster we started):
    :func:`without_numba_blas_probe` then applies. A library call never marks its caller's process."""
    if not _OWN_PROCESS:
        _OWN_PROCESS.append(True)


class _HideScipy:
    """A ``sys.meta_path`` finder that makes ``scipy`` / ``scipy.*`` (not yet imported) unimportable, for one
    thread only: another thread importing SciPy meanwhile is not affected."""

    def __init__(self, thread_id: int) -> None:
        self.thread_id = thread_id

    def find_spec(self, fullname, path=None, target=None):
        if threading.get_ident() == self.thread_id and (fullname == "scipy" or fullname.startswith("scipy.")):
            raise ModuleNotFoundError(f"{fullname} hidden while Numba's CPU target is set up", name=fullname)
        return None


@contextlib.contextmanager
def without_numba_blas_probe():
    """Set Numba's CPU target up inside this block without its BLAS probe. Yields whether the probe is skipped.

    The first compiled-kernel call of a process imports ``numba.np.arraymath``, whose import calls
    ``_check_blas()``: ``import scipy.linalg.cython_blas``, i.e. all of ``scipy.linalg`` (0.12-0.14 s holding the
    GIL, measured; 0.15 s with what SciPy's array-API layer imports from NumPy). The probe's only use is
    ``_HAVE_BLAS``, which picks BLAS over a plain loop for the inner products of ``np.correlate`` /
    ``np.convolve`` in *jitted* code; none of our kernels calls those (nor any BLAS routine: a kernel that did
    would import SciPy at its own compilation, after this block). So in a process of ours
    (:func:`mark_own_process`) the block hides SciPy from this thread while the target loads, and Numba records
    "no BLAS" -- the start-up of ``guidedmatch colmap`` is that much shorter. Anywhere else (a library call in the
    user's process, whose own jitted code may want BLAS for those two functions), or when the target or
    ``scipy.linalg`` is already loaded, it does nothing."""
    if not _OWN_PROCESS or "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        yield False
        return
    finder = _HideScipy(threading.get_ident())
    sys.meta_path.insert(0, finder)
    try:
        yield True
    finally:
        sys.meta_path.remove(finder)


def plain_sigterm() -> None:
    """SIGTERM ends the process at once, without a stack dump: importing pycolmap installs glog's failure signal
    handler for SIGTERM too, which prints ~20 lines of "*** SIGTERM received ... stack trace" (a crash, to a user whose
    job scheduler or ``timeout`` stopped the run) and symbolizes inside the handler, where it can deadlock (1 of 60
    processes signalled while importing never ended). The default action is what ``kill -9`` does to our files:
    every stored pair complete, a rerun resumes. Main thread only (``signal.signal`` elsewhere raises); pycolmap is
    imported first, so that its import cannot install the handler again afterwards. For our own processes (the
    CLI's commands, our worker processes), not for a library user's."""
    import signal

    if threading.current_thread() is threading.main_thread():
        import pycolmap  # noqa: F401 - its import installs the handler replaced here

        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def hugepage_env(environ=None, *, thp_mode: str | None = None, glibc: str | None = None) -> dict | None:
    """The environment to run a command in so that glibc's malloc backs its large blocks with transparent huge
    pages (``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``), or None when that does not apply: not glibc >= 2.35, the
    kernel's THP mode is not ``madvise`` (``always`` needs nothing, ``never`` allows nothing), the user set
    ``GLIBC_TUNABLES`` already, or ``GUIDEDMATCH_HUGEPAGES=0``.

    Why: OpenCV's SIFT allocates its upsampled scale space afresh for every image, ~2.7 million page faults for
    Herz-Jesus-P8's 8 images, as much CPU time in the kernel as in SIFT itself; with huge pages 0.25 million, and
    ``guidedmatch extract`` 9.1-10.5 s -> 7.2-8.3 s (docs/performance.md). A tunable is read at process start only:
    :func:`reexec_with_hugepages` starts the command again with it.

    >>> hugepage_env({}, thp_mode="always [madvise] never", glibc="glibc 2.36")["GLIBC_TUNABLES"]
    'glibc.malloc.hugetlb=1'
    >>> [hugepage_env(e, thp_mode=m, glibc=g) for e, m, g in [({}, "[always] madvise never", "glibc 2.36"),
    ...  ({}, "always [madvise] never", "glibc 2.31"), ({"GLIBC_TUNABLES": "x=1"}, "always [madvise] never", "glibc 2.36"),
    ...  ({"GUIDEDMATCH_HUGEPAGES": "0"}, "always [madvise] never", "glibc 2.36")]]
    [None, None, None, None]
    """
    environ = dict(os.environ if environ is None else environ)
    if "GLIBC_TUNABLES" in environ or environ.get("GUIDEDMATCH_HUGEPAGES", "1") == "0":
        return None
    if glibc is None:
        try:
            glibc = os.confstr("CS_GNU_LIBC_VERSION") or ""
        except (AttributeError, ValueError, OSError):
            return None
    parts = glibc.split()
    try:
        version = tuple(int(x) for x in parts[1].split(".")[:2]) if len(parts) == 2 and parts[0] == "glibc" else ()
    except ValueError:
        return None
    if not version or version < (2, 35):
        return None
    if thp_mode is None:
        try:
            with open("/sys/kernel/mm/transparent_hugepage/enabled") as fh:
                thp_mode = fh.read()
        except OSError:
            return None
    if "[madvise]" not in thp_mode:
        return None
    environ["GLIBC_TUNABLES"] = HUGEPAGE_TUNABLES
    environ[_HUGEPAGES_OURS] = HUGEPAGE_TUNABLES   # which value this process set (hugepages_off_for_children)
    return environ


HUGEPAGE_TUNABLES = "glibc.malloc.hugetlb=1"
_HUGEPAGES_OURS = "GUIDEDMATCH_SET_GLIBC_TUNABLES"


def hugepages_off_for_children() -> bool:
    """Take the huge-page tunable that :func:`reexec_with_hugepages` set out of this process's environment, so that
    processes started from now on (a matching cluster's workers) run without it; a ``GLIBC_TUNABLES`` the user set is
    left alone. True when it was removed. This process keeps its own malloc setting (glibc reads it at start only).

    Why: the pages help the extraction (OpenCV's scale space) and cost the matching -- fox's ``guidedmatch colmap``
    with them in every process 71.9-82.2 s against 62.5-75.1 s without (alternating fresh runs, collection history,
    nineteenth round)."""
    if os.environ.get(_HUGEPAGES_OURS) is None or os.environ.get("GLIBC_TUNABLES") != os.environ[_HUGEPAGES_OURS]:
        return False
    del os.environ["GLIBC_TUNABLES"], os.environ[_HUGEPAGES_OURS]
    return True


def reexec_with_hugepages() -> None:
    """Start this process's command again (same interpreter, options and arguments: ``sys.orig_argv``) with
    :func:`hugepage_env`, when it applies; returns only when it does not. For the command line's own process, before
    it has done anything (never from a library call: the process is replaced)."""
    env = hugepage_env()
    argv = getattr(sys, "orig_argv", None)
    if env is None or not argv:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *argv[1:]], env)


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


def _loaded_objects() -> list[str]:
    """Paths of this process's shared objects in the order the dynamic loader loaded them (glibc's
    ``dl_iterate_phdr`` walks the link map in that order); ``[]`` where it is not available."""
    import ctypes

    class _Info(ctypes.Structure):
        _fields_ = [("addr", ctypes.c_void_p), ("name", ctypes.c_char_p), ("phdr", ctypes.c_void_p),
                    ("phnum", ctypes.c_uint16)]

    names: list[str] = []

    def visit(info, size, data):
        names.append((info.contents.name or b"").decode("utf-8", "replace"))
        return 0

    try:
        callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(_Info), ctypes.c_size_t, ctypes.c_void_p)(visit)
        ctypes.CDLL(None).dl_iterate_phdr(callback, None)
    except (OSError, AttributeError):
        return []
    return names


def zlib_shadowed() -> str | None:
    """Why zlib cannot be used in this process (a sentence for an error or warning), or None when it can.

    pycolmap 4.2.1's wheel links zlib(-ng) into its extension and exports its functions (``deflate``,
    ``deflateEnd``, ...), and the extension also needs the system's ``libz.so.1``. When pycolmap is the first
    module of a process to load that library, the loader binds the library's own internal calls to pycolmap's
    copies (``LD_DEBUG=bindings`` shows ``libz.so.1`` bound to ``pycolmap/_core...so``: ``deflateReset``,
    ``deflateEnd``, ...). From then on every user of the system zlib -- Python's ``zlib``, so ``np.savez_compressed``
    and ``gzip``; Pillow's PNG writer, so matplotlib's ``savefig``; OpenCV's PNG codec -- mixes two zlib
    implementations on one stream and the process aborts (``free(): invalid pointer``). ``import pycolmap`` as
    the first line of a script does it (so does ``import hloc``, which imports pycolmap first). Anything that loads
    zlib earlier prevents it: ``import guidedmatch`` imports Python's ``zlib`` first for this reason, and NumPy,
    OpenCV and Dask load it too. The test: in load order, ``libz.so`` comes after pycolmap's extension, and that
    extension exports ``deflateEnd``. Linux only; None elsewhere, and None while pycolmap is not imported."""
    if "pycolmap" not in sys.modules or not sys.platform.startswith("linux"):
        return None
    if _ZLIB_VERDICT:  # once pycolmap is loaded the load order is fixed: decided once per process
        return _ZLIB_VERDICT[0]
    objects = _loaded_objects()
    core = next((i for i, n in enumerate(objects)
                 if os.path.basename(os.path.dirname(n)) == "pycolmap" and n.endswith(".so")), None)
    libz = next((i for i, n in enumerate(objects) if os.path.basename(n).startswith("libz.so")), None)
    verdict = None
    if core is not None and libz is not None and libz > core:
        import ctypes

        try:
            exports = hasattr(ctypes.CDLL(objects[core]), "deflateEnd")
        except OSError:
            exports = False
        if exports:
            verdict = ("pycolmap was imported before anything else in this process loaded zlib, and its extension "
                       "exports its own zlib, to which the system libz.so.1 got bound: any zlib use in this process "
                       "(PNG files, np.savez_compressed, gzip) would abort it ('free(): invalid pointer'). Import "
                       "guidedmatch (or zlib, or numpy) before pycolmap")
    _ZLIB_VERDICT.append(verdict)
    return verdict


def openblas_coretype(flags, machine: str) -> str | None:
    """The OpenBLAS kernel family (an ``OPENBLAS_CORETYPE`` value) a CPU with these ``/proc/cpuinfo`` ``flags``
    runs, or None (not x86-64, or no AVX2 + FMA: OpenBLAS's own choice is as good as ours).

    >>> openblas_coretype("fpu sse2 avx avx2 fma avx512f avx512dq avx512cd avx512bw avx512vl".split(), "x86_64")
    'SkylakeX'
    >>> openblas_coretype({"avx2", "fma", "avx512f"}, "x86_64"), openblas_coretype({"avx2", "fma"}, "aarch64")
    ('Haswell', None)
    """
    if str(machine).lower() not in ("x86_64", "amd64"):
        return None
    flags = set(flags)
    return next((core for core, needs in _OPENBLAS_CORES if needs <= flags), None)


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def pin_faiss_blas() -> str | None:
    """Make faiss's bundled OpenBLAS run the kernels this CPU supports; ``import guidedmatch`` calls it. Returns the
    ``OPENBLAS_CORETYPE`` it set, or None.

    The faiss-cpu wheels (1.15.1 included) bundle OpenBLAS 0.3.15, which does not recognise recent server CPUs and
    then falls back to its generic ``Prescott`` (SSE3) kernels: on this project's machine (an AVX-512 Xeon) every
    faiss GEMM ran 3-4x slower than NumPy's -- k-means training plus adding 61.6k SIFT descriptors to an IVF index
    0.86-1.1 -> 0.19 s, ``faiss.knn`` (61.6k x 496, k=1) 0.44 -> 0.08-0.11 s (docs/pairs.md). OpenBLAS reads
    ``OPENBLAS_CORETYPE`` once, when its library loads, so this sets it (from ``/proc/cpuinfo``:
    :func:`openblas_coretype`) before faiss is first imported. It changes nothing when faiss is already imported,
    on other platforms, when the variable is already set (your choice is kept), or with
    ``GUIDEDMATCH_FAISS_CORETYPE=off``; ``GUIDEDMATCH_FAISS_CORETYPE=NAME`` sets ``NAME`` instead. The variable stays
    set for the process and the worker processes it starts; OpenBLAS libraries loaded later (NumPy's, if NumPy is
    imported after guidedmatch) read it too, and the kernel family named is one the CPU runs. What happened is in
    :func:`faiss_blas` and in every benchmark's metadata."""
    if _FAISS_PIN:
        return _FAISS_PIN[0][0]
    setting = os.environ.get("GUIDEDMATCH_FAISS_CORETYPE", "auto").strip()
    core, why = None, None
    if "faiss" in sys.modules:
        why = "faiss was imported before guidedmatch"
    elif not sys.platform.startswith("linux"):
        why = "not Linux"
    elif os.environ.get("OPENBLAS_CORETYPE"):
        why = "OPENBLAS_CORETYPE was already set"
    elif setting.lower() == "off":
        why = "GUIDEDMATCH_FAISS_CORETYPE=off"
    else:
        core = setting if setting.lower() != "auto" else openblas_coretype(_cpu_flags(), os.uname().machine)
        why = "set by guidedmatch" if core else "no AVX2 + FMA: OpenBLAS's own choice kept"
        if core:
            os.environ["OPENBLAS_CORETYPE"] = core
    _FAISS_PIN.append((core, why))
    return core


def faiss_blas() -> dict:
    """The kernel family faiss's OpenBLAS runs in this process (imports faiss): ``{"core": name or None,
    "pinned": what pin_faiss_blas set or None, "why": ..., "generic": bool}`` -- ``generic`` when it is a
    pre-AVX2 fallback although the CPU allows better (:func:`pin_faiss_blas` could not apply)."""
    import faiss  # noqa: F401 - its OpenBLAS must be loaded to be reported
    from threadpoolctl import threadpool_info

    core = next((lib.get("architecture") for lib in threadpool_info()
                 if lib.get("internal_api") == "openblas" and "faiss" in str(lib.get("filepath", ""))), None)
    pinned, why = _FAISS_PIN[0] if _FAISS_PIN else (None, "pin_faiss_blas not called")
    better = openblas_coretype(_cpu_flags(), os.uname().machine) if hasattr(os, "uname") else None
    generic = bool(core and better and core.lower() in _GENERIC_CORES)
    return {"core": core, "pinned": pinned, "why": why, "generic": generic}


def require_zlib(path) -> None:
    """Raise :class:`~guidedmatch.errors.OutputError` naming ``path`` when zlib cannot be used in this process
    (:func:`zlib_shadowed`) -- before a write that would otherwise abort the process."""
    why = zlib_shadowed()
    if why is not None:
        from .errors import OutputError

        raise OutputError(f"cannot write {path}: {why}")
