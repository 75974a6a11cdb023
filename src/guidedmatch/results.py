"""Small result types shared by every module.

* :class:`Failure` -- the falsy result an estimator returns instead of ``None`` or an exception
  (after scikit-image's ``FailedEstimation``): ``if not res: print(res.reason)``.
* :class:`MatchResult` -- the output of every matcher: ``pairs (M, 2) int64`` index pairs
  ``(i1, i2)`` into image-1 / image-2 features, ``distances (M,) float32`` descriptor distances
  (L2 for float descriptors, Hamming bit count for binary ones), optional per-match ``flags``
  and a ``stats`` dict (comparisons, timings, model updates, fallbacks, ...).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Failure:
    """Falsy result of an estimation that did not succeed.

    Attributes:
        reason: one human-readable sentence saying why (e.g. ``"fewer than 8 correspondences (5)"``).
        details: optional machine-readable extras (counts, thresholds).
    """

    reason: str
    details: dict = field(default_factory=dict)

    def __bool__(self) -> bool:  # noqa: D105 - falsy by design
        return False

    def __str__(self) -> str:
        return f"Failure: {self.reason}"


def empty_pairs() -> np.ndarray:
    """An empty ``(0, 2) int64`` pair array."""
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True)
class MatchResult:
    """Matches between two feature sets.

    Attributes:
        pairs: ``(M, 2) int64``; row ``(i, j)`` matches image-1 feature ``i`` to image-2 feature ``j``.
        distances: ``(M,) float32`` descriptor distance of each pair (L2, or Hamming bits for binary).
        stats: run statistics. Always has ``"comparisons"`` (exact number of descriptor distances
            evaluated) and ``"time_s"`` (wall time of matching, detection excluded); matchers add more
            (``"fallbacks"``: list of ``{"what", "reason"}`` dicts for every fallback taken).
        flags: optional per-match arrays of length M (e.g. ``"phase"``, ``"in_band"``, ``"so_prob"``).
    """

    pairs: np.ndarray
    distances: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)
    flags: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pairs = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2)
        distances = np.asarray(self.distances, dtype=np.float32).reshape(-1)
        if len(pairs) != len(distances):
            raise ValueError(f"pairs ({len(pairs)}) and distances ({len(distances)}) differ in length")
        object.__setattr__(self, "pairs", pairs)
        object.__setattr__(self, "distances", distances)

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def num_matches(self) -> int:
        return len(self.pairs)

    def to_cv_dmatches(self) -> list:
        """The matches as a list of ``cv2.DMatch`` (queryIdx = image 1, trainIdx = image 2)."""
        import cv2

        return [cv2.DMatch(int(i), int(j), float(d)) for (i, j), d in zip(self.pairs, self.distances)]
