"""Overlap region ``omega* = argmax_omega N_G(omega)`` of a match permutation (Talker §4.3, Eq. 10-11).

Windows are half-open 0-based rank ranges; :class:`Window` names the four ends. The sweeps and the coordinate
ascent are Numba kernels in :mod:`._kernels`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..validation import check_choice
from ._kernels import _refine_window_nb, _sweep_kendall
from .ranks import estimate_n_good

__all__ = ["Window", "search_overlap", "refine_window"]


class Window(NamedTuple):
    """Rank windows of omega* among all N matches, half-open: image-1 ranks ``[i1_lo, i1_hi)``, image-2 ranks
    ``[i2_lo, i2_hi)``. A tuple, so it compares equal to ``(i1_lo, i1_hi, i2_lo, i2_hi)``."""

    i1_lo: int
    i1_hi: int
    i2_lo: int
    i2_hi: int


def refine_window(sigma, w, q: int, passes: int = 6) -> Window:
    """Ascent of N_G from window w (our addition to Talker §4.3): exact line search (every rank, one O(N log N)
    sweep) over each end alone, and joint shifts of the two lower (resp. upper) ends within +-q in steps of q/8 --
    correct matches sit on the diagonal, so a corner that is off in both images needs a joint move.

    ``sigma``: ``(N,) int64`` permutation; ``w``: start window ``(i1_lo, i1_hi, i2_lo, i2_hi)``; ``q``: grid step
    (ranks). Never lowers N_G (ties: more matches)."""
    sigma = np.ascontiguousarray(sigma, dtype=np.int64)
    inv = np.empty_like(sigma)
    inv[sigma] = np.arange(len(sigma))
    out = _refine_window_nb(sigma, inv, np.array(w, dtype=np.int64), int(max(q, 1)), int(max(q // 8, 1)),
                            int(passes))
    return Window(*(int(v) for v in out))


def _grid(n: int, grid_fraction: float) -> np.ndarray:
    q = max(1, int(round(grid_fraction * n)))
    return np.unique(np.concatenate([np.arange(0, n, q), [n]])).astype(np.int64)


def _best_window(k, cnt, g):
    """Pick the (a, c) maximizing N_G (ties: larger window, then first)."""
    a_idx, c_idx = np.triu_indices(g + 1, k=1)
    a_idx, c_idx = a_idx[a_idx < g], c_idx[a_idx < g]
    nn = cnt[a_idx, c_idx].astype(np.float64)
    kk = k[a_idx, c_idx].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        kh = np.where(nn >= 2, 2.0 * kk / (nn * (nn - 1.0)), np.nan)
    ng = estimate_n_good(kh, nn)
    ng = np.where(np.isnan(ng), 0.0, ng)
    best = np.lexsort((-nn, -ng))[0]
    return int(a_idx[best]), int(c_idx[best]), float(ng[best])


def search_overlap(sigma, grid_fraction: float = 0.1, method: str = "k1d", refine: bool = True,
                   rounds: int = 3) -> Window:
    """Overlap region ``omega* = argmax_omega N_G(omega)`` (Talker §4.3, Eq. 10-11; Teng & Dong §III-B.2).

    Window ends lie on the grid ``0, q, 2q, ..., N`` with ``q = max(1, round(grid_fraction * N))``.
    ``N(omega)``, ``K_hat(omega)`` are those of the matches with image-1 rank in ``[i1_lo, i1_hi)`` and image-2 rank in
    ``[i2_lo, i2_hi)``. ``"k1d"``: first image-1 windows with image 2 = all, then image-2 windows with that image-1
    window fixed (O(G^2 N log N), G = N/q); with ``rounds > 1`` (our addition) the two stages alternate, the image-1
    stage then restricted to the current image-2 window, until the window stops changing (Talker's K1D is
    ``rounds=1``). ``"k2d"``: all window pairs jointly (O(G^3 N log N)). ``"none"``: full.
    ``refine`` (our addition, not in Talker): afterwards each of the 4 ends is moved within +-q of its grid value by
    coordinate ascent on N_G (step q/8, then 1), which removes most of the grid quantization error.

    Args:
        sigma: ``(N,) int64`` permutation (image-1 rank -> image-2 rank).

    Returns:
        :class:`Window` ``(i1_lo, i1_hi, i2_lo, i2_hi)``: half-open rank windows.
    """
    sigma = np.ascontiguousarray(sigma, dtype=np.int64)
    n = len(sigma)
    check_choice("search_overlap", "method", method, ("k1d", "k2d", "none"))
    full = Window(0, n, 0, n)
    if method == "none" or n < 2:
        return full
    bounds = _grid(n, grid_fraction)
    g = len(bounds) - 1
    inv = np.empty(n, dtype=np.int64)
    inv[sigma] = np.arange(n, dtype=np.int64)
    k = np.zeros((g + 1, g + 1), dtype=np.int64)
    cnt = np.zeros((g + 1, g + 1), dtype=np.int64)
    if method == "k1d":
        w = full
        for _ in range(max(int(rounds), 1)):
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(sigma, w.i2_lo, w.i2_hi, bounds, k, cnt)
            a1, c1, _ = _best_window(k, cnt, g)
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(inv, int(bounds[a1]), int(bounds[c1]), bounds, k, cnt)
            a2, c2, _ = _best_window(k, cnt, g)
            new = Window(int(bounds[a1]), int(bounds[c1]), int(bounds[a2]), int(bounds[c2]))
            if new == w:
                break
            w = new
        return refine_window(sigma, w, int(bounds[1] - bounds[0])) if refine else w
    best_key, best_w = (-1.0, -1), full  # (N_G, matches inside) of the best window so far, the window
    for a1 in range(g):
        for c1 in range(a1 + 1, g + 1):
            k[:] = 0
            cnt[:] = 0
            _sweep_kendall(inv, int(bounds[a1]), int(bounds[c1]), bounds, k, cnt)
            a2, c2, ng = _best_window(k, cnt, g)
            nw = int(cnt[a2, c2])
            if (ng, nw) > best_key:
                best_key = (ng, nw)
                best_w = Window(int(bounds[a1]), int(bounds[c1]), int(bounds[a2]), int(bounds[c2]))
    return refine_window(sigma, best_w, int(bounds[1] - bounds[0])) if refine else best_w
