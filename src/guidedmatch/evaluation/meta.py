"""Run metadata and atomic JSON output for benchmark scripts (CONVENTIONS: every benchmark JSON carries
the git commit, library versions, CPU model and thread settings of the run)."""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

THREAD_ENV_VARS = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                   "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS",
                   "GLIBC_TUNABLES")   # glibc.malloc.hugetlb=1: the command line's huge pages (_runtime.hugepage_env)


def _repo_root() -> Path:
    """The repository root (this file is ``src/guidedmatch/evaluation/meta.py``)."""
    return Path(__file__).resolve().parents[3]


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_info(repo: str | os.PathLike | None = None) -> dict[str, Any]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the repository (None when not a git checkout
    or without commits). ``dirty`` = uncommitted changes to tracked files other than the benchmark outputs
    (``reports/``, ``benchmarks/results/``: a rerun overwrites the previous, committed results)."""
    root = Path(repo) if repo is not None else _repo_root()
    commit = _git(["rev-parse", "HEAD"], root)
    status = _git(["status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)reports",
                   ":(exclude)benchmarks/results"], root)
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def _version(module: str) -> str | None:
    try:
        mod = __import__(module)
    except Exception:  # noqa: BLE001 - any import failure means "not available"
        return None
    return str(getattr(mod, "__version__", "unknown"))


def cpu_model() -> str | None:
    """CPU model name from ``/proc/cpuinfo`` (Linux), else ``platform.processor()`` or None."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith(("model name", "hardware", "cpu model")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def cpu_vector(flags) -> str | None:
    """The widest x86 SIMD extension among ``/proc/cpuinfo`` ``flags``: ``"AVX-512"``, ``"AVX2"``, ``"AVX"``,
    ``"SSE4.2"``, or None. Our kernels (NumPy's BLAS, faiss, Numba) run twice as many lanes per instruction with
    AVX-512 as with AVX2; COLMAP's matcher gains less from it, so the matching-time ratio depends on it (an AVX-512
    Xeon: fox 0.49x COLMAP's; an AVX2 EPYC: 0.65x, accuracy history, twenty-second round).

    >>> cpu_vector("fpu sse4_2 avx avx2 fma avx512f".split()), cpu_vector({"sse4_2", "avx", "avx2"}), cpu_vector(())
    ('AVX-512', 'AVX2', None)
    """
    flags = set(flags)
    for name, flag in (("AVX-512", "avx512f"), ("AVX2", "avx2"), ("AVX", "avx"), ("SSE4.2", "sse4_2")):
        if flag in flags:
            return name
    return None


def cpu_label(meta: dict) -> str:
    """``"<cpu_model> (<cpu_vector>)"`` of a run's metadata for report headers, e.g. ``"AMD EPYC (AVX2)"``.

    >>> cpu_label({"cpu_model": "AMD EPYC", "cpu_vector": "AVX2"}), cpu_label({"cpu_model": "x"}), cpu_label({})
    ('AMD EPYC (AVX2)', 'x', 'None')
    """
    vec = meta.get("cpu_vector")
    return f"{meta.get('cpu_model')}" + (f" ({vec})" if vec else "")


def run_metadata(seed: int | None = None) -> dict[str, Any]:
    """Everything needed to interpret a benchmark number later, as one flat dict.

    Keys: ``git_commit`` (None outside a git checkout / before the first commit), ``git_dirty``;
    versions ``python``, ``numpy``, ``scipy``, ``cv2``, ``numba``, ``faiss``, ``pycolmap`` (its SIFT and matcher
    are the peers'), ``guidedmatch`` (None when
    not installed); ``cpu_model`` (``/proc/cpuinfo``), ``cpu_vector`` (its widest SIMD extension:
    :func:`cpu_vector`), ``logical_cores`` (``os.cpu_count()``),
    ``usable_cores`` (CPU affinity); threads: ``numba_num_threads`` (``numba.get_num_threads()``),
    ``cv2_num_threads``, ``faiss_omp_threads``, ``faiss_blas`` (the kernels of faiss's OpenBLAS:
    ``_runtime.faiss_blas``) and the environment variables ``NUMBA_NUM_THREADS``,
    ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ... (None when unset);
    ``platform``, ``machine``, ``timestamp_utc`` (ISO 8601), ``seed``; ``load_average`` (1-minute load average when
    the run started, None where the OS has none: above ~1 on 2 cores, other jobs were running).
    """
    git = git_info()
    meta: dict[str, Any] = {"git_commit": git["commit"], "git_dirty": git["dirty"],
                            "python": sys.version.split()[0]}
    for name in ("numpy", "scipy", "cv2", "numba", "faiss", "pycolmap", "guidedmatch"):
        meta[name] = _version(name)
    meta["cpu_model"] = cpu_model()
    from .._runtime import _cpu_flags   # an empty set without /proc/cpuinfo: cpu_vector None

    meta["cpu_vector"] = cpu_vector(_cpu_flags())
    meta["logical_cores"] = os.cpu_count()
    try:
        meta["usable_cores"] = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        meta["usable_cores"] = None
    try:
        import numba

        meta["numba_num_threads"] = int(numba.get_num_threads())
        meta["numba_threading_layer"] = _numba_layer(numba)
    except Exception:  # noqa: BLE001
        meta["numba_num_threads"] = None
    try:
        import cv2

        meta["cv2_num_threads"] = int(cv2.getNumThreads())
    except Exception:  # noqa: BLE001
        meta["cv2_num_threads"] = None
    try:
        import faiss

        meta["faiss_omp_threads"] = int(faiss.omp_get_max_threads())
    except Exception:  # noqa: BLE001
        meta["faiss_omp_threads"] = None
    try:
        from .._runtime import faiss_blas

        meta["faiss_blas"] = faiss_blas()
    except Exception:  # noqa: BLE001
        meta["faiss_blas"] = None
    for k in THREAD_ENV_VARS:
        meta[k] = os.environ.get(k)
    meta["platform"] = platform.platform()
    meta["machine"] = platform.machine()
    meta["timestamp_utc"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    meta["seed"] = seed
    meta["load_average"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return meta


def _numba_layer(numba) -> str | None:
    try:
        return str(numba.threading_layer())
    except Exception:  # noqa: BLE001 - raises before the first parallel function ran
        return None


def to_jsonable(obj: Any) -> Any:
    """Recursively convert to JSON-ready Python: NumPy scalars/arrays -> int/float/bool/list, tuples/sets
    -> lists, ``Path`` -> str, dataclasses -> dicts, dict keys -> str; non-finite floats (NaN, inf) ->
    ``None`` so the output is strict JSON."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, (str, type(None))):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    return str(obj)


def json_default(obj: Any) -> Any:
    """``default=`` hook for ``json.dump(s)``: NumPy scalars/arrays, paths, sets, dataclasses, dates
    (anything else -> ``str``). Unlike :func:`to_jsonable` it cannot reach plain-float NaN/inf."""
    return to_jsonable(obj)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON (see :func:`to_jsonable`; NaN/inf become ``null``) atomically: a temp
    file in the same folder, flushed and fsynced, then given normal permissions and renamed over ``path``
    (:func:`guidedmatch.features.publish`, i.e. ``os.replace``). Creates the parent folder. Returns the path."""
    from ..features import publish

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def default_cache(name: str) -> str:
    """Where a benchmark keeps what it may reuse (extracted databases, finished runs): ``$GUIDEDMATCH_CACHE/NAME``,
    default ``~/.cache/guidedmatch/NAME`` -- outside the repository.

    >>> default_cache("large").endswith("large")
    True
    """
    import os
    from pathlib import Path

    root = os.environ.get("GUIDEDMATCH_CACHE") or str(Path.home() / ".cache" / "guidedmatch")
    return str(Path(root) / name)
