"""Synthetic match permutations under the spatial-order assumptions A1-A3 (Talker et al. 2016, §6.1).

A match set between two images is, in rank space, a permutation: image-1 x-rank ``i`` -> image-2 x-rank
``sigma[i]``. :func:`generate_permutation` builds one the way Talker's synthetic tests do:

* ``n_good`` *correct* matches keep their order (A1) and lie inside random overlap windows ``O1`` (image 1)
  and ``O2`` (image 2), uniformly interleaved with the incorrect ones (A3);
* the remaining ``n - n_good`` *incorrect* matches pair the leftover image-1 and image-2 slots at random (A2);
* optional noise: ``n_swaps`` local swaps of image-2 positions between correct matches that are at most
  ``swap_radius`` apart in image-2 order (as from feature localisation error);
* optional held-out correct matches (``n_holdout``): generated together with the others and then removed,
  so that their true gaps between the kept matches are known -- they play the role of "new features" for the
  search-range test of Teng & Dong §III-C.

Coordinates are also produced (pixels, OpenCV convention; only x matters for spatial order): the ``n + n_holdout``
slots of each image get sorted uniform x values in ``[0, width)``, all distinct, and matches are returned in a
random order (index != rank), so callers exercise the rank computation too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SyntheticPermutation", "generate_permutation"]


@dataclass(frozen=True, eq=False)
class SyntheticPermutation:
    """A generated match set with ground truth (all ranks 0-based, windows half-open ``[lo, hi)``).

    Attributes:
        x1, x2: ``(n,) float64`` image-1 / image-2 x of the kept matches, in random match order (pixels).
        sigma: ``(n,) int64`` the permutation: ``sigma[i]`` = image-2 x-rank of the match with image-1 x-rank ``i``.
        is_good: ``(n,) bool`` per match (match order of ``x1``/``x2``): True for the correct ones.
        n_good: number of kept correct matches (``is_good.sum()``).
        window1, window2: true overlap windows as rank ranges ``[lo, hi)`` among the kept matches: lowest and
            highest rank of a kept correct match in image 1 / image 2 (Talker §4.3 definition of ``omega*``).
        holdout_x1, holdout_x2: ``(m,) float64`` x of the held-out correct matches (new features).
        holdout_gap1, holdout_gap2: ``(m,) int64`` their true gaps among the kept matches: number of kept matches
            with smaller x in image 1 / image 2 (gap ``h`` lies between image-1 ranks ``h-1`` and ``h``).
    """

    x1: np.ndarray
    x2: np.ndarray
    sigma: np.ndarray
    is_good: np.ndarray
    n_good: int
    window1: tuple[int, int]
    window2: tuple[int, int]
    holdout_x1: np.ndarray
    holdout_x2: np.ndarray
    holdout_gap1: np.ndarray
    holdout_gap2: np.ndarray


def generate_permutation(
    n: int,
    n_good: int,
    *,
    n_holdout: int = 0,
    overlap: tuple[float, float] | None = None,
    n_swaps: int = 0,
    swap_radius: int = 2,
    width: float = 1000.0,
    rng: np.random.Generator | None = None,
    seed: int | None = 0,
) -> SyntheticPermutation:
    """Generate a match permutation under A1-A3 with random partial overlap (Talker §6.1).

    Args:
        n: number of kept matches (``>= 0``).
        n_good: number of kept correct matches (``0 <= n_good <= n``).
        n_holdout: extra correct matches generated and then held out (their true gaps are returned).
        overlap: relative sizes ``(f1, f2)`` of the overlap windows O1, O2 as fractions of all ``n + n_holdout``
            slots; ``None`` draws each uniformly so that ``|O| >= n_good + n_holdout`` (Talker: "size (> N_G) and
            location of O1 and O2 are randomly chosen"). Positions are always random.
        n_swaps: number of local swaps of image-2 positions among correct matches (order noise).
        swap_radius: maximal distance (in image-2 order among correct matches) of a swapped pair.
        width: image width in pixels for the x coordinates.
        rng, seed: randomness (``rng`` wins; else ``np.random.default_rng(seed)``).

    Returns:
        :class:`SyntheticPermutation`.
    """
    rng = rng if rng is not None else np.random.default_rng(seed)
    n, n_good, n_holdout = int(n), int(n_good), int(n_holdout)
    if not 0 <= n_good <= n:
        raise ValueError(f"need 0 <= n_good <= n, got n_good={n_good}, n={n}")
    total = n + n_holdout
    n_corr = n_good + n_holdout  # correct matches before hold-out

    def window(frac: float | None) -> np.ndarray:
        if frac is None:
            size = int(rng.integers(n_corr, total + 1)) if total > 0 else 0
        else:
            size = int(np.clip(round(frac * total), n_corr, total))
        start = int(rng.integers(0, total - size + 1)) if total > 0 else 0
        return np.arange(start, start + size)

    f1, f2 = (None, None) if overlap is None else overlap
    o1, o2 = window(f1), window(f2)
    # correct matches: order-preserving pairing of random slots inside O1 and O2 (A1, A3)
    g1 = np.sort(rng.choice(o1, size=n_corr, replace=False))
    g2 = np.sort(rng.choice(o2, size=n_corr, replace=False))
    for _ in range(int(n_swaps)):  # local order noise among correct matches
        if n_corr < 2:
            break
        a = int(rng.integers(0, n_corr - 1))
        b = min(n_corr - 1, a + int(rng.integers(1, max(int(swap_radius), 1) + 1)))
        g2[a], g2[b] = g2[b], g2[a]
    # incorrect matches: leftover slots paired at random (A2)
    b1 = np.setdiff1d(np.arange(total), g1)
    b2 = rng.permutation(np.setdiff1d(np.arange(total), g2))
    slot1 = np.concatenate([g1, b1])
    slot2 = np.concatenate([g2, b2])
    good = np.zeros(total, dtype=bool)
    good[:n_corr] = True
    hold = np.zeros(total, dtype=bool)
    if n_holdout:
        hold[rng.choice(n_corr, size=n_holdout, replace=False)] = True

    xs1 = np.sort(rng.uniform(0.0, width, total))
    xs2 = np.sort(rng.uniform(0.0, width, total))
    keep = ~hold
    k1, k2 = slot1[keep], slot2[keep]
    # ranks among kept matches
    kept1 = np.zeros(total, dtype=bool)
    kept1[k1] = True
    kept2 = np.zeros(total, dtype=bool)
    kept2[k2] = True
    rank1_of_slot = np.cumsum(kept1) - 1
    rank2_of_slot = np.cumsum(kept2) - 1
    r1, r2 = rank1_of_slot[k1], rank2_of_slot[k2]
    sigma = np.empty(n, dtype=np.int64)
    sigma[r1] = r2
    order = rng.permutation(n)  # random match order
    x1, x2 = xs1[k1][order], xs2[k2][order]
    is_good = good[keep][order]
    gk = good[keep]
    if gk.any():
        w1 = (int(r1[gk].min()), int(r1[gk].max()) + 1)
        w2 = (int(r2[gk].min()), int(r2[gk].max()) + 1)
    else:
        w1 = w2 = (0, 0)
    # true gaps of held-out matches: number of kept slots to their left
    cum1 = np.concatenate([[0], np.cumsum(kept1)])
    cum2 = np.concatenate([[0], np.cumsum(kept2)])
    h1, h2 = slot1[hold], slot2[hold]
    return SyntheticPermutation(
        x1=x1, x2=x2, sigma=sigma, is_good=is_good, n_good=int(gk.sum()), window1=w1, window2=w2,
        holdout_x1=xs1[h1], holdout_x2=xs2[h2],
        holdout_gap1=cum1[h1].astype(np.int64), holdout_gap2=cum2[h2].astype(np.int64),
    )
