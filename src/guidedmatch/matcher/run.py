"""A guided match from top to bottom (Teng & Dong §III-A, the system architecture): :func:`match` and
:class:`_GuidedRun`, whose :meth:`~_GuidedRun.run` reads like the paper's figure -- draw order, progressive
unguided phase, model updates every ``update_every`` correspondences (``num_updates`` times), guided pass, filters,
result. The steps live next door: ``start.py`` (1-2), ``models.py`` (3), ``guided.py`` (4-5), ``filters.py`` (6-7).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from .. import kernels
from ..bruteforce import check_descriptors, match_bruteforce
from ..config import MatcherConfig, Mode
from ..errors import InputError
from ..features import as_features
from ..jit import compile_monitor, exclude_compile_time
from ..results import (CandidateStats, Fallback, MatchResult, MatchStats, ModelUpdate, PhaseTimes, default_flags,
                       empty_pairs)
from ..validation import config_from
from .filters import Filters, _drop_unverified, _planar, one_to_one
from .guided import GuidedPass
from .models import GuidanceModels, ModelFits
from .start import UnguidedStart
from .state import _Accepted, _Collected, _frames


# ====================================================================================================== entry point
def match(features1, features2, mode: "str | Mode" = "so+epi+ia", config=None, *, return_models: bool = False,
          first=None, start_memo=None):
    """Match image-1 features to image-2 features with ``mode`` (the package's one matching entry point).

    Args:
        features1, features2: :class:`~guidedmatch.features.Features`, or a tuple ``(keypoints (N,2) px,
            descriptors (N,D), image_size (w,h))`` (float descriptors: L2; uint8: packed bits, Hamming).
        mode: ``"bf" | "epi" | "so" | "so+epi" | "so+epi+ia"`` (:data:`~guidedmatch.config.MODES`) or a
            :class:`~guidedmatch.config.Mode`.
        config: :class:`~guidedmatch.config.MatcherConfig`, a dict of its fields, or None (defaults).
        return_models: also return the final :class:`GuidanceModels` (None for ``bf`` or when no model was fitted).
        first: a prior on which image-1 features are likely to have a match, e.g. from other images of a collection
            (:mod:`guidedmatch.collection.second_look`): an int array of image-1 feature indices, or a sequence of
            them (tiers, earliest first). Each tier is drawn before the rest, in the same round-robin draw order
            (step 1); nothing else changes -- every drawn feature is still matched against all of image 2 and the
            verdict decides on its own matches. None (default): the paper's draw order. Ignored by ``bf``.
        start_memo: a :class:`~guidedmatch.prepared.StartMemo` of this pair (the same images, the same image-2
            index): the unguided start takes the results it holds instead of searching those features again, and
            adds the features it searches (the matches are the same with or without it; ``stats.details
            ["start_memo_hits"]`` counts the features taken). A memo of other images' sizes is ignored.

    Returns:
        :class:`~guidedmatch.results.MatchResult`: ``pairs (M,2) int64`` sorted by image-1 index, ``distances (M,)
        float32``, ``flags`` (``phase``, ``single_candidate``, ``in_band``, ``so_prob``) and ``stats``
        (:class:`~guidedmatch.results.MatchStats`). With ``return_models=True``: ``(MatchResult, GuidanceModels |
        None)``.

    Raises:
        ConfigError: unknown mode or bad config. InputError: descriptors of different kinds or lengths, bad arrays.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> xy, desc = rng.uniform(0, 100, (50, 2)), rng.integers(0, 255, (50, 32)).astype(np.float32)
    >>> res = match((xy, desc, (100, 100)), (xy[::-1], desc[::-1], (100, 100)), "so+epi+ia")
    >>> bool(np.all(res.pairs[:, 1] == 49 - res.pairs[:, 0])), len(res) == 50
    (True, True)
    >>> res.stats.comparisons == 50 * 50   # too few features for guidance to win: brute force, reported
    True
    >>> res.stats.details["auto_bf"].split(":")[0], res.geometry.verdict
    ('brute force instead of guided matching', 'verified')
    """
    from ..prepared import PreparedImage, prepare

    mode = Mode.parse(mode)
    config = config_from(MatcherConfig, config)
    p1 = features1 if isinstance(features1, PreparedImage) else None
    p2 = features2 if isinstance(features2, PreparedImage) else None
    f1 = p1.features if p1 is not None else as_features(features1, "features1")
    f2 = p2.features if p2 is not None else as_features(features2, "features2")
    d1, d2, binary = check_descriptors(f1.descriptors, f2.descriptors,
                                       known_finite=p1 is not None and p2 is not None and p1.finite and p2.finite)
    tiers = _tiers(first, len(d1))
    with compile_monitor() as jit:  # a first call compiles Numba kernels: reported apart from time_s
        why = _bf_wins(config, len(d1), len(d2), binary) if mode.guided else None
        run = None if not mode.guided or why else _GuidedRun(config, mode, p1 or prepare(f1), p2 or prepare(f2),
                                                             d1, d2, binary, first=tiers,
                                                             start_memo=start_memo)
        res = _match_bf(config, f1, f2, d1, d2, binary, mode, why) if run is None else run.run()
    res = exclude_compile_time(res, jit.seconds)
    return (res, run.guidance if run is not None else None) if return_models else res



def _tiers(first, n1: int) -> tuple[np.ndarray, ...]:
    """``first`` (None, one index array or a sequence of them) as a tuple of int64 index arrays, checked against the
    ``n1`` image-1 features (InputError naming the problem).

    >>> _tiers([np.array([3, 1]), [0]], 4)
    (array([3, 1]), array([0]))
    >>> _tiers(np.array([2]), 4), _tiers(None, 4)
    ((array([2]),), ())
    """
    if first is None:
        return ()
    tiers = (first,) if isinstance(first, np.ndarray) and first.ndim == 1 else tuple(first)
    out = []
    for t in tiers:
        a = np.asarray(t)
        if a.size == 0:
            out.append(np.zeros(0, np.int64))
            continue
        if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
            raise InputError(f"first: image-1 feature indices must be 1-D integer arrays, got {a.dtype} {a.shape}")
        if a.min() < 0 or a.max() >= n1:
            raise InputError(f"first: feature index out of range [0, {n1}): {int(a.min())}..{int(a.max())}")
        out.append(a.astype(np.int64, copy=False))
    return tuple(out)


def _bf_wins(c: MatcherConfig, n1: int, n2: int, binary: bool) -> str | None:
    """Why brute force replaces a guided mode (``auto_bf``), or None.

    Guidance has a fixed cost (three robust fits, the spatial-order model, the verdict checks) that brute force does
    not pay; below a size it cannot win. Measured (CPU time, best of 3, Herz-Jesus-P8 pairs 0002-0003 / 0002-0005 /
    0000-0005, guided with ``auto_bf=False``), guided / BF:
    SIFT 0.99 / 0.63 / 0.25 at 2000 features, 0.72 / 0.61 / 0.50 at 4000, <= 0.41 from 8000 on;
    ORB 1.85 / 2.94 at 2000, 1.37 / 1.91 at 4000, 0.76 / 1.31 at 8000, 0.51 / 0.73 at 12000, 0.30 / 0.45 at 16000;
    AKAZE 2.4-2.7 at 2000, 1.1-1.2 at 4000, 0.57-1.04 at 8000, 0.28 / 0.37 at 12000; BRISK 2.0-2.9 at 2000, 1.4-2.1
    at 4000 (it has < 8000 features here). Hence BF below 2000 float and 12000 binary features.
    """
    if not c.auto_bf:
        return None
    size = (float(n1) * float(n2)) ** 0.5
    limit = c.bf_below_binary if binary else c.bf_below_float
    if size < limit:
        kind = "binary" if binary else "float"
        return (f"brute force instead of guided matching: sqrt(N1*N2) = {size:.0f} < bf_below_{kind} = {limit} "
                f"({kind} descriptors), where guidance cannot win")
    return None


def _match_bf(c: MatcherConfig, f1, f2, d1, d2, binary, mode: Mode, auto_reason: str | None = None) -> MatchResult:
    """Mode ``bf`` (or a guided mode replaced by brute force, ``auto_reason``): exact 2-NN over all of image 2,
    ratio / max-distance / mutual tests, one-to-one if on for ``mode``, and the two-view verdict from one robust
    fit on the matches (:func:`~guidedmatch.geometry.two_view_geometry`; nothing selected them by a model)."""
    from ..geometry import VerdictConfig, two_view_geometry

    t0 = time.perf_counter()
    res = match_bruteforce(d1, d2, ratio=c.ratio, mutual=c.mutual, max_distance=c.max_distance)
    pairs, dist = res.pairs, res.distances
    dropped = 0
    if c.one_to_one_in(mode) and len(pairs):
        sel = one_to_one(pairs[:, 0], pairs[:, 1], dist)
        dropped = len(pairs) - len(sel)
        pairs, dist = pairs[sel], dist[sel]
    t1 = time.perf_counter()
    geometry = two_view_geometry(f1.keypoints[pairs[:, 0]], f2.keypoints[pairs[:, 1]], f1.image_size,
                                 f2.image_size, VerdictConfig(seed=c.seed),
                                 frames=_frames(c, f1, f2, pairs[:, 0], pairs[:, 1]))
    n1, n2 = len(d1), len(d2)
    details = dict(res.stats.details, verdict_s=time.perf_counter() - t1)
    flags = default_flags(len(pairs))
    fallbacks = []
    if auto_reason:  # a guided mode answered by brute force: the guided modes' rule for unverified pairs applies
        details.update(requested_mode=mode.name, auto_bf=auto_reason)
        q, j, dist, flags, geometry, n_drop = _drop_unverified(
            c, pairs[:, 0], pairs[:, 1], dist, flags, geometry, lambda w, r: fallbacks.append(Fallback(w, r)))
        pairs = np.stack([q, j], axis=1) if len(q) else empty_pairs()
        details["dropped_unverified"] = n_drop
    stats = dataclasses.replace(res.stats, time_s=time.perf_counter() - t0, dropped_by_one_to_one=dropped,
                                phase_queries=(n1,), phase_comparisons=(n1 * n2,), queries_matched_against=n1,
                                config=c, details=details, fallbacks=tuple(res.stats.fallbacks) + tuple(fallbacks))
    return MatchResult(pairs, dist, stats, flags, geometry)



# ============================================================================================== the guided run
def _kept(keep: np.ndarray, q, j, d, flags: dict, geometry):
    """The matches selected by ``keep`` (their flags, and the verdict reported over them)."""
    return (q[keep], j[keep], d[keep], {k: v[keep] for k, v in flags.items()},
            geometry.with_inliers(geometry.inliers[keep]))


class _GuidedRun(UnguidedStart, ModelFits, GuidedPass, Filters):
    """State of one guided match (not public); :meth:`run` is the method in order."""

    def __init__(self, config: MatcherConfig, mode: Mode, p1, p2, d1, d2, binary, first: tuple = (),
                 start_memo=None):
        self.c = config
        self.first = first  # tiers of image-1 features drawn before the rest (match(first=...))
        self.start_memo = start_memo  # StartMemo of this pair: searched features not searched again
        self.start_memo_hits = 0
        self.mode = mode
        self.p1, self.p2 = p1, p2  # guidedmatch.prepared.PreparedImage of each side
        self.f1, self.f2 = p1.features, p2.features
        self.d1, self.d2, self.binary = d1, d2, binary
        # descriptors in the kernel's form, prepared once per image: packed words (binary); byte-valued float
        # descriptors (OpenCV SIFT) as exact uint8 copies (int32 L2 in the kernel) when both sides are byte-valued
        self.byte_exact = bool(p1.byte_exact and p2.byte_exact)
        if binary or self.byte_exact:
            self.kdesc1, self.kdesc2 = p1.kdesc, p2.kdesc
        else:
            self.kdesc1, self.kdesc2 = d1, d2
        self.checks: list[dict] = []            # verdict checks of the unguided start
        self.decision = None                    # the last TwoViewGeometry decided on unguided evidence
        self.early_exit: str | None = None
        self.unguided_search = None             # "gemm" | "gemm+ivf" | "ivf" | "popcount" (UnguidedSearch.used)
        self.unguided_comparisons = 0
        self.last_alignment = None              # SafeAlignment of the latest model fit (mode IA)
        self.fallbacks: list[Fallback] = []
        self.ncand: list[np.ndarray] = []
        self.timing = dict.fromkeys((f.name for f in dataclasses.fields(PhaseTimes)), 0.0)
        self.updates: list[ModelUpdate] = []
        self.dropped_outside_overlap = 0
        self.no_region = 0
        self.band_only = 0
        self.d2_sqnorms = None
        self.phase_queries: dict[int, int] = {}
        self.phase_comparisons: dict[int, int] = {}
        self.guidance: GuidanceModels | None = None
        self.strip_cache: dict[int, kernels.StripIndex] = {}  # strip indexes of the current models' image-2 points
        self.mutual_comparisons = 0
        self.no_strips = kernels.build_strips(np.zeros((0, 2)), 1.0)

    def fallback(self, what: str, reason: str) -> None:
        """Report a degraded step (:class:`~guidedmatch.results.Fallback`)."""
        self.fallbacks.append(Fallback(what, reason, len(self.updates)))

    def account(self, nq: int, ncomp: int) -> None:
        """Count ``nq`` queries and ``ncomp`` descriptor distances in the current phase (= updates done)."""
        k = len(self.updates)
        self.phase_queries[k] = self.phase_queries.get(k, 0) + int(nq)
        self.phase_comparisons[k] = self.phase_comparisons.get(k, 0) + int(ncomp)

    # ------------------------------------------------------------------------------------------ the method
    def run(self) -> MatchResult:
        """The method: steps 1-8 of the module doc, in order (one method each, below in the same order)."""
        t_start = time.perf_counter()
        order = self.draw_order()
        got = _Collected()
        models, rest = self.progressive_phase(order, got)
        self.final_pass(models, rest, got)
        q, j, d, single, phase = got.arrays()
        q, j, d, flags, dropped_recheck = self.recheck(models, q, j, d, dict(phase=phase, single_candidate=single))
        q, j, d, flags, dropped_o2o, dropped_mutual = self.filters(q, j, d, flags)
        o = np.argsort(q, kind="stable")
        q, j, d = q[o], j[o], d[o]
        flags = {k: v[o] for k, v in flags.items()}
        dropped = (self.c.unverified == "drop" and self.decision is not None
                   and self.decision.verdict == "no-overlap")  # result() returns none of them: nothing to score
        flags["so_prob"] = np.full(len(q), np.nan, np.float32) if dropped else self.so_probabilities(models, q, j)
        return self.result(t_start, models, q, j, d, flags, dropped_recheck, dropped_o2o, dropped_mutual)

    def progressive_phase(self, order: np.ndarray, got: _Collected) -> tuple[GuidanceModels | None, np.ndarray]:
        """Steps 2-4 (§III-A): mini-batches, unguided until the first models (:meth:`unguided_start`), guided after;
        refit the models after every ``update_every`` new correspondences, ``num_updates`` times. Returns the last
        models and the queries left for the final pass (none after an early exit)."""
        c = self.c
        if c.num_updates == 0 or len(order) == 0:
            return None, order
        models, ptr = self.unguided_start(order, got)
        if models is None:  # no verified evidence: nothing guides; early exit leaves the rest unmatched
            if self.early_exit is None and ptr < len(order):
                return None, order[ptr:]
            return None, order[:0]
        since = 0
        total = sum(len(a.q) for a, _ in got.parts)
        drawn = accepted = 0  # guided queries so far and their accepted matches (the acceptance rate)
        while ptr < len(order) and len(self.updates) < c.num_updates:
            # batches sized by the observed acceptance rate to reach the next update in about one batch (at least
            # batch_size): few kernel calls on low-overlap pairs, the same update points on rich ones
            rate = (accepted + 1.0) / (drawn + 1.0) if drawn else 1.0
            bs = int(min(max(c.batch_size, np.ceil((c.update_every - since) / rate)), 8 * c.batch_size + c.update_every))
            batch = order[ptr: ptr + (bs if drawn else c.batch_size)]
            ptr += len(batch)
            t0 = time.perf_counter()
            acc = self.guided_batch(models, batch) if models.guided else self.unguided_batch(batch)
            self.timing["guided_progressive_s"] += time.perf_counter() - t0
            got.add(acc, len(self.updates))
            drawn += len(batch)
            accepted += len(acc.q)
            since += len(acc.q)
            total += len(acc.q)
            if since >= c.update_every:
                since = 0
                models = self.fit_models(*got.pairs_so_far())
        if len(self.updates) < c.num_updates and len(self.d1):
            self.fallback("updates", f"only {len(self.updates)} of {c.num_updates} model updates: "
                          f"{total} correspondences from all {len(self.d1)} features (need {c.update_every} per update)")
        return models, order[ptr:]

    # ------------------------------------------------------------------------------------ step 8: result
    def so_probabilities(self, models: GuidanceModels | None, q, j) -> np.ndarray:
        """Per-match spatial-order probability within the final match set (Talker Eq. 12), float32; NaN when not
        computed (mode without SO, < 2 matches) or when the model of the final set is unusable (reported)."""
        t0 = time.perf_counter()
        out = np.full(len(q), np.nan, np.float32)
        if self.mode.use_so and len(q) >= 2:
            from .. import spatial_order

            pa1 = models.pts1a if models is not None else self.f1.keypoints
            pa2 = models.pts2a if models is not None else self.f2.keypoints
            # the matches already lie inside the model's overlap window: no new window search, no gap table
            so = spatial_order.fit_spatial_order(pa1[q, 0], pa2[j, 0],
                                                 spatial_order.SpatialOrderConfig(overlap="none", gap_table=False))
            if so.usable:
                out = np.asarray(so.probabilities, np.float32)
            else:
                self.fallback("so_prob", f"per-match probabilities not computed: spatial-order model of the final "
                              f"matches unusable ({so.reason}); so_prob = NaN")
        self.timing["so_prob_s"] = time.perf_counter() - t0
        return out

    def result(self, t_start, models, q, j, d, flags, dropped_recheck, dropped_o2o, dropped_mutual) -> MatchResult:
        """Step 8: the MatchResult with its :class:`~guidedmatch.results.MatchStats` (every count of the run) and the
        two-view verdict decided on the unguided evidence, reported over the final matches
        (:func:`~guidedmatch.geometry.report_geometry`); ``unverified="drop"`` empties an unverified result."""
        from ..geometry import VerdictConfig, report_geometry

        t0 = time.perf_counter()
        x1, x2 = self.f1.keypoints[q], self.f2.keypoints[j]
        if self.decision is None:  # no unguided start ran (num_updates = 0): every match is unguided evidence
            got = _Collected()
            got.add(_Accepted(q, j, d, np.zeros(len(q), bool)), 0)
            self.decide(got)
        final_F = models.F if models is not None and models.F is not None else None
        geometry = report_geometry(self.decision, x1, x2, F=final_F, config=VerdictConfig(seed=self.c.seed))
        dropped_planar = 0
        homography = bool(geometry) and geometry.model == "H" and len(q) > 0
        planar = homography and _planar(geometry, final_F, x1, x2)
        recheck = planar and self.c.planar_recheck
        if planar and self.c.planar_inliers == "larger" and final_F is not None and np.all(np.isfinite(final_F)):
            # COLMAP's PLANAR_OR_PANORAMIC rule: the "H" pair carries the larger of the H and F inlier sets; when it
            # is F's, the guided matches off H are F inliers and stay (no planar recheck)
            from ..geometry import with_larger_inlier_set

            geometry = with_larger_inlier_set(geometry, final_F, x1, x2, VerdictConfig(seed=self.c.seed))
            recheck = recheck and geometry.evidence["planar_inliers"] == "H"
        if recheck:
            # a planar scene (or pure rotation): the epipolar band of an F fitted to it constrains nothing along the
            # plane, the verified homography does -- guided matches off it are dropped (unguided ones stay, as in BF)
            keep = (flags["phase"] == 0) | geometry.inliers
            dropped_planar = int((~keep).sum())
            if dropped_planar:
                q, j, d, flags, geometry = _kept(keep, q, j, d, flags, geometry)
        elif homography and not planar and self.c.nonplanar_as_F:
            # "H" decided on a few correspondences of a 3-D scene with a dominant plane: the final matches are not
            # planar by COLMAP's rule, so the pair is reported as F with the F inliers (off the plane included)
            from ..geometry import reported_as_fundamental

            geometry = reported_as_fundamental(geometry, final_F, x1, x2, VerdictConfig(seed=self.c.seed))
        dropped_frames = 0
        f1, f2 = self.f1, self.f2
        if (self.c.frame_check and geometry and len(q) and f1.angles is not None and f2.angles is not None
                and f1.scales is not None and f2.scales is not None):
            # repeated structure: a twin in the epipolar band satisfies F but not the pair's rotation / scale change:
            # matches whose frame disagrees are dropped (frame_check_scope="guided": the guided ones only)
            from ..geometry import consistent_similarity

            same = consistent_similarity(np.asarray(f1.angles)[q], np.asarray(f2.angles)[j],
                                         np.asarray(f1.scales)[q], np.asarray(f2.scales)[j], geometry.inliers,
                                         self.c.frame_check_deg, self.c.frame_check_octaves,
                                         positions=(f1.keypoints[q], f1.image_size),
                                         grid=self.c.frame_check_grid)
            keep = same | (flags["phase"] == 0) if self.c.frame_check_scope == "guided" else same
            dropped_frames = int((~keep).sum())
            if dropped_frames:
                q, j, d, flags, geometry = _kept(keep, q, j, d, flags, geometry)
        self.timing["verdict_s"] += time.perf_counter() - t0
        q, j, d, flags, geometry, dropped_unverified = _drop_unverified(self.c, q, j, d, flags, geometry,
                                                                        self.fallback)
        n1, n2 = len(self.d1), len(self.d2)
        nphase = len(self.updates) + 1
        phase_comparisons = tuple(self.phase_comparisons.get(k, 0) for k in range(nphase))
        stats = MatchStats(
            method=self.mode.name, comparisons=int(sum(phase_comparisons)) + self.mutual_comparisons,
            time_s=time.perf_counter() - t_start, num_features=(n1, n2), metric="hamming" if self.binary else "l2",
            byte_exact_kernel=self.byte_exact, timing=PhaseTimes(**self.timing), updates=tuple(self.updates),
            candidates_per_query=CandidateStats.of(np.concatenate(self.ncand) if self.ncand else np.zeros(0, np.int64)),
            queries_matched_against=int(sum(len(x) for x in self.ncand)),
            dropped_outside_overlap=self.dropped_outside_overlap, queries_without_candidates=self.no_region,
            band_only_outside_window=self.band_only, dropped_by_recheck=dropped_recheck,
            dropped_by_one_to_one=dropped_o2o, dropped_by_mutual=dropped_mutual,
            F=None if models is None or models.F is None else np.asarray(models.F),
            alignment_H2=None if models is None or np.allclose(models.H2, np.eye(3)) else np.asarray(models.H2),
            phase_queries=tuple(self.phase_queries.get(k, 0) for k in range(nphase)),
            phase_comparisons=phase_comparisons, fallbacks=tuple(self.fallbacks), config=self.c,
            details=dict(unguided_search=self.unguided_search, verdict_checks=tuple(self.checks),
                         early_exit=self.early_exit, unguided_comparisons=int(self.unguided_comparisons),
                         dropped_unverified=dropped_unverified, dropped_off_homography=dropped_planar,
                         dropped_off_frame=dropped_frames, start_memo_hits=self.start_memo_hits))
        pairs = np.stack([q, j], axis=1) if len(q) else empty_pairs()
        return MatchResult(pairs, d, stats, flags, geometry)
