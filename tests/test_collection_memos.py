"""Start memos: the first pass's unguided searches, reused by the second look (guidedmatch.prepared.StartMemo,
guidedmatch.collection.memos). The rule they rest on: a query's search result depends on the query and image 2
alone, so a match given a memo returns bit-identical matches, verdicts and comparison counts."""
from __future__ import annotations

import pickle
import shutil
import sqlite3

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

import guidedmatch as gm
from guidedmatch.collection.memos import StartMemos, dump, load
from guidedmatch.matcher import MatcherConfig, match
from guidedmatch.prepared import StartMemo, prepare
from guidedmatch.testing.scenes import make_scene

SIZE = (800, 600)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_a_memo_round_trips_its_values_and_dtypes_exactly(data):
    n1 = data.draw(st.integers(1, 300))
    memo = StartMemo(n1, 50)
    searched = np.zeros(n1, bool)
    for path in data.draw(st.lists(st.sampled_from(["gemm", "ivf", "popcount"]), min_size=1, max_size=3,
                                   unique=True)):
        q = np.asarray(data.draw(st.lists(st.integers(0, n1 - 1), min_size=1, max_size=n1, unique=True)), np.int64)
        n = len(q)
        floats = st.one_of(st.floats(allow_nan=False, width=64), st.integers(0, 2**24).map(float),
                           st.just(np.inf))
        res = (data.draw(arrays(np.int64, n, elements=st.integers(-1, 2**40))),
               data.draw(arrays(np.float64, n, elements=floats)),
               data.draw(arrays(np.int64, n, elements=st.integers(-1, 49))),
               data.draw(arrays(np.float32 if path == "popcount" else np.float64, n,
                                elements=st.floats(0, 1e6, width=32))),
               data.draw(arrays(np.int64, n, elements=st.integers(0, 2**33))))
        memo.put(path, q, *res)
        back = pickle.loads(pickle.dumps(memo))
        assert back.has(path, q).all() and back.fits(n1, 50) and not back.fits(n1 + 1, 50)
        for want, got in zip(res, back.get(path, q)):
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        searched[q] = True
    assert back.held == sum(int(back.has(p, np.arange(n1)).sum()) for p in back.parts)
    assert load(dump(memo)).held == memo.held


@pytest.fixture(scope="module")
def sift_pair():
    scene = make_scene(SIZE, roll_deg=20.0, seed=2)
    return prepare(gm.detect(scene.image1, "sift", 2500)), prepare(gm.detect(scene.image2, "sift", 2500))


def _signature(res) -> tuple:
    return (res.pairs.tobytes(), res.distances.tobytes(), res.geometry.verdict, res.geometry.num_inliers,
            res.geometry.inliers.tobytes(), res.stats.comparisons, res.stats.details["unguided_comparisons"],
            res.stats.details["unguided_search"])


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), budget=st.sampled_from([0.002, 0.02, None]),
       rent=st.sampled_from([0.0, 0.25]), prior=st.integers(0, 800), unguided_index=st.booleans(),
       guided=st.booleans())
def test_a_match_given_the_memo_of_an_earlier_one_is_bit_identical(sift_pair, seed, budget, rent, prior,
                                                                  unguided_index, guided):
    """The first match records its searches; a second match of the pair with another draw order (the second look's
    prior: a random set of features first) and the memo gives what it gives without the memo, and takes from the memo
    exactly the features both starts drew (the exact and the index path apart)."""
    p1, p2 = sift_pair
    cfg = MatcherConfig(max_unguided=budget, exact_rent=rent, unguided_index=unguided_index,
                        **({} if guided else dict(guide_margin=100.0)))  # weak: the whole start
    memo = StartMemo(len(p1), len(p2))
    first_pass = match(p1, p2, "so+epi+ia", cfg, start_memo=memo)
    assert _signature(first_pass) == _signature(match(p1, p2, "so+epi+ia", cfg))  # recording changes nothing
    first = np.random.default_rng(seed).permutation(len(p1))[:prior]
    again = match(p1, p2, "so+epi+ia", cfg, first=first, start_memo=pickle.loads(pickle.dumps(memo)))
    plain = match(p1, p2, "so+epi+ia", cfg, first=first)
    assert _signature(again) == _signature(plain)
    hits = again.stats.details["start_memo_hits"]
    assert 0 <= hits <= memo.held
    if prior == 0:  # the same draw order: the second start searches what the first searched, all from the memo
        assert hits == memo.held > 0


def test_a_memo_of_other_images_is_ignored(sift_pair):
    p1, p2 = sift_pair
    cfg = MatcherConfig(guide_margin=100.0)
    wrong = StartMemo(len(p1) + 1, len(p2))
    wrong.put("ivf", np.arange(10), np.zeros(10, np.int64), np.zeros(10), np.zeros(10, np.int64), np.zeros(10),
              np.ones(10, np.int64))
    res = match(p1, p2, "so+epi+ia", cfg, start_memo=wrong)
    assert _signature(res) == _signature(match(p1, p2, "so+epi+ia", cfg))
    assert res.stats.details["start_memo_hits"] == 0


def test_the_store_keeps_memos_within_its_bound_and_hands_each_out_once():
    store = StartMemos(keep_below=64, max_mb=0.05)
    memos = []
    for k in range(4):
        m = StartMemo(5000, 10)
        m.put("ivf", np.arange(1000 * k, 1000 * k + 1000), *(np.zeros(1000, np.int64) for _ in range(5)))
        memos.append(m)
        store.add(("a", f"b{k}"), m)
    s = store.summary()
    assert s["kept"] + s["dropped"] == 4 and s["dropped"] >= 1 and store.bytes <= store.max_bytes
    kept = [k for k in range(4) if ("a", f"b{k}") in store._store]
    got = store.for_task([("a", f"b{kept[0]}"), ("x", "y")])
    assert list(got) == [("a", f"b{kept[0]}")] and load(got[("a", f"b{kept[0]}")]).held == 1000
    assert store.take(("a", f"b{kept[0]}")) is None and store.summary()["taken"] == 1
    assert store.take((f"b{kept[-1]}", "a")) is None  # oriented: the other orientation is another search


def _rows(db):
    con = sqlite3.connect(db)
    try:
        return sorted(con.execute("SELECT pair_id, rows, config, data, F, E, H FROM two_view_geometries")) + sorted(
            con.execute("SELECT pair_id, rows, data FROM matches"))
    finally:
        con.close()


@pytest.mark.parametrize("workers", [0, 2])
def test_the_second_look_with_the_first_pass_memos_writes_the_same_database(sequence_db, tmp_path, workers):
    """match_into_database with the second look: with memos (the default) and without (start_memo_mb=0) the same
    rows, in-process and on a local cluster; the memos were used; on the cluster each worker loads each image once
    for all the stages (the image cache is shared by the stages of the run's cluster)."""
    from guidedmatch.collection.pairs import exhaustive_pairs
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.sfm.stages import match_into_database

    out, rows = {}, {}
    for mb in (512.0, 0.0):
        db = tmp_path / f"m{mb:g}.db"
        shutil.copyfile(sequence_db, db)
        src = ColmapSource(db)
        try:
            # weak_below high: every verified pair of the rendered sequence is looked at again (and has a memo);
            # guided at these sizes: an unguided start to remember, not brute force
            out[mb] = match_into_database(src, exhaustive_pairs(src.names()), db,
                                          dict(progress=False, workers=workers, matcher=dict(auto_bf=False)),
                                          second_look=dict(start_memo_mb=mb, weak_below=10**6))
        finally:
            src.close()
        rows[mb] = _rows(db)
    assert rows[512.0] == rows[0.0]
    look = out[512.0]["second_look"]
    memos = look["start_memos"]
    assert out[0.0]["second_look"]["start_memos"] is None
    assert memos["kept"] > 0 and memos["taken"] > 0 and memos["hits"] > 0 and memos["dropped"] == 0
    assert out[512.0]["report"].totals["start_memos"]["kept"] == memos["kept"]
    assert look["looked"] >= memos["taken"]
    if workers:
        images = out[512.0]["report"].totals["images"]
        loads = out[512.0]["report"].totals["image_loads"] + sum(r["image_loads"] for r in look["rounds"])
        assert out[512.0]["report"].totals["backend"] == "local-cluster"
        assert images <= loads <= 2 * images
