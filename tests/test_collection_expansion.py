"""Verified expansion: triangle-closing pairs in rounds (guidedmatch.collection.expansion)."""
from __future__ import annotations

import itertools
import shutil
import sqlite3

import pytest

from guidedmatch.cli import main as cli_main
from guidedmatch.collection.expansion import (ExpansionConfig, match_collection_expanded, read_verified_graph,
                                              triangle_candidates)
from guidedmatch.collection.pairs import sequential_pairs
from guidedmatch.errors import ConfigError

CFG = dict(progress=False, workers=0, threads=1)


def _fs(pairs):
    return {frozenset(p) for p in pairs}


def test_candidates_are_exactly_the_untried_triangle_closing_pairs():
    names = list("abcdefg")
    verified = _fs([("a", "b"), ("b", "c"), ("c", "d"), ("b", "d"), ("e", "f")])
    tried = verified | _fs([("a", "c")])  # a-c tried (not verified): never proposed again
    got, support, total = triangle_candidates(names, tried, verified)
    # slow reference: every pair with a common verified neighbour, minus the tried ones
    want = set()
    for x, y in itertools.combinations(names, 2):
        if any(frozenset((x, b)) in verified and frozenset((b, y)) in verified for b in names):
            if frozenset((x, y)) not in tried:
                want.add(frozenset((x, y)))
    assert _fs(got) == want == _fs([("a", "d")]) and total == 1 and support == [1]
    got2, sup2, _ = triangle_candidates(names, verified, verified)
    assert got2 == [("a", "c"), ("a", "d")] and sup2 == [1, 1]  # equal support: in the order of the names
    square = _fs([("a", "b"), ("b", "c"), ("a", "d"), ("d", "c"), ("c", "e")])
    got3, sup3, _ = triangle_candidates("abcde", square, square)
    assert got3 == [("a", "c"), ("b", "d"), ("b", "e"), ("d", "e")] and sup3 == [2, 2, 1, 1]  # most supported first
    capped, _, total = triangle_candidates("abcde", square, square, limit=1)
    assert capped == [("a", "c")] and total == 4
    assert triangle_candidates(names, set(), set()) == ([], [], 0)


def _rows(db):
    con = sqlite3.connect(db)
    try:
        return (sorted(con.execute("SELECT pair_id, rows, cols, data FROM matches")),
                sorted(con.execute("SELECT pair_id, rows, config, data FROM two_view_geometries")))
    finally:
        con.close()


def _run(db, expand=None, sink_wrapper=None):
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    src = ColmapSource(db)
    pairs = sequential_pairs(src.names(), 1)
    with ColmapSink(db) as sink:
        use = sink_wrapper(sink) if sink_wrapper else sink
        return match_collection_expanded(src, pairs, use, CFG, expand)


def test_rounds_add_the_triangle_closing_pairs_until_nothing_new_is_verified(sequence_db, tmp_path):
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    rep = _run(db)
    names = sorted(n for n in _names(db))
    shortlist = _fs(sequential_pairs(names, 1))
    tried, verified = read_verified_graph(db)
    stages = rep.stages
    assert stages[0]["stage"] == "shortlist" and stages[0]["pairs"] == len(shortlist)
    assert stages[1]["stage"] == "expansion 1"
    # round 1 = exactly the triangle-closing pairs of the shortlist's verified graph
    v0 = {p for p in shortlist if p in verified}
    want1 = _fs(triangle_candidates(names, shortlist, v0)[0])
    assert stages[1]["pairs"] == len(want1) > 0
    # at the end no triangle-closing pair is left untried, or the last round verified nothing
    left = triangle_candidates(names, tried, verified)[0]
    assert not left or stages[-1]["verified"] == 0
    assert rep.expansion["rounds"] == len(stages) - 1 and rep.tried_pairs == len(tried)
    assert "expansion" in rep.summary()
    # the isolated view is never verified with anything: its pairs stay out of the expansion
    iso = names[-1]
    assert not any(iso in p for p in verified)


def _names(db):
    con = sqlite3.connect(db)
    try:
        return [n for (n,) in con.execute("SELECT name FROM images")]
    finally:
        con.close()


@pytest.mark.parametrize("crash_after", [2, 8])
def test_a_crash_in_any_stage_then_a_rerun_gives_the_uninterrupted_database(sequence_db, tmp_path, crash_after,
                                                                              crashing_sink):
    ref = tmp_path / "ref.db"
    shutil.copyfile(sequence_db, ref)
    _run(ref, dict(max_pairs_per_round=2))  # capped rounds: the replayed round lists matter
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    with pytest.raises(KeyboardInterrupt):
        _run(db, dict(max_pairs_per_round=2), sink_wrapper=crashing_sink(crash_after))
    _run(db, dict(max_pairs_per_round=2))
    assert _rows(db) == _rows(ref)


def test_max_rounds_zero_is_the_shortlist_only_and_caps_are_reported(sequence_db, tmp_path):
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    rep = _run(db, dict(max_rounds=0))
    assert [s["stage"] for s in rep.stages] == ["shortlist"] and rep.expansion["stopped"] == "max_rounds=0"
    db2 = tmp_path / "db2.db"
    shutil.copyfile(sequence_db, db2)
    rep2 = _run(db2, dict(max_pairs_per_round=1, max_rounds=2))
    assert rep2.expansion["rounds"] <= 2
    assert all(s["pairs"] <= 1 for s in rep2.stages[1:])
    assert rep2.expansion["capped_rounds"] == sum(bool(s["capped"]) for s in rep2.stages[1:]) >= 1


def test_bad_settings_and_sinks_are_config_errors(sequence_db, tmp_path):
    with pytest.raises(ConfigError):
        ExpansionConfig(max_rounds=-1)
    with pytest.raises(ConfigError):
        ExpansionConfig(max_pairs_per_round=0)

    class H5Like:
        kind = "h5"
        path = tmp_path / "m.h5"

    from guidedmatch.collection.sources import ColmapSource

    with pytest.raises(ConfigError, match="COLMAP database"):
        match_collection_expanded(ColmapSource(sequence_db), [], H5Like(), CFG)


def test_cli_expand_rounds_without_expansion_is_exit_2(sequence_db, tmp_path, capsys):
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    rc = cli_main(["colmap", str(db), "--pairs", "sequential:1", "--expand-rounds", "2", "--no-progress"])
    assert rc == 2 and "--expand-rounds needs" in capsys.readouterr().err


def test_cli_retrieval_expands_by_default_and_no_expand_does_not(sequence_db, tmp_path, capsys):
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    assert cli_main(["colmap", str(db), "--pairs", "retrieval:1", "--no-progress", "--log", "none"]) == 0
    out = capsys.readouterr().out
    assert "retrieval  :" in out and "shortlist  :" in out and "expansion  :" in out
    db2 = tmp_path / "db2.db"
    shutil.copyfile(sequence_db, db2)
    assert cli_main(["colmap", str(db2), "--pairs", "retrieval:1", "--no-expand", "--no-progress", "--log",
                     "none"]) == 0
    assert "expansion" not in capsys.readouterr().out


def test_expansion_rounds_draw_the_chained_then_tracked_keypoints_first(sequence_db, tmp_path, monkeypatch):
    """The shortlist is matched in the paper's order; every expansion round with the prior of the verified graph
    before it (second_look.priors, both orientations of every candidate); prior=False: never."""
    import numpy as np

    from guidedmatch.collection import engine
    from guidedmatch.collection.second_look import _read_inliers, priors

    calls = []
    real = engine.match_collection

    def spy(source, pairs, sink, config=None, *, client=None, first=None, start_memos=None):
        pairs = [tuple(p) for p in pairs]
        want = None
        if first is not None:   # the graph before this round (its own pairs never tried yet)
            _, inliers, nkp = _read_inliers(sink)
            want = priors(pairs, inliers, nkp)
        calls.append((pairs, first, want))
        return real(source, pairs, sink, config, client=client, first=first, start_memos=start_memos)

    monkeypatch.setattr(engine, "match_collection", spy)
    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    rep = _run(db, dict(prior=True))
    assert len(calls) == len(rep.stages) >= 2 and calls[0][1] is None   # the shortlist: no prior
    for pairs, first, want in calls[1:]:
        assert first is not None and set(first) == {q for a, c in pairs for q in ((a, c), (c, a))}
        for k in first:
            assert all(np.array_equal(x, y) for x, y in zip(first[k], want[k]))
        assert any(len(first[k][0]) for k in first)   # triangle-closing pairs have chained keypoints
    assert sorted(map(tuple, rep.prior_pairs)) == sorted(p for pairs, _, _ in calls[1:] for p in pairs)
    assert rep.expansion["prior"] is True and all(s.get("prior") for s in rep.stages[1:])

    calls.clear()
    db2 = tmp_path / "db2.db"
    shutil.copyfile(sequence_db, db2)
    rep2 = _run(db2)   # the default: no prior
    assert all(first is None for _, first, _ in calls) and rep2.prior_pairs == [] and not rep2.expansion["prior"]


def test_the_second_look_skips_the_pairs_the_expansion_matched_with_the_prior(sequence_db, tmp_path):
    from guidedmatch.collection.second_look import _candidates, second_look, SecondLookConfig, _read_inliers
    from guidedmatch.collection.sinks import ColmapSink
    from guidedmatch.collection.sources import ColmapSource

    db = tmp_path / "db.db"
    shutil.copyfile(sequence_db, db)
    rep = _run(db, dict(prior=True))
    with ColmapSink(db) as sink:
        tried, inliers, nkp = _read_inliers(sink)
        cfg = SecondLookConfig(min_chained=1, weak_below=10**9)   # every weak or chain-tied pair is a candidate
        everything, _, _ = _candidates(tried, inliers, nkp, set(), cfg)
        skipped = {frozenset(p) for p in rep.prior_pairs}
        left, _, _ = _candidates(tried, inliers, nkp, skipped, cfg)
        assert skipped & {frozenset(p) for p in everything}     # the test means something
        assert {frozenset(p) for p in left} == {frozenset(p) for p in everything} - skipped
        look = second_look(ColmapSource(db), sink, CFG, dict(min_chained=1, weak_below=10**9, orphan_pairs=0),
                           state_path=False, looked=rep.prior_pairs)
    assert look["looked"] == len(left)
