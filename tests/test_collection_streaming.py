"""PairStream (collection/streaming.py): pairs added a few at a time, the loop in the caller's hands, give what
match_collection gives; pairs the sink holds are skipped; a failing pair is retried, then reported."""
from __future__ import annotations

import concurrent.futures as cf

import numpy as np
import pytest

from guidedmatch.collection.engine import match_collection
from guidedmatch.collection.streaming import PairStream
from guidedmatch.features import Features
from guidedmatch.testing.arc_views import arc_views


def make_views(n_views: int = 4) -> dict[str, Features]:
    """Cameras on an arc looking at a point cloud (overlapping views with known correspondences)."""
    return arc_views(n_views, 1000, seed=3)


class Source:
    def __init__(self, feats, fail=()):
        self.feats, self.fail = feats, set(fail)

    def names(self):
        return list(self.feats)

    def num_features(self, name):
        return len(self.feats[name])

    def load(self, name):
        if name in self.fail:
            raise OSError(f"cannot read {name} (test double)")
        return self.feats[name]

    def close(self):
        pass


class Sink:
    def __init__(self, done=()):
        self.rows, self.preset = {}, {frozenset(p) for p in done}

    def done_pairs(self, candidates=None):
        return set(self.preset) | set(self.rows)

    def write(self, a, b, pairs, scores, geometry):
        key = frozenset((a, b))
        assert key not in self.rows, f"{key} written twice"
        self.rows[key] = ((a, b), pairs.copy(), scores.copy(), int(geometry.num_inliers))


def drive(stream: PairStream, batches, threads: int = 2) -> None:
    """What guidedmatch.sfm.overlap does: add pairs in batches, submit to free threads, write in this thread."""
    with cf.ThreadPoolExecutor(threads) as pool, PairStream.thread_limits():
        for batch in batches:
            stream.add(batch)
            while stream.waiting and len(stream.inflight) < threads:
                stream.submit(pool)
            while stream.inflight or stream.waiting:
                done, _ = cf.wait(list(stream.inflight), return_when=cf.FIRST_COMPLETED)
                for fut in done:
                    stream.finish(fut)
                while stream.waiting and len(stream.inflight) < threads:
                    stream.submit(pool)


def test_pairs_in_batches_match_as_match_collection():
    feats = make_views()
    names = list(feats)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    ref = Sink()
    match_collection(Source(feats), pairs, ref, dict(progress=False, workers=0))
    sink = Sink(done=[pairs[0]])
    stream = PairStream(Source(feats), sink, dict(progress=False))
    # the pairs arrive as images would: those among the first 2 images, then 3, then 4; one pair twice, one reversed
    drive(stream, [pairs[:1], [p for p in pairs if "view3.jpg" not in p], pairs + [pairs[2][::-1]]])
    stream.close()
    rep = stream.report(2, "test")
    assert rep.skipped == 1 and rep.done == len(pairs) - 1 and not rep.failed
    assert set(sink.rows) == set(ref.rows) - {frozenset(pairs[0])}
    for key, (ab, m, s, inl) in sink.rows.items():
        rab, rm, rs, rinl = ref.rows[key]
        assert ab == rab and inl == rinl and inl > 50, key
        np.testing.assert_array_equal(m, rm)
        np.testing.assert_array_equal(s, rs)
    assert rep.totals["backend"] == "in-process" and rep.totals["verified_pairs"] == len(pairs) - 1
    assert 1 <= rep.totals["max_tasks_in_flight"] <= 2
    assert len(stream.pairs) == len(pairs) and set(stream.pairs) == set(pairs)   # the first orientation kept


def test_a_failing_pair_is_retried_then_reported():
    feats = make_views(n_views=3)
    stream = PairStream(Source(feats, fail=["view2.jpg"]), Sink(), dict(progress=False, retries=2))
    drive(stream, [[("view0.jpg", "view1.jpg"), ("view0.jpg", "view2.jpg")]])
    rep = stream.report(2, "test")
    assert rep.done == 1 and [p for p, _ in rep.failed] == [("view0.jpg", "view2.jpg")]
    assert "cannot read view2.jpg" in rep.failed[0][1]
    bad = next(r for r in rep.per_pair if r["status"] == "failed")
    assert bad["attempts"] == 3 and rep.totals["retried"] == 1
