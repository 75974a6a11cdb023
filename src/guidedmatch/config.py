"""The matcher's settings: the matching mode (:class:`Mode`) and :class:`MatcherConfig`, validated at construction.

Light module (no Numba, no OpenCV at import): the CLI checks ``--mode`` / ``--config`` with it before any work.
Every bad value raises :class:`~guidedmatch.errors.ConfigError` (a ``ValueError``) naming the field, the accepted
values and the value received.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, get_args

from .base import APPROACHES, USAC_METHOD_NAMES, Alignment, RansacMethod
from .errors import ConfigError
from .validation import check_bool, check_choice, check_fields, check_number

__all__ = ["MODES", "Mode", "MatcherConfig", "Alignment", "RansacMethod", "Overlap"]

ModeName = Literal["bf", "epi", "so", "so+epi", "so+epi+ia"]
#: The matching modes, cheapest guidance last (Teng & Dong §IV compare BF, SO, SO+EPI, SO+EPI+IA; EPI is the classic
#: epipolar-guided baseline). The one list every module and the CLI use.
MODES: tuple[str, ...] = get_args(ModeName)
# Alignment (the approaches of guidedmatch.alignment, APPROACHES) and RansacMethod (the OpenCV USAC variants of
# guidedmatch.epipolar, USAC_METHOD_NAMES) are defined in guidedmatch.base and found here too
#: Overlap-window searches of the spatial-order model (Talker §4.3)
Overlap = Literal["k1d", "k2d", "none"]


@dataclass(frozen=True)
class Mode:
    """A matching mode parsed once: which guidance the progressive matcher uses.

    ``use_so``: restrict candidates to the spatial-order x-range (§III-C); ``use_epi``: to the epipolar band
    (§III-D); ``use_ia``: in coordinates aligned by the homography from F (§III-E). ``bf`` uses none of them and
    compares every pair (the paper's baseline).

    >>> Mode.parse("so+epi+ia")
    Mode(name='so+epi+ia', use_so=True, use_epi=True, use_ia=True)
    >>> Mode.parse("bf").guided
    False
    """

    name: str
    use_so: bool
    use_epi: bool
    use_ia: bool

    @property
    def guided(self) -> bool:
        """True for every mode except ``bf``."""
        return self.use_so or self.use_epi or self.use_ia

    @classmethod
    def parse(cls, mode: "str | Mode") -> "Mode":
        """``"so+epi+ia"`` (case-insensitive) or a Mode -> Mode; ConfigError listing :data:`MODES` otherwise."""
        if isinstance(mode, Mode):
            return mode
        name = mode.lower() if isinstance(mode, str) else mode
        if name not in MODES:
            raise ConfigError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
        parts = set(name.split("+"))
        return cls(name, "so" in parts, "epi" in parts, "ia" in parts)


@dataclass(frozen=True)
class MatcherConfig:
    """Matcher settings; defaults are the paper's where it states them (§IV). Validated at construction.

    Every option means the same in every mode; options of a guidance a mode does not use are ignored by it
    (e.g. ``band_px`` in ``so``). ``MatcherConfig.paper()`` turns off the additions beyond the paper.

    >>> MatcherConfig(band_px=3.0).band_px
    3.0
    >>> MatcherConfig(so_threshold=-1)
    Traceback (most recent call last):
    ...
    guidedmatch.errors.ConfigError: MatcherConfig.so_threshold must be a finite number > 0 and < 1; got -1
    """

    num_groups: int = 16                 # x-interval groups of image-1 features drawn round-robin (§III-A; count not published)
    update_every: int = 200              # new correspondences between model updates (§IV: 200)
    num_updates: int = 3                 # model updates before the final vectorized pass (§IV: 3)
    so_threshold: float = 0.01           # Th: keep image-2 gaps whose correctness probability >= Th (§III-C, §IV)
    band_px: float = 5.0                 # epipolar band half-width in (aligned) image-2 pixels (§IV: 5 px)
    alignment: Alignment = "c_inplane"   # alignment a|b|c|c_inplane|d (§III-E): c_inplane = the in-plane twist the text
                                         # describes (default); c = K2 R_u R^T K2^-1 as printed (paper()); validated over
                                         # image 2's keypoints, falling back to c_inplane, then none (reported)
    ratio: float | None = 0.8            # Lowe ratio (keep d1 < ratio * d2) among the candidates; None disables
    single_candidate: Literal["reject", "accept"] = "reject"  # exactly one candidate: no ratio test possible; drop/keep
    mutual: bool = False                 # every mode: keep (i, j) only if i is j's nearest neighbour among ALL image-1
                                         # features (full reverse search; in guided modes M x N1 extra comparisons, counted)
    one_to_one: bool | None = None       # keep only the closest image-1 feature per image-2 feature (beyond the paper;
                                         # Oxford, 12 pairs: precision 88.9 % -> 94.2 %, true -2.5 %). None: in the guided
                                         # modes only (bf stays the paper's ratio-test baseline); True / False: every mode
    max_distance: float | None = None    # drop matches with a larger descriptor distance (L2 or Hamming bits); None: no limit
    ransac_method: RansacMethod = "magsac"  # F estimator (OpenCV USAC): magsac|accurate|default|prosac|ransac|lmeds
    ransac_threshold: float = 1.5        # RANSAC inlier threshold for F, pixels
    so_overlap: Overlap = "k1d"          # overlap-window search of the SO model: k1d|k2d|none (Talker §4.3)
    batch_size: int = 64                 # queries per mini-batch in the progressive phase (speed only)
    strip_px: float | None = None        # width of the strips indexing image-2 features for the candidate kernel;
                                         # None: chosen from the lines' slopes and the point density (speed only)
    recheck: bool = True                 # beyond the paper: re-test early matches against the final models
    planar_recheck: bool = True          # beyond the paper: when the verdict is a homography (planar scene / pure
                                         # rotation: F and its band constrain nothing along the plane) and the final
                                         # matches still look planar (H inliers >= h_ratio * F inliers), drop the guided
                                         # matches that are not its inliers (Oxford wall 1-2: 2.2 % -> 0.6 % wrong)
    nonplanar_as_F: bool = True          # beyond the paper: an "H" verdict whose final matches are not planar by COLMAP's
                                         # rule (H inliers < h_ratio * F inliers of the final F) is reported as "F" with
                                         # the F inliers, the off-plane ones included, as COLMAP's verification does
                                         # (fox: 448 of 689 "H" pairs, their off-plane inliers are the depth cues)
    planar_inliers: Literal["H", "larger"] = "H"  # a planar "H" verdict (H inliers >= h_ratio * F inliers): report the H
                                         # inliers (off-H guided matches dropped by planar_recheck), or "larger": the
                                         # larger of the H and the final F inlier sets, COLMAP's PLANAR_OR_PANORAMIC rule
                                         # (the off-plane few carry a short baseline's parallax)
    frame_check: bool = True             # beyond the paper: drop the matches of a verified pair whose keypoint scale change
                                         # (and rotation, with frame_check_deg) disagrees with the pair's (the verified
                                         # inliers' median log-scale ratio, circular mean rotation): a repeated
                                         # structure's twin in the epipolar band passes F but not its frame
                                         # (geometry.consistent_similarity). Scale only; against the pair's median at
                                         # 0.5 octave: buddha 0.230 -> 0.223 deg (COLMAP 0.217), wrong inliers 6.2 % ->
                                         # 3.2 % with the second look (benchmarks/results/accuracy)
    frame_check_deg: float | None = None  # frame_check: largest rotation difference from the pair's, degrees; None:
                                         # the rotation is not checked (scale only)
    frame_check_octaves: float = 0.5     # frame_check: largest |log2 scale ratio| difference from the reference (0.75: fox
                                         # 0.480 deg but Herz-Jesus-P8 0.207 -> 0.217, COLMAP 0.214)
    frame_check_grid: int = 6            # frame_check: the reference is the median of the pair's inliers in the same cell of
                                         # a G x G grid over image 1 -- the scale change follows depth (buddha 0.211 ->
                                         # 0.205 deg, P25 0.366 -> 0.361, COLMAP 0.214 / 0.381); 0: the pair's median
    frame_check_scope: Literal["all", "guided"] = "all"  # frame_check: every match, or only the guided ones (the
                                         # unguided ones passed the ratio test against all of image 2, as in BF)
    outside_window: Literal["drop", "band", "band_all"] = "band"  # image-1 feature outside the SO window ω*: "drop"
                                         # (paper §III-B.2) or, when an F model exists and the feature lies within the
                                         # x-extent of the F inliers, "band": match it in the epipolar band only (beyond
                                         # the paper); "band_all": every feature outside ω* in the band
    min_model_matches: int = 16          # fewer correspondences than this: no model is fitted (reported)
    seed: int = 0                        # seeds RANSAC and the draw order within groups without responses
    start: Literal["verified", "paper"] = "verified"  # "verified": the first model guides only once the two-view verdict
                                         # on the unguided correspondences is "verified" (beyond the paper);
                                         # "paper": first model after update_every correspondences, whatever they are
    first_check: int = 32                # unguided correspondences before the first verdict check (start="verified")
    check_growth: float = 1.5            # the next check waits until the evidence has grown by this factor
    guide_margin: float = 1.5            # the first model guides only when the verified model's inliers reach this
                                         # multiple of max(random-inlier bound, 15); a weaker verified pair is matched
                                         # unguided within max_unguided (0001-0007 at 8192: a weak F guided 234 wrong
                                         # matches into its band, BF+ratio returns 163)
    frame_hypotheses: bool = True        # verdicts: when RANSAC on all the evidence verifies nothing, fit one more F
                                         # on the matches whose detector orientations turned alike (geometry step 4;
                                         # Herz-Jesus 0000-0006 at ~40k: 9.6 % -> 27 % correct, no-overlap -> verified);
                                         # the first guiding F must then pass the verdict's rule too (matcher step 3)
    verdict_iters: int = 250             # RANSAC iterations of each verdict check (a verified but weak one is redone
                                         # at 10000 on the orientation-consistent subset; a strong one stops early
                                         # anyway): Herz-Jesus-P8, 28 + 5 pairs, the same matches as 1000 on all 33 at
                                         # 8192 and 31 of 33 at ~40k (the 2 others: more GT inliers); 4x cheaper checks
    max_unguided: float | None = None    # early "no-overlap" exit: stop when the unguided start has spent this fraction of
                                         # N1*N2 comparisons without verified evidence; None: 0.02 with the approximate
                                         # index of image 2 (an index comparison costs ~3x a GEMM one: rejecting an
                                         # unrelated 8192-feature pair in < 1/10 of brute force; 0.025 only kept one
                                         # 16 %-correct weak pair, docs/pairs.md), 0.5 with exact search (binary: no index)
    unguided_index: bool = True          # unguided start (start="verified") searches a faiss IVF index of image 2
                                         # (guidedmatch.prepared; built once per image) instead of exact GEMM
    exact_rent: float = 0.18             # ski-rental: the unguided start searches exactly (GEMM) for its first queries,
                                         # up to min(index build cost, exact_rent * exit budget) comparisons (added to
                                         # the budget: an unrelated pair stops at <= 2 * 1.18 < 3 % of N1*N2), then
                                         # the IVF index (built then if not prepared): ~40k SIFT adjacent Herz-Jesus
                                         # pairs are decided within that and never build one; no rent when it buys
                                         # fewer than max(batch_size, 2 first_check) queries (0: index first)
    unverified: Literal["drop", "keep"] = "drop"  # guided modes, verdict "no-overlap": return no matches (counted in
                                         # stats.details["dropped_unverified"]) or keep the unguided ones; mode "bf"
                                         # always keeps its matches (the baseline)
    auto_bf: bool = True                 # guided modes: brute force when guidance cannot win (sqrt(N1*N2) below
                                         # bf_below_float / bf_below_binary); same result type, said in stats.details
    bf_below_float: int = 2000           # float descriptors: BF below this geometric-mean feature count (measured)
    bf_below_binary: int = 12000         # binary descriptors: BF below this (popcount BF is cheap; ORB/AKAZE crossover)

    def __post_init__(self) -> None:
        o = type(self).__name__
        check_number(o, "num_groups", self.num_groups, lo=1, integer=True)
        check_number(o, "update_every", self.update_every, lo=8, integer=True)
        check_number(o, "num_updates", self.num_updates, lo=0, integer=True)
        check_number(o, "so_threshold", self.so_threshold, lo=0, hi=1, lo_open=True, hi_open=True)
        check_number(o, "band_px", self.band_px, lo=0, lo_open=True)
        check_choice(o, "alignment", self.alignment, APPROACHES)
        check_number(o, "ratio", self.ratio, lo=0, hi=1, lo_open=True, allow_none=True)
        check_choice(o, "single_candidate", self.single_candidate, ("reject", "accept"))
        check_bool(o, "mutual", self.mutual)
        if self.one_to_one is not None:
            check_bool(o, "one_to_one", self.one_to_one)
        check_number(o, "max_distance", self.max_distance, lo=0, allow_none=True)
        check_choice(o, "ransac_method", self.ransac_method, USAC_METHOD_NAMES)
        check_number(o, "ransac_threshold", self.ransac_threshold, lo=0, lo_open=True)
        check_choice(o, "so_overlap", self.so_overlap, get_args(Overlap))
        check_number(o, "batch_size", self.batch_size, lo=1, integer=True)
        check_number(o, "strip_px", self.strip_px, lo=0, lo_open=True, allow_none=True)
        check_bool(o, "recheck", self.recheck)
        check_bool(o, "planar_recheck", self.planar_recheck)
        check_bool(o, "nonplanar_as_F", self.nonplanar_as_F)
        check_choice(o, "planar_inliers", self.planar_inliers, ("H", "larger"))
        check_bool(o, "frame_check", self.frame_check)
        if self.frame_check_deg is not None:
            check_number(o, "frame_check_deg", self.frame_check_deg, lo=0, hi=180, lo_open=True)
        check_number(o, "frame_check_octaves", self.frame_check_octaves, lo=0, lo_open=True)
        check_number(o, "frame_check_grid", self.frame_check_grid, lo=0, hi=64, integer=True)
        check_choice(o, "frame_check_scope", self.frame_check_scope, ("all", "guided"))
        check_choice(o, "outside_window", self.outside_window, ("drop", "band", "band_all"))
        check_number(o, "min_model_matches", self.min_model_matches, lo=8, integer=True)
        check_number(o, "seed", self.seed, lo=0, integer=True)
        check_choice(o, "start", self.start, ("verified", "paper"))
        check_number(o, "first_check", self.first_check, lo=8, integer=True)
        check_number(o, "check_growth", self.check_growth, lo=1, lo_open=True, hi=16)
        check_bool(o, "frame_hypotheses", self.frame_hypotheses)
        check_number(o, "verdict_iters", self.verdict_iters, lo=1, integer=True)
        check_number(o, "guide_margin", self.guide_margin, lo=1, hi=100)
        check_number(o, "max_unguided", self.max_unguided, lo=0, lo_open=True, hi=1, allow_none=True)
        check_bool(o, "unguided_index", self.unguided_index)
        check_number(o, "exact_rent", self.exact_rent, lo=0, hi=1)
        check_choice(o, "unverified", self.unverified, ("drop", "keep"))
        check_bool(o, "auto_bf", self.auto_bf)
        check_number(o, "bf_below_float", self.bf_below_float, lo=0, integer=True)
        check_number(o, "bf_below_binary", self.bf_below_binary, lo=0, integer=True)

    @classmethod
    def paper(cls, **overrides) -> "MatcherConfig":
        """The paper's configuration: no re-check, no one-to-one filter, features outside ω* dropped (§III-B.2), the
        printed alignment (c), the first model after ``update_every`` unguided correspondences (exact search, no
        verdict gate, no early exit), no automatic brute force, matches kept whatever the verdict. The two-view
        verdict is still reported."""
        return cls(**{"recheck": False, "planar_recheck": False, "nonplanar_as_F": False, "frame_check": False, "outside_window": "drop", "one_to_one": False, "alignment": "c",
                      "start": "paper", "auto_bf": False, "unverified": "keep", **overrides})

    def replace(self, **changes) -> "MatcherConfig":
        """A copy with ``changes`` (validated; unknown names listed)."""
        check_fields(type(self), changes)
        return dataclasses.replace(self, **changes)

    def one_to_one_in(self, mode: Mode) -> bool:
        """Whether the one-to-one filter runs in ``mode`` (``one_to_one=None``: guided modes only)."""
        return mode.guided if self.one_to_one is None else self.one_to_one
