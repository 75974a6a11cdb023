"""Settings of a collection run: :class:`CollectionConfig` and the matcher settings a collection changes from the
one-off defaults (:data:`COLLECTION_MATCHER_DEFAULTS`). What the settings do: :mod:`guidedmatch.collection.engine`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

from ..config import MODES, MatcherConfig
from ..errors import ConfigError
from ..validation import check_bool, check_choice, check_number, config_from

__all__ = ["CollectionConfig", "COLLECTION_MATCHER_DEFAULTS", "collection_matcher_config"]


#: matcher settings a collection changes from :class:`~guidedmatch.config.MatcherConfig`'s one-off defaults (a dict
#: given as ``CollectionConfig.matcher`` is applied on top of these; a ``MatcherConfig`` instance is taken as it is).
#: ``exact_rent=0``: every image of a collection is indexed once for all its pairs (its ``PreparedImage`` is cached),
#: so the unguided start searches the index from its first query instead of renting exact search first -- the rent
#: only pays off for one-off pairs. Herz-Jesus-P8 ~40k SIFT, 28 pairs with prepared images: 4.05 -> 3.61 s, GT
#: inliers 186,104 -> 188,491, same verdicts; the 50k COLMAP database: ~0.1 s CPU less per pair (docs/collections.md).
#: ``planar_inliers="larger"``: a collection feeds a mapper, so a planar "H" pair carries COLMAP's inliers for a
#: PLANAR_OR_PANORAMIC pair, the larger of its H and F inlier sets (fox, 3 mapper seeds: 0.493 -> 0.475 deg, AUC@1
#: 0.488 -> 0.501, COLMAP's matcher 0.477 / 0.498; buddha, P8, P25 unchanged); a one-off pair keeps "H" and the planar
#: re-check, which keeps a planar scene's guided matches on its homography (Oxford wall 1-2: 2.2 % -> 0.6 % wrong).
#: ``num_updates=1``: the first model -- fitted once the two-view verdict on the unguided evidence is strong -- guides
#: the final pass directly, without the paper's two further refits after 200 and 400 guided correspondences: each
#: refit (F, alignment, spatial order) and the guided mini-batches between them cost more than they change the
#: matches of a verified pair (fox, 300 pairs in one thread: 40.7 -> 25.8 ms per pair, inliers -0.8 %). Same
#: features, COLMAP's mapper, 3 seeds (2026-12-05): P8 0.205 -> 0.199 deg, P25 0.363 -> 0.364 (AUC@1 0.616 ->
#: 0.625), buddha 0.205 -> 0.206, fox 0.487 -> 0.481 (AUC@1 0.489 -> 0.495), all at least COLMAP's matcher's; a
#: one-off match keeps the paper's 3 (its experiments).
COLLECTION_MATCHER_DEFAULTS = {"exact_rent": 0.0, "planar_inliers": "larger", "num_updates": 1}


def collection_matcher_config(value=None) -> MatcherConfig:
    """The matcher settings of a collection: ``value`` (None, a dict of :class:`MatcherConfig` fields, or an
    instance, taken as it is) over :data:`COLLECTION_MATCHER_DEFAULTS`."""
    if isinstance(value, MatcherConfig):
        return value
    if value is None or isinstance(value, dict):
        return config_from(MatcherConfig, {**COLLECTION_MATCHER_DEFAULTS, **(value or {})})
    return config_from(MatcherConfig, value)  # raises the usual ConfigError


@dataclass(frozen=True)
class CollectionConfig:
    """Settings of :func:`~guidedmatch.collection.engine.match_collection` (the scheduling and the memory bound:
    :mod:`guidedmatch.collection.engine`).

    ``matcher`` accepts a dict of its fields.
    """

    mode: str = "so+epi+ia"                    # matcher mode for every pair (guidedmatch.matcher.MODES)
    matcher: MatcherConfig = field(default_factory=lambda: collection_matcher_config())  # matcher settings: a dict
                                               # of fields is applied over COLLECTION_MATCHER_DEFAULTS
    workers: int | None = None                 # None: auto (engine doc); 0: in-process; N: local cluster of N processes
    threads: int | None = None                 # in-process: pairs matched at once by this many threads (None: 1 per core)
    scheduler: str | None = None               # address of a running Dask scheduler, e.g. "tcp://10.0.0.1:8786"
    retries: int = 1                           # extra attempts of a failed pair before it is reported failed
    progress: bool = True                      # tqdm progress bar (pairs/s, ETA) on stderr
    log_path: str | None = None                # JSON lines: one line per pair, then one summary line (appended)
    chunk_pairs: int = 16                      # pairs per task; a task's pairs share one anchor image
    tasks_per_worker: int = 2                  # tasks in flight per worker (one running, one queued): bounds memory
    cache_mb: float = 1024.0                   # per worker process: LRU bound on cached images, MB (engine doc)
    inprocess_max_work: int = 10_000_000       # auto: in-process when sum over pairs of (n1 + n2) is at most this
    report_max_pairs: int = 100_000            # per-pair dicts kept in the report (the log gets all of them)
    shared_quantizer: str = "off"              # one IVF coarse quantizer for all images: "on", "auto" (from 16
                                               # images) or "off" (opt-in: fox 0.52x -> 0.48x, poses worse; quantizer.py)

    def __post_init__(self) -> None:
        own = "CollectionConfig"
        check_choice(own, "mode", self.mode, MODES)
        object.__setattr__(self, "matcher", collection_matcher_config(self.matcher))
        check_number(own, "workers", self.workers, lo=0, integer=True, allow_none=True)
        check_number(own, "threads", self.threads, lo=1, integer=True, allow_none=True)
        if self.scheduler is not None and (not isinstance(self.scheduler, str) or not self.scheduler.strip()):
            raise ConfigError(f"{own}.scheduler must be an address like 'tcp://host:8786' or None; "
                              f"got {self.scheduler!r}")
        if self.scheduler is not None and self.workers is not None:
            raise ConfigError(f"{own}: give workers (a local cluster) or scheduler (a running one), not both")
        check_number(own, "retries", self.retries, lo=0, integer=True)
        check_bool(own, "progress", self.progress)
        if self.log_path is not None and not isinstance(self.log_path, (str, os.PathLike)):
            raise ConfigError(f"{own}.log_path must be a path or None; got {self.log_path!r}")
        check_number(own, "chunk_pairs", self.chunk_pairs, lo=1, integer=True)
        check_number(own, "tasks_per_worker", self.tasks_per_worker, lo=1, integer=True)
        check_number(own, "cache_mb", self.cache_mb, lo=0)
        check_number(own, "inprocess_max_work", self.inprocess_max_work, lo=0, integer=True)
        check_number(own, "report_max_pairs", self.report_max_pairs, lo=0, integer=True)
        check_choice(own, "shared_quantizer", self.shared_quantizer, ("auto", "on", "off"))
