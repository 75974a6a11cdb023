"""Steps 4-5 of a guided match: the strip indexes of the aligned image-2 points, guided batches between model
updates and the final vectorized pass (one call of the Numba candidate kernel)."""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from .. import exact, kernels
from .models import GuidanceModels
from .state import _Accepted, _Collected


class GuidedPass:
    """Steps 4-5 of :class:`~guidedmatch.matcher.run._GuidedRun` (a mixin: the run's state lives in ``run.py``)."""

    def strips(self, m: GuidanceModels, lines: np.ndarray, axis: int) -> kernels.StripIndex:
        """Strip index of the aligned image-2 points for lines mostly along ``axis`` (0: horizontal-ish), built on
        first use under the current models.

        Strip width ``w = sqrt(6 / (rho * s))`` (clipped to [4 band, 256] px) balances the per-strip cost (a visit,
        a loop exit) against the points scanned outside the band in each strip (``rho * s * w`` per unit length;
        ``rho`` = image-2 points per px² of their bounding box, ``s`` = median |slope| of the lines against the
        strip direction); the constant 6 is from Herz-Jesus 0002/0003 (flat optimum 96-192 px at s = 0.07).
        Cells along the strip are band/2 high. Speed only: the candidates are the exact region either way.
        """
        if axis in self.strip_cache:
            return self.strip_cache[axis]
        band = float(self.c.band_px)
        if self.c.strip_px:
            w = float(self.c.strip_px)
        elif len(lines) == 0 or m.F is None:
            w = 64.0
        else:
            x, y = m.pts2a[:, 0], m.pts2a[:, 1]  # (per-column min/max: np.ptp(axis=0) on (N, 2) is 10x slower)
            area = (x.max() - x.min()) * (y.max() - y.min()) if len(x) else 1.0
            rho = len(x) / max(float(area), 1.0)
            s = float(np.median(np.abs(lines[:, axis]) / np.maximum(np.abs(lines[:, 1 - axis]), 1e-12)))
            w = float(np.clip(np.sqrt(6.0 / max(rho * max(s, 1e-3), 1e-12)), 4.0 * band, 256.0))
        self.strip_cache[axis] = kernels.build_strips(m.pts2a, max(w, 1e-3), axis, max(band / 2.0, 0.5))
        return self.strip_cache[axis]

    def guided_batch(self, m: GuidanceModels, queries: np.ndarray) -> _Accepted:
        """Steps 4-5: best two candidates of each query in its search region (:func:`search_regions`), one call of
        the Numba kernel; features outside ω* (not rescued) are dropped unmatched."""
        keep, lo, hi, lines, rescued = m.regions(queries)
        self.dropped_outside_overlap += int((~keep).sum())
        self.band_only += int(rescued.sum())
        if lines is None:
            lines = np.zeros((len(queries), 3))
        q = queries[keep]
        lines, lo, hi = lines[keep], lo[keep], hi[keep]
        # process queries in image-1 position order (32 px cells row by row: the point order of a row-strip index):
        # neighbours share candidates, which stay in cache; the order changes nothing but speed
        o = kernels.build_strips(m.pts1a[q], 32.0, axis=1, cell=32.0).items
        use_band = m.F is not None
        vertical = np.abs(lines[:, 0]) > np.abs(lines[:, 1]) if use_band else np.zeros(len(q), bool)
        cols = self.strips(m, lines[~vertical], 0)
        rows = self.strips(m, lines[vertical], 1) if (1 in self.strip_cache or vertical.any()) else self.no_strips
        i1, s1, i2, s2, nc, i3, s3 = kernels.guided_top2(q[o], self.kdesc1, self.kdesc2, lines[o], use_band,
                                                         float(self.c.band_px), lo[o], hi[o], cols, rows,
                                                         return_third=True)
        inv = np.empty_like(o)
        inv[o] = np.arange(len(o))
        i1, s1, i2, s2, nc, i3, s3 = i1[inv], s1[inv], i2[inv], s2[inv], nc[inv], i3[inv], s3[inv]
        if not (self.binary or self.byte_exact):  # float L2 summed in a CPU-dependent order: recompute exactly
            i1, s1, s2 = self.exact_top2(m, q, lines, lo, hi, use_band, np.stack([i1, i2, i3], 1),
                                         np.stack([s1, s2, s3], 1))
        self.account(len(queries), int(nc.sum()))
        self.ncand.append(nc)
        self.no_region += int((nc == 0).sum())
        return self.select(q, i1, s1, s2, nc)

    def exact_top2(self, m: GuidanceModels, q, lines, lo, hi, use_band: bool, cand, approx):
        """Exact top 2 (:func:`guidedmatch.exact.exact_top`) of float queries ``q`` from the candidate kernel's best
        three (``cand``, ``approx``: its vectorized float32 sums, relative error below
        :func:`~guidedmatch.exact.sum_gamma`); a query whose third is too close to its second to certify is
        recomputed over its whole search region (the kernel's predicate, evaluated on the aligned image-2 points).
        Returns ``(i1, s1, s2)``, squared distances float64."""
        band = float(self.c.band_px)
        x, y = m.pts2a[:, 0], m.pts2a[:, 1]

        def region(i):
            ok = (x >= lo[i]) & (x <= hi[i])
            if use_band:
                a, b, c = lines[i]
                ok &= np.abs(a * x + b * y + c) <= band
            return np.flatnonzero(ok)

        top, sq = exact.exact_top(self.d1[q], self.d2, cand, approx, 2, gamma=exact.sum_gamma(self.d1.shape[1]),
                                  domain=region)
        return top[:, 0], sq[:, 0], sq[:, 1]

    def final_pass(self, models: GuidanceModels | None, rest: np.ndarray, got: _Collected) -> None:
        """Step 5: every remaining image-1 feature in one vectorized call (unguided when no model was fitted)."""
        if len(rest):
            t0 = time.perf_counter()
            acc = self.guided_batch(models, rest) if models is not None and models.guided else self.unguided_batch(rest)
            self.timing["final_pass_s"] += time.perf_counter() - t0
            got.add(acc, len(self.updates))
        if models is not None and models.guided:
            self.guidance = dataclasses.replace(models, final_queries=np.asarray(rest, np.int64))
