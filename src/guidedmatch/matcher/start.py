"""Steps 1-2 of a guided match: the draw order of image-1 features (§III-A) and the unguided start -- exact search,
then the approximate index (ski-rental), the two-view verdict on the evidence and its full-strength re-check."""
from __future__ import annotations

import time

import numpy as np

from .. import kernels
from ..bruteforce import _knn2_exact_sq, knn2
from .models import GuidanceModels
from .state import _Accepted, _Collected, _frames, _has_frames


def draw_order(x: np.ndarray, width: float, num_groups: int, key: np.ndarray) -> np.ndarray:
    """Round-robin draw order of image-1 features over x-interval groups (Teng & Dong §III-A, "Feature Grouping").

    Feature ``i`` belongs to group ``g = clip(floor(x_i / width * G), 0, G - 1)``. Within a group features are taken
    by ascending ``key`` (ties by index); the order is: the first of every group (groups left to right), then the
    second of every group, and so on.

    Args:
        x: ``(N,)`` image-1 x-coordinates, px. width: image width, px (>= max x + 1 in practice).
        num_groups: ``G``. key: ``(N,) float32`` rank key (the matcher uses ``-response``, or seeded uniform noise).

    Returns:
        ``(N,) int64`` permutation of ``arange(N)``.

    >>> draw_order(np.array([0.0, 1.0, 60.0, 61.0, 2.0]), 100.0, 2, np.array([3, 1, 2, 1, 2], np.float32))
    array([1, 3, 4, 2, 0])
    """
    n = len(x)
    if n == 0:
        return np.zeros(0, np.int64)
    g = np.clip((np.asarray(x, np.float64) / width * num_groups).astype(np.int64), 0, num_groups - 1)
    by_key = _argsort_f32(key)
    # stable counting sort by group keeps the key order inside each group
    order_g, offsets = kernels.counting_order(g[by_key], num_groups)
    order_g = by_key[order_g]
    within = np.empty(n, np.int64)
    within[order_g] = np.arange(n) - np.repeat(offsets[:-1], np.diff(offsets))  # rank inside the group
    # round-robin: rank within group, then group (a stable sort of within * G + g, done by counting)
    rr, _ = kernels.counting_order(within * num_groups + g, (int(within.max()) + 1) * num_groups)
    return rr


def tiered_draw_order(x: np.ndarray, width: float, num_groups: int, key: np.ndarray, tiers) -> np.ndarray:
    """:func:`draw_order` tier by tier: the features of ``tiers[0]`` (index arrays; a feature in several tiers counts
    in its first), then those of ``tiers[1]`` not drawn yet, ..., then all the others; each part in the round-robin
    draw order of its own features. ``(N,) int64`` permutation.

    >>> x = np.array([0.0, 1.0, 60.0, 61.0, 2.0])
    >>> tiered_draw_order(x, 100.0, 2, np.array([3, 1, 2, 1, 2], np.float32), [np.array([0, 4])])
    array([4, 0, 1, 3, 2])
    """
    n = len(x)
    tier = np.full(n, len(tiers), np.int64)
    for t in range(len(tiers) - 1, -1, -1):  # earlier tiers written last: they win
        tier[np.asarray(tiers[t], np.int64)] = t
    parts = []
    for t in range(len(tiers) + 1):
        idx = np.flatnonzero(tier == t)
        if len(idx):
            parts.append(idx[draw_order(x[idx], width, num_groups, key[idx])])
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _argsort_f32(key: np.ndarray) -> np.ndarray:
    """Stable ascending argsort of float32 ``key`` (ties by index) through one SIMD sort of unique uint64 keys
    (order-preserving float bits << 32 | index); 5x faster than NumPy's stable float sort at 40k."""
    b = np.ascontiguousarray(key, np.float32).view(np.uint32).astype(np.uint64)
    b = np.where(b >> np.uint64(31), ~b & np.uint64(0xFFFFFFFF), b | np.uint64(0x80000000))
    comp = (b << np.uint64(32)) | np.arange(len(b), dtype=np.uint64)
    return (np.sort(comp) & np.uint64(0xFFFFFFFF)).astype(np.int64)


class UnguidedStart:
    """Steps 1-2 of :class:`~guidedmatch.matcher.run._GuidedRun` (a mixin: the run's state lives in ``run.py``)."""

    def draw_order(self) -> np.ndarray:
        """Step 1 (§III-A): :func:`draw_order` keyed by detector response (strongest first), else seeded noise; with
        a prior (``match(first=...)``) tier by tier (:func:`tiered_draw_order`)."""
        n1 = len(self.d1)
        if n1 == 0 or len(self.d2) == 0:
            return np.zeros(0, np.int64)
        x = self.f1.keypoints[:, 0]
        w = max(float(self.f1.image_size[0]), float(x.max()) + 1)
        r = self.f1.responses
        if r is not None and np.any(r != r[0]):
            key = -r.astype(np.float32)
        else:
            key = np.random.default_rng(self.c.seed).random(n1, np.float32)
        if self.first:
            return tiered_draw_order(x, w, self.c.num_groups, key, self.first)
        return draw_order(x, w, self.c.num_groups, key)

    def unguided_start(self, order: np.ndarray, got: _Collected) -> tuple[GuidanceModels | None, int]:
        """Step 2 (§III-A; the gate is beyond the paper): match drawn features against all of image 2
        until a first model may guide. Returns ``(models or None, queries consumed)``.

        ``start="paper"``: the first model is fitted after ``update_every`` correspondences (exact search), whatever
        they are; the verdict on them is only reported. ``start="verified"``: the unguided correspondences are the
        evidence (no model selected them). After ``first_check`` of them, and each time they have grown by
        ``check_growth``, :func:`~guidedmatch.geometry.two_view_geometry` decides; the first model is fitted as soon
        as it says "verified" -- a model fitted on too little evidence never guides. The search is exact for the first
        ``min(index build comparisons, exact_rent * exit budget)`` comparisons, then the approximate index of image 2
        (:class:`~guidedmatch.prepared.UnguidedSearch`, ``unguided_index``, ``exact_rent``). When the
        start has spent ``max_unguided * N1 * N2`` comparisons plus the exact rent without verified evidence it stops
        (early exit, verdict from the last check: "no-overlap" / "too-few-matches"), the remaining features are not
        matched.
        """
        from ..prepared import UnguidedSearch

        c = self.c
        n1, n2 = len(self.d1), len(self.d2)
        paper = c.start == "paper"
        kind = UnguidedSearch.choose(self.p2, use_index=c.unguided_index and not paper)
        frac = c.max_unguided if c.max_unguided is not None else (0.02 if kind == "ivf" else 0.5)
        budget = frac * n1 * n2
        # ski-rental: exact search until it has cost what building the index costs (capped at exact_rent of the exit
        # budget), the index after -- the same rule whether or not image 2 was prepared, so the same matches
        rent = min(float(self.p2.build_comparisons), c.exact_rent * budget) if kind == "ivf" else 0.0
        if rent < max(c.batch_size, 2 * c.first_check) * n2:
            rent = 0.0  # too few exact queries to reach a first verdict check: pure overhead (8192 SIFT: 37 queries)
        budget += rent  # the rent is not taken from the index's evidence budget: the exit at <= (1 + exact_rent) frac
        # (up to 1.25x that while fewer than 8 correspondences exist: no model could be tested on them yet)
        models = None
        total = ptr = 0
        next_check = max(c.first_check, c.min_model_matches)
        checked_at = -1
        with UnguidedSearch(self.p1, self.p2, kind, exact_budget=rent, memo=self.start_memo) as search:
            while ptr < len(order):
                if search.exact:
                    n = c.batch_size
                    if kind == "ivf":  # the last exact batch is cut to the rent
                        n = int(min(n, max(1, np.ceil((rent - search.exact_comparisons) / max(n2, 1)))))
                else:
                    n = max(c.batch_size, 256)  # an index search has no GEMM to fill
                    if not paper and total and ptr:
                        # the queries expected to reach the next verdict check at the acceptance rate so far (+10 %),
                        # in one call: a faiss call costs ~0.3 ms fixed and its coarse GEMM is 2x faster per query
                        # in batches of 1000+ (8192 SIFT: 4352 queries 17.2 ms in 256s, 13.2 ms in 1024s)
                        n = max(n, min(4096, int(1.1 * (next_check - total) * ptr / total)))
                if not paper and ptr:  # the last batch before the budget is cut to fit it (+ <= 8 queries)
                    left = (budget - self.unguided_comparisons) / max(search.per_query(), 1.0)
                    n = int(min(n, max(8, np.ceil(left)))) if left > 0 else min(n, 64)  # past it (< 8 found): 64 at a time
                batch = order[ptr: ptr + n]
                ptr += len(batch)
                t0 = time.perf_counter()
                acc = self.unguided_batch(batch, search)
                self.timing["initial_bf_s"] += time.perf_counter() - t0
                self.unguided_search = search.used
                got.add(acc, 0)
                total += len(acc.q)
                if paper:
                    if total >= c.update_every and total >= c.min_model_matches:
                        self.decide(got)
                        models = self.fit_models(*got.pairs_so_far())
                        break
                    continue
                if total >= next_check:
                    checked_at = total
                    g = self.decide(got)
                    if g and not self.strong(g):
                        g = self.recheck_weak(got)  # weak at the quick check: a full-strength search decides
                    if self.strong(g):
                        # the first model is fitted anew (ransac_method, 10000 iterations): the verdict's quick F is only a
                        # gate (reusing a quick PROSAC F lost 20-70 % of the true matches on 0000-0003 / 0002-0006),
                        # but it must pass the verdict's rule (frame_hypotheses, fit_fundamental)
                        models = self.fit_models(*got.pairs_so_far(), verdict=g)
                        break
                    next_check = max(next_check + 1, int(np.ceil(total * c.check_growth)))
                if self.unguided_comparisons >= budget and ptr < len(order):
                    if total < 8 and self.unguided_comparisons < 1.25 * budget:
                        continue  # fewer than F's 8 correspondences: nothing could be tested yet; a little longer
                    self.early_exit = (f"unguided start spent {self.unguided_comparisons / max(n1 * n2, 1):.1%} of "
                                       f"N1*N2 ({budget / max(n1 * n2, 1):.1%} allowed) on {ptr} of {n1} features "
                                       f"without evidence strong enough to guide; the remaining {len(order) - ptr} "
                                       "features are not matched")
                    break
            self.timing["index_build_s"] += search.index_build_s
            self.timing["initial_bf_s"] -= search.index_build_s
            self.unguided_search = search.used
            self.start_memo_hits = search.memo_hits
        if models is None:
            if checked_at != total or self.decision is None:
                self.decide(got)  # the verdict on all the evidence there is
            if paper:
                self.fallback("updates", f"only 0 of {c.num_updates} model updates: {total} correspondences from all "
                              f"{n1} features (need {c.update_every} per update)")
                return None, ptr
            what = "early_exit" if self.early_exit else "no_model"
            weak = " (verified, but below guide_margin: no model guided)" if self.decision else ""
            why = self.early_exit or (f"the unguided correspondences were never verified strongly enough to guide "
                                      f"(last verdict {self.decision.verdict!r}{weak}); every feature matched "
                                      "against all of image 2")
            self.fallback(what, why + f"; {self.decision.reason}")
        return models, ptr

    def strong(self, g) -> bool:
        """A verified verdict strong enough to guide: the model's inliers reach ``guide_margin`` times
        ``max(random-inlier bound, min_inliers)`` (a weak one is reported, not followed)."""
        if not g:
            return False
        e = g.evidence
        n, bound = (e["H_inliers"], e["random_bound_H"]) if g.model == "H" else (e["F_inliers"], e["random_bound_F"])
        return n >= self.c.guide_margin * max(bound, 15.0)

    def recheck_weak(self, got: _Collected):
        """Redo a verified but weak quick check at full strength (10000 RANSAC iterations): on the
        orientation-consistent subset of the evidence (geometry step 4, ``second_search="only"``; the quick check's F
        stays a hypothesis) when the features have orientations and ``frame_hypotheses`` is on, else over all the
        evidence. At the inlier ratios of weak pairs (20-35 %) 10000 draws over all the evidence never reach RANSAC's
        confidence and cost ~12 ms at 50-130 correspondences; the subset's ratio is 2-4x higher (Herz-Jesus-P8, all
        pairs, 8192 and ~40k SIFT: faster, and more GT inliers on both sets, docs/pairs.md)."""
        if self.c.verdict_iters >= 10000:
            return self.decision
        if _has_frames(self.c, self.f1, self.f2):
            return self.decide(got, second_search="only", second_iters=10000)
        return self.decide(got, 10000)

    def decide(self, got: _Collected, max_iters: int | None = None, **second):
        """The two-view verdict on the unguided correspondences so far (phase 0: no model selected them), with
        ``verdict_iters`` RANSAC iterations (or ``max_iters``); ``second``: ``second_search`` / ``second_iters`` of
        :func:`~guidedmatch.geometry.two_view_geometry`."""
        from ..geometry import VerdictConfig, two_view_geometry

        t0 = time.perf_counter()
        q = np.concatenate([a.q for a, p in got.parts if p == 0]) if got.parts else np.zeros(0, np.int64)
        j = np.concatenate([a.j for a, p in got.parts if p == 0]) if got.parts else np.zeros(0, np.int64)
        # uniform MAGSAC++ (the calibrated rule). PROSAC on ratio-sorted evidence finds weak models in fewer
        # iterations (AKAZE 0000-0005 at 12k) but also "verified" a false F on 0001-0007 at 8192 (45 of 247 inliers
        # correct under the GT cameras), so it is not used for the decision.
        prior = self.decision.F if self.decision is not None and self.decision.model == "F" else None
        g = two_view_geometry(self.f1.keypoints[q], self.f2.keypoints[j], self.f1.image_size, self.f2.image_size,
                              VerdictConfig(seed=self.c.seed, max_iters=max_iters or self.c.verdict_iters),
                              F_prior=prior, frames=_frames(self.c, self.f1, self.f2, q, j), **second)
        self.decision = g
        self.checks.append(dict(evidence=int(len(q)), verdict=g.verdict, model=g.model, strong=self.strong(g),
                                iterations=int(second.get("second_iters") or max_iters or self.c.verdict_iters),
                                search="orientation subset" if second else "all",
                                F_inliers=g.evidence.get("F_inliers"), H_inliers=g.evidence.get("H_inliers"),
                                bound_F=round(float(g.evidence.get("random_bound_F", 0.0)), 1),
                                comparisons=int(self.unguided_comparisons)))
        self.timing["verdict_s"] += time.perf_counter() - t0
        return g

    def unguided_batch(self, queries: np.ndarray, search=None) -> _Accepted:
        """Step 2: 2-NN of ``queries`` over all of image 2: ``search`` (:class:`~guidedmatch.prepared.UnguidedSearch`,
        the unguided start) or exact (a final pass without models)."""
        if search is not None:
            i1, s1, i2, s2, comp = search.query(queries)
            self.account(len(queries), comp)
            self.unguided_comparisons += comp
            nq = max(len(queries), 1)
            self.ncand.append(np.full(len(queries), comp // nq, np.int64))
            # single-candidate logic: an index search that found one neighbour has no second to test against
            found = np.where(i2 >= 0, 2, np.where(i1 >= 0, 1, 0))
            return self.select(queries, i1, s1, s2, np.minimum(found, len(self.d2)))
        if self.d2_sqnorms is None and not self.binary:
            self.d2_sqnorms = self.p2.sqnorms
        if self.binary:
            (i1, s1, _i2, s2), _ = knn2(self.d1[queries], self.d2, checked=True)
        else:  # exact squared distances, as select() takes them
            i1, s1, _i2, s2 = _knn2_exact_sq(self.d1[queries], self.d2, d2_sqnorms=self.d2_sqnorms)
        n2 = len(self.d2)
        self.account(len(queries), len(queries) * n2)
        nc = np.full(len(queries), n2, np.int64)
        self.ncand.append(nc)
        return self.select(queries, i1, s1, s2, nc)
