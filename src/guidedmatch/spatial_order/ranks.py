"""Ranks, the match permutation and Kendall inversions (Talker §4.1-§4.2, Eq. 1-2, 5, 8; Teng & Dong §III-B.1).

Matches are sorted by x in each image; the match set becomes the permutation ``sigma`` (``sigma[i]`` = image-2
x-rank of the match with image-1 x-rank ``i``, 0-based). Inversions are counted in O(N log N) with a Fenwick tree
(:mod:`._kernels`).
"""
from __future__ import annotations

import numpy as np

from ._kernels import _inversions_dense

__all__ = [
    "match_ranks",
    "permutation_from_coordinates",
    "inversions_per_match",
    "kendall_distance",
    "normalized_kendall_distance",
    "estimate_n_good",
]


def match_ranks(x: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    """x-rank of every match in one image, ``(N,) int64``, 0-based.

    Ties are broken stably: by x, then by y (if given), then by match index (``np.lexsort`` is stable).
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    keys = (x,) if y is None else (np.asarray(y, dtype=np.float64).reshape(-1), x)
    order = np.lexsort(keys)
    ranks = np.empty(len(x), dtype=np.int64)
    ranks[order] = np.arange(len(x), dtype=np.int64)
    return ranks


def permutation_from_coordinates(x1, x2, y1=None, y2=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The match permutation ``sigma`` from matched coordinates (Teng & Dong §III-B.1).

    Args:
        x1, x2: ``(N,)`` x of match m in image 1 / image 2 (pixels). y1, y2: optional ``(N,)`` tie-breakers.

    Returns:
        ``(sigma, rank1, rank2)``: ``sigma (N,) int64`` with ``sigma[rank1[m]] = rank2[m]``, and the ranks.
    """
    r1, r2 = match_ranks(x1, y1), match_ranks(x2, y2)
    sigma = np.empty(len(r1), dtype=np.int64)
    sigma[r1] = r2
    return sigma, r1, r2


def _dense(seq) -> tuple[np.ndarray, int]:
    a = np.asarray(seq).reshape(-1)
    if a.size == 0:
        return np.zeros(0, dtype=np.int64), 0
    uniq, inv = np.unique(a, return_inverse=True)
    return inv.astype(np.int64).reshape(-1), int(len(uniq))


def inversions_per_match(sigma) -> tuple[np.ndarray, np.ndarray]:
    """Per-match inversion counts (Talker §4.2; Teng & Dong §III-B.3), O(N log N).

    ``H^l[i] = #{j < i : sigma[j] > sigma[i]}``, ``H^r[i] = #{j > i : sigma[j] < sigma[i]}``; ``H = H^l + H^r``.
    Works for any real sequence (ties are not inversions). For a permutation, with ``C[i] = #{j < i : sigma[j] <
    sigma[i]}``: ``H^l = i - C``, ``H^r = sigma[i] - C``.

    Returns:
        ``(H^l, H^r)``, each ``(N,) int64``.
    """
    r, nv = _dense(sigma)
    if r.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return _inversions_dense(r, nv)


def kendall_distance(sigma) -> int:
    """Kendall distance ``K = #{(i, j) : i < j, sigma[i] > sigma[j]}`` (Talker Eq. 1-2), O(N log N) Fenwick tree.

    ``sigma``: ``(N,)`` any real sequence (ties count as no inversion); ``N in {0, 1}`` gives 0.
    """
    hl, _ = inversions_per_match(sigma)
    return int(hl.sum())


def normalized_kendall_distance(x1, x2, y1=None, y2=None) -> float:
    """``K_hat = 2K / (N(N-1))`` of the permutation of matched coordinates (Talker Eq. 5; Teng & Dong Eq. 2).

    Ties are broken as in :func:`match_ranks`. Returns nan when ``N < 2``.
    """
    sigma, _, _ = permutation_from_coordinates(x1, x2, y1, y2)
    n = len(sigma)
    if n < 2:
        return float("nan")
    return 2.0 * kendall_distance(sigma) / (n * (n - 1.0))


def estimate_n_good(k_hat, n):
    """Number of correct matches N_G from Talker Eq. 8 (Teng & Dong Eq. 1).

    Solves ``(1/6) N_G^2 - (1/2 - N/3) N_G - N(N-1)(1/2 - K_hat) = 0`` for the root in ``[0, N]``:
    ``N_G = 3 [ -(N/3 - 1/2) + sqrt((N/3 - 1/2)^2 + (2/3) N (N-1)(1/2 - K_hat)) ]``; ``N_G = N`` at ``K_hat = 0``
    (exactly) and ``0`` when ``K_hat >= 1/2``. Broadcasts over arrays; nan ``k_hat`` gives nan.
    """
    k = np.asarray(k_hat, dtype=np.float64)
    nn = np.asarray(n, dtype=np.float64)
    b = nn / 3.0 - 0.5
    c = nn * (nn - 1.0) * (0.5 - k)
    disc = np.maximum(b * b + (2.0 / 3.0) * np.maximum(c, 0.0), 0.0)
    root = 3.0 * (-b + np.sqrt(disc))
    out = np.where(k >= 0.5, 0.0, np.clip(root, 0.0, nn))
    out = np.where(k == 0.0, nn, out)
    out = np.where(np.isnan(k), np.nan, out)
    return float(out) if out.ndim == 0 else out
