"""Collection engine: scheduling, resume, retries, local cluster -- with in-memory test doubles.

The doubles implement the FeatureSource / MatchSink interfaces of INTERFACES.md: a dict-backed source of synthetic
multi-view features (3-D points seen by cameras with known poses, one view of unrelated points) and a list-backed
sink. The CLI / COLMAP database tests (kill and resume, pycolmap mapping) are further down.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from guidedmatch.collection import cache as engine_cache
from guidedmatch.collection import inprocess, planning
from guidedmatch.collection.cache import _ImageCache, _TaskSpec
from guidedmatch.collection.config import collection_matcher_config
from guidedmatch.collection.engine import CollectionConfig, match_collection, plan_tasks
from guidedmatch.errors import ConfigError, InputError
from guidedmatch.features import Features
from guidedmatch.geometry import VERDICTS
from guidedmatch.matcher import MatcherConfig, match
from guidedmatch.testing.arc_views import arc_views


def make_views(n_views: int = 4, n_points: int = 1200, seed: int = 0) -> dict[str, Features]:
    """``n_views`` cameras on an arc looking at a point cloud (overlapping), plus ``"other"``: unrelated points."""
    return arc_views(n_views, n_points, seed, unrelated=800)


class DictSource:
    """FeatureSource double: features in a dict (picklable); ``fail`` names raise on load, ``die`` names kill the
    process loading them (a worker dying mid-task)."""

    kind = "dict"

    def __init__(self, feats: dict, fail=(), die=()):
        self.feats, self.fail, self.die = feats, set(fail), set(die)
        self.path = None
        self.loads = 0

    def names(self):
        return list(self.feats)

    def image_size(self, name):
        return self.feats[name].image_size

    def num_features(self, name):
        return len(self.feats[name])

    def load(self, name):
        if name in self.die and os.environ.get("GM_TEST_IN_WORKER") == "1":
            os._exit(17)
        if name in self.fail:
            raise OSError(f"cannot read the features of {name} (test double)")
        self.loads += 1
        return self.feats[name]

    def close(self):
        pass


class ListSink:
    """MatchSink double: every write in a dict keyed by the unordered pair (a second write of a pair is an error)."""

    def __init__(self, done=()):
        self.rows: dict[frozenset, tuple] = {}
        self.order: list = []
        self.preset = {frozenset(p) for p in done}

    def done_pairs(self):
        return set(self.preset) | set(self.rows)

    def write(self, name1, name2, pairs, scores, geometry):
        key = frozenset((name1, name2))
        assert key not in self.rows, f"pair {key} written twice"
        assert pairs.dtype == np.int64 and pairs.ndim == 2 and pairs.shape[1] == 2
        assert scores.dtype == np.float32 and scores.shape == (len(pairs),)
        assert geometry is not None and len(geometry.inliers) == len(pairs)
        self.rows[key] = (name1, name2, pairs.copy(), scores.copy(), geometry)
        self.order.append(key)

    def close(self):
        pass


@pytest.fixture(scope="module")
def views():
    return make_views()


def all_pairs(names):
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def reference(feats, a, b, mode="so+epi+ia", first=None, config=None):
    """The slow, obviously-correct path: one direct matcher call per pair (its result carries the verdict)."""
    res = match(feats[a], feats[b], mode, config or collection_matcher_config(), first=first)  # a collection's settings
    return res, res.geometry


def assert_same_as_reference(sink, feats, pairs, first=None, config=None):
    assert set(sink.rows) == {frozenset(p) for p in pairs}
    for a, b in pairs:
        n1, n2, got, scores, geom = sink.rows[frozenset((a, b))]
        assert (n1, n2) == (a, b)
        res, g = reference(feats, a, b, first=(first or {}).get((a, b)), config=config)
        np.testing.assert_array_equal(got, res.pairs)
        np.testing.assert_array_equal(scores, res.distances)
        assert geom.verdict == g.verdict and geom.num_inliers == g.num_inliers


# ------------------------------------------------------------------------------------------------ in-process
def test_in_process_matches_every_pair_like_the_direct_calls(views, tmp_path):
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    log = tmp_path / "pairs.jsonl"
    before = time.time()
    rep = match_collection(src, pairs, sink, CollectionConfig(progress=False, log_path=str(log), chunk_pairs=3))
    after = time.time()
    assert rep.totals["backend"] == "in-process" and "auto" in rep.totals["backend_reason"]
    assert rep.done == len(pairs) == 10 and rep.skipped == 0 and rep.failed == []
    assert_same_as_reference(sink, views, pairs)
    # overlapping views verified, the unrelated view never
    for key, (a, b, _, _, geom) in sink.rows.items():
        assert bool(geom) == ("other.jpg" not in key), (a, b, geom.reason)
    assert rep.totals["verified_pairs"] == 6
    assert rep.totals["inliers"] == sum(r[4].num_inliers for r in sink.rows.values() if r[4])
    assert rep.totals["matches"] == sum(len(r[2]) for r in sink.rows.values())
    # the cache holds the whole collection: every image loaded exactly once
    assert src.loads == 5  # in-process: this very source object
    # every pair takes its two images from the cache, loaded there by a pair or by the start-up prefetch
    t = rep.totals
    assert t["image_loads"] == 5 and t["cache_hits"] == 2 * len(pairs) - (5 - t["prefetched_images"])
    assert 0 <= t["prefetched_indexes"] <= t["prefetched_images"] <= 5
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [ln["event"] for ln in lines] == ["pair"] * 10 + ["summary"]
    assert {frozenset(ln["pair"]) for ln in lines[:-1]} == {frozenset(p) for p in pairs}
    assert all(ln["status"] == "done" and ln["verdict"] in VERDICTS for ln in lines[:-1])
    # each pair's wall-clock interval (Unix time; load + match) lies within the call
    assert all(before <= ln["t_start"] <= ln["t_end"] <= after for ln in lines[:-1])
    assert lines[-1]["done"] == 10 and lines[-1]["failed"] == []
    assert "10 matched" in rep.summary()


@pytest.mark.parametrize("threads", [1, 3])
def test_in_process_threads_give_the_direct_calls_matches_and_report_the_thread_count(views, threads):
    # the thread pool changes the order pairs finish in, never a pair's matches or verdict
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    rep = match_collection(src, pairs, sink, dict(progress=False, workers=0, threads=threads, chunk_pairs=2))
    assert rep.done == len(pairs) and not rep.failed and rep.totals["threads"] == threads
    assert_same_as_reference(sink, views, pairs)
    assert src.loads == 5 and f"{threads} thread" in rep.summary()


GUIDED = MatcherConfig(auto_bf=False)   # these small views would be matched by brute force (which ignores a prior)


def _late_priors(feats, pairs):
    """A prior per pair that changes the matches: image-1 features the paper's order draws last (reversed draw)."""
    from guidedmatch.matcher.start import draw_order

    out = {}
    for a, b in pairs:
        f = feats[a]
        order = draw_order(f.keypoints[:, 0], f.image_size[0], MatcherConfig().num_groups,
                           np.random.default_rng(0).random(len(f), np.float32))
        out[(a, b)] = [order[::-1][:300].copy()]
    return out


@pytest.mark.parametrize("threads", [1, 2])
def test_a_prior_per_pair_reaches_the_matcher(views, threads):
    """match_collection(first={pair: prior}) gives each pair the matches of match(..., first=prior), and they differ
    from the matches without it for some pairs (the prior is not dropped on the way)."""
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    first = _late_priors(views, pairs)
    rep = match_collection(src, pairs, sink, dict(progress=False, workers=0, threads=threads, chunk_pairs=2,
                                                  matcher=GUIDED), first=first)
    assert rep.done == len(pairs) and not rep.failed
    assert_same_as_reference(sink, views, pairs, first, GUIDED)
    differ = [p for p in pairs
              if not np.array_equal(sink.rows[frozenset(p)][2], reference(views, *p, config=GUIDED)[0].pairs)]
    assert differ, "the prior changed no pair's matches"


def test_auto_backend_rule(monkeypatch):
    monkeypatch.setattr(planning, "_usable_cores", lambda: 2)
    cfg = CollectionConfig(inprocess_max_work=1000)
    assert planning._choose_backend(cfg, None, 1000)[:2] == ("in-process", 0)
    assert planning._choose_backend(cfg, None, 1001)[:2] == ("local-cluster", 2)
    monkeypatch.setattr(planning, "_usable_cores", lambda: 1)
    assert planning._choose_backend(cfg, None, 10**9)[0] == "in-process"
    assert planning._choose_backend(CollectionConfig(workers=3), None, 1)[:2] == ("local-cluster", 3)


def test_cache_bound_evicts_and_keeps_the_pair_being_matched(views):
    names = list(views)
    one = views[names[0]].keypoints.nbytes + views[names[0]].descriptors.nbytes
    spec = _TaskSpec("t", "so+epi+ia", MatcherConfig(), cache_bytes=int(2.5 * one),
                     single_thread=False)
    cache = _ImageCache(DictSource(views), spec)
    for a, b in all_pairs(names):
        cache.get(a, (a, b))
        cache.get(b, (a, b))
        assert a in cache.items and b in cache.items
        assert len(cache.items) <= 3 and cache.bytes == sum(i.nbytes for i in cache.items.values())
    # a bound smaller than one image still keeps the two pinned images
    tiny = _ImageCache(DictSource(views), spec.__class__(**{**spec.__dict__, "cache_bytes": 0}))
    tiny.get(names[0], (names[0], names[1]))
    tiny.get(names[1], (names[0], names[1]))
    assert list(tiny.items) == [names[0], names[1]]
    tiny.get(names[2], (names[2], names[3]))
    assert list(tiny.items) == [names[2]]


def test_prefetch_builds_the_queued_indexes_in_order_until_told_to_stop():
    rng = np.random.default_rng(3)
    feats = {n: Features(rng.uniform(0, 500, (1500, 2)), rng.integers(0, 256, (1500, 128)).astype(np.float32),
                         (500, 500)) for n in ("a", "b", "c", "d")}
    spec = _TaskSpec("t", "so+epi+ia", MatcherConfig(), cache_bytes=2**30, single_thread=False)
    cache = _ImageCache(DictSource(feats), spec)
    cache.get("b", ("b",))  # already loaded by a pair: reached, not counted as a reuse
    stop = threading.Event()
    assert inprocess._prefetch_indexes(cache, ["b", "c"], stop) == 2
    assert list(cache.items) == ["b", "c"] and cache.hits == 0 and cache.loads == 2 and cache.prefetch_loads == 1
    assert all(cache.items[n].prepared._index is not None for n in "bc")
    stop.set()
    assert inprocess._prefetch_indexes(cache, ["d"], stop) == 0 and "d" not in cache.items
    # a full cache stops it too (it never evicts what the pairs loaded)
    full = _ImageCache(DictSource(feats), spec.__class__(**{**spec.__dict__, "cache_bytes": 0}))
    assert inprocess._prefetch_indexes(full, ["a"], threading.Event()) == 0 and not full.items
    # a failing load is left to the pair that needs it
    bad = _ImageCache(DictSource(feats, fail={"a"}), spec)
    assert inprocess._prefetch_indexes(bad, ["a", "b"], threading.Event()) == 0
    # the order: each queued pair's second image, in the order the in-process runner takes the tasks
    q = planning._Queue(plan_tasks([("a", "b"), ("a", "c"), ("b", "c"), ("d", "a")], ["a", "b", "c", "d"], 2))
    assert inprocess._index_order(q) == ["b", "c", "a"]


class _Sized:
    """A cached image of a given size whose "index" the simulation below builds when it is searched."""

    def __init__(self, nbytes: int):
        self.nbytes, self._index = nbytes, None


class _SizedSource:
    def __init__(self, sizes):
        self.sizes = sizes

    def load(self, name):
        return _Sized(self.sizes[name])


def _simulate(plan, sizes, cache_bytes):
    """Run ``plan`` in order through the engine's own image cache, one pair at a time as the in-process runner
    does; ``{image: index builds}`` (an image is indexed when a pair searches it, i.e. it is the second image)."""
    with mock.patch.object(engine_cache, "_prepare_fn", lambda: None):  # the sizes are what is cached
        cache = _ImageCache(_SizedSource(sizes), _TaskSpec("t", "so+epi+ia", MatcherConfig(), cache_bytes=cache_bytes,
                                                           single_thread=False))
    builds = dict.fromkeys(sizes, 0)
    for tasks in plan.values():
        for task in tasks:
            for a, b in task:
                cache.get(a, (a, b))
                item = cache.get(b, (a, b))
                assert a in cache.items and b in cache.items
                if item.prepared._index is None:
                    item.prepared._index, builds[b] = object(), builds[b] + 1
    return builds, cache


@settings(max_examples=80, deadline=None)
@given(st.integers(3, 14), st.data())
def test_plan_sweeps_a_collection_larger_than_the_cache_and_indexes_each_image_once(n, data):
    names = [f"im{i:02d}" for i in range(n)]
    sizes = {k: data.draw(st.integers(1, 10)) for k in names}
    everything = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    pairs = data.draw(st.lists(st.sampled_from(everything), min_size=1, unique=True))
    pairs = [(b, a) if data.draw(st.booleans()) else (a, b) for a, b in pairs]   # any orientation
    cache_bytes = data.draw(st.integers(2 * max(sizes.values()), sum(sizes.values()) + 10))
    chunk = data.draw(st.integers(1, 5))
    plan = plan_tasks(pairs, names, chunk, sizes=sizes, cache_bytes=cache_bytes)
    got = [p for tasks in plan.values() for t in tasks for p in t]
    assert sorted(got) == sorted(pairs)                                  # every pair once, orientation kept
    used = {x for p in pairs for x in p}
    if sum(sizes[k] for k in used) <= cache_bytes:                       # fits: the plain anchor plan
        assert plan == plan_tasks(pairs, names, chunk)
    else:
        blocks = planning.resident_blocks(sorted(used), sizes, cache_bytes)
        for (k, a), tasks in plan.items():
            assert all(x == a and blocks[b] == k for t in tasks for x, b in t)
        assert [k for k, _ in plan] == sorted(k for k, _ in plan)       # sweep after sweep
    builds, _ = _simulate(plan, sizes, cache_bytes)
    assert max(builds.values()) <= 1                                     # no image is indexed twice


def test_plan_sweeps_cut_the_loads_of_an_exhaustive_collection():
    names = [f"im{i:02d}" for i in range(30)]
    sizes = dict.fromkeys(names, 10)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    cache_bytes = 100                                                    # 10 images of 30: blocks of 7
    plain, _ = _simulate(plan_tasks(pairs, names, 16), sizes, cache_bytes)
    swept, cache = _simulate(plan_tasks(pairs, names, 16, sizes=sizes, cache_bytes=cache_bytes), sizes, cache_bytes)
    assert sum(plain.values()) > 300 and sum(swept.values()) == 29      # each searched image indexed once
    assert cache.loads < 5 * 30                                          # 5 sweeps: each image at most once a sweep


def test_cache_evicts_images_without_an_index_first(monkeypatch):
    monkeypatch.setattr(engine_cache, "_prepare_fn", lambda: None)
    cache = _ImageCache(_SizedSource(dict.fromkeys("abcd", 10)),
                        _TaskSpec("t", "so+epi+ia", MatcherConfig(), cache_bytes=30, single_thread=False))
    cache.get("a", ("a",)).prepared._index = object()                   # oldest, but indexed
    cache.get("b", ("b",))
    cache.get("c", ("c",))
    cache.get("d", ("d",))                                               # over the bound: b goes, not a
    assert list(cache.items) == ["a", "c", "d"]
    cache.items["c"].prepared._index = cache.items["d"].prepared._index = object()
    cache.get("b", ("b",))                                               # only indexed ones left: LRU (a)
    assert list(cache.items) == ["c", "d", "b"]


def test_small_cache_same_matches_more_loads(views):
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    rep = match_collection(src, pairs, sink, dict(progress=False, cache_mb=0.0, chunk_pairs=2))
    assert rep.done == 10
    assert rep.totals["image_loads"] > 5
    assert_same_as_reference(sink, views, pairs)


def test_resume_skips_done_pairs_and_rerun_does_nothing(views):
    names = list(views)
    pairs = all_pairs(names)
    src = DictSource(views)
    sink = ListSink(done=pairs[:4])
    rep = match_collection(src, pairs, sink, dict(progress=False, workers=0))
    assert rep.skipped == 4 and rep.done == 6
    assert set(sink.rows) == {frozenset(p) for p in pairs[4:]}
    again = match_collection(src, pairs, sink, dict(progress=False))
    assert again.done == 0 and again.skipped == 10 and again.totals["backend"] == "none"
    assert again.totals["image_loads"] == 0


def test_failed_pair_is_retried_then_reported_never_missing(views, tmp_path):
    src = DictSource(views, fail={"view3.jpg"})
    sink = ListSink()
    pairs = all_pairs(src.names())
    log = tmp_path / "log.jsonl"
    rep = match_collection(src, pairs, sink, dict(progress=False, workers=0, retries=2, log_path=str(log)))
    bad = [p for p in pairs if "view3.jpg" in p]
    assert rep.done == len(pairs) - len(bad) and len(rep.failed) == len(bad) == 4
    assert {frozenset(p) for p, _ in rep.failed} == {frozenset(p) for p in bad}
    assert all("OSError" in r and "view3.jpg" in r for _, r in rep.failed)
    assert set(sink.rows) == {frozenset(p) for p in pairs if p not in bad}
    recs = [json.loads(line) for line in log.read_text().splitlines()]
    failed = [r for r in recs if r.get("status") == "failed"]
    assert len(failed) == 4 and all(r["attempts"] == 3 and len(r["errors"]) == 3 for r in failed)
    assert rep.totals["retried"] == 4
    assert "4 failed" in rep.summary()
    # a rerun (the file readable again) completes exactly the failed pairs
    src.fail.clear()
    rep2 = match_collection(src, pairs, sink, dict(progress=False, workers=0))
    assert rep2.done == 4 and rep2.skipped == 6 and not rep2.failed
    assert_same_as_reference(sink, views, pairs)


# ------------------------------------------------------------------------------------------------ checks
def test_bad_pairs_and_configs_fail_before_any_work(views):
    src, sink = DictSource(views), ListSink()
    with pytest.raises(InputError, match="not in the feature source.*'nope.jpg'"):
        match_collection(src, [("view0.jpg", "nope.jpg")], sink, dict(progress=False))
    assert sink.rows == {} and src.loads == 0
    for bad in (dict(mode="fast"), dict(workers=-1), dict(workers=2, scheduler="tcp://x:1"), dict(retries=-1),
                dict(chunk_pairs=0), dict(matcher=dict(ratio=2.0)), dict(matcher=dict(nope=1)), dict(cache_mb=-1),
                dict(scheduler="")):
        with pytest.raises(ConfigError):
            CollectionConfig(**bad)


def test_a_collection_changes_the_one_off_matcher_defaults_and_a_dict_goes_on_top():
    """A collection feeds a mapper: COLMAP's inliers for a planar pair, the index from the first query and one model
    fit; a dict of settings is applied over those, a MatcherConfig taken as it is."""
    from guidedmatch.collection.config import COLLECTION_MATCHER_DEFAULTS
    from guidedmatch.config import MatcherConfig

    c = CollectionConfig().matcher
    assert c.planar_inliers == "larger" and c.exact_rent == 0.0 and MatcherConfig().planar_inliers == "H"
    assert c.num_updates == 1 and MatcherConfig().num_updates == 3   # one model fit in a collection, the paper's 3 one-off
    assert c == MatcherConfig().replace(**COLLECTION_MATCHER_DEFAULTS)
    assert CollectionConfig(matcher=dict(planar_inliers="H")).matcher.planar_inliers == "H"
    assert collection_matcher_config(MatcherConfig()) == MatcherConfig()


def test_duplicate_reversed_and_self_pairs_are_dropped_and_reported(views):
    src, sink = DictSource(views), ListSink()
    pairs = [("view0.jpg", "view1.jpg"), ("view1.jpg", "view0.jpg"), ("view0.jpg", "view1.jpg"),
             ("view1.jpg", "view2.jpg"), ("view2.jpg", "view2.jpg")]
    rep = match_collection(src, pairs, sink, dict(progress=False))
    assert rep.done == 2 and rep.totals["pairs"] == 2 and set(sink.rows) == {frozenset(p) for p in pairs[::3]}
    assert rep.totals["dropped"] == dict(self_pairs=1, duplicates=1, reversed_duplicates=1)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 7), st.integers(0, 7)).filter(lambda p: p[0] != p[1]), max_size=40,
                unique_by=lambda p: frozenset(p)), st.integers(1, 5))
def test_plan_tasks_covers_each_pair_once_grouped_by_anchor(raw, chunk):
    names = [f"im{i}" for i in range(8)]
    pairs = [(names[a], names[b]) for a, b in raw]
    for how in ("first", "second"):
        plan = plan_tasks(pairs, names, chunk, anchor=how)
        got = [p for tasks in plan.values() for t in tasks for p in t]
        assert sorted(got) == sorted(pairs)
        size = {k: sum(map(len, v)) for k, v in plan.items()}
        if how == "first":
            assert list(plan) == sorted(plan, key=names.index)
        else:  # most pairs first, ties in source order
            assert list(plan) == sorted(plan, key=lambda k: (-size[k], names.index(k)))
        for anchor, tasks in plan.items():
            for t in tasks:
                assert 1 <= len(t) <= chunk
                for a, b in t:
                    if how == "first":
                        assert anchor in (a, b) and names.index(anchor) == min(names.index(a), names.index(b))
                    else:
                        assert anchor == b  # the indexed image
            assert all(len(t) == chunk for t in list(tasks)[:-1])  # only an anchor's last task is short
    with pytest.raises(ValueError, match="anchor"):
        plan_tasks(pairs, names, chunk, anchor="middle")


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)).filter(lambda p: p[0] != p[1]), max_size=30,
                unique_by=lambda p: frozenset(p)), st.integers(1, 4), st.integers(1, 3), st.randoms(use_true_random=False))
def test_queue_hands_out_every_task_once_and_suspects_only_when_idle(raw, chunk, per_anchor, rnd):
    """_Queue under a random completion order: every planned pair is handed out exactly once, at most per_anchor
    tasks of an anchor are in flight while another anchor still has a free slot, suspects wait for an idle cluster."""
    from guidedmatch.collection.planning import _Queue

    names = [f"im{i}" for i in range(7)]
    pairs = [(names[a], names[b]) for a, b in raw]
    q = _Queue(plan_tasks(pairs, names, chunk), per_anchor)
    q.suspects.append([("x", "y")])
    inflight, seen = [], []
    while q or inflight:
        got = q.take(idle=not inflight) if q else None
        if got is None:
            anchor, task = inflight.pop(rnd.randrange(len(inflight)))
            q.finished(anchor)
            continue
        anchor, task = got
        if task == [("x", "y")]:
            assert not inflight  # a suspect runs alone
        elif anchor is not None and q.inflight[anchor] > per_anchor:  # over its share only when all others are full
            assert all(q.inflight[a] >= per_anchor for a in q.plan)
        seen += task
        inflight.append((anchor, task))
        if rnd.random() < 0.5 and inflight:
            a, t = inflight.pop(rnd.randrange(len(inflight)))
            q.finished(a)
    assert sorted(seen) == sorted(pairs + [("x", "y")])
    assert not q.inflight  # every anchor's bookkeeping closed


def test_report_keeps_at_most_report_max_pairs_the_log_keeps_all(views, tmp_path):
    src, sink = DictSource(views), ListSink()
    log = tmp_path / "log.jsonl"
    rep = match_collection(src, all_pairs(src.names()), sink, dict(progress=False, report_max_pairs=3,
                                                                  log_path=str(log)))
    assert rep.done == 10 and len(rep.per_pair) == 3
    assert sum(1 for line in log.read_text().splitlines() if '"event": "pair"' in line) == 10
    d = rep.to_dict()
    assert json.loads(json.dumps(d))["done"] == 10


# ------------------------------------------------------------------------------------------------ local cluster
@pytest.fixture(scope="module")
def cluster_client():
    """One 2-worker cluster of single-threaded processes for the cluster tests (started once: ~5 s here).

    The workers get the test doubles by value (this test module is not importable there) and the environment
    variable that arms DictSource's ``die`` names (this process never loads them)."""
    import cloudpickle
    from distributed import Client, LocalCluster

    from guidedmatch.collection.dask_backend import _SINGLE_THREAD_ENV

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                               env={**_SINGLE_THREAD_ENV, "GM_TEST_IN_WORKER": "1"}, silence_logs=40)
        client = Client(cluster, set_as_default=False)
    yield client
    client.close()
    cluster.close()
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def test_two_worker_cluster_gives_the_same_matches(views, cluster_client, tmp_path):
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    rep = match_collection(src, pairs, sink, dict(progress=False, chunk_pairs=2), client=cluster_client)
    assert rep.totals["backend"] == "client" and rep.totals["workers"] == 2 and rep.done == 10 and not rep.failed
    assert_same_as_reference(sink, views, pairs)
    workers = {r["worker"] for r in rep.per_pair}
    assert workers <= set(cluster_client.scheduler_info()["workers"]) and len(workers) >= 1
    # images are shipped to a worker once, not once per pair: loads <= images x workers < pairs x 2
    assert rep.totals["image_loads"] <= 5 * 2 < 2 * len(pairs)


def test_a_prior_per_pair_reaches_the_cluster_workers(views, cluster_client):
    src, sink = DictSource(views), ListSink()
    pairs = all_pairs(src.names())
    first = _late_priors(views, pairs)
    rep = match_collection(src, pairs, sink, dict(progress=False, chunk_pairs=2, matcher=GUIDED), client=cluster_client,
                           first=first)
    assert rep.totals["backend"] == "client" and rep.done == 10 and not rep.failed
    assert_same_as_reference(sink, views, pairs, first, GUIDED)


def test_a_pair_killing_its_worker_is_quarantined_then_reported_others_complete(views, cluster_client):
    """A pair whose worker dies on it (os._exit while loading) fails the tasks running next to it; those pairs are
    rerun alone and complete, the killer is retried alone and reported failed -- nothing is silently missing."""
    feats = {k: views[k] for k in ("view0.jpg", "view1.jpg", "other.jpg")}
    src, sink = DictSource(feats, die={"other.jpg"}), ListSink()
    pairs = all_pairs(src.names())
    rep = match_collection(src, pairs, sink, dict(progress=False, chunk_pairs=2, retries=0), client=cluster_client)
    bad = [p for p in pairs if "other.jpg" in p]
    good = [p for p in pairs if p not in bad]
    assert {frozenset(p) for p, _ in rep.failed} == {frozenset(p) for p in bad}
    assert all("task failed" in r and "KilledWorker" in r for _, r in rep.failed), rep.failed
    assert rep.done == len(good) == 1
    assert_same_as_reference(sink, feats, good)


# ------------------------------------------------------------------------------------------------ CLI on COLMAP
SRC = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, "src"))


def run_cli(*args, timeout=240, **kw):
    import subprocess

    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("GM_TEST_IN_WORKER", None)
    return subprocess.run([sys.executable, "-m", "guidedmatch.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=timeout, **kw)


@pytest.fixture(scope="module")
def rendered_db(tmp_path_factory):
    """5 rendered views of a textured wall (known poses) + 1 isolated view -> a COLMAP database (ours, SIFT)."""
    from guidedmatch.collection.sources import images_to_database
    from guidedmatch.testing.multiview import make_multiview, write_views

    mv = make_multiview(5, (480, 360), seed=2)
    root = tmp_path_factory.mktemp("rendered")
    write_views(mv, root / "img")
    images_to_database(root / "img", root / "fresh.db", max_features=1500, progress=False)
    return root, mv


def db_rows(path) -> dict:
    """Every pair's matches and two-view geometry (config, inlier matches) of a COLMAP database, by names."""
    import pycolmap

    db = pycolmap.Database.open(str(path))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        out = {}
        for i1 in names:  # every image pair (the bulk readers skip rows with zero matches)
            for i2 in names:
                if i1 < i2 and db.exists_matches(i1, i2):
                    tvg = db.read_two_view_geometry(i1, i2) if db.exists_two_view_geometry(i1, i2) else None
                    out[frozenset((names[i1], names[i2]))] = (
                        np.asarray(db.read_matches(i1, i2)).tolist(),
                        None if tvg is None else (int(tvg.config), np.asarray(tvg.inlier_matches).tolist()))
        return out
    finally:
        db.close()


def test_cli_kill_9_mid_run_then_rerun_equals_an_uninterrupted_run_and_maps(rendered_db, tmp_path):
    """`guidedmatch colmap DB --workers 2` killed (SIGKILL, whole process group) after its first pairs: the
    database stays valid, a rerun (auto backend: in-process) skips the stored pairs and completes it, and the
    result equals an uninterrupted in-process run pair for pair; pycolmap.incremental_mapping then registers every connected view with no verification step
    and the non-overlapping pairs have no two-view geometry inliers."""
    import shutil
    import signal
    import subprocess
    import time

    import pycolmap

    from guidedmatch.base import DEFAULT_INLIER_PX
    from guidedmatch.collection.pairs import exhaustive_pairs
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    root, mv = rendered_db
    db, ref = tmp_path / "db.db", tmp_path / "ref.db"
    shutil.copy(root / "fresh.db", db)
    shutil.copy(root / "fresh.db", ref)
    n_pairs = len(mv.names) * (len(mv.names) - 1) // 2
    log = tmp_path / "run1.jsonl"
    env = {**os.environ, "PYTHONPATH": SRC}
    env.pop("GM_TEST_IN_WORKER", None)
    err = tmp_path / "run1.stderr"
    with open(err, "wb") as err_file:  # kept for the message below: a run that ends by itself says why
        # --no-second-look: the reference below is the engine's run alone (the second look's own kill and rerun
        # are tested in test_collection_second_look.py)
        proc = subprocess.Popen([sys.executable, "-m", "guidedmatch.cli", "colmap", str(db), "--workers", "2",
                                 "--log", str(log), "--no-progress", "--no-second-look"], env=env, start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=err_file)
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and proc.poll() is None:
            if log.exists() and log.read_text().count('"event": "pair"') >= 2:
                break
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)  # the command and its worker processes, at once
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, (f"the run ended by itself (exit {proc.returncode}) before it could be "
                                                f"killed; its stderr: {err.read_text(errors='replace')[-2000:]}")
    stored = db_rows(db)  # a valid database: every stored pair has its matches and its geometry
    assert 2 <= len(stored) < n_pairs and all(g is not None for _, g in stored.values())

    r2 = run_cli("colmap", db, "--log", tmp_path / "run2.jsonl", "--timeline", tmp_path / "run2.png",  # auto:
                 "--no-second-look")
    assert r2.returncode == 0, r2.stderr                                  # in-process for this small rest
    assert f"{len(stored)} skipped" in r2.stdout
    assert f"timeline   : {tmp_path / 'run2.png'}" in r2.stdout and (tmp_path / "run2.png").stat().st_size > 0
    summary = json.loads((tmp_path / "run2.jsonl").read_text().splitlines()[-1])
    assert summary["event"] == "summary" and summary["done"] == n_pairs - len(stored) and summary["failed"] == []

    src = ColmapSource(ref)  # the uninterrupted reference run (in-process), then what the CLI does after matching
    with ColmapSink(ref) as sink:
        rep = match_collection(src, exhaustive_pairs(src.names()), sink, dict(progress=False, workers=0))
        sink.tighten_inliers(DEFAULT_INLIER_PX)
    assert rep.done == n_pairs and not rep.failed
    assert db_rows(db) == db_rows(ref)

    rows = db_rows(db)
    for i, j in mv.non_overlapping_pairs():
        _, g = rows[frozenset((mv.names[i], mv.names[j]))]
        assert g[1] == [], (mv.names[i], mv.names[j])
    recs = pycolmap.incremental_mapping(db, root / "img", tmp_path / "sparse")
    assert len(recs) == 1
    registered = {im.name for im in next(iter(recs.values())).images.values() if im.has_pose}
    assert registered == set(mv.names) - {mv.names[k] for k in mv.isolated}

    r3 = run_cli("colmap", db, "--log", "none", "--timeline", tmp_path / "run3.png")  # a rerun skips every pair
    assert r3.returncode == 0 and f"{n_pairs} skipped" in r3.stdout
    assert "no pair was matched in this run: no figure" in r3.stdout and not (tmp_path / "run3.png").exists()


def test_cli_refuses_a_second_writer_and_bad_inputs_with_one_line(rendered_db, tmp_path):
    import shutil

    from guidedmatch.collection.sinks import ColmapSink

    root, mv = rendered_db
    db = tmp_path / "db.db"
    shutil.copy(root / "fresh.db", db)

    def one_line_error(r, *needles):
        assert r.returncode == 2, (r.returncode, r.stderr)
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("guidedmatch: error:"), r.stderr
        for n in needles:
            assert n in err[0], err[0]

    one_line_error(run_cli("colmap", tmp_path / "missing.db"), "not found")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{mv.names[0]} {mv.names[1]}\n{mv.names[0]} nope.png\n")
    one_line_error(run_cli("colmap", db, "--pairs", pairs, "--workers", "0"), "nope.png")
    one_line_error(run_cli("colmap", db, "--config", "band_px=-1"), "band_px")
    one_line_error(run_cli("colmap", db, "--timeline", tmp_path / "t.jpg"), "--timeline", "PNG")
    one_line_error(run_cli("colmap", db, "--timeline", "/proc/nope/t.png"), "--timeline", "/proc/nope")
    one_line_error(run_cli("colmap", db, "--max-inliers-per-pair", "-1"), "--max-inliers-per-pair")
    one_line_error(run_cli("colmap", db, "--inlier-px", "-1"), "--inlier-px")
    one_line_error(run_cli("colmap", db, "--inlier-px", "nan"), "--inlier-px")
    one_line_error(run_cli("colmap", db, "--refit-below-deg", "-1"), "--refit-below-deg")
    one_line_error(run_cli("colmap", db, "--refit-below-deg", "nan"), "--refit-below-deg")
    with ColmapSink(db):  # another writer holds the database
        one_line_error(run_cli("colmap", db, "--workers", "0"), "being written by another process")
    assert db_rows(db) == {}


def test_cli_cache_smaller_than_the_collection_sweeps_and_writes_the_same_database(rendered_db, tmp_path):
    """--cache-mb 1 (less than one image): the pairs run in sweeps, the summary says so, and the database holds the
    same matches and geometries as a run with the whole collection cached."""
    import shutil

    root, mv = rendered_db
    small, big = tmp_path / "small.db", tmp_path / "big.db"
    shutil.copy(root / "fresh.db", small)
    shutil.copy(root / "fresh.db", big)
    r = run_cli("colmap", small, "--workers", "0", "--threads", "2", "--cache-mb", "1", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "sweeps over resident blocks" in r.stdout, r.stdout
    r = run_cli("colmap", big, "--workers", "0", "--threads", "2", "--no-progress")
    assert r.returncode == 0 and "sweeps" not in r.stdout, r.stdout
    assert db_rows(small) == db_rows(big) and len(db_rows(big)) == len(mv.names) * (len(mv.names) - 1) // 2
    assert run_cli("colmap", small, "--cache-mb", "0").returncode == 2  # argparse: a positive integer


def test_cli_pair_whose_features_cannot_be_loaded_fails_with_one_line_and_the_rest_is_written(rendered_db, tmp_path):
    """A worker raising on one image (its keypoint blob holds NaNs): its pairs are retried, then reported; the CLI
    writes every other pair and exits 2 with one line naming the reason."""
    import shutil
    import sqlite3

    root, mv = rendered_db
    db = tmp_path / "db.db"
    shutil.copy(root / "fresh.db", db)
    bad = mv.names[1]
    con = sqlite3.connect(db)  # corrupt one image's keypoints in place (same size, NaN coordinates)
    (iid,) = con.execute("SELECT image_id FROM images WHERE name = ?", (bad,)).fetchone()
    (blob,) = con.execute("SELECT data FROM keypoints WHERE image_id = ?", (iid,)).fetchone()
    con.execute("UPDATE keypoints SET data = ? WHERE image_id = ?", (np.full(len(blob) // 4, np.nan, np.float32)
                                                                    .tobytes(), iid))
    con.commit()
    con.close()
    r = run_cli("colmap", db, "--workers", "0", "--retries", "1", "--no-progress")
    n_bad = len(mv.names) - 1
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and f"{n_bad} of " in err[0] and "non-finite" in err[0], r.stderr
    rows = db_rows(db)
    assert len(rows) == len(mv.names) * (len(mv.names) - 1) // 2 - n_bad
    assert all(bad not in k for k in rows)


def test_cli_hloc_round_trip_equals_in_memory_matches(views, tmp_path):
    """features.h5 -> `guidedmatch hloc` -> matches.h5 read back: per pair the same matches as matching the
    loaded features in memory (matches0[i] = j, -1 elsewhere); a rerun skips every pair."""
    import h5py

    from guidedmatch.collection.sinks import names_to_pair
    from guidedmatch.collection.sources import H5Source, write_features_h5

    feats = {k: views[k] for k in ("view0.jpg", "view1.jpg", "view2.jpg", "other.jpg")}
    write_features_h5(tmp_path / "feats.h5", feats, as_half=False)
    pairs = [("view0.jpg", "view1.jpg"), ("view2.jpg", "view1.jpg"), ("other.jpg", "view0.jpg")]
    (tmp_path / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in pairs))
    r = run_cli("hloc", tmp_path / "feats.h5", tmp_path / "pairs.txt", tmp_path / "m.h5", "--workers", "0")
    assert r.returncode == 0, r.stderr
    src = H5Source(tmp_path / "feats.h5")
    with h5py.File(tmp_path / "m.h5", "r") as fh:
        for a, b in pairs:
            fa, fb = src.load(a), src.load(b)
            res = match(fa, fb)
            m0 = fh[names_to_pair(a, b)]["matches0"][()]
            assert len(m0) == len(fa)
            got = np.c_[np.flatnonzero(m0 >= 0), m0[m0 >= 0]]
            np.testing.assert_array_equal(got, res.pairs[np.argsort(res.pairs[:, 0])])
    r2 = run_cli("hloc", tmp_path / "feats.h5", tmp_path / "pairs.txt", tmp_path / "m.h5", "--log", "none")
    assert r2.returncode == 0 and "3 skipped" in r2.stdout, r2.stdout + r2.stderr


def _two_copies_and_pairs(rendered_db, tmp_path, n):
    """Two copies ``a.db``, ``b.db`` of the rendered collection's fresh database and a pairs file of its first ``n``
    consecutive pairs."""
    import shutil

    root, mv = rendered_db
    a, b = tmp_path / "a.db", tmp_path / "b.db"
    shutil.copy(root / "fresh.db", a)
    shutil.copy(root / "fresh.db", b)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("".join(f"{mv.names[i]} {mv.names[i + 1]}\n" for i in range(n)))
    return a, b, pairs


def test_cli_geometry_colmap_runs_colmaps_verification(rendered_db, tmp_path):
    """--geometry colmap: raw matches from the engine, then pycolmap's verification writes the two-view geometries;
    the matches are the same as with our geometry."""
    a, b, pairs = _two_copies_and_pairs(rendered_db, tmp_path, 3)
    r = run_cli("colmap", a, "--pairs", pairs, "--geometry", "colmap", "--workers", "0", "--log", "none")
    assert r.returncode == 0, r.stderr
    assert "verified   : 3 pairs" in r.stdout
    r = run_cli("colmap", b, "--pairs", pairs, "--workers", "0", "--log", "none")
    assert r.returncode == 0, r.stderr
    ra, rb = db_rows(a), db_rows(b)
    assert set(ra) == set(rb) and len(ra) == 3
    for k in ra:
        assert ra[k][0] == rb[k][0]  # same matches
        assert ra[k][1] is not None and ra[k][1][0] in (2, 3, 4, 5, 6) and len(ra[k][1][1]) > 0  # COLMAP verified


def test_cli_scheduler_address_attaches_to_a_running_cluster(rendered_db, cluster_client, tmp_path):
    """`--scheduler ADDRESS`: the pairs run on the running cluster's workers (shared storage: same machine), the
    command does not stop the cluster, and the result equals the in-process one."""
    a, b, pairs = _two_copies_and_pairs(rendered_db, tmp_path, 4)
    address = cluster_client.scheduler.address
    r = run_cli("colmap", a, "--pairs", pairs, "--scheduler", address, "--log", tmp_path / "a.jsonl")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "a.jsonl").read_text().splitlines()[-1])
    assert summary["backend"] == "scheduler" and summary["done"] == 4
    workers = {json.loads(x)["worker"] for x in (tmp_path / "a.jsonl").read_text().splitlines()[:-1]}
    assert workers <= set(cluster_client.scheduler_info()["workers"])
    assert len(cluster_client.scheduler_info()["workers"]) == 2  # still running
    r = run_cli("colmap", b, "--pairs", pairs, "--workers", "0", "--log", "none")
    assert r.returncode == 0, r.stderr
    assert db_rows(a) == db_rows(b)
    r = run_cli("colmap", a, "--scheduler", "tcp://127.0.0.1:9", "--log", "none", "--no-progress")  # nobody listens
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "cannot connect" in r.stderr, r.stderr


def test_cli_inlier_px_hands_the_mapper_the_precise_inliers(rendered_db, tmp_path):
    """--inlier-px: the default (1.5) keeps, of the inliers --inlier-px 0 stores, those within 1.5 px of the pair's
    model (at least 15 per pair; the raw matches all kept), says so, and the mapper still registers every view that
    overlaps another; --geometry colmap leaves COLMAP's verification alone."""
    import shutil

    import pycolmap

    from guidedmatch.collection.sinks import tighten_two_view_inliers

    root, mv = rendered_db
    everything, tight = tmp_path / "all.db", tmp_path / "tight.db"
    shutil.copy(root / "fresh.db", everything)
    shutil.copy(root / "fresh.db", tight)
    assert run_cli("colmap", everything, "--workers", "0", "--no-progress", "--inlier-px", "0").returncode == 0
    r = run_cli("colmap", tight, "--workers", "0", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "inliers within 1.5 px of their pair's F / H (at least 15 per pair" in r.stdout, r.stdout
    a, b = db_rows(everything), db_rows(tight)
    assert a.keys() == b.keys()
    assert sum(len(g[1]) for _, g in b.values()) < sum(len(g[1]) for _, g in a.values())
    for key, (m, g) in b.items():
        assert m == a[key][0] and set(map(tuple, g[1])) <= set(map(tuple, a[key][1][1]))
        assert len(g[1]) >= min(15, len(a[key][1][1]))
    tighten_two_view_inliers(everything, 1.5)      # the same selection, applied afterwards
    assert db_rows(everything) == b
    recs = pycolmap.incremental_mapping(tight, root / "img", tmp_path / "sparse")
    registered = {im.name for im in max(recs.values(), key=lambda x: x.num_reg_images()).images.values()
                  if im.has_pose}
    assert registered == set(mv.names) - {mv.names[k] for k in mv.isolated}


def test_cli_cap_above_leaves_a_small_database_whole(rendered_db, tmp_path):
    """--max-inliers-per-pair with the default --cap-above (100,000): the rendered scene's few thousand inliers are
    all kept, and the summary says why; the same database and cap with --cap-above 0 is capped."""
    import shutil

    root, _ = rendered_db
    whole, capped = tmp_path / "whole.db", tmp_path / "capped.db"
    shutil.copy(root / "fresh.db", whole)
    shutil.copy(root / "fresh.db", capped)
    r = run_cli("colmap", whole, "--workers", "0", "--no-progress", "--max-inliers-per-pair", "130")
    assert r.returncode == 0, r.stderr
    assert "the cap of 130 per pair applies above 100,000 in all" in r.stdout, r.stdout
    assert any(len(g[1]) > 130 for _, g in db_rows(whole).values())
    r = run_cli("colmap", capped, "--workers", "0", "--no-progress", "--max-inliers-per-pair", "130", "--cap-above", "0")
    assert r.returncode == 0 and max(len(g[1]) for _, g in db_rows(capped).values()) == 130
    assert run_cli("colmap", whole, "--cap-above", "-5").returncode == 2


def test_cli_max_inliers_per_pair_caps_the_mappers_inliers(rendered_db, tmp_path):
    """--max-inliers-per-pair K: every geometry keeps at most K inliers (the raw matches all of theirs), the summary
    says how many were kept, and the mapper still registers every view that overlaps another."""
    import shutil

    import pycolmap

    root, mv = rendered_db
    full, capped = tmp_path / "full.db", tmp_path / "capped.db"
    shutil.copy(root / "fresh.db", full)
    shutil.copy(root / "fresh.db", capped)
    assert run_cli("colmap", full, "--workers", "0", "--no-progress").returncode == 0
    r = run_cli("colmap", capped, "--workers", "0", "--no-progress", "--max-inliers-per-pair", "130",
                "--cap-above", "0")
    assert r.returncode == 0, r.stderr
    assert "inliers (at most 130 per pair" in r.stdout, r.stdout
    a, b = db_rows(full), db_rows(capped)
    assert a.keys() == b.keys()
    assert any(len(g[1]) > 130 for _, g in a.values())            # the cap had something to do
    for key, (m, g) in b.items():
        assert m == a[key][0]                                    # raw matches untouched
        assert len(g[1]) == min(130, len(a[key][1][1])) and set(map(tuple, g[1])) <= set(map(tuple, a[key][1][1]))
    recs = pycolmap.incremental_mapping(capped, root / "img", tmp_path / "sparse")
    registered = {im.name for im in max(recs.values(), key=lambda x: x.num_reg_images()).images.values()
                  if im.has_pose}
    assert registered == set(mv.names) - {mv.names[k] for k in mv.isolated}
