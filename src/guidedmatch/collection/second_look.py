"""Second look: weak pairs, and rejected pairs that a third view ties together, matched again with a prior.

The guided matcher rejects an unrelated pair cheaply: its unguided start stops after ``max_unguided`` of the
``N1 * N2`` comparisons (0.02 with the approximate index) without verified evidence, and a verified but *weak* pair
(below ``guide_margin``, so nothing guides it) keeps only the unguided matches found within that budget. True pairs
with a wide baseline -- a few dozen correct matches among 8192 features, where COLMAP's exhaustive matcher verifies
15-100 inliers -- are rejected or starved that way: the start draws features in the paper's order, and few of the
first thousand have a match in the other image. On buddha (67 images around a statue) COLMAP verified 712 pairs
and we 425; a budget of 0.1 for *every* pair (666 pairs) took the median pose error from 0.223 to 0.209 deg (COLMAP
0.217) -- at five times the cost of every unrelated pair.

The collection knows which pairs deserve another look, and which of their features to try first:

* **weak pairs**: verified with fewer than ``weak_below`` inliers;
* **rejected pairs tied by a third view**: if ``a-b`` and ``b-c`` are verified, keypoint ``i`` of ``a`` matched to
  ``j`` of ``b``, which is matched to ``k`` of ``c``, gives the *chained* correspondence ``a:i <-> c:k`` without
  comparing a descriptor of ``a`` and ``c``. A rejected pair with at least ``min_chained`` of them shares scene
  points. Images of different scenes have no verified common neighbour: an across-scene pair is never looked at
  again.

:func:`second_look` matches them again with a **prior** (``prior=True``, :func:`priors`): image 1's chained
keypoints are drawn first, then its *tracked* ones (inliers of any verified pair), then the rest (the matcher's
``first``, :func:`guidedmatch.matcher.match`). Nothing else changes: every drawn feature is matched against all of
image 2 with the ratio test and the verdict decides on the pair's own correspondences -- the chains choose the pairs
and the order, never the evidence. (Seeding the matcher with the chains as its first *evidence* was measured and
rejected: its guided matches on wide baselines were 10 % wrong and the poses got worse, 0.230 -> 0.247 deg on
buddha.) With the prior the first pass's budget is enough: on 60 of buddha's candidates (``tools/prior_ab.py``) the
prior at 0.02 verified 51 (33 with >= 64 inliers, 4,758 inliers) in 2.6 s, the paper's order at 0.1 -- the earlier
rule -- 52 (30, 4,318) in 5.5 s, at 0.02 22 (0). Pairs the second look verifies can tie new pairs together, so it runs in rounds until a
round verifies nothing new, no candidate is left or ``max_rounds`` ran (reported).

**Orphans first.** An image with no verified pair at all has no chain and no tracked keypoint: nothing above can
reach it. Before the chain rounds, each such image is matched against its ``orphan_pairs`` most similar images by
the collection's visual words (:func:`guidedmatch.collection.retrieval.most_similar`; the retrieval stage's cache when
there is one), the orphan as image 1 and with the longer start ``orphan_unguided`` (0.1): a few pairs per orphan,
whatever the collection's size. Its verified pairs then give the chain rounds their chains. In ``guidedmatch sfm`` on
the 220-image collection (OpenCV SIFT), buddha's 00065 (2,124 features, grayscale) lost all 20 of its pairs at the
first pass's budget and stayed out of the model; against its 5 most similar images at 0.1 two verify (00039 with 29
inliers, 00049 with 61). The distractor photos of that collection are orphans too: each costs ``orphan_pairs`` longer
rejections, and the verdict rejects them (measured: no across-scene pair verified).

Resumable like the verified expansion: each round's pair list is saved (atomically) in
``<database>.second_look.json`` before it is matched, with a key of the settings and of the graph it started from
(the tried pairs, and the verified pairs outside the saved rounds); the priors of a round come from the verified
pairs outside it, which the round does not change; a rerun replays an unfinished round (matching its pairs again
with the same priors gives the same rows), skips a finished one only where the database holds the match rows it
wrote (a fingerprint in the state: a database removed and made again under the same name has the same graph after
its first pass, but not the rounds' rows, which are matched again and reported) and stops where the finished run
stopped, so a run killed at any moment, then rerun, ends with the same database as an uninterrupted run.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..strip_index import sorted_join
from ..validation import check_bool, check_number, config_from

__all__ = ["SecondLookConfig", "chained_correspondences", "chain_support", "describe", "priors", "second_look",
           "tracked_keypoints"]


@dataclass(frozen=True)
class SecondLookConfig:
    """Settings of :func:`second_look`."""

    min_chained: int = 16          # chained correspondences (through verified common neighbours) a rejected pair needs
    max_unguided: float | None = None  # the second look's unguided budget, a fraction of N1*N2; None: the first
                                   # pass's (0.02 with the index) -- the prior finds the matches within it
    prior: bool = True             # draw image 1's chained keypoints first, then its tracked ones (matcher `first`)
    weak_below: int = 64           # verified pairs with fewer inliers (weak: matched unguided only) are looked at too
    max_rounds: int = 3            # rounds at most (0: no second look)
    max_pairs_per_round: int = 50_000  # candidates matched per round at most (most chained first)
    orphan_pairs: int = 5          # an image with no verified pair: its most similar images (retrieval words) matched
                                   # again first, the orphan as image 1 (0: off); buddha 00065 at OpenCV SIFT: 2 of 5
    orphan_unguided: float = 0.1   # those pairs' unguided budget (fraction of N1*N2): a chain-less pair has no prior
    start_memo_mb: float = 512.0   # memory for the first pass's searches of the pairs looked at again (memos.py;
                                   # the same matches, found faster; 0: off); fox: 46 MB

    def __post_init__(self) -> None:
        own = "SecondLookConfig"
        check_number(own, "min_chained", self.min_chained, lo=1, integer=True)
        check_number(own, "max_unguided", self.max_unguided, lo=0, hi=1, lo_open=True, allow_none=True)
        check_bool(own, "prior", self.prior)
        check_number(own, "weak_below", self.weak_below, lo=0, integer=True)
        check_number(own, "max_rounds", self.max_rounds, lo=0, integer=True)
        check_number(own, "max_pairs_per_round", self.max_pairs_per_round, lo=1, integer=True)
        check_number(own, "orphan_pairs", self.orphan_pairs, lo=0, integer=True)
        check_number(own, "orphan_unguided", self.orphan_unguided, lo=0, hi=1, lo_open=True)
        check_number(own, "start_memo_mb", self.start_memo_mb, lo=0)


# ------------------------------------------------------------------------------------------------ the chains
def chained_correspondences(a, c, inliers: dict, num_keypoints: dict, neighbours: dict, cache: dict | None = None
                            ) -> np.ndarray:
    """Distinct ``(i in a, k in c)`` pairs chained through every verified common neighbour ``b`` of ``a`` and ``c``:
    ``i`` matched to ``j`` in ``a-b``'s inliers and ``j`` to ``k`` in ``b-c``'s. ``(K, 2) int64``, sorted.

    One merge of the inlier lists of every ``a-b`` and ``b-c`` on ``b``'s keypoint
    (:func:`~guidedmatch.strip_index.sorted_join`): its cost follows the inliers, not the images' keypoint counts.

    Args:
        inliers: ``{(x, y): (M, 2) int array}`` inlier matches of every verified pair (either order; column 0 indexes
            ``x``'s keypoints). num_keypoints: ``{image: count}``. neighbours: ``{image: set of verified neighbours}``.
        cache: a dict shared by calls on the same ``inliers`` (each pair's matches oriented and sorted once), or None.

    >>> inl = {("a", "b"): np.array([[0, 5], [1, 6]]), ("c", "b"): np.array([[9, 5], [8, 7]])}
    >>> chained_correspondences("a", "c", inl, {"a": 2, "b": 8, "c": 10}, {"a": {"b"}, "c": {"b"}}).tolist()
    [[0, 9]]
    """
    cache = {} if cache is None else cache
    common = sorted(neighbours.get(a, set()) & neighbours.get(c, set()))
    if not common:
        return np.zeros((0, 2), np.int64)
    ba = [_oriented(b, a, inliers, cache) for b in common]     # b's keypoint j <-> a's keypoint i, sorted by j
    bc = [_oriented(b, c, inliers, cache) for b in common]     # b's keypoint j <-> c's keypoint k, sorted by j
    # one join for every b at once: b's keypoint j keyed (position of b) * 2^32 + j, so both sides stay sorted (a
    # merge: searchsorted of sorted keys)
    na, nc = [len(x[0]) for x in ba], [len(x[0]) for x in bc]
    shift = np.arange(len(common), dtype=np.int64) << 32
    i = np.concatenate([x[1] for x in ba])
    j = np.concatenate([x[0] for x in ba]) + np.repeat(shift, na)
    jb = np.concatenate([x[0] for x in bc]) + np.repeat(shift, nc)
    k = np.concatenate([x[1] for x in bc])
    lo, cnt = sorted_join(j, jb)                               # the b-c matches of each a-b match's j
    has = cnt > 0
    i, lo, cnt = i[has], lo[has], cnt[has]
    if not len(i):
        return np.zeros((0, 2), np.int64)
    if int(cnt.max()) == 1:                                    # one-to-one inliers (the usual case)
        ik = np.stack([i, k[lo]], axis=1)
    else:
        rows = np.repeat(lo - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))
        ik = np.stack([np.repeat(i, cnt), k[rows]], axis=1)
    n = int(max(num_keypoints.get(c, 0), ik[:, 1].max() + 1))
    code = np.unique(ik[:, 0] * n + ik[:, 1])                   # (i, k) sorted lexicographically, each once
    return np.stack([code // n, code % n], axis=1)


def _oriented(x, y, inliers: dict, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """The inlier matches of ``x-y`` as ``(x's keypoints, y's keypoints)``, sorted by x's (stable); cached."""
    got = cache.get((x, y))
    if got is None:
        if (x, y) in inliers:
            m = np.asarray(inliers[(x, y)], np.int64).reshape(-1, 2)
        else:
            m = np.asarray(inliers[(y, x)], np.int64).reshape(-1, 2)[:, ::-1]
        o = np.argsort(m[:, 0], kind="stable")
        got = cache[(x, y)] = (np.ascontiguousarray(m[o, 0]), np.ascontiguousarray(m[o, 1]))
    return got


def _neighbours(inliers: dict) -> dict:
    """``{image: set of images it has a verified pair with}`` of the verified pairs ``inliers`` holds."""
    neighbours: dict = {}
    for x, y in inliers:
        neighbours.setdefault(x, set()).add(y)
        neighbours.setdefault(y, set()).add(x)
    return neighbours


def tracked_keypoints(inliers: dict) -> dict:
    """``{image: sorted keypoint indices}`` of the keypoints that are an inlier of at least one verified pair.

    >>> inl = {("a", "b"): np.array([[0, 5], [1, 6]]), ("c", "b"): np.array([[9, 5]])}
    >>> {k: v.tolist() for k, v in sorted(tracked_keypoints(inl).items())}
    {'a': [0, 1], 'b': [5, 6], 'c': [9]}
    """
    parts: dict = {}
    for (x, y), m in inliers.items():
        m = np.asarray(m, np.int64).reshape(-1, 2)
        parts.setdefault(x, []).append(m[:, 0])
        parts.setdefault(y, []).append(m[:, 1])
    return {n: np.unique(np.concatenate(p)) for n, p in parts.items()}


def priors(pairs, inliers: dict, num_keypoints: dict) -> dict:
    """The matcher's prior draw order (``first`` of :func:`guidedmatch.matcher.match`) for every pair of ``pairs``, both
    ways: ``{(a, c): (a's chained keypoints, a's tracked keypoints), (c, a): (c's ..., c's ...)}`` from the verified
    pairs ``inliers`` (:func:`chained_correspondences`, :func:`tracked_keypoints`). A chained keypoint of ``a`` sees
    a scene point that a common neighbour also sees in ``c``: it is the one most likely to find its match in ``c``;
    a tracked one sees a point some other image sees.

    >>> inl = {("a", "b"): np.array([[0, 5], [1, 6]]), ("c", "b"): np.array([[9, 5], [8, 7]])}
    >>> p = priors([("a", "c")], inl, {"a": 2, "b": 8, "c": 10})
    >>> [t.tolist() for t in p[("a", "c")]], [t.tolist() for t in p[("c", "a")]]
    ([[0], [0, 1]], [[9], [8, 9]])
    """
    neighbours = _neighbours(inliers)
    tracked = tracked_keypoints(inliers)
    none = np.zeros(0, np.int64)
    out, cache = {}, {}
    for a, c in pairs:
        ch = chained_correspondences(a, c, inliers, num_keypoints, neighbours, cache)
        out[(a, c)] = (np.unique(ch[:, 0]), tracked.get(a, none))
        out[(c, a)] = (np.unique(ch[:, 1]), tracked.get(c, none))
    return out


def chain_support(candidates, inliers: dict, num_keypoints: dict) -> list[int]:
    """Number of chained correspondences (:func:`chained_correspondences`) of every ``(a, c)`` in ``candidates``."""
    neighbours, cache = _neighbours(inliers), {}
    return [len(chained_correspondences(a, c, inliers, num_keypoints, neighbours, cache)) for a, c in candidates]


# ------------------------------------------------------------------------------------------------ the graph
def _read_inliers(sink) -> tuple[set, dict, dict]:
    """``(tried pairs as frozensets, {(name1, name2): inlier matches} of the verified ones, {name: keypoints})``,
    read through the sink's own pycolmap connection (nothing else may touch a database pycolmap holds, sink_base)."""
    import pycolmap

    db = sink._db
    names = sink._names
    tried = set(sink.done_pairs()) if not getattr(sink, "overwrite", False) else set()
    inliers = {}
    pids, counts = db.read_two_view_geometry_num_inliers()
    for pid, n in zip(pids, counts):
        if int(n) > 0:
            i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
            a, b = names.get(int(i1)), names.get(int(i2))
            if a is not None and b is not None:
                inliers[(a, b)] = np.asarray(db.read_two_view_geometry(i1, i2).inlier_matches,
                                             np.int64).reshape(-1, 2)
    return tried, inliers, dict(sink._nkp)


def _candidates(tried: set, inliers: dict, nkp: dict, looked: set, cfg: SecondLookConfig):
    """The pairs not looked at yet: weak verified pairs (fewer than ``weak_below`` inliers; support = inliers) and
    rejected ones (tried, not verified) with a verified common neighbour and at least ``min_chained`` chained
    correspondences (support = chains); highest support first (ties by name); ``(pairs, support, total)``."""
    verified = {frozenset(p) for p in inliers}
    neighbours, cache = _neighbours(inliers), {}
    out = []
    for (x, y), m in inliers.items():
        p = frozenset((x, y))
        if len(m) < cfg.weak_below and p not in looked:
            out.append((-len(m), *sorted(p)))
    for p in tried:
        if p in verified or p in looked or len(p) != 2:
            continue
        a, c = sorted(p)
        if not (neighbours.get(a, set()) & neighbours.get(c, set())):
            continue
        k = len(chained_correspondences(a, c, inliers, nkp, neighbours, cache))
        if k >= cfg.min_chained:
            out.append((-k, a, c))
    out.sort()
    total = len(out)
    out = out[:cfg.max_pairs_per_round]
    return [(a, c) for _, a, c in out], [-k for k, _, _ in out], total


def _graph_key(tried: set, inliers: dict, rounds: list, cfg: SecondLookConfig, matcher, looked=()) -> str:
    """The state's key: settings, and the graph before the second look -- rebuilt from the saved rounds, whose pairs
    a resumed run's database may already hold rewritten: each such pair as it was before its first round (tried or
    not, verified or not: ``before`` / ``tried_before``), so a resumed run finds the key of the uninterrupted one."""
    own: dict = {}
    for r in rounds:
        for p, b, tb in zip(r["pairs"], r["before"], r.get("tried_before", [True] * len(r["pairs"]))):
            own.setdefault(frozenset(p), (b, tb))
    tried0 = {frozenset(p) for p in tried if frozenset(p) not in own} | {p for p, (_, tb) in own.items() if tb}
    verified0 = ({frozenset(p) for p in inliers if frozenset(p) not in own}
                 | {p for p, (b, _) in own.items() if b > 0})
    h = hashlib.sha256()
    h.update(json.dumps([sorted(sorted(p) for p in tried0), sorted(sorted(p) for p in verified0), asdict(cfg),
                         repr(matcher)] + ([list(looked)] if len(looked) else [])).encode())
    return h.hexdigest()[:32]


class _Again:
    """A sink wrapper for which the pairs in ``again`` are not done (they are matched once more; writes replace
    their rows)."""

    def __init__(self, sink, again):
        self.sink = sink
        self.again = {frozenset(p) for p in again}
        self.kind = getattr(sink, "kind", "")

    def done_pairs(self, candidates=None):
        from .engine import _done_pairs

        return _done_pairs(self.sink, candidates) - self.again

    def write(self, *args, **kwargs):
        return self.sink.write(*args, **kwargs)


def _orphans(tried: set, inliers: dict) -> list:
    """The images of the tried pairs with no verified pair, sorted."""
    seen = {n for p in tried for n in p}
    verified = {n for p in inliers for n in p}
    return sorted(seen - verified)


def _orphan_round(source, orphans: list, tried: set, cfg: SecondLookConfig) -> dict | None:
    """The orphan round (module doc): ``(orphan, partner)`` for the ``orphan_pairs`` images most similar to each of
    ``orphans`` (the images without a verified pair; :func:`guidedmatch.collection.retrieval.most_similar`), each
    unordered pair once, or None when there is no orphan."""
    if not orphans or not cfg.orphan_pairs:
        return None
    from .retrieval import most_similar

    t = time.perf_counter()
    similar = most_similar(source, orphans, cfg.orphan_pairs, config=dict(progress=False))
    pairs, seen = [], set()
    for o in orphans:
        for m in similar[o]:
            if frozenset((o, m)) not in seen:
                seen.add(frozenset((o, m)))
                pairs.append([o, m])
    return dict(kind="orphans", orphans=len(orphans), pairs=pairs, candidates=len(pairs), capped=False,
                before=[0] * len(pairs), tried_before=[frozenset(p) in tried for p in pairs],
                chain_s=time.perf_counter() - t, done=False)


def _chain_round(tried: set, inliers: dict, nkp: dict, looked: set, cfg: SecondLookConfig) -> dict | None:
    """The next round of weak and chain-tied rejected pairs (:func:`_candidates`), or None when there is none."""
    t = time.perf_counter()
    pairs, support, total = _candidates(tried, inliers, nkp, looked, cfg)
    if not pairs:
        return None
    have = {frozenset(p): len(m) for p, m in inliers.items()}
    return dict(kind="chains", pairs=[list(p) for p in pairs], candidates=total, capped=total > len(pairs),
                before=[have.get(frozenset(p), 0) for p in pairs],   # inliers before (a replay counts from these)
                support_max=max(support), support_min=min(support), chain_s=time.perf_counter() - t, done=False)


def second_look(source, sink, config=None, look: SecondLookConfig | dict | None = None, *,
                state_path: str | os.PathLike | None | bool = True, client=None, looked=(), start_memos=None) -> dict:
    """Match the images without a verified pair against their most similar images with a longer start (the orphan
    round), then the weak pairs and the rejected pairs with enough chained correspondences again, with a prior (and
    ``max_unguided`` when set), in rounds (module doc). ``sink``: an open
    :class:`~guidedmatch.collection.sinks.ColmapSink` with ``geometry="ours"``; ``config``: the
    :class:`~guidedmatch.collection.engine.CollectionConfig` of the first pass (its matcher settings are kept). Returns
    the stage record: ``rounds`` (per round: kind, candidates, pairs, verified, time_s), ``verified`` (pairs the
    second look verified), ``orphans`` (images without a verified pair before it, and how many of them have one
    after), ``stopped`` (why), ``time_s``, ``state``. ``looked``: pairs already matched with the prior (the verified
    expansion's, :class:`~guidedmatch.collection.expansion.ExpansionConfig` ``prior``): never candidates here.
    ``start_memos``: the :class:`~guidedmatch.collection.memos.StartMemos` the first pass recorded into (the same
    matches, faster); the second look only takes from it (its ``recording`` is switched off)."""
    from .config import CollectionConfig
    from .engine import match_collection

    cfg = config_from(SecondLookConfig, look)
    if getattr(sink, "kind", None) != "colmap" or getattr(sink, "geometry", None) != "ours":
        raise ConfigError("the second look reads our two-view geometries back: give a ColmapSink(geometry='ours')")
    cconf = config_from(CollectionConfig, config)
    base = cconf.matcher
    budget = base.max_unguided if cfg.max_unguided is None else max(cfg.max_unguided, base.max_unguided or 0.0)
    cconf = dataclasses.replace(cconf, matcher=dataclasses.replace(base, max_unguided=budget))
    oconf = dataclasses.replace(cconf, matcher=dataclasses.replace(
        base, max_unguided=max(cfg.orphan_unguided, budget or 0.0)))
    t0 = time.perf_counter()
    db = Path(sink.path)
    state = Path(str(db) + ".second_look.json") if state_path is True else (Path(state_path) if state_path else None)
    tried, inliers, nkp = _read_inliers(sink)
    saved = _load(state)
    skip = {frozenset(p) for p in looked}
    key = _graph_key(tried, inliers, saved.get("rounds", []), cfg, base, sorted(sorted(p) for p in skip))
    if saved.get("key") != key:
        saved = {}
    rounds = list(saved.get("rounds", []))
    if start_memos is not None:
        start_memos.recording = False  # the last stage: nothing will match its pairs again, it only takes memos
    stopped = saved.get("stopped")
    looked = {frozenset(p) for r in rounds for p in r["pairs"]} | skip
    orphans_before = None
    record = []
    k = 0
    while True:
        chain_rounds = sum(r.get("kind") != "orphans" for r in rounds[:k])
        if k < len(rounds):
            if rounds[k].get("kind") != "orphans" and chain_rounds >= cfg.max_rounds:
                stopped = stopped or f"max_rounds={cfg.max_rounds} reached"
                break
            r = rounds[k]
        else:
            if stopped is not None:
                break
            r = None
            if cfg.max_rounds > 0 and not rounds:   # the orphan round comes first, once
                orphans = _orphans(tried, inliers)
                orphans_before = len(orphans)
                r = _orphan_round(source, orphans, tried, cfg)
            if r is None:
                if chain_rounds >= cfg.max_rounds:
                    stopped = f"max_rounds={cfg.max_rounds} reached"
                    _save(state, key, rounds, stopped)
                    break
                r = _chain_round(tried, inliers, nkp, looked, cfg)
            if r is None:
                stopped = "no rejected pair with enough chained correspondences left"
                _save(state, key, rounds, stopped)
                break
            rounds.append(r)
            looked |= {frozenset(p) for p in r["pairs"]}
            _save(state, key, rounds, None)
        k += 1
        pairs = [tuple(p) for p in r["pairs"]]
        orphan = r.get("kind") == "orphans"
        stale = bool(r.get("done")) and r.get("rows") != _round_rows(sink, pairs)
        if r.get("done") and not stale:
            record.append(dict(round=k, kind=r.get("kind", "chains"), pairs=len(pairs), verified=r.get("verified", 0),
                               inliers_gained=r.get("inliers_gained", 0), time_s=0.0, replayed=True))
            continue
        t1 = time.perf_counter()
        first = None
        if cfg.prior and not orphan:  # from the graph without this round's own pairs: a replay after a crash finds
            own = {frozenset(p) for p in pairs}  # the same priors
            first = priors(pairs, {p: m for p, m in inliers.items() if frozenset(p) not in own}, nkp)
        rep = match_collection(source, pairs, _Again(sink, pairs), oconf if orphan else cconf, client=client,
                               first=first, start_memos=start_memos)
        tried, inliers, nkp = _read_inliers(sink)
        after = {frozenset(p): len(m) for p, m in inliers.items()}
        mine = [frozenset(p) for p in pairs]
        new = sum(p in after and b == 0 for p, b in zip(mine, r["before"]))
        gained = sum(after.get(p, 0) - b for p, b in zip(mine, r["before"]))
        r.update(done=True, verified=new, inliers_gained=gained, failed=len(rep.failed), rows=_round_rows(sink, pairs))
        record.append(dict(round=k, kind=r.get("kind", "chains"), candidates=r.get("candidates"), pairs=len(pairs),
                           verified=new, inliers_gained=gained, failed=len(rep.failed),
                           chain_s=r.get("chain_s", 0.0), time_s=time.perf_counter() - t1, stale=stale,
                           backend=rep.totals.get("backend"), startup_s=rep.totals.get("startup_s", 0.0),
                           image_loads=rep.totals.get("image_loads", 0)))
        if new == 0 and not orphan:
            stopped = "a round verified no new pair"
        _save(state, key, rounds, stopped)
    verified = sum(r.get("verified", 0) for r in rounds)
    orphan_rounds = [r for r in rounds if r.get("kind") == "orphans"]
    orphans_after = len(_orphans(tried, inliers))
    if orphans_before is None:  # a replay: the count of the round that was saved
        orphans_before = orphan_rounds[0]["orphans"] if orphan_rounds else orphans_after
    return dict(rounds=record, verified=verified, inliers_gained=sum(r.get("inliers_gained", 0) for r in rounds),
                looked=sum(len(r["pairs"]) for r in rounds), stopped=stopped,
                orphans=dict(before=orphans_before, after=orphans_after,
                             pairs=sum(len(r["pairs"]) for r in orphan_rounds),
                             verified=sum(r.get("verified", 0) for r in orphan_rounds),
                             max_unguided=oconf.matcher.max_unguided),
                max_unguided=budget, min_chained=cfg.min_chained, time_s=time.perf_counter() - t0,
                state=str(state) if state else None,
                start_memos=start_memos.summary() if start_memos is not None else None)


def describe(record: dict) -> str:
    """One line for a person of :func:`second_look`'s record.

    >>> describe(dict(looked=7, verified=3, inliers_gained=120, time_s=1.5, rounds=[1, 2], stopped="done",
    ...               orphans=dict(before=2, after=1, pairs=4, verified=1, max_unguided=0.1)))
    '7 weak, rejected or orphan pairs matched again: 3 newly verified, +120 inliers (1.50 s, 2 round(s); stopped: done); images without a verified pair: 2 -> 1 (4 pairs at 0.1)'
    """
    o = record.get("orphans") or {}
    text = (f"{record['looked']} weak, rejected or orphan pairs matched again: {record['verified']} newly verified, "
            f"{record['inliers_gained']:+,} inliers ({record['time_s']:.2f} s, {len(record['rounds'])} round(s); "
            f"stopped: {record['stopped']})")
    stale = sum(isinstance(r, dict) and bool(r.get("stale")) for r in record["rounds"])
    if stale:
        text += f"; {stale} saved round(s) not in this database (made again?): matched again"
    if o.get("before"):
        text += (f"; images without a verified pair: {o['before']} -> {o['after']} ({o['pairs']} pairs at "
                 f"{o['max_unguided']:g})")
    return text


def _round_rows(sink, pairs) -> str:
    """A fingerprint of the match rows of a round's ``pairs`` in the sink's database (absent rows included): a
    finished round is skipped only when the database holds what it wrote. A state file outlives a database removed
    and made again under the same name, whose first pass gives the same graph -- hence the same key -- without the
    rounds' rows (seen on Herz-Jesus-P8: the rerun kept a rejected pair the second look had verified). The raw
    matches, not the geometries: the mapper's inlier selection and the cap rewrite those afterwards."""
    db, h = sink._db, hashlib.sha256()
    for a, b in pairs:
        i1, i2 = sorted((sink._id(a), sink._id(b)))
        m = np.asarray(db.read_matches(i1, i2), np.uint32) if db.exists_matches(i1, i2) else None
        h.update(b"-" if m is None else m.tobytes() + b"|")
    return h.hexdigest()[:32]


def _load(path: Path | None) -> dict:
    if path is None or not path.exists():
        return {}
    try:
        return dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError):
        return {}


def _save(path: Path | None, key: str, rounds: list, stopped: str | None) -> None:
    if path is None:
        return
    from ..features import atomic_write_text

    atomic_write_text(path, json.dumps(dict(key=key, rounds=rounds, stopped=stopped)))
