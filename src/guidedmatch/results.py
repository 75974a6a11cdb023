"""Small result types shared by every module.

* :class:`Failure` -- the falsy result an estimator returns instead of ``None`` or an exception
  (after scikit-image's ``FailedEstimation``): ``if not res: print(res.reason)`` (defined in
  :mod:`guidedmatch.base`, which the estimators import without importing this module).
* :class:`MatchResult` -- the output of every matcher: ``pairs (M, 2) int64`` index pairs
  ``(i1, i2)`` into image-1 / image-2 features, ``distances (M,) float32`` descriptor distances
  (L2 for float descriptors, Hamming bit count for binary ones), per-match ``flags`` and the run's
  :class:`MatchStats` (comparisons, timings, model updates, fallbacks, ...).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .base import Failure  # noqa: F401 - defined on the lowest floor (estimators return it), found here too

if TYPE_CHECKING:  # pragma: no cover
    from .config import MatcherConfig
    from .geometry import TwoViewGeometry


def empty_pairs() -> np.ndarray:
    """An empty ``(0, 2) int64`` pair array."""
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True)
class Fallback:
    """A degraded step of a run, reported instead of hidden.

    Attributes:
        what: the step: ``"fundamental"`` (F estimation failed), ``"alignment"``, ``"focal1"`` / ``"focal2"``
            (Bougnoux focal unusable, ``w + h`` used), ``"spatial_order"`` (SO model unusable), ``"updates"``
            (fewer model updates than configured), ``"so_prob"`` (per-match probabilities not computed),
            ``"no_model"`` (the unguided evidence was never verified: no model guided), ``"early_exit"`` (the
            unguided start stopped at its comparison budget without verified evidence: verdict no-overlap).
        reason: one sentence: what failed and what was done instead.
        at_update: number of model updates completed when it happened (0 = during the unguided phase).
    """

    what: str
    reason: str
    at_update: int = 0


@dataclass(frozen=True)
class ModelUpdate:
    """One refit of the models on all correspondences so far (Teng & Dong §III-A; §III-B..E). ``None``: not fitted.

    Attributes:
        update: 1-based index of the update.
        num_correspondences: correspondences the models were fitted on.
        F_inliers: RANSAC inliers of F (None: F not estimated or failed).
        F_fit: how F was fitted: ``"ransac"`` (USAC on all the correspondences), ``"verdict inliers"`` (first
            update: refitted on the inliers of the two-view verdict's F, when the verdict's inlier ratio is too low
            for a fresh fit or the fresh fit failed the verdict's rule) or ``"verdict"`` (the verdict's F itself).
        focal: ``(f1, f2)`` focal lengths used by the alignment, pixels (mode IA).
        focal_fallback: ``(bool, bool)``: the Bougnoux focal was unusable and ``w + h`` was used.
        roll_deg: camera roll removed by the alignment, degrees.
        H2: ``(3, 3)`` alignment homography of image 2 (mode IA; None: identity).
        alignment_scale: ``(min, max)`` local scale of H2 over the image-2 keypoints (band width in original px
            = ``band_px / scale``).
        alignment: the approach used after validation (``MatcherConfig.alignment``, ``"c_inplane"`` or ``"none"``
            when the requested one failed :func:`~guidedmatch.alignment.check_alignment`; reported as a fallback).
        so_usable: the spatial-order model was usable (None: not fitted in this mode).
        n_good: N_G(ω*), Talker's estimate of the correct matches inside the overlap window (Eq. 10).
        k_hat: normalized Kendall distance inside ω*.
        window1_x, window2_x: x-ranges of ω* in (aligned) image 1 / image 2, pixels.
    """

    update: int
    num_correspondences: int
    F_inliers: int | None = None
    F_fit: str | None = None
    focal: tuple[float, float] | None = None
    focal_fallback: tuple[bool, bool] | None = None
    roll_deg: float | None = None
    H2: np.ndarray | None = None
    alignment_scale: tuple[float, float] | None = None
    alignment: str | None = None
    so_usable: bool | None = None
    n_good: float | None = None
    k_hat: float | None = None
    window1_x: tuple[float, float] | None = None
    window2_x: tuple[float, float] | None = None


@dataclass(frozen=True)
class PhaseTimes:
    """Wall time of each step of a guided run, seconds (``time.perf_counter``).

    Attributes:
        initial_bf_s: unguided phase (queries against all of image 2).
        model_fit_s: all model updates (F, alignment, spatial order).
        guided_progressive_s: guided mini-batches between the updates.
        final_pass_s: the final vectorized pass.
        recheck_s: re-check of early matches against the final models (incl. the in-band flag).
        filter_s: one-to-one and mutual filters.
        so_prob_s: per-match spatial-order probabilities.
        verdict_s: two-view verdicts on the unguided evidence (:func:`~guidedmatch.geometry.two_view_geometry`) and
            the report over the final matches.
        index_build_s: building image 2's approximate index for the unguided start (0 when it was prepared).
    """

    initial_bf_s: float = 0.0
    model_fit_s: float = 0.0
    guided_progressive_s: float = 0.0
    final_pass_s: float = 0.0
    recheck_s: float = 0.0
    filter_s: float = 0.0
    so_prob_s: float = 0.0
    verdict_s: float = 0.0
    index_build_s: float = 0.0


@dataclass(frozen=True)
class CandidateStats:
    """Distribution of the candidate-set size (descriptor distances evaluated) per image-1 query matched.

    Attributes: ``mean``, ``p50``, ``p90``, ``p99`` (percentiles), ``max`` -- image-2 features per query.
    """

    mean: float = 0.0
    p50: float = 0.0
    p90: float = 0.0
    p99: float = 0.0
    max: int = 0

    @classmethod
    def of(cls, ncand: np.ndarray) -> "CandidateStats":
        """From the per-query candidate counts ``(Q,)``."""
        if len(ncand) == 0:
            return cls()
        p = np.percentile(ncand, [50, 90, 99])
        return cls(float(ncand.mean()), float(p[0]), float(p[1]), float(p[2]), int(ncand.max()))


@dataclass(frozen=True)
class MatchStats:
    """Statistics of one matcher run (every matcher: guided modes, brute force, the peers of ``evaluation``).

    Counts are exact; times are wall-clock seconds of matching only (detection excluded).

    Attributes:
        method: ``"bf" | "epi" | "so" | "so+epi" | "so+epi+ia"`` or a peer's name (``"faiss_flat"``, ...).
        comparisons: descriptor distances evaluated (the paper's "# matches", §IV-A); None when the library
            does not expose it (FLANN).
        time_s: wall time of the whole match, seconds.
        num_features: ``(N1, N2)``.
        metric: ``"l2"`` (float descriptors) or ``"hamming"`` (packed binary).
        byte_exact_kernel: guided kernel compared byte-valued float descriptors (SIFT) exactly as uint8/int32.
        timing: :class:`PhaseTimes` of a guided run (None for brute force and peers).
        updates: one :class:`ModelUpdate` per model refit, in order.
        candidates_per_query: :class:`CandidateStats` over every query matched (unguided ones count N2).
        queries_matched_against: image-1 features searched (unguided or in a region, including regions found empty);
            the others were dropped outside ω*.
        dropped_outside_overlap: image-1 features not matched because they lie outside ω* (§III-B.2).
        queries_without_candidates: queries whose search region held no image-2 feature.
        band_only_outside_window: queries outside ω* matched in the epipolar band only (``outside_window="band"``).
        dropped_by_recheck: early matches outside the final search region (``recheck``).
        dropped_by_one_to_one: matches removed by the one-to-one filter.
        dropped_by_mutual: matches removed by the mutual check.
        F: ``(3, 3)`` final fundamental matrix in original pixels (None: no epipolar model).
        alignment_H2: ``(3, 3)`` final alignment homography of image 2 (None: identity / not IA).
        phase_queries: ``(num_model_updates + 1,)`` image-1 features drawn while ``k`` updates were done
            (index ``k``); phase 0 is the unguided start, the last one the final pass.
        phase_comparisons: descriptor distances evaluated in each of those phases (the mutual check's reverse
            search is counted in ``comparisons`` only).
        fallbacks: every :class:`Fallback` taken, in order.
        config: the :class:`~guidedmatch.config.MatcherConfig` of the run (None for peers).
        details: method-specific extras (brute force: ``block_rows``; peers: thread counts, index type, ...).
    """

    method: str
    comparisons: int | None
    time_s: float
    num_features: tuple[int, int] = (0, 0)
    metric: str = "l2"
    byte_exact_kernel: bool = False
    timing: PhaseTimes | None = None
    updates: tuple[ModelUpdate, ...] = ()
    candidates_per_query: CandidateStats | None = None
    queries_matched_against: int = 0
    dropped_outside_overlap: int = 0
    queries_without_candidates: int = 0
    band_only_outside_window: int = 0
    dropped_by_recheck: int = 0
    dropped_by_one_to_one: int = 0
    dropped_by_mutual: int = 0
    F: np.ndarray | None = None
    alignment_H2: np.ndarray | None = None
    phase_queries: tuple[int, ...] = ()
    phase_comparisons: tuple[int, ...] = ()
    fallbacks: tuple[Fallback, ...] = ()
    config: "MatcherConfig | None" = None
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def bf_comparisons(self) -> int:
        """``N1 * N2``: what brute force evaluates."""
        return int(self.num_features[0]) * int(self.num_features[1])

    @property
    def comparison_ratio(self) -> float:
        """``comparisons / (N1 N2)`` (NaN when comparisons are unknown)."""
        if self.comparisons is None:
            return float("nan")
        return self.comparisons / max(1, self.bf_comparisons)

    @property
    def num_model_updates(self) -> int:
        """Model updates done (``len(updates)``)."""
        return len(self.updates)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field plus ``bf_comparisons``, ``comparison_ratio``, ``num_model_updates``
        (arrays -> lists, NaN/inf -> None)."""
        from .evaluation.meta import to_jsonable

        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d.update(bf_comparisons=self.bf_comparisons, comparison_ratio=self.comparison_ratio,
                 num_model_updates=self.num_model_updates)
        return to_jsonable(d)

    def __getitem__(self, key: str) -> Any:
        """Read access by name (``stats["comparisons"]``), for code written against the former dict; prefer
        attributes. Looks up fields and properties, then ``details``."""
        if key in _STATS_NAMES:
            return getattr(self, key)
        return self.details[key]

    def get(self, key: str, default: Any = None) -> Any:
        """``self[key]`` or ``default``."""
        try:
            return self[key]
        except KeyError:
            return default


_STATS_NAMES = frozenset([f.name for f in dataclasses.fields(MatchStats)]
                         + ["bf_comparisons", "comparison_ratio", "num_model_updates"])

#: Keys of :attr:`MatchResult.flags` (every matcher of the package returns all of them).
FLAG_KEYS = ("phase", "single_candidate", "in_band", "so_prob")


def default_flags(m: int) -> dict[str, np.ndarray]:
    """The flags of ``m`` matches made without guidance: phase 0, not single-candidate, in band (no band tested),
    ``so_prob`` NaN (not computed)."""
    return dict(phase=np.zeros(m, np.int64), single_candidate=np.zeros(m, bool), in_band=np.ones(m, bool),
                so_prob=np.full(m, np.nan, np.float32))


@dataclass(frozen=True)
class MatchResult:
    """Matches between two feature sets.

    Attributes:
        pairs: ``(M, 2) int64``; row ``(i, j)`` matches image-1 feature ``i`` to image-2 feature ``j``.
        distances: ``(M,) float32`` descriptor distance of each pair (L2, or Hamming bits for binary).
        stats: :class:`MatchStats` of the run (``stats.comparisons``: exact number of descriptor distances
            evaluated; ``stats.time_s``; ``stats.fallbacks``: every fallback taken).
        flags: per-match arrays of length M, always the keys of :data:`FLAG_KEYS`:
            ``phase (M,) int64`` model updates done when the match was made (0 = unguided);
            ``single_candidate (M,) bool`` the query had exactly one candidate (kept by ``single_candidate="accept"``);
            ``in_band (M,) bool`` image-2 point within ``band_px`` of the final epipolar line (True without F);
            ``so_prob (M,) float32`` spatial-order probability of the match within the final match set
            (Talker Eq. 12), NaN when not computed (modes without SO, fewer than 2 matches, or a fallback).
            Missing keys are filled with :func:`default_flags`.
        geometry: the two-view verdict of the pair (:class:`~guidedmatch.geometry.TwoViewGeometry`) when computed.
    """

    pairs: np.ndarray
    distances: np.ndarray
    stats: MatchStats
    flags: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: "TwoViewGeometry | None" = None

    def __post_init__(self) -> None:
        pairs = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2)
        distances = np.asarray(self.distances, dtype=np.float32).reshape(-1)
        if len(pairs) != len(distances):
            raise ValueError(f"pairs ({len(pairs)}) and distances ({len(distances)}) differ in length")
        if not isinstance(self.stats, MatchStats):
            raise TypeError(f"MatchResult.stats must be a MatchStats, got {type(self.stats).__name__}")
        flags = {**default_flags(len(pairs)), **self.flags}
        for k, v in flags.items():
            if len(v) != len(pairs):
                raise ValueError(f"flags[{k!r}] has {len(v)} entries for {len(pairs)} matches")
        object.__setattr__(self, "pairs", pairs)
        object.__setattr__(self, "distances", distances)
        object.__setattr__(self, "flags", flags)

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def num_matches(self) -> int:
        return len(self.pairs)

    def to_cv_dmatches(self) -> list:
        """The matches as a list of ``cv2.DMatch`` (queryIdx = image 1, trainIdx = image 2)."""
        import cv2

        return [cv2.DMatch(int(i), int(j), float(d)) for (i, j), d in zip(self.pairs, self.distances)]
