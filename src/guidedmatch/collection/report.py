"""What a collection run reports: :class:`CollectionReport` (the result of
:func:`~guidedmatch.collection.engine.match_collection`) and :class:`PairOutcome` (one pair's result, as it travels
from the worker that matched it to the writer).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..geometry import TwoViewGeometry

__all__ = ["CollectionReport", "PairOutcome"]


@dataclass(frozen=True)
class CollectionReport:
    """What :func:`~guidedmatch.collection.engine.match_collection` did.

    Attributes:
        done: pairs matched and written in this run.
        skipped: pairs already in the sink (``sink.done_pairs()``), not matched again.
        failed: ``[((name1, name2), reason), ...]`` pairs that failed after ``retries`` retries (not written).
        per_pair: one dict per finished pair (done or failed; the first ``report_max_pairs``): names, features,
            matches, verdict, model, inliers, geometry source, times, worker, attempts, errors.
        totals: sums and run facts (backend and its rule, workers, work, matches, verified pairs, inliers, cache
            hits / loads, pairs/s, in-flight bound, ...).
        wall_s: wall time of the call, seconds (cluster start / stop included).
    """

    done: int
    skipped: int
    failed: list
    per_pair: list
    totals: dict
    wall_s: float

    @property
    def ok(self) -> bool:
        """True when no pair failed."""
        return not self.failed

    def to_dict(self) -> dict:
        """JSON-ready dict (pairs as lists)."""
        return dict(done=self.done, skipped=self.skipped,
                    failed=[dict(pair=list(p), reason=r) for p, r in self.failed],
                    per_pair=self.per_pair, totals=self.totals, wall_s=self.wall_s)

    def summary(self) -> str:
        """A few human-readable lines."""
        t = self.totals
        lines = [f"pairs      : {t.get('pairs', 0)} ({self.done} matched, {self.skipped} skipped as already done, "
                 f"{len(self.failed)} failed)",
                 f"backend    : {t.get('backend')} ({_workers_text(t)}); {t.get('backend_reason')}",
                 f"matches    : {t.get('matches', 0)}; verified pairs {t.get('verified_pairs', 0)} of {self.done}, "
                 f"inlier matches {t.get('inliers', 0)}",
                 f"time       : {self.wall_s:.2f} s wall ({t.get('pairs_per_s', 0.0):.2f} pairs/s matched), "
                 f"matching (verdicts included) {t.get('match_s', 0.0):.2f} s summed over pairs"]
        if t.get("sweeps"):
            lines.append(f"cache      : the images exceed cache_mb {t.get('cache_mb')}: {t['sweeps']} sweeps over "
                         f"resident blocks, {t.get('image_loads', 0)} image loads (a larger cache_mb / --cache-mb: "
                         "fewer)")
        if t.get("startup_s"):
            lines.append(f"cluster    : start {t['startup_s']:.2f} s, stop {t.get('shutdown_s', 0.0):.2f} s")
        for (a, b), reason in self.failed[:5]:
            lines.append(f"failed     : {a} {b}: {reason}")
        if len(self.failed) > 5:
            lines.append(f"failed     : ... and {len(self.failed) - 5} more (see the log)")
        return "\n".join(lines)


@dataclass
class PairOutcome:
    """One pair's result as it travels from a worker to the writer.

    ``pairs (M, 2) int64`` / ``scores (M,) float32`` (the matcher's descriptor distances) and ``geometry`` are set
    when ``ok``; ``reason`` says why not otherwise. ``stats`` is the JSON-ready per-pair record. ``memo``: the pair's
    :class:`~guidedmatch.prepared.StartMemo` when the run keeps them (:mod:`guidedmatch.collection.memos`).
    """

    name1: str
    name2: str
    ok: bool
    reason: str = ""
    pairs: np.ndarray | None = None
    scores: np.ndarray | None = None
    geometry: TwoViewGeometry | None = None
    stats: dict = field(default_factory=dict)
    memo: Any = None


def _workers_text(t: dict) -> str:
    if t.get("backend") == "in-process":
        n = t.get("threads", 1)
        return f"{n} thread{'s' if n != 1 else ''}"
    return f"{t.get('workers')} worker(s)"


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
