"""Search-range (gap) table (Teng & Dong §III-C): which image-2 gaps a new image-1 feature may match into.

For every image-1 gap ``h`` and image-2 gap ``k`` of the ``n`` matches inside omega*, a hypothetical match has
``H = h + k - 2 C[h, k]`` inversions (``C[h, k] = #{m < h : sigma(m) < k}``); gaps whose correctness probability
``P(G | H) >= threshold`` are admissible. :func:`build_gap_table` is the fused O(n^2)-time, O(n)-memory Numba pass
(``_gap_kernel`` in :mod:`._kernels`) used by the fit; :func:`gap_inversion_table` and :func:`gap_probability_table`
are dense O(n^2)-memory references for tests and diagnostics. The table always uses the **Gaussian** model of
``P(H | G)`` (``SpatialOrderConfig.probability`` affects the per-match probabilities only).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._kernels import _gap_kernel
from .config import SpatialOrderConfig
from .probability import (
    _OUT_OF_RANGE,
    _P_G_CLIP,
    OrderNoise,
    _beta_moments,
    bad_inversion_range,
    probability_correct,
)

__all__ = ["GapTable", "build_gap_table", "gap_inversion_table", "gap_probability_table"]


class GapTable(NamedTuple):
    """Admissible image-2 gaps per image-1 gap ``h = 0..n`` (all int64; see ``SpatialOrderModel``).

    ``gap_lo, gap_hi (n+1,)``: hull of the admissible gaps (``gap_lo > gap_hi``: none); ``count (n+1,)``: number
    admissible; ``runs_ptr (n+2,)``, ``runs (R, 2)``: the exact admissible sets as inclusive runs ``(first, last)``,
    those of row ``h`` being ``runs[runs_ptr[h]:runs_ptr[h+1]]`` (CSR).
    """

    gap_lo: np.ndarray
    gap_hi: np.ndarray
    count: np.ndarray
    runs_ptr: np.ndarray
    runs: np.ndarray


def gap_inversion_table(sigma) -> tuple[np.ndarray, np.ndarray]:
    """Inversions of a hypothetical match in every gap pair (Teng & Dong §III-C), vectorized 2-D prefix sums.

    Image-1 gap ``h`` (``i_h = h - 0.5`` in 0-based ranks, Teng & Dong's ``i + 0.5``) and image-2 gap ``k``:
    ``C[h, k] = #{m < h : sigma(m) < k}``, ``H^l = h - C``, ``H^r = k - C``.

    Returns:
        ``(H^l, H^r)``, each ``(N+1, N+1) int64`` (rows: image-1 gaps, columns: image-2 gaps). O(N^2) memory --
        for tests and diagnostics; :func:`fit_spatial_order` uses a fused Numba pass that never stores it.
    """
    sigma = np.asarray(sigma, dtype=np.int64)
    n = len(sigma)
    a = np.zeros((n + 1, n + 1), dtype=np.int64)
    a[np.arange(n) + 1, sigma + 1] = 1
    c = a.cumsum(0).cumsum(1)
    hh = np.arange(n + 1)[:, None]
    kk = np.arange(n + 1)[None, :]
    return hh - c, kk - c


def gap_probability_table(sigma, n_good, config: SpatialOrderConfig | None = None,
                          noise: tuple[float, float] = (0.0, 0.0), *, method: str = "gaussian") -> np.ndarray:
    """``(N+1, N+1)`` probability that a new feature in image-1 gap h matches correctly into image-2 gap k.

    Dense NumPy reference (O(N^2) memory) of what :func:`build_gap_table` thresholds (``config.threshold``), with
    ``method="gaussian"`` as there; ``method="exact"`` evaluates the exact model instead (diagnostics only, slow:
    O(|S_beta| H) per cell). ``config``: num_beta and var_floor (default ``SpatialOrderConfig()``);
    ``config.probability`` is not used. ``noise = (mean, var)`` is the order noise added to ``H | G``
    (``model.order_noise`` of a fitted model).
    """
    config = SpatialOrderConfig() if config is None else config
    noise = OrderNoise(*noise)
    hl, hr = gap_inversion_table(sigma)
    n = len(sigma)
    hh, kk = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    p = probability_correct(hh.ravel(), kk.ravel(), (hl + hr).ravel(), n, n_good, n, method=method,
                            num_beta=config.num_beta, var_floor=config.var_floor + noise.var, new_feature=True,
                            mean_shift=noise.mean)
    return p.reshape(n + 1, n + 1)


def build_gap_table(sigma_w, n_good: float, config: SpatialOrderConfig,
                    noise: tuple[float, float] = (0.0, 0.0)) -> GapTable:
    """The thresholded search-range table of the window permutation ``sigma_w`` (``(n,) int64``), fused Numba pass.

    Gaussian ``P(H | G)`` with ``config.num_beta`` beta nodes and variance floor ``config.var_floor + noise.var``,
    mean shifted by ``noise.mean`` (:func:`~guidedmatch.spatial_order.order_noise`); gaps with
    ``P(G | H) >= config.threshold`` are admitted. Equals thresholding :func:`gap_probability_table` except for
    cells within rounding of the threshold (tested).
    """
    noise = OrderNoise(*noise)
    n = len(sigma_w)
    nb = max(float(n) - float(n_good), 0.0)
    gaps = np.arange(n + 1, dtype=np.float64)
    m1, s1 = _beta_moments(gaps, n, nb, config.num_beta)  # image-1 gaps: rows
    m2, s2 = m1, s1  # image-2 gaps: same left counts 0..n, same population
    blo, bhi = bad_inversion_range(gaps, n, n_good)
    p_good = float(np.clip(n_good / max(n, 1), *_P_G_CLIP))
    th = float(config.threshold)  # in (0, 1) (validated)
    return GapTable(*_gap_kernel(np.ascontiguousarray(sigma_w, dtype=np.int64), m1, s1, m2, s2, blo, bhi, nb,
                                 math.log(p_good), math.log(1.0 - p_good), math.log(th / (1.0 - th)),
                                 float(max(config.var_floor + noise.var, 1e-9)), math.log(_OUT_OF_RANGE),
                                 float(noise.mean)))
