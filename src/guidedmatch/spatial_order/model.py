"""The fitted spatial-order model: fitting, search-range lookup, per-match probabilities
(Talker §4-§5; Teng & Dong §III-B, §III-C). The steps are in the package docstring."""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..validation import config_from
from .config import SpatialOrderConfig
from ._kernels import _window_fit_gaussian
from .gap_table import GapTable, build_gap_table
from .probability import (_OUT_OF_RANGE, _P_G_CLIP, OrderNoise, _hermite_nodes, order_noise,
                          probability_correct)
from .ranks import estimate_n_good, inversions_per_match, permutation_from_coordinates
from .window import Window, refine_window, search_overlap

__all__ = ["SpatialOrderModel", "fit_spatial_order", "admissible_x_ranges", "match_probabilities"]


@dataclass(frozen=True, eq=False)
class SpatialOrderModel:
    """Spatial-order model of one match set (see the package docstring). Arrays are read-only by convention.

    Attributes:
        usable, reason: False + one sentence when the input has no usable order structure ("" when usable).
        n: number of matches given. n_window: matches inside omega*. n_good: N_G(omega*) (Talker Eq. 10).
        k_hat: normalized Kendall distance of the matches inside omega*.
        window1_x, window2_x: x-ranges (inclusive, pixels) of omega*'s rank windows in image 1 / image 2.
        x1_sorted, x2_sorted: ``(n_window,)`` x of the matches inside omega*, ascending, in image 1 / image 2.
        gap_lo, gap_hi: ``(n_window+1,) int64`` per image-1 gap, lowest / highest admissible image-2 gap
            (``gap_lo > gap_hi``: none admissible).
        gap_count: ``(n_window+1,) int64`` number of admissible image-2 gaps per image-1 gap.
        gap_contiguous: ``(n_window+1,) bool`` admissible set equals its hull.
        gap_runs_ptr, gap_runs: exact admissible sets as runs (CSR): runs of image-1 gap ``h`` are
            ``gap_runs[gap_runs_ptr[h]:gap_runs_ptr[h+1]]``, rows ``(first, last)`` image-2 gaps, inclusive.
        sigma: ``(n,) int64`` permutation of all matches (image-1 rank -> image-2 rank).
        rank1, rank2: ``(n,) int64`` x-rank of each given match in image 1 / image 2.
        omega: :class:`Window` ``(i1_lo, i1_hi, i2_lo, i2_hi)``, rank windows of omega*, half-open, among all n
            matches.
        in_window: ``(n,) bool`` per given match: inside omega* (image-1 rank in window 1 and image-2 in window 2).
        sigma_window: ``(n_window,) int64`` the re-ranked sub-permutation inside omega*.
        probabilities: ``(n,) float64`` P(i in G | H) per given match (model ``config.probability``), 0 outside
            omega*.
        config: the config used. timings: seconds per stage.
        order_noise: :class:`OrderNoise` ``(mean, var)`` of the inversions among likely-correct matches, added to
            ``H | G`` in the search-range table.
    """

    usable: bool
    reason: str
    n: int
    n_window: int
    n_good: float
    k_hat: float
    window1_x: tuple[float, float]
    window2_x: tuple[float, float]
    x1_sorted: np.ndarray
    x2_sorted: np.ndarray
    gap_lo: np.ndarray
    gap_hi: np.ndarray
    gap_count: np.ndarray
    gap_contiguous: np.ndarray
    gap_runs_ptr: np.ndarray
    gap_runs: np.ndarray
    sigma: np.ndarray
    rank1: np.ndarray
    rank2: np.ndarray
    omega: Window
    in_window: np.ndarray
    sigma_window: np.ndarray
    probabilities: np.ndarray
    config: SpatialOrderConfig = field(default_factory=SpatialOrderConfig)
    timings: dict = field(default_factory=dict)
    order_noise: OrderNoise = OrderNoise(0.0, 0.0)  # (mean, variance) of H_G added to H | G (see order_noise())

    def __bool__(self) -> bool:  # falsy when unusable, like guidedmatch.results.Failure
        return bool(self.usable)


# --------------------------------------------------------------------------------------------------------------
# One candidate window and its model
# --------------------------------------------------------------------------------------------------------------


class WindowFit(NamedTuple):
    """The matches inside one candidate window and their model (Talker Eq. 8, 10, 12).

    ``ranks1, ranks2 (nw,) int64``: image-1 ranks of the matches inside (ascending) and their image-2 ranks among all
    matches; ``sigma_w (nw,) int64``: the re-ranked sub-permutation; ``hl, hr (nw,) int64``: its per-match
    inversions; ``k_hat``, ``n_good``: K_hat and N_G of the window; ``prob (nw,)``: P(G | H) per match.
    """

    ranks1: np.ndarray
    ranks2: np.ndarray
    sigma_w: np.ndarray
    hl: np.ndarray
    hr: np.ndarray
    k_hat: float
    n_good: float
    prob: np.ndarray

    def consistency_score(self) -> tuple[int, float]:
        """Ranking key of the self-consistency pass: windows whose sum of P (the model's own expected number of
        correct matches) is >= 0.75 N_G count as consistent and rank by N_G (Talker's criterion) above all
        inconsistent ones, which rank by sum of P."""
        sum_p = float(self.prob.sum())
        return (1, float(self.n_good)) if sum_p >= 0.75 * self.n_good else (0, sum_p)


def _window_fit(sigma, w: Window, config: SpatialOrderConfig, method: str) -> WindowFit | None:
    """The sub-permutation inside window ``w`` and its N_G, K_hat, inversions and per-match probabilities
    (``method``: model of P(H | G)); None when fewer than 2 matches are inside.

    The Gaussian model (every call of the window search) runs as one ``nogil`` kernel
    (:func:`._kernels._window_fit_gaussian`: a collection's pair threads spent ~0.1 s of 28 pairs at 11k features
    holding the GIL in these NumPy steps); :func:`_window_fit_numpy` is the same computation in NumPy (the
    reference of the tests, and the path of the "exact" model)."""
    if method == "gaussian":
        w = Window(*w)
        nodes, weights = _hermite_nodes(max(int(config.num_beta), 1))
        r1, r2, sw, hl, hr, k_hat, n_good, prob = _window_fit_gaussian(
            np.ascontiguousarray(sigma, np.int64), int(w.i1_lo), int(w.i1_hi), int(w.i2_lo), int(w.i2_hi), nodes,
            weights, float(config.var_floor), _P_G_CLIP[0], _P_G_CLIP[1], _OUT_OF_RANGE)
        if len(sw) < 2:
            return None
        return WindowFit(r1, r2, sw, hl, hr, float(k_hat), float(n_good), prob)
    return _window_fit_numpy(sigma, w, config, method)


def _window_fit_numpy(sigma, w: Window, config: SpatialOrderConfig, method: str) -> WindowFit | None:
    """:func:`_window_fit` in NumPy, for any ``method``."""
    n = len(sigma)
    w = Window(*w)
    ranks_in = np.arange(w.i1_lo, w.i1_hi)
    ranks1 = ranks_in[(sigma[ranks_in] >= w.i2_lo) & (sigma[ranks_in] < w.i2_hi)]  # image-1 ranks inside omega
    ranks2 = sigma[ranks1]
    nw = len(ranks2)
    if nw < 2:
        return None
    mark = np.zeros(n, dtype=np.int64)
    mark[ranks2] = 1
    sigma_w = (np.cumsum(mark) - 1)[ranks2]
    hl, hr = inversions_per_match(sigma_w)
    k_hat = 2.0 * float(hl.sum()) / (nw * (nw - 1.0))
    n_good = float(estimate_n_good(k_hat, nw))
    prob = probability_correct(np.arange(nw), sigma_w, hl + hr, nw - 1, n_good, nw, method=method,
                               num_beta=config.num_beta, var_floor=config.var_floor)
    return WindowFit(ranks1, ranks2, sigma_w, hl, hr, k_hat, n_good, prob)


def _select_window(sigma, config: SpatialOrderConfig) -> tuple[Window, WindowFit | None]:
    """omega* and its fit: :func:`search_overlap`, then (our addition) the self-consistency pass.

    Talker's omega* spans the extreme correct matches, so the pass re-windows to the extreme ranks of the matches
    with P >= 1/2, re-refines, and keeps the candidate with the best :meth:`WindowFit.consistency_score` (a window
    that wrongly includes non-overlapping margins breaks A3 and makes the probabilities of the correct matches
    collapse). The probabilities here are always the Gaussian model's.
    """
    n = len(sigma)
    w = search_overlap(sigma, config.grid_fraction, config.overlap, config.refine)
    fit = _window_fit(sigma, w, config, "gaussian")
    if config.overlap == "none" or fit is None:
        return w, fit
    best_w, best_fit, best_score = w, fit, fit.consistency_score()
    cur = fit
    for _ in range(config.trim_rounds):
        likely = cur.prob >= 0.5
        if likely.sum() < 2:
            break
        trimmed = Window(int(cur.ranks1[likely].min()), int(cur.ranks1[likely].max()) + 1,
                         int(cur.ranks2[likely].min()), int(cur.ranks2[likely].max()) + 1)
        candidates = [trimmed]
        if config.refine:
            candidates.append(refine_window(sigma, trimmed, 2 * max(1, int(round(config.grid_fraction * n)))))
        cur = None
        for cand in candidates:  # the trimmed window itself and its refinement
            fc = _window_fit(sigma, cand, config, "gaussian")
            if fc is None:
                continue
            sc = fc.consistency_score()
            if sc > best_score:
                best_w, best_fit, best_score = cand, fc, sc
            cur = fc
        if cur is None:
            break
    return best_w, best_fit


def _unusable(reason, n, config, sigma=None, rank1=None, rank2=None, k_hat=float("nan"), n_good=0.0,
              timings=None) -> SpatialOrderModel:
    z = np.zeros(0, dtype=np.int64)
    sigma = z if sigma is None else sigma
    return SpatialOrderModel(
        usable=False, reason=reason, n=int(n), n_window=0, n_good=float(n_good), k_hat=float(k_hat),
        window1_x=(-np.inf, np.inf), window2_x=(-np.inf, np.inf),
        x1_sorted=np.zeros(0), x2_sorted=np.zeros(0),
        gap_lo=np.zeros(1, dtype=np.int64), gap_hi=np.zeros(1, dtype=np.int64),
        gap_count=np.ones(1, dtype=np.int64), gap_contiguous=np.ones(1, dtype=bool),
        gap_runs_ptr=np.array([0, 1], dtype=np.int64), gap_runs=np.zeros((1, 2), dtype=np.int64),
        sigma=sigma, rank1=z if rank1 is None else rank1, rank2=z if rank2 is None else rank2,
        omega=Window(0, len(sigma), 0, len(sigma)), in_window=np.zeros(int(n), dtype=bool), sigma_window=z,
        probabilities=np.zeros(int(n)), config=config, timings=timings or {},
    )


class _Coordinates(NamedTuple):
    """Validated ``(n,) float64`` coordinates (y1, y2 may be None), or ``reason`` != "" when unusable."""

    x1: np.ndarray | None
    x2: np.ndarray | None
    y1: np.ndarray | None
    y2: np.ndarray | None
    n: int
    reason: str = ""


def _coordinates(x1, x2, y1, y2) -> _Coordinates:
    """The coordinates as float arrays, or the reason why they carry no usable order information."""
    try:
        x1 = np.asarray(x1, dtype=np.float64).reshape(-1)
        x2 = np.asarray(x2, dtype=np.float64).reshape(-1)
        y1 = None if y1 is None else np.asarray(y1, dtype=np.float64).reshape(-1)
        y2 = None if y2 is None else np.asarray(y2, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        return _Coordinates(None, None, None, None, 0, f"coordinates not convertible to float arrays ({exc})")
    n = len(x1)
    reason = ""
    if len(x2) != n or (y1 is not None and len(y1) != n) or (y2 is not None and len(y2) != n):
        reason = f"coordinate arrays differ in length ({len(x1)}, {len(x2)})"
    elif n < 2:
        reason = f"fewer than 2 matches ({n})"
    else:
        for name, arr in (("x1", x1), ("x2", x2), ("y1", y1), ("y2", y2)):
            if arr is not None and not np.all(np.isfinite(arr)):
                reason = f"non-finite {name} coordinates ({int((~np.isfinite(arr)).sum())} of {n})"
                break
        else:
            if np.ptp(x1) == 0.0 or np.ptp(x2) == 0.0:
                reason = "all x equal in one image: no order information"
    return _Coordinates(x1, x2, y1, y2, n, reason)


# --------------------------------------------------------------------------------------------------------------
# Fit and lookup
# --------------------------------------------------------------------------------------------------------------


def fit_spatial_order(x1, x2, config: SpatialOrderConfig | dict | None = None, *, y1=None,
                      y2=None, likely_correct=None) -> SpatialOrderModel:
    """Fit the spatial-order model to matched coordinates (Talker §4-§5; Teng & Dong §III-B, §III-C).

    Args:
        x1, x2: ``(N,)`` x (pixels) of match m in image 1 / image 2 (e.g. image-2 coordinates after alignment).
        config: :class:`SpatialOrderConfig`, a dict of its fields, or None (defaults).
        y1, y2: optional ``(N,)`` y, used only to break x ties (then match index).
        likely_correct: optional ``(N,) bool``, matches known to be (mostly) correct by other means, e.g. the
            RANSAC inliers of F; when given, the order noise (:func:`order_noise`) is measured on them instead of on
            the matches with ``P >= 1/2``.

    Returns:
        :class:`SpatialOrderModel`; ``usable=False`` with a reason (never an exception) when N < 2, coordinates are
        not finite, all x are equal in an image, lengths differ, or there is no significant order structure:
        ``K_hat(omega*) >= 1/2``, or ``z = (1/2 - K_hat) / sd_null < min(min_z, 1.5 + 0.6 ln N)`` with
        ``sd_null^2 = (2n + 5) / (18 n (n - 1))`` the variance of K_hat of a random permutation of the n window matches.
        The ``ln N`` term pays for the window search picking the best of many windows; it was calibrated on uniform
        random permutations (max z over 100 draws: 2.8, 3.8, 4.9, 5.2, 4.9 at N = 10, 50, 200, 600, 2000). So
        all-correct sets need N >= 8, and very weak structure (N_G ~ 10 % of N) is reported unusable.
        A bad ``config`` raises :class:`~guidedmatch.errors.ConfigError`.

    Example: 30 matches in the same x order in both images except 3 wrong ones (matches 3, 17, 25).

    >>> import numpy as np
    >>> x1 = np.arange(30.0)
    >>> x2 = 2.0 * x1 + 1.0
    >>> x2[[3, 17, 25]] = [55.5, 2.5, 20.5]
    >>> model = fit_spatial_order(x1, x2)
    >>> bool(model), model.n_window, round(model.n_good, 1)  # usable, all in omega*, N_G (Talker Eq. 8)
    (True, 30, 24.3)
    >>> [round(float(p), 2) for p in model.probabilities[[2, 3, 17]]]  # P(G | H): a correct match, two wrong ones
    [0.98, 0.0, 0.0]
    >>> keep, lo, hi, _ = admissible_x_ranges(model, [10.5])  # a new image-1 feature at x = 10.5
    >>> bool(keep[0]), float(lo[0]), float(hi[0])  # its image-2 x search interval (true position: 22)
    (True, 11.0, 33.0)
    """
    config = config_from(SpatialOrderConfig, config)
    t0 = time.perf_counter()
    coords = _coordinates(x1, x2, y1, y2)
    if coords.reason:
        return _unusable(coords.reason, coords.n, config)
    x1, x2, y1, y2, n = coords.x1, coords.x2, coords.y1, coords.y2, coords.n

    sigma, r1, r2 = permutation_from_coordinates(x1, x2, y1, y2)
    t1 = time.perf_counter()
    w, fit = _select_window(sigma, config)
    t2 = time.perf_counter()
    x1s_all = np.sort(x1)
    x2s_all = np.sort(x2)
    timings = {"ranks": t1 - t0, "overlap": t2 - t1}
    if fit is None:
        return _unusable("fewer than 2 matches inside the overlap window", n, config, sigma, r1, r2,
                         timings=timings)
    nw = len(fit.sigma_w)
    in_window = (r1 >= w.i1_lo) & (r1 < w.i1_hi) & (r2 >= w.i2_lo) & (r2 < w.i2_hi)
    null_sd = math.sqrt((2.0 * nw + 5.0) / (18.0 * nw * (nw - 1.0)))
    z = (0.5 - fit.k_hat) / null_sd
    z_crit = min(config.min_z, 1.5 + 0.6 * math.log(n))
    if fit.k_hat >= 0.5 or z < z_crit:
        return _unusable(f"no significant order structure: K_hat={fit.k_hat:.3f} over {nw} matches "
                         f"({z:.1f} null sd below 1/2 < {z_crit:.1f})", n, config, sigma, r1, r2, fit.k_hat,
                         fit.n_good, timings)
    prob_w = fit.prob  # Gaussian model: drives the order noise and (through it) the gap table
    prob_out = prob_w  # the reported per-match probabilities, of the model config.probability
    if config.probability != "gaussian":
        prob_out = probability_correct(np.arange(nw), fit.sigma_w, fit.hl + fit.hr, nw - 1, fit.n_good, nw,
                                       method=config.probability, num_beta=config.num_beta,
                                       var_floor=config.var_floor)
    probs = np.zeros(n)
    # input match m with image-1 rank r1[m]; position of r1[m] in fit.ranks1
    pos = np.full(n, -1, dtype=np.int64)
    pos[fit.ranks1] = np.arange(nw)
    m_in = np.nonzero(in_window)[0]
    probs[m_in] = prob_out[pos[r1[m_in]]]
    noise = OrderNoise(0.0, 0.0)
    if config.order_noise:
        if likely_correct is not None and len(likely_correct) == n:
            lc = np.zeros(nw)
            lc[pos[r1[m_in]]] = np.asarray(likely_correct, bool)[m_in]
            noise = order_noise(fit.sigma_w, lc)
        else:
            noise = order_noise(fit.sigma_w, prob_w)
    t3 = time.perf_counter()
    if config.gap_table:
        table = build_gap_table(fit.sigma_w, fit.n_good, config, noise)
    else:  # no table: lookups refuse (see admissible_x_ranges)
        empty = np.zeros(0, np.int64)
        table = GapTable(empty, empty, empty, empty, np.zeros((0, 2), np.int64))
    t4 = time.perf_counter()
    timings.update({"probabilities": t3 - t2, "gap_table": t4 - t3, "total": t4 - t0})
    return SpatialOrderModel(
        usable=True, reason="", n=n, n_window=nw, n_good=fit.n_good, k_hat=fit.k_hat,
        window1_x=(float(x1s_all[w.i1_lo]), float(x1s_all[w.i1_hi - 1])),
        window2_x=(float(x2s_all[w.i2_lo]), float(x2s_all[w.i2_hi - 1])),
        x1_sorted=x1s_all[fit.ranks1], x2_sorted=x2s_all[np.sort(fit.ranks2)],
        gap_lo=table.gap_lo, gap_hi=table.gap_hi, gap_count=table.count,
        gap_contiguous=(table.count == np.maximum(table.gap_hi - table.gap_lo + 1, 0)),
        gap_runs_ptr=table.runs_ptr, gap_runs=table.runs, sigma=sigma, rank1=r1, rank2=r2, omega=w,
        in_window=in_window, sigma_window=fit.sigma_w, probabilities=probs, config=config, timings=timings,
        order_noise=noise,
    )


def admissible_x_ranges(model: SpatialOrderModel, xq) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image-2 x search interval for new image-1 features (Teng & Dong §III-B.2 and §III-C).

    Args:
        model: a fitted :class:`SpatialOrderModel`.
        xq: ``(M,)`` image-1 x (pixels) of new features.

    Returns:
        ``(keep, lo, hi, contiguous)``. ``keep (M,) bool``: False when xq is outside ``window1_x``, not finite, or
        no gap is admissible. ``lo, hi (M,) float64``: the hull of the admissible image-2 gaps as an x interval;
        gap ``k`` spans ``(x2_sorted[k-1], x2_sorted[k])`` with ``x2_sorted[-1] := -inf``, ``x2_sorted[n] := +inf``;
        treat the interval as closed (features at the bounding matched positions included). ``lo = hi = nan``
        where ``keep`` is False. ``contiguous (M,) bool``: the admissible gap set equals its hull. The image-1 gap
        is ``np.searchsorted(model.x1_sorted, xq, side="left")``. Unusable model: keep all True, lo=-inf, hi=+inf.
    """
    xq = np.asarray(xq, dtype=np.float64).reshape(-1)
    m = len(xq)
    if not model.usable:
        return (np.ones(m, dtype=bool), np.full(m, -np.inf), np.full(m, np.inf), np.ones(m, dtype=bool))
    if len(model.gap_lo) != model.n_window + 1:
        raise ValueError("this model was fitted with gap_table=False: it has no search-range table")
    h = np.searchsorted(model.x1_sorted, xq, side="left")
    glo = model.gap_lo[h]
    ghi = model.gap_hi[h]
    x1_lo, x1_hi = model.window1_x
    keep = (xq >= x1_lo) & (xq <= x1_hi) & (glo <= ghi)
    x2lo = np.concatenate([[-np.inf], model.x2_sorted])  # lower bound of gap k: x2_sorted[k-1]
    x2hi = np.concatenate([model.x2_sorted, [np.inf]])  # upper bound of gap k: x2_sorted[k]
    nw = model.n_window
    lo = x2lo[np.clip(glo, 0, nw)]
    hi = x2hi[np.clip(ghi, 0, nw)]
    lo = np.where(keep, lo, np.nan)
    hi = np.where(keep, hi, np.nan)
    return keep, lo, hi, model.gap_contiguous[h].copy()


def match_probabilities(x1, x2, model_or_config=None) -> np.ndarray:
    """``P(i in G | H^l, H^r)`` per given match (Talker Eq. 12; Teng & Dong Eq. 6-9), 0 outside omega*.

    Args:
        x1, x2: ``(N,)`` matched x in image 1 / image 2 (pixels).
        model_or_config: a model fitted on exactly these matches (its stored probabilities are returned), or a
            :class:`SpatialOrderConfig` / None (a model is fitted first). Unusable model: all zeros.
    """
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1)
    if isinstance(model_or_config, SpatialOrderModel):
        model = model_or_config
        if model.n != len(x1):
            raise ValueError(f"model was fitted on {model.n} matches, got {len(x1)}")
    else:
        cfg = dataclasses.replace(config_from(SpatialOrderConfig, model_or_config), gap_table=False)  # no table needed
        model = fit_spatial_order(x1, x2, cfg)
    if not model.usable:
        return np.zeros(len(x1))
    return model.probabilities.copy()
