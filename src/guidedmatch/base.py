"""The lowest floor of the package: the names every layer shares and the :class:`Failure` value type.

Imports nothing from ``guidedmatch`` (nor NumPy / OpenCV), so any module may import it without an import cycle:
the configs validate against these names, the estimators return :class:`Failure`, the results carry both. Each
name is also found where users look for it: ``guidedmatch.Failure`` / ``guidedmatch.results.Failure``,
``guidedmatch.alignment.APPROACHES``, ``guidedmatch.epipolar.USAC_METHODS`` (the OpenCV parameters of each name),
``guidedmatch.geometry.VERDICTS``, ``guidedmatch.config.Alignment`` / ``RansacMethod``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

__all__ = ["Alignment", "APPROACHES", "RansacMethod", "USAC_METHOD_NAMES", "Verdict", "VERDICTS", "Failure",
           "DEFAULT_INLIER_PX", "DEFAULT_REFIT_DEG", "COLMAP_MIN_INLIERS"]

#: Alignment approaches of :func:`guidedmatch.alignment.align_from_fundamental` (§III-E): the paper's four
#: (``"a"``-``"d"``) plus ``"c_inplane"`` (the intended approach 3)
Alignment = Literal["a", "b", "c", "c_inplane", "d"]
APPROACHES: tuple[str, ...] = get_args(Alignment)

#: OpenCV USAC variants of :func:`guidedmatch.epipolar.estimate_fundamental` (the keys of
#: ``guidedmatch.epipolar.USAC_METHODS``, which holds each one's OpenCV parameters)
RansacMethod = Literal["magsac", "accurate", "default", "prosac", "ransac", "lmeds"]
USAC_METHOD_NAMES: tuple[str, ...] = get_args(RansacMethod)

#: Two-view verdicts of :func:`guidedmatch.geometry.two_view_geometry`
Verdict = Literal["verified", "no-overlap", "too-few-matches"]
#: verdict -> meaning.
VERDICTS = {
    "verified": "a fundamental matrix or homography supported by more inliers than random correspondences reach",
    "no-overlap": "no model is supported beyond chance: the images do not overlap (or share too little to tell)",
    "too-few-matches": "fewer correspondences than a model needs (8 for F, 4 for H): nothing can be verified",
}

#: The inliers a COLMAP mapper gets from ``guidedmatch colmap`` / ``sfm`` (``--inlier-px``): those within this many
#: pixels of their pair's verified F (Sampson) or H (transfer error) -- the verdict decides at 3 px, the mapper
#: gets the more precise ones (docs/collections.md, "The inliers the mapper gets")
DEFAULT_INLIER_PX = 1.5
#: ``--refit-below-deg``: before that selection, the F of a pair whose inliers' median triangulation angle (under the
#: pose of E = K2^T F K1, the database's camera guesses) is below this many degrees is fitted again on its own
#: inliers -- at small baselines the verdict's early F is least determined (docs/collections.md, "The inliers the
#: mapper gets"; 0 = never)
DEFAULT_REFIT_DEG = 3.0
#: COLMAP's ``min_num_inliers``: a pair with fewer verified inliers is no edge of its view graph (our verdict's
#: ``VerdictConfig.min_inliers`` default, and the floor of the mapper's inliers per pair under ``--inlier-px``)
COLMAP_MIN_INLIERS = 15


@dataclass(frozen=True)
class Failure:
    """Falsy result of an estimation that did not succeed.

    Attributes:
        reason: one human-readable sentence saying why (e.g. ``"fewer than 8 correspondences (5)"``).
        details: optional machine-readable extras (counts, thresholds).

    >>> res = Failure("fewer than 8 correspondences (5)")
    >>> bool(res), str(res)
    (False, 'Failure: fewer than 8 correspondences (5)')
    """

    reason: str
    details: dict = field(default_factory=dict)

    def __bool__(self) -> bool:  # noqa: D105 - falsy by design
        return False

    def __str__(self) -> str:
        return f"Failure: {self.reason}"
