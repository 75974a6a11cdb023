"""Second look: rejected pairs tied by chained correspondences, matched again (guidedmatch.collection.second_look)."""
from __future__ import annotations

import itertools
import shutil
import sqlite3

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from guidedmatch.cli import main as cli_main
from guidedmatch.collection.expansion import read_verified_graph
from guidedmatch.collection.second_look import (SecondLookConfig, chain_support, chained_correspondences, describe,
                                                 second_look)
from guidedmatch.errors import ConfigError

CFG = dict(progress=False, workers=0, threads=1)


def _chains_reference(a, c, inliers, names):
    """Slow reference: every (i, k) with some b, i <-> j in a-b and j <-> k in b-c, one match at a time."""
    def matches(x, y):
        if (x, y) in inliers:
            return [(int(p), int(q)) for p, q in inliers[(x, y)]]
        if (y, x) in inliers:
            return [(int(q), int(p)) for p, q in inliers[(y, x)]]
        return None

    out = set()
    for b in names:
        ab, bc = matches(a, b), matches(b, c)
        if ab is None or bc is None or b in (a, c):
            continue
        for i, j in ab:
            for j2, k in bc:
                if j == j2:
                    out.add((i, k))
    return sorted(out)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(3, 6), st.floats(0.3, 1.0), st.booleans())
def test_chained_correspondences_equal_the_slow_reference(seed, n, density, one_to_one):
    rng = np.random.default_rng(seed)
    names = [f"im{k}" for k in range(n)]
    nkp = {x: int(rng.integers(5, 30)) for x in names}
    inliers = {}
    for x, y in itertools.combinations(names, 2):
        if rng.random() < density:
            m = int(rng.integers(0, min(nkp[x], nkp[y]) + 1))
            # one-to-one matches (inliers of our two-view geometries are), stored in either order; or a keypoint in
            # several matches (another matcher's rows): every chain through each of them
            if one_to_one:
                pair = np.stack([rng.permutation(nkp[x])[:m], rng.permutation(nkp[y])[:m]], axis=1)
            else:
                pair = np.stack([rng.integers(0, nkp[x], m), rng.integers(0, nkp[y], m)], axis=1)
            if rng.random() < 0.5:
                inliers[(x, y)] = pair
            else:
                inliers[(y, x)] = pair[:, ::-1]
    nbr = {}
    for x, y in inliers:
        nbr.setdefault(x, set()).add(y)
        nbr.setdefault(y, set()).add(x)
    for a, c in itertools.combinations(names, 2):
        got = chained_correspondences(a, c, inliers, nkp, nbr)
        assert got.tolist() == [list(p) for p in _chains_reference(a, c, inliers, names)]
    assert chain_support([(names[0], names[1])], inliers, nkp) == [
        len(_chains_reference(names[0], names[1], inliers, names))]


def test_settings_are_validated():
    for bad in (dict(min_chained=0), dict(max_unguided=0.0), dict(max_unguided=1.5), dict(max_rounds=-1),
                dict(max_pairs_per_round=0), dict(orphan_pairs=-1), dict(orphan_unguided=0.0), dict(orphan_unguided=2.0)):
        with pytest.raises(ConfigError):
            SecondLookConfig(**bad)


@pytest.fixture(scope="module")
def matched_db(sequence_db, tmp_path_factory):
    """The rendered sequence's database (6 overlapping views + 1 view looking away), every pair matched."""
    from guidedmatch.collection.engine import match_collection
    from guidedmatch.collection.pairs import exhaustive_pairs
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    db = tmp_path_factory.mktemp("second_look") / "db.db"
    shutil.copyfile(sequence_db, db)
    src = ColmapSource(db)
    with ColmapSink(db) as sink:
        match_collection(src, exhaustive_pairs(src.names()), sink, CFG)
    src.close()
    return db


def _rows(db):
    con = sqlite3.connect(db)
    try:
        return sorted(con.execute("SELECT pair_id, rows, config, data FROM two_view_geometries"))
    finally:
        con.close()


def _reject(db, pairs):
    """Rewrite the geometries of ``pairs`` as our sink writes a rejected pair (a row with no inliers)."""
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.geometry import two_view_geometry

    none = two_view_geometry(np.zeros((0, 2)), np.zeros((0, 2)), (480, 360), (480, 360))
    assert not none
    with ColmapSink(db, overwrite=True) as sink:
        for a, b in pairs:
            sink.write(a, b, np.zeros((0, 2), np.int64), np.zeros(0, np.float32), none)


def _strongest(db, k):
    """The ``k`` verified pairs with the most inliers (a stand-in for pairs the first pass rejected)."""
    con = sqlite3.connect(db)
    try:
        names = dict(con.execute("SELECT image_id, name FROM images"))
        rows = sorted(con.execute("SELECT pair_id, rows FROM two_view_geometries WHERE rows > 0"), key=lambda r: -r[1])
    finally:
        con.close()
    base = 2147483647
    return [(names[(p - p % base) // base], names[p % base]) for p, _ in rows[:k]]


def _weaken(db, pair, keep=20):
    """Rewrite a verified pair as a weak one: its matches, only ``keep`` of them inliers."""
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.matcher import match

    src = ColmapSource(db)
    res = match(src.load(pair[0]), src.load(pair[1]), "so+epi+ia", dict(exact_rent=0.0))
    src.close()
    mask = np.zeros(len(res), bool)
    mask[np.flatnonzero(res.geometry.inliers)[:keep]] = True
    with ColmapSink(db, overwrite=True) as sink:
        sink.write(pair[0], pair[1], res.pairs, res.distances, res.geometry.with_inliers(mask))


def _look(db, sink_wrapper=None, **look):
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    src = ColmapSource(db)
    try:
        with ColmapSink(db) as sink:
            return second_look(src, sink_wrapper(sink) if sink_wrapper else sink, CFG, {"weak_below": 0, **look})
    finally:
        src.close()


def test_rejected_pairs_tied_by_chains_are_matched_again_and_verified(matched_db, tmp_path):
    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    ref = _rows(db)
    pairs = _strongest(db, 2)
    _reject(db, pairs)
    _, verified = read_verified_graph(db)
    assert not any(frozenset(p) in verified for p in pairs)
    rec = _look(db)
    tried, verified = read_verified_graph(db)
    assert all(frozenset(p) in verified for p in pairs)
    r1 = _chain_rounds(rec)[0]
    assert r1["pairs"] == r1["candidates"] >= 2 and rec["verified"] >= 2 and rec["stopped"]
    # the pairs matched again with a longer start: a strong pair is decided at its first check, so its rows come back
    assert _rows(db) == ref
    # the view looking away shares no verified neighbour with anything: never a candidate, never verified
    iso = sorted(n for p in tried for n in p)[-1]
    assert not any(iso in p for p in verified)
    # a rerun replays the finished rounds: nothing is matched again
    again = _look(db)
    assert all(r.get("replayed") for r in again["rounds"]) and _rows(db) == ref


def test_weak_pairs_are_matched_again_and_get_their_inliers_back(matched_db, tmp_path):
    db2 = tmp_path / "db2.db"
    shutil.copyfile(matched_db, db2)
    ref = _rows(db2)
    pair = _strongest(db2, 1)[0]
    _weaken(db2, pair)
    assert _rows(db2) != ref
    rec = _look(db2, weak_below=21, min_chained=10**6)   # only the weakened pair has fewer than 21 inliers
    assert _chain_rounds(rec)[0]["pairs"] == 1 and rec["verified"] == 0 and rec["inliers_gained"] > 0
    assert _rows(db2) == ref  # matched again, the pair is what the first pass wrote


@pytest.mark.parametrize("crash_at, weak_below", [(1, 0), (7, 0), (7, 40)])
def test_a_crash_in_a_round_then_a_rerun_gives_the_uninterrupted_database(matched_db, tmp_path, crashing_sink,
                                                                          crash_at, weak_below):
    """Killed in the orphan round (the 1st write) or in a chain round (the 7th: after the orphan round's 5 pairs),
    with and without weak pairs in the rounds (their inliers before the round rebuild the state's key)."""
    ref = tmp_path / "ref.db"
    shutil.copyfile(matched_db, ref)
    pairs = _strongest(ref, 3)
    _reject(ref, pairs)
    _weaken(ref, _strongest(ref, 1)[0])
    db = tmp_path / "db.db"
    shutil.copyfile(ref, db)
    first = _look(ref, weak_below=weak_below)
    assert [r["kind"] for r in first["rounds"]][:2] == ["orphans", "chains"]
    with pytest.raises(KeyboardInterrupt):
        _look(db, sink_wrapper=crashing_sink(crash_at), weak_below=weak_below)
    rec = _look(db, weak_below=weak_below)
    assert _rows(db) == _rows(ref) and rec["verified"] >= 3


def test_min_chained_above_every_chain_matches_nothing_and_max_rounds_zero_is_off(matched_db, tmp_path):
    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    _reject(db, _strongest(db, 1))
    before = _rows(db)
    rec = _look(db, min_chained=10**6, orphan_pairs=0)
    assert rec["rounds"] == [] and rec["looked"] == 0 and "no rejected pair" in rec["stopped"] and _rows(db) == before
    rec0 = _look(db, max_rounds=0, min_chained=16)
    assert rec0["rounds"] == [] and rec0["stopped"] == "max_rounds=0 reached" and _rows(db) == before


def _chain_rounds(rec):
    return [r for r in rec["rounds"] if r["kind"] == "chains"]


def _pairs_of(db, name):
    tried, _ = read_verified_graph(db)
    return sorted(tuple(sorted(p)) for p in tried if name in p)


def test_an_image_without_a_verified_pair_is_matched_against_its_most_similar_images(matched_db, tmp_path):
    """An orphan (every pair of a view rejected) gets a verified pair back in the orphan round, before any chain
    round (chains off here); the view looking away stays without one: no false edge at the longer start."""
    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    tried, verified = read_verified_graph(db)
    names = sorted({n for p in tried for n in p})
    iso = [n for n in names if not any(n in p for p in verified)]
    assert len(iso) == 1
    orphan = next(n for n in names if n not in iso)
    _reject(db, [tuple(p) for p in _pairs_of(db, orphan)])
    _, verified = read_verified_graph(db)
    assert not any(orphan in p for p in verified)
    rec = _look(db, min_chained=10**6, orphan_pairs=3)
    o = rec["orphans"]
    assert rec["rounds"][0]["kind"] == "orphans" and rec["rounds"][0]["pairs"] == o["pairs"] <= 2 * 3
    assert o["before"] == 2 and o["after"] == 1 and o["verified"] >= 1 and o["max_unguided"] == 0.1
    _, verified = read_verified_graph(db)
    assert any(orphan in p for p in verified) and not any(iso[0] in p for p in verified)
    assert "images without a verified pair: 2 -> 1" in describe(rec)
    # off: nothing is matched
    db2 = tmp_path / "db2.db"
    shutil.copyfile(matched_db, db2)
    _reject(db2, [tuple(p) for p in _pairs_of(db2, orphan)])
    rec2 = _look(db2, min_chained=10**6, orphan_pairs=0)
    assert rec2["rounds"] == [] and rec2["orphans"]["pairs"] == 0


def test_most_similar_ranks_like_the_shortlist(matched_db):
    """most_similar's k images of a view are that view's partners in the retrieval shortlist with the same k."""
    from guidedmatch.collection.retrieval import most_similar, retrieval_pairs
    from guidedmatch.collection.sources import ColmapSource

    src = ColmapSource(matched_db)
    conf = dict(coarse=16, fine=16, sample=5000, progress=False)
    names = src.names()
    sim = most_similar(src, names, 2, config=conf, cache=None)
    pairs = retrieval_pairs(src, None, dict(conf, k=2), cache=None).pairs
    src.close()
    for n in names:
        assert len(sim[n]) == 2 and n not in sim[n]
        assert all(tuple(sorted((n, m))) in {tuple(sorted(p)) for p in pairs} for m in sim[n])


def test_the_second_look_needs_our_geometries(matched_db, tmp_path):
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    with ColmapSink(db, geometry="colmap") as sink, pytest.raises(ConfigError, match="geometry='ours'"):
        second_look(ColmapSource(db), sink, CFG)


def test_cli_second_look_is_on_by_default_reported_and_can_be_turned_off(matched_db, tmp_path, capsys):
    for k, flags in enumerate(([], ["--second-look"])):
        db = tmp_path / f"db{k}.db"
        shutil.copyfile(matched_db, db)
        _reject(db, _strongest(db, 1))
        assert cli_main(["colmap", str(db), *flags, "--no-progress", "--log", "none"]) == 0
        out = capsys.readouterr().out
        assert "second look:" in out and "1 newly verified" in out, out
    db2 = tmp_path / "db2.db"
    shutil.copyfile(matched_db, db2)
    _reject(db2, _strongest(db2, 1))
    assert cli_main(["colmap", str(db2), "--no-second-look", "--no-progress", "--log", "none"]) == 0
    assert "second look" not in capsys.readouterr().out


def test_cli_says_when_the_second_look_cannot_run(matched_db, tmp_path, capsys):
    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    con = sqlite3.connect(db)
    con.execute("DELETE FROM matches")
    con.execute("DELETE FROM two_view_geometries")
    con.commit()
    con.close()
    assert cli_main(["colmap", str(db), "--geometry", "colmap", "--second-look", "--no-progress", "--log",
                     "none"]) == 0
    assert "second look: not run" in capsys.readouterr().out
    for p in tmp_path.glob("db.db*"):   # by default it is simply not part of a --geometry colmap run
        p.unlink()
    shutil.copyfile(matched_db, db)
    assert cli_main(["colmap", str(db), "--geometry", "colmap", "--no-progress", "--log", "none"]) == 0
    assert "second look" not in capsys.readouterr().out


def test_cli_second_look_settings_reach_it_and_are_checked_before_any_work(matched_db, tmp_path, capsys):
    db = tmp_path / "db.db"
    shutil.copyfile(matched_db, db)
    _reject(db, _strongest(db, 1))

    def geometries():
        con = sqlite3.connect(db)
        try:
            return sorted(con.execute("SELECT pair_id, rows FROM two_view_geometries"))
        finally:
            con.close()

    before = geometries()
    for flags, words in ((["--second-look-config", "no_such=1"], "no_such"),
                         (["--second-look-config", "min_chained=0"], "min_chained"),
                         (["--no-second-look", "--second-look-config", "weak_below=0"], "needs the second look")):
        assert cli_main(["colmap", str(db), *flags, "--no-progress", "--log", "none"]) == 2
        err = capsys.readouterr().err
        assert "--second-look-config" in err and words in err, err
        assert geometries() == before   # refused before any work
    # a chain requirement no pair meets: the rejected pair is not looked at again (by default it is: the test above)
    assert cli_main(["colmap", str(db), "--second-look-config", "min_chained=1000000", "--second-look-config",
                     "weak_below=0", "--no-progress", "--log", "none"]) == 0
    out = capsys.readouterr().out
    assert "second look:" in out and "0 newly verified" in out, out


def test_a_database_made_again_under_the_same_name_gets_the_rounds_rows_again(matched_db, tmp_path):
    """The state file outlives the database: a new database with the same first pass (the same graph, so the same
    key) must not skip the finished rounds, whose rows it does not hold (Herz-Jesus-P8 kept a rejected pair that
    the second look had verified)."""
    pre = tmp_path / "pre.db"
    shutil.copyfile(matched_db, pre)
    _reject(pre, _strongest(pre, 2))
    db = tmp_path / "db.db"
    shutil.copyfile(pre, db)
    first = _look(db)
    done = _rows(db)
    assert done != _rows(pre) and first["verified"] >= 2
    shutil.copyfile(pre, db)   # the database made again; db.db.second_look.json stays
    again = _look(db)
    assert _rows(db) == done
    assert any(r.get("stale") for r in again["rounds"]) and not any(r.get("replayed") for r in again["rounds"])
    assert "not in this database" in describe(again)
    # and a rerun on the database that holds the rounds still matches nothing
    third = _look(db)
    assert all(r.get("replayed") for r in third["rounds"]) and _rows(db) == done


def test_one_cluster_serves_the_first_pass_and_the_second_look(sequence_db, tmp_path, monkeypatch):
    """match_into_database with workers=2: one local cluster is started for the run, the first pass and every second
    look round run on it (the rounds report no start-up of their own), and the database equals an in-process run's."""
    from guidedmatch.collection import dask_backend, engine
    from guidedmatch.collection.pairs import exhaustive_pairs
    from guidedmatch.collection.sources import ColmapSource
    from guidedmatch.sfm.stages import match_into_database

    starts = []

    def counting(n, start=dask_backend._start_local_cluster):
        starts.append(n)
        return start(n)

    monkeypatch.setattr(dask_backend, "_start_local_cluster", counting)
    monkeypatch.setattr(engine, "_start_local_cluster", counting)
    out = {}
    for workers in (2, 0):
        db = tmp_path / f"w{workers}.db"
        shutil.copyfile(sequence_db, db)
        src = ColmapSource(db)
        try:
            out[workers] = match_into_database(src, exhaustive_pairs(src.names()), db,
                                               dict(progress=False, workers=workers), second_look={})
        finally:
            src.close()
    rep, look = out[2]["report"], out[2]["second_look"]
    assert starts == [2]
    assert rep.totals["backend"] == "local-cluster" and "one cluster for every stage" in rep.totals["backend_reason"]
    assert rep.totals["startup_s"] > 0 and look["rounds"]
    assert all(r["backend"] == "local-cluster" and r["startup_s"] == 0 for r in look["rounds"])
    assert out[0]["report"].totals["backend"] == "in-process"
    assert [r["pairs"] for r in out[0]["second_look"]["rounds"]] == [r["pairs"] for r in look["rounds"]]
    assert _rows(tmp_path / "w2.db") == _rows(tmp_path / "w0.db")
