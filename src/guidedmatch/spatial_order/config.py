"""Configuration of :func:`~guidedmatch.spatial_order.fit_spatial_order`, validated at construction."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..validation import check_bool, check_choice, check_number
from .probability import PROBABILITY_METHODS

__all__ = ["OVERLAP_METHODS", "SpatialOrderConfig"]

OVERLAP_METHODS = ("k1d", "k2d", "none")  # overlap-window searches, see search_overlap


@dataclass(frozen=True)
class SpatialOrderConfig:
    """Parameters of :func:`~guidedmatch.spatial_order.fit_spatial_order` (Talker §4-§5; Teng & Dong §III-B/C).

    Every field is checked in ``__post_init__``; a bad value raises :class:`~guidedmatch.errors.ConfigError`.

    ``probability`` chooses the model of ``P(H | G)`` for the reported **per-match** probabilities
    (``SpatialOrderModel.probabilities``, :func:`~guidedmatch.spatial_order.match_probabilities`) only. The overlap
    window's self-consistency pass, the order-noise estimate and the **search-range (gap) table** always use the
    Gaussian model: the exact hypergeometric sums cost O(|S_beta| H) per cell, far too much for the (n+1)^2 cells
    of the table (see ``docs/spatial_order.md``), so ``"exact"`` never changes the window or the admitted gaps.

    >>> SpatialOrderConfig(threshold=0.05).threshold
    0.05
    >>> SpatialOrderConfig(overlap="k3d")
    Traceback (most recent call last):
    ...
    guidedmatch.errors.ConfigError: SpatialOrderConfig.overlap must be one of 'k1d', 'k2d', 'none'; got 'k3d'
    """

    threshold: float = 0.01  # Th: keep image-2 gaps whose correctness probability >= Th (§III-C), in (0, 1)
    grid_fraction: float = 0.1  # Talker's window grid step q = round(grid_fraction * N), in (0, 1]
    overlap: Literal["k1d", "k2d", "none"] = "k1d"  # omega* search: K1D / K2D (Talker §4.3) or none (full overlap)
    probability: Literal["gaussian", "exact"] = "gaussian"  # per-match P(H|G): Talker's fast Gaussian | exact sums
    num_beta: int = 5  # k values of beta around their expectation (Gaussian model), 1..64
    refine: bool = True  # refine omega*'s grid ends to single ranks (coordinate ascent on N_G; not in Talker)
    trim_rounds: int = 2  # re-window to extreme ranks of matches with P >= 1/2, keep max sum P (not in Talker)
    var_floor: float = 1.0  # added to Var(H | G) (inversions^2, > 0): tolerance for local order noise
    gap_table: bool = True  # build the (n+1)^2 search-range table (False: per-match probabilities only, O(n log n))
    order_noise: bool = True  # estimate local order noise from the data and widen P(H|G) by it (not in Talker)
    min_z: float = 5.0  # usable only if (1/2 - K_hat(omega*)) / sd_null >= min(min_z, 1.5 + 0.6 ln N), >= 0

    def __post_init__(self) -> None:
        owner = type(self).__name__
        check_number(owner, "threshold", self.threshold, lo=0.0, hi=1.0, lo_open=True, hi_open=True)
        check_number(owner, "grid_fraction", self.grid_fraction, lo=0.0, hi=1.0, lo_open=True)
        check_choice(owner, "overlap", self.overlap, OVERLAP_METHODS)
        check_choice(owner, "probability", self.probability, PROBABILITY_METHODS)
        check_number(owner, "num_beta", self.num_beta, lo=1, hi=64, integer=True)
        check_bool(owner, "refine", self.refine)
        check_number(owner, "trim_rounds", self.trim_rounds, lo=0, integer=True)
        check_number(owner, "var_floor", self.var_floor, lo=0.0, lo_open=True)
        check_bool(owner, "gap_table", self.gap_table)
        check_bool(owner, "order_noise", self.order_noise)
        check_number(owner, "min_z", self.min_z, lo=0.0)
