"""guidedmatch: guided image feature matching with feature spatial order (Teng & Dong) and epipolar geometry.

One namespace for the public API (``import guidedmatch as gm``)::

    f1, f2 = gm.detect("left.jpg"), gm.detect("right.jpg")      # Features (SIFT by default)
    res = gm.match(f1, f2, "so+epi+ia", config={"band_px": 3})  # MatchResult: pairs (M,2), distances (M,), stats
    res.stats.comparisons, res.stats.fallbacks                   # MatchStats: every field documented

Names are loaded on first use (``import guidedmatch`` itself imports no NumPy, OpenCV or Numba); ``dir(gm)`` and
``gm.__all__`` list them. Architecture and the paper sections behind each module: ``docs/architecture.md``.
"""
from __future__ import annotations

import importlib
import sys
import zlib as _zlib  # noqa: F401 - load the system zlib before pycolmap can: see _runtime.zlib_shadowed

__version__ = "0.1.0"

#: public name -> module (relative to the package) that defines it
_EXPORTS = {
    # features and matching
    "detect": "features", "Features": "features", "load_image": "features",
    "match": "matcher", "GuidanceModels": "matcher",
    "MatcherConfig": "config", "Mode": "config", "MODES": "config",
    "MatchResult": "results", "MatchStats": "results", "ModelUpdate": "results", "Fallback": "results",
    "PhaseTimes": "results", "CandidateStats": "results", "Failure": "base",
    "match_bruteforce": "bruteforce",
    "prepare": "prepared", "PreparedImage": "prepared", "PreparedConfig": "prepared", "StartMemo": "prepared",
    # estimators
    "estimate_fundamental": "epipolar",
    "fit_spatial_order": "spatial_order", "SpatialOrderConfig": "spatial_order",
    "align_from_fundamental": "alignment", "check_alignment": "alignment", "safe_alignment": "alignment",
    "two_view_geometry": "geometry", "TwoViewGeometry": "geometry", "VerdictConfig": "geometry",
    "spread_matches": "geometry",
    # collections (COLMAP / hloc)
    "open_source": "collection", "images_to_database": "collection", "exhaustive_pairs": "collection",
    "sequential_pairs": "collection", "pairs_from_spec": "collection", "ColmapSink": "collection",
    "H5MatchesSink": "collection", "cap_two_view_inliers": "collection",
    "tighten_two_view_inliers": "collection",
    "match_collection": "collection.engine", "CollectionConfig": "collection.engine",
    "CollectionReport": "collection.engine",
    # errors
    "GuidedMatchError": "errors", "ConfigError": "errors", "InputError": "errors", "ImageReadError": "errors",
    "OutputError": "errors", "DatabaseError": "errors", "DatabaseBusyError": "errors", "MemoryLimitError": "errors",
}

__all__ = sorted(_EXPORTS) + ["__version__"]

from ._runtime import pin_faiss_blas as _pin_faiss_blas

# faiss's bundled OpenBLAS falls back to generic SSE3 kernels on recent CPUs: name the CPU's own kernels before faiss
# loads (3-4x faster index builds; _runtime.pin_faiss_blas). Too late if faiss is already imported: say so if slow.
if _pin_faiss_blas() is None and "faiss" in sys.modules:
    from ._runtime import faiss_blas as _faiss_blas

    _blas = _faiss_blas()
    if _blas["generic"]:
        import warnings

        warnings.warn(f"faiss was imported before guidedmatch and its bundled OpenBLAS runs the generic "
                      f"{_blas['core']} kernels on this CPU (3-4x slower GEMMs: index builds, faiss peers); "
                      "import guidedmatch first or set OPENBLAS_CORETYPE before importing faiss", RuntimeWarning,
                      stacklevel=2)

if "pycolmap" in sys.modules:  # imported before us: it may already have captured the system zlib
    from ._runtime import zlib_shadowed as _zlib_shadowed

    _why = _zlib_shadowed()
    if _why:
        import warnings

        warnings.warn(_why, RuntimeWarning, stacklevel=2)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'guidedmatch' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
