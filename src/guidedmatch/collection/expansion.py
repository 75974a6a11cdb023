"""Verified expansion: match the pairs that close a triangle of verified pairs, in rounds.

After a shortlist (e.g. retrieval pairs) is matched, a pair ``a-c`` that was never tried but has a common verified
neighbour (``a-b`` and ``b-c`` verified) very likely overlaps too. :func:`match_collection_expanded` matches the
shortlist, then in rounds every such triangle-closing pair (most common verified neighbours first, at most
``max_pairs_per_round``), until a round adds no verified pair, no candidate is left or ``max_rounds`` ran. This
recovers the overlapping pairs a shortlist misses -- what COLMAP users emulate with transitive matching.

Optionally (``prior=True``, off by default) a round's pairs are matched with the second look's prior
(:func:`guidedmatch.collection.second_look.priors`): image 1's chained keypoints -- matched to the other image
through a verified common neighbour, which a triangle-closing pair always has -- are drawn first, then its tracked
ones, and the second look skips those pairs (:attr:`StagedReport.prior_pairs`): one attempt per pair instead of
two. On the 220-image collection: 19 % fewer descriptor comparisons, 0.8 % fewer verified pairs, the same recall;
on buddha (``retrieval:20``) 28 % less CPU but 600 verified pairs instead of 612 and a median pose error of 0.225 deg
instead of 0.216 (COLMAP 0.217): not the default (docs/collections.md).

The verified graph is read back from the sink: a COLMAP database's ``two_view_geometries`` (a pair is tried when it
has a geometry row -- or, with ``geometry="colmap"``, a matches row -- and verified when its geometry has inlier
matches; :func:`read_verified_graph`).

Resumable: every round's candidate list is saved (atomically) before it is matched, in ``<database>.expansion.json``
with a key of the shortlist and the settings; a rerun replays the saved rounds (their pairs already in the database
are skipped) before it computes a new one, so a run killed at any moment, then rerun, ends with the same database
as an uninterrupted run.
"""
from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..validation import check_bool, check_number, config_from

__all__ = ["ExpansionConfig", "StagedReport", "read_verified_graph", "triangle_candidates",
           "match_collection_expanded"]

_PAIR_ID_BASE = 2147483647  # COLMAP: pair_id = id1 * 2147483647 + id2, id1 < id2


@dataclass(frozen=True)
class ExpansionConfig:
    """Settings of the verified expansion (:func:`match_collection_expanded`)."""

    max_rounds: int = 10                  # rounds of triangle closing at most (0: no expansion)
    max_pairs_per_round: int = 50_000     # candidates matched per round at most (most supported first)
    min_support: int = 1                  # common verified neighbours a candidate needs
    min_inliers: int = 1                  # inlier matches that make a pair verified (its geometry's inliers)
    prior: bool = False                   # our geometries: draw each candidate's chained, then tracked keypoints first
                                          # (second_look.priors) and the second look skips these pairs: 19 % fewer
                                          # comparisons on the 220 images, but buddha 0.216 -> 0.225 deg (one attempt
                                          # per pair instead of two; docs/collections.md)

    def __post_init__(self) -> None:
        own = "ExpansionConfig"
        check_number(own, "max_rounds", self.max_rounds, lo=0, integer=True)
        check_number(own, "max_pairs_per_round", self.max_pairs_per_round, lo=1, integer=True)
        check_number(own, "min_support", self.min_support, lo=1, integer=True)
        check_number(own, "min_inliers", self.min_inliers, lo=1, integer=True)
        check_bool(own, "prior", self.prior)


# ---------------------------------------------------------------------------------------------------- the graph
def read_verified_graph(database_path, min_inliers: int = 1, *, tried_from: str = "geometry"):
    """``(tried, verified)``: sets of ``frozenset((name1, name2))`` of a COLMAP database.

    ``tried``: pairs with a two-view geometry row (``tried_from="geometry"``, what :class:`ColmapSink` with
    ``geometry="ours"`` writes for every matched pair) or a matches row (``"matches"``); ``verified``: pairs whose
    two-view geometry has at least ``min_inliers`` inlier matches. Read with a read-only SQLite connection (the
    writer may hold the database open).
    """
    from .sink_base import pycolmap_opened

    if pycolmap_opened(database_path):  # Python's sqlite3 must not touch a file pycolmap holds here (sink_base)
        return _verified_graph_pycolmap(database_path, min_inliers, tried_from)
    uri = Path(database_path).resolve().as_uri() + "?mode=ro"
    con = sqlite3.connect(uri, uri=True, timeout=30.0)
    try:
        ids = dict(con.execute("SELECT image_id, name FROM images"))

        def names(pid):
            pid = int(pid)
            i2 = pid % _PAIR_ID_BASE
            i1 = (pid - i2) // _PAIR_ID_BASE
            a, b = ids.get(i1), ids.get(i2)
            return frozenset((a, b)) if a is not None and b is not None else None

        geo = con.execute("SELECT pair_id, rows FROM two_view_geometries").fetchall()
        verified = {s for pid, r in geo if int(r) >= min_inliers and (s := names(pid)) is not None}
        table = "two_view_geometries" if tried_from == "geometry" else "matches"
        tried = {s for (pid,) in con.execute(f"SELECT pair_id FROM {table}") if (s := names(pid)) is not None}
    finally:
        con.close()
    return tried, verified


def _verified_graph_pycolmap(database_path, min_inliers: int, tried_from: str):
    """:func:`read_verified_graph` through pycolmap (for a database this process already holds with pycolmap):
    :func:`~guidedmatch.collection.sinks.done_pairs_in` and :func:`~guidedmatch.collection.sinks.verified_pairs_in`,
    as a sink reads them."""
    from .sinks import done_pairs_in, verified_pairs_in
    from .colmap_source import _open_colmap

    db = _open_colmap(Path(database_path))
    try:
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        tried = done_pairs_in(db, ids, "ours" if tried_from == "geometry" else "matches")
        return tried, verified_pairs_in(db, ids, min_inliers)
    finally:
        db.close()


def sink_verified_graph(sink, min_inliers: int = 1):
    """``(tried, verified)`` as :func:`read_verified_graph`, read through the sink's own database connection (the
    writer's view: a separate connection did not always see the pairs an in-process run had just written) --
    ``tried`` = ``sink.done_pairs()``, ``verified`` = pairs whose two-view geometry has ``min_inliers`` inliers."""
    from .sinks import verified_pairs_in

    db = getattr(sink, "_db", None)
    if db is None:
        return read_verified_graph(sink.path, min_inliers,
                                   tried_from="geometry" if sink.geometry == "ours" else "matches")
    verified = verified_pairs_in(db, sink._ids, min_inliers)
    return set(sink.done_pairs()), verified


def triangle_candidates(names, tried, verified, min_support: int = 1, limit: int | None = None):
    """Untried pairs ``(a, c)`` with at least ``min_support`` common verified neighbours ``b`` (``a-b`` and ``b-c``
    verified), most supported first (ties: the order of ``names``); ``(pairs, support, total)`` with ``total`` the
    number of candidates before ``limit``.

    >>> v = {frozenset(p) for p in [("a", "b"), ("b", "c"), ("c", "d")]}
    >>> triangle_candidates("abcd", set(v), v)[0]
    [('a', 'c'), ('b', 'd')]
    """
    import scipy.sparse as sp

    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    n = len(names)
    e = np.array([sorted((index[a], index[b])) for a, b in (tuple(s) for s in verified)
                  if a in index and b in index], np.int64).reshape(-1, 2)
    if len(e) == 0:
        return [], [], 0
    adj = sp.coo_matrix((np.ones(2 * len(e), np.int32), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                        shape=(n, n)).tocsr()
    common = sp.triu(adj @ adj, k=1).tocoo()
    keep = common.data >= min_support
    i, j, s = common.row[keep], common.col[keep], common.data[keep]
    untried = np.array([frozenset((names[a], names[b])) not in tried for a, b in zip(i, j)], bool)
    i, j, s = i[untried], j[untried], s[untried]
    order = np.lexsort((j, i, -s))
    total = len(order)
    if limit is not None:
        order = order[:limit]
    return [(names[i[k]], names[j[k]]) for k in order], [int(s[k]) for k in order], total


# ---------------------------------------------------------------------------------------------------- the report
@dataclass(frozen=True)
class StagedReport:
    """What :func:`match_collection_expanded` did, stage by stage.

    Attributes:
        stages: one dict per stage: ``{"stage": "retrieval" | "shortlist" | "expansion N", "pairs", "matched",
            "skipped", "failed", "verified", "time_s", ...}`` (retrieval: words, reused; expansion: candidates,
            support, capped).
        reports: the :class:`~guidedmatch.collection.engine.CollectionReport` of every matching stage.
        expansion: ``{"rounds", "stopped" (why), "capped_rounds", "max_rounds", "max_pairs_per_round", "state"}``.
        wall_s: wall time of the call (the retrieval stage is timed where it ran: ``stages[0]["time_s"]``).
    """

    stages: list
    reports: list
    expansion: dict
    wall_s: float
    verified_pairs: int = 0
    tried_pairs: int = 0
    failed: list = field(default_factory=list)
    prior_pairs: list = field(default_factory=list)   # the expansion pairs matched with the prior (second_look skips)

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def done(self) -> int:
        return sum(r.done for r in self.reports)

    @property
    def skipped(self) -> int:
        return sum(r.skipped for r in self.reports)

    @property
    def per_pair(self) -> list:
        return [p for r in self.reports for p in r.per_pair]

    @property
    def totals(self) -> dict:
        t = dict(self.reports[-1].totals) if self.reports else {}
        t.update(pairs=sum(r.totals.get("pairs", 0) for r in self.reports),
                 matches=sum(r.totals.get("matches", 0) for r in self.reports),
                 inliers=sum(r.totals.get("inliers", 0) for r in self.reports),
                 match_s=sum(r.totals.get("match_s", 0.0) for r in self.reports),
                 verified_pairs=self.verified_pairs, tried_pairs=self.tried_pairs)
        return t

    def to_dict(self) -> dict:
        """JSON-ready; has the keys of ``CollectionReport.to_dict`` (done, skipped, failed, totals) plus the stages."""
        return dict(done=self.done, skipped=self.skipped, totals=self.totals,
                    stages=self.stages, expansion=self.expansion, wall_s=self.wall_s,
                    verified_pairs=self.verified_pairs, tried_pairs=self.tried_pairs,
                    failed=[dict(pair=list(p), reason=r) for p, r in self.failed],
                    reports=[dict(r.to_dict(), per_pair=[]) for r in self.reports])

    def summary(self) -> str:
        lines = []
        for s in self.stages:
            if s["stage"] == "retrieval":
                lines.append(f"retrieval  : {s['pairs']} pairs (K={s.get('k')}, {s.get('words')} words, "
                             f"{s.get('images')} images, reused: {s.get('reused')}), {s['time_s']:.2f} s")
            else:
                extra = ""
                if "candidates" in s:
                    extra = f" of {s['candidates']} candidates" + (" (capped)" if s.get("capped") else "")
                lines.append(f"{s['stage']:<11}: {s['pairs']} pairs{extra}, {s['matched']} matched, {s['skipped']} "
                             f"skipped, {s['verified']} verified, {s['time_s']:.2f} s")
        e = self.expansion
        if e:
            lines.append(f"expansion  : {e['rounds']} round(s), stopped: {e['stopped']}"
                         + (f"; cap of {e['max_pairs_per_round']} pairs per round hit in {e['capped_rounds']} "
                            f"round(s)" if e.get("capped_rounds") else ""))
        ret = sum(s["time_s"] for s in self.stages if s["stage"] == "retrieval")
        share = f" ({ret:.2f} s retrieval = {100 * ret / (self.wall_s + ret):.1f} % + {self.wall_s:.2f} s matching)"
        lines.append(f"total      : {self.tried_pairs} pairs tried, {self.verified_pairs} verified, "
                     f"{self.wall_s + ret:.2f} s wall" + (share if ret else ""))
        if self.reports:
            r = self.reports[-1]
            t = r.totals
            lines.append(f"backend    : {t.get('backend')}; {t.get('backend_reason')}")
        for (a, b), reason in self.failed[:5]:
            lines.append(f"failed     : {a} {b}: {reason}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- the run
def _state_key(pairs, cfg: ExpansionConfig) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([sorted(sorted(p) for p in pairs), asdict(cfg)]).encode())
    return h.hexdigest()[:32]


def _load_state(path: Path | None, key: str) -> list:
    """The rounds saved by an earlier run with the same shortlist and settings (else [])."""
    if path is None or not path.exists():
        return []
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return list(state.get("rounds", [])) if state.get("key") == key else []


def _save_state(path: Path | None, key: str, rounds: list) -> None:
    if path is None:
        return
    from ..features import atomic_write_text

    atomic_write_text(path, json.dumps(dict(key=key, rounds=rounds)))


def match_collection_expanded(source, pairs, sink, config=None, expand: ExpansionConfig | dict | None = None, *,
                              state_path: str | os.PathLike | None | bool = True, client=None,
                              start_memos=None) -> StagedReport:
    """Match ``pairs`` (the shortlist), then the triangle-closing pairs in rounds (module doc).

    Args:
        source, pairs, sink, config, client, start_memos: as
            :func:`~guidedmatch.collection.engine.match_collection` (each stage given them); the
            sink must be a :class:`~guidedmatch.collection.sinks.ColmapSink` (the verified graph is read from its
            database). A :class:`~guidedmatch.collection.pairs.PairList` made by a retrieval spec contributes
            the retrieval stage (``pairs.report["retrieval"]``) to the report.
        expand: :class:`ExpansionConfig` or a dict of its fields (``max_rounds=0``: the shortlist only).
        state_path: where the rounds are saved (True: ``<database>.expansion.json``; None: nowhere -- then a
            resumed run recomputes the rounds from the database, which ends in the same set of pairs only when no
            cap was hit).

    Returns:
        :class:`StagedReport`.
    """
    from .engine import match_collection

    ecfg = config_from(ExpansionConfig, expand)
    db = getattr(sink, "path", None)
    if getattr(sink, "kind", None) != "colmap" or db is None:
        raise ConfigError("verified expansion reads the verified pairs back from a COLMAP database: give a "
                          "ColmapSink (an hloc matches.h5 stores no two-view geometry)")
    geometry = getattr(sink, "geometry", "ours")
    if geometry == "none":
        raise ConfigError("verified expansion needs two-view geometries: ColmapSink(geometry='ours' or 'colmap')")
    tried_from = "geometry" if geometry == "ours" else "matches"
    state = (Path(str(db) + ".expansion.json") if state_path is True else (Path(state_path) if state_path else None))
    t_start = time.perf_counter()
    names = list(source.names())
    stages: list = []
    reports: list = []
    failed: list = []
    info = getattr(pairs, "report", {}).get("retrieval") if hasattr(pairs, "report") else None
    if info:
        stages.append(dict(stage="retrieval", pairs=info.get("pairs"), time_s=info.get("time_s", 0.0),
                           **{k: info.get(k) for k in ("k", "words", "images", "reused", "vocabulary_s",
                                                       "assign_s", "shortlist_s", "cache")}))
    shortlist = [tuple(p) for p in getattr(pairs, "pairs", pairs)]

    with_prior = ecfg.prior and geometry == "ours"
    prior_pairs: list = []

    def run(stage: str, todo, extra: dict, prior: bool = False) -> set:
        t = time.perf_counter()
        first = None
        if prior:  # from the verified graph without this round's own pairs: a replay after a crash finds the same
            from .second_look import _read_inliers, priors   # priors (the round's pairs were never tried before it)

            _, inliers, nkp = _read_inliers(sink)
            own = {frozenset(p) for p in todo}
            first = priors(todo, {p: m for p, m in inliers.items() if frozenset(p) not in own}, nkp)
            prior_pairs.extend(todo)
            extra = dict(extra, prior=True, prior_s=time.perf_counter() - t)
        rep = match_collection(source, todo, sink, config, client=client, first=first, start_memos=start_memos)
        if geometry == "colmap":
            sink.verify()  # COLMAP's verification of the pairs with matches and no geometry yet
        reports.append(rep)
        failed.extend(rep.failed)
        tried, verified = (sink_verified_graph(sink, ecfg.min_inliers) if hasattr(sink, "_names")
                           else read_verified_graph(db, ecfg.min_inliers, tried_from=tried_from))
        stages.append(dict(stage=stage, pairs=len(todo), matched=rep.done, skipped=rep.skipped,
                           failed=len(rep.failed), verified=sum(frozenset(p) in verified for p in todo),
                           time_s=time.perf_counter() - t, **extra))
        return tried, verified

    tried, verified = run("shortlist", pairs, {})
    key = _state_key(shortlist, ecfg)
    saved_rounds = _load_state(state, key)
    rounds_done = 0
    capped = 0
    stopped = "max_rounds=0" if ecfg.max_rounds == 0 else None
    while rounds_done < ecfg.max_rounds:
        if rounds_done < len(saved_rounds):  # replay a round saved by an earlier (interrupted) run
            r = saved_rounds[rounds_done]
            cand = [tuple(p) for p in r["pairs"]]
            total, hit, support = r["candidates"], r["capped"], r.get("support_max", 0)
        else:
            cand, sup, total = triangle_candidates(names, tried, verified, ecfg.min_support,
                                                   ecfg.max_pairs_per_round)
            hit = total > len(cand)
            support = max(sup) if sup else 0
            if not cand:
                stopped = "no triangle-closing pair left"
                break
            saved_rounds = saved_rounds[:rounds_done] + [dict(pairs=[list(p) for p in cand], candidates=total,
                                                              capped=hit, support_max=support)]
            _save_state(state, key, saved_rounds)
        rounds_done += 1
        capped += bool(hit)
        tried, verified = run(f"expansion {rounds_done}", cand, dict(candidates=total, capped=bool(hit),
                                                                      support_max=support), prior=with_prior)
        if stages[-1]["verified"] == 0:  # the round's pairs were all untried: none verified = nothing added
            stopped = "a round added no verified pair"
            break
    if stopped is None:
        stopped = f"max_rounds={ecfg.max_rounds} reached"
    expansion = dict(rounds=rounds_done, stopped=stopped, capped_rounds=capped, max_rounds=ecfg.max_rounds,
                     max_pairs_per_round=ecfg.max_pairs_per_round, prior=with_prior,
                     state=str(state) if state else None)
    return StagedReport(stages, reports, expansion, time.perf_counter() - t_start, verified_pairs=len(verified),
                        tried_pairs=len(tried), failed=failed, prior_pairs=prior_pairs)
