"""The matcher's kernel warm-ups, registered with :mod:`guidedmatch.jit` when the matcher is imported.

:mod:`guidedmatch.jit` measures compilation and runs helper processes, but imports neither the matcher nor its
kernels; what to run for a warm-up is registered here (:func:`guidedmatch.jit.register_warmup`):

* ``"match"``: the matcher on the strongest features of each image (:func:`warm_up_match`);
* ``"guided_kernels_needed"``: whether a run is guided at these feature counts (:func:`guided_kernels_needed`);
* ``"cache_index"``: the on-disk cache index of the guided candidate kernel (a first run has none for its dtype);
* ``"guided"`` / ``"order"``: the helper groups of a first run (:func:`precompile_guided`, :func:`precompile_order`).
"""
from __future__ import annotations

import numpy as np

from .. import exact, jit, kernels
from ..config import MatcherConfig, Mode
from ..validation import config_from
from .models import search_regions
from .run import _bf_wins, match


def _strongest(f, n: int):
    """The ``n`` strongest features of ``f`` (by response; the first ``n`` without responses), in index order."""
    if len(f) <= n:
        return f
    if f.responses is not None:
        idx = np.sort(np.argsort(-f.responses, kind="stable")[:n])
    else:
        idx = np.arange(n)
    return f.subset(idx)


def warm_up_match(f1, f2, mode: str, config=None, max_features: int = jit.WARM_UP_FEATURES) -> None:
    """``match`` in ``mode`` on the ``max_features`` strongest features of each image (same descriptor dtype and
    length, hence the same kernel specializations); guided (``auto_bf`` off) when the full run is guided, since the
    subset may be below the brute-force threshold. Errors propagate (:func:`guidedmatch.jit.warm_up` swallows them:
    the real run reports them)."""
    a, b = _strongest(f1, max_features), _strongest(f2, max_features)
    if len(a) == 0 or len(b) == 0:
        return
    cfg = config_from(MatcherConfig, config)
    binary = np.asarray(f1.descriptors).dtype == np.uint8
    if Mode.parse(mode).guided and (len(a), len(b)) != (len(f1), len(f2)) and \
            _bf_wins(cfg, len(f1), len(f2), binary) is None:
        cfg = cfg.replace(auto_bf=False)  # the full run is guided (not auto-bf): its smaller warm-up too
    match(a, b, mode=mode, config=cfg)


def guided_kernels_needed(f1, f2, modes, config=None) -> bool:
    """Whether matching ``f1`` with ``f2`` in any of ``modes`` runs the guided matcher (a guided mode that ``auto_bf``
    does not replace by brute force at these feature counts)."""
    cfg = config_from(MatcherConfig, config)
    binary = np.asarray(f1.descriptors).dtype == np.uint8
    return any(Mode.parse(m).guided and _bf_wins(cfg, len(f1), len(f2), binary) is None for m in modes)


def cache_index():
    """Keys of the on-disk cache index of the guided candidate kernel (Numba internals)."""
    return kernels._guided_ser._cache._cache_file._load_index()


def precompile_guided(detector: str) -> None:
    """Helper group ``"guided"``: the brute-force top-k (mode ``bf``, the unguided phase, the IVF coarse step), the
    exact recompute (:mod:`guidedmatch.exact`) and, for SIFT, the exact-uint8 descriptor check; then the guided candidate kernel of ``detector``'s descriptor kind and
    the strip index's counting sort (every guided mode). Direct calls on small arrays of the argument types the
    matcher passes."""
    rng = np.random.default_rng(0)
    n = 64
    desc = rng.integers(0, 256, (n, 128)).astype(np.float32)
    if detector == "sift":
        d = kernels.as_exact_uint8(desc)
        cand, approx = kernels.topk_gemm_serial(desc @ desc.T, np.ones(n, np.float32), np.ones(n, np.float32), 4)
        exact.exact_top(desc, desc, cand, approx, 2, delta=1.0)  # the exact recompute of every float search
        exact.exact_top_among(desc[0], desc, np.arange(n), 2)    # its rare fallback
    else:
        d = kernels.pack_bits_u64(desc[:, :32].astype(np.uint8))
        kernels.hamming_top2(d, d)
        kernels.hamming_col_best(d, d)
    pts = rng.uniform(0, 100, (n, 2))
    cols, rows = kernels.build_strips(pts, 16.0, 0), kernels.build_strips(pts, 16.0, 1)
    lines = np.tile([0.0, 1.0, -50.0], (n, 1))
    kernels.guided_top2(np.arange(n), d, d, lines, True, 5.0, np.full(n, -np.inf), np.full(n, np.inf), cols, rows)


def precompile_order(detector: str) -> None:
    """Helper group ``"order"``: the spatial-order kernels (modes with ``so``), through
    :func:`~guidedmatch.spatial_order.fit_spatial_order` and a lookup on a synthetic monotone match set with outliers,
    and the search-region kernel. ``detector`` does not matter here (no descriptors)."""
    from ..spatial_order import admissible_x_ranges, fit_spatial_order

    rng = np.random.default_rng(0)
    m = 300
    x1 = rng.uniform(0, 1000, m)
    x2 = 0.9 * x1 + 40 + rng.normal(0, 2, m)
    x2[:30] = rng.uniform(0, 1000, 30)  # wrong matches
    y = rng.uniform(0, 800, m)
    model = fit_spatial_order(x1, x2, y1=y, y2=y, likely_correct=np.arange(m) >= 30)
    admissible_x_ranges(model, x1[:8] + 0.5)
    search_regions(np.c_[x1[:8], y[:8]], model, np.eye(3), (0.0, 1000.0), "band")  # the region kernel


jit.register_warmup("match", warm_up_match)
jit.register_warmup("guided_kernels_needed", guided_kernels_needed)
jit.register_warmup("cache_index", cache_index)
jit.register_warmup("guided", precompile_guided)
jit.register_warmup("order", precompile_order)
