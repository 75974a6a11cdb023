"""The fault-injection suite, reduced: kill -9 mid-run (in-process and Dask), a full disk, two writers, the
corrupt-input table and a bounded fuzz of every subcommand's arguments. The full version is
``python -m guidedmatch.evaluation.bench_faults`` (benchmarks/results/faults.md)."""
import shutil

import numpy as np
import pytest

from guidedmatch.evaluation import bench_faults as bf
from guidedmatch.evaluation.faults_common import (Row, SmallFS, compare_db, db_state, make_collection, partial_rows,
                                                  run_cli, table_markdown)
from guidedmatch.evaluation.faults_inputs import (fuzz_arguments, input_cases, make_features_h5, run_cases,
                                                  run_inprocess)


@pytest.fixture(scope="module")
def coll(tmp_path_factory):
    """12 rendered views, 400 SIFT features each, and the tables of an uninterrupted in-process run."""
    work = tmp_path_factory.mktemp("faults")
    c = make_collection(work / "collection", n_images=12, size=(320, 240), max_features=400, seed=2)
    ref_db = bf._fresh(work / "ref.db", c["db"])
    run = run_cli(bf._colmap_args(ref_db, "in-process"))
    assert run.rc == 0, run.stderr
    c["work"], c["ref"] = work, db_state(ref_db)
    assert len(c["ref"]["geometries"]) == 66 and c["ref"]["integrity"] == "ok"
    return c


def test_db_state_sees_half_stored_pairs_and_differences(coll, tmp_path):
    """The checks the suite relies on can fail: a pair without its geometry row, a changed inlier set."""
    import sqlite3

    db = shutil.copy(coll["work"] / "ref.db", tmp_path / "x.db")
    con = sqlite3.connect(db)
    pid = con.execute("SELECT pair_id FROM two_view_geometries ORDER BY pair_id LIMIT 1 OFFSET 3").fetchone()[0]
    con.execute("DELETE FROM two_view_geometries WHERE pair_id = ?", (pid,))
    pid2 = con.execute("SELECT pair_id FROM matches ORDER BY length(data) DESC LIMIT 1").fetchone()[0]
    con.execute("UPDATE matches SET data = zeroblob(length(data)) WHERE pair_id = ?", (pid2,))
    con.commit()
    con.close()
    state = db_state(tmp_path / "x.db")
    assert partial_rows(state) == 1
    diffs = compare_db(state, coll["ref"])
    assert any("1 missing" in d for d in diffs) and any("differ" in d for d in diffs)
    assert compare_db(coll["ref"], coll["ref"]) == []


@pytest.mark.parametrize("backend, after", [("in-process", [3, 30]), ("dask", [10])])
def test_kill_9_mid_run_then_rerun(coll, backend, after):
    """kill -9 once the run has logged ``after`` pairs: right after the kill every stored pair is complete and as
    in the uninterrupted run, integrity_check says ok; the rerun skips every stored pair and ends with the same
    tables (pairs, matches, inlier sets, F, H) -- the uninterrupted in-process run's also for the Dask backend."""
    row = bf.kill_colmap(coll, coll["work"], backend, len(after), np.random.default_rng(0), after_pairs=after)
    assert (row.trials, row.survived, row.lost, row.corrupt) == (len(after), len(after), 0, 0), row.details
    # the rerun prints no traceback; the killed run's Dask workers may (a heartbeat's CommClosedError once their
    # scheduler died with the main process) -- counted in the bench's table, not asserted here
    assert not any(d["rerun_traceback"] for d in row.details), row.details
    if backend == "in-process":
        assert row.tracebacks == 0, row.details
    assert all(d["killed"] for d in row.details)
    assert sum(d["committed_before"] for d in row.details) > 0   # the kills came after pairs were stored


def test_disk_full_while_writing_the_database(coll, tmp_path):
    """A filesystem with room for the sink's margin and 256 KiB more (a tmpfs where mounting is
    permitted, else RLIMIT_FSIZE): exit 2 naming the database, only complete pairs stored, the rerun with space
    completes without redoing them."""
    from guidedmatch.collection.sinks import SPACE_MARGIN

    base = coll["db"].stat().st_size
    full = (coll["work"] / "ref.db").stat().st_size
    ok, d = bf.disk_full_colmap(coll, tmp_path / "fs", coll["ref"], base + SPACE_MARGIN + (256 << 10), grown=full)
    assert ok, d
    assert d["rc"] == 2 and ("disk full" in d["message"] or "file size limit" in d["message"]), d
    assert d["pairs_stored"] > 0, d   # refused mid-run, not at the start


def test_small_fs_method(tmp_path):
    fs = SmallFS(tmp_path / "fs", 1 << 20)
    try:
        assert fs.method in ("tmpfs", "rlimit")
        assert (fs.preexec() is None) == (fs.method == "tmpfs")
        if fs.method == "tmpfs":
            assert fs.free() <= 1 << 20
    finally:
        fs.close()


def test_two_writers_on_one_database(coll, tmp_path):
    """Two guidedmatch colmap on one database at once: the second refuses with a clear message (exit 2) or both
    finish -- the database equal to the uninterrupted run's either way."""
    db = bf._fresh(tmp_path / "db.db", coll["db"])
    runs = bf._concurrent([bf._colmap_args(db, "in-process")] * 2, [0.0, 0.3])
    outcomes = sorted("ok" if r.rc == 0 else "refused" if bf._refused_clearly(r) else f"exit {r.rc}: {r.stderr}"
                      for r in runs)
    assert outcomes in (["ok", "ok"], ["ok", "refused"]), outcomes
    assert not any(r.bug for r in runs)
    assert compare_db(db_state(db), coll["ref"]) == []


@pytest.fixture(scope="module")
def input_env(coll, tmp_path_factory):
    small = make_collection(coll["work"] / "small", n_images=4, size=(320, 240), max_features=300, seed=7)
    return dict(db=small["db"], names=small["names"], images=small["images"],
                features=make_features_h5(small["db"], coll["work"] / "small-features.h5"))


@pytest.mark.parametrize("group", ["database", "h5", "pairs", "images (match)"])
def test_corrupt_inputs(input_env, tmp_path, group):
    """Each corrupt input: exit 2 with a message naming the file, or the documented handling -- no traceback."""
    cases = [c for c in input_cases() if c.group == group]
    assert len(cases) >= 5
    results = run_cases(cases, tmp_path, input_env, runner=run_inprocess)
    failed = [(r["case"], r["rc"], r["problems"], r["message"]) for r in results if not r["ok"]]
    assert not failed, failed


def test_fuzzed_arguments_of_every_subcommand(tmp_path):
    """Hypothesis-drawn argument lists from each subparser's own options plus junk: exit 0 or 2, never a traceback
    or an internal error (in this process: SystemExit, stdout and stderr captured)."""
    row = fuzz_arguments(tmp_path, examples=6, seed=0)
    commands = {d["command"] for d in row.details}
    assert {"match", "colmap", "hloc", "sfm", "demo", "bench"} <= commands
    assert row.trials >= 6 * 4 and row.tracebacks == 0, row.notes


def test_inprocess_runner_reports_a_traceback(monkeypatch):
    """The fuzzer's runner turns an exception escaping main into a traceback on stderr (so the check can fail)."""
    import guidedmatch.cli as cli

    def boom(argv=None):
        raise KeyError("x")
    monkeypatch.setattr(cli, "main", boom)
    run = run_inprocess(["match"])
    assert run.rc is None and run.bug


def test_table_and_main_wiring(tmp_path, monkeypatch):
    """main() writes faults.md + faults.json with run metadata (classes stubbed: their work is tested above)."""
    import json

    monkeypatch.setattr(bf, "make_collection", lambda *a, **k: {"names": ["a"] * 12})
    import guidedmatch.evaluation.faults_inputs as fi

    r = Row("x")
    r.add(True, lost=0)
    r.add(False, lost=2, corrupt=True, bug=True, case="c", rc=1, message="m")
    monkeypatch.setattr(fi, "corrupt_inputs", lambda *a, **k: [r])
    fz = Row("fuzz")
    fz.trials = 3
    fz.details.append(dict(command="match", examples=3, failed=0, timeouts=0, exit_codes=["2"], failures=[]))
    monkeypatch.setattr(fi, "fuzz_arguments", lambda *a, **k: fz)
    args = bf.build_parser().parse_args(["--out", str(tmp_path), "--faults", "inputs,fuzz"])
    assert bf.main(args) == 0
    md = (tmp_path / "faults.md").read_text()
    assert "| x | 2 | 1 | 2 | 1 | 1 |" in md and table_markdown([r, fz]) in md and "| match | 3 | 0 | 0 | 2 |" in md
    fz.fault = "fuzz again"   # --merge-faults keeps the rows this run does not produce
    args = bf.build_parser().parse_args(["--out", str(tmp_path), "--faults", "fuzz", "--merge-faults"])
    assert bf.main(args) == 0
    md = (tmp_path / "faults.md").read_text()
    assert "| x | 2 | 1 | 2 | 1 | 1 |" in md and "| fuzz | 3 |" in md and "| fuzz again | 3 |" in md
    data = json.loads((tmp_path / "faults.json").read_text())
    assert "git_commit" in data["meta"] and data["kill_trials"] == 30
    assert data["rows"][0]["details"][1]["case"] == "c" and "timestamp_utc" in data["meta"]
    with pytest.raises(Exception, match="unknown fault class"):
        bf.main(bf.build_parser().parse_args(["--out", str(tmp_path), "--faults", "nope"]))


def test_kill_9_in_a_retrieval_and_expansion_run(coll, tmp_path):
    """The retrieval stage, the shortlist and the expansion rounds killed at random moments: the rerun ends with
    the uninterrupted retrieval run's tables and skips every pair stored before the kill."""
    c = {k: v for k, v in coll.items() if k != "ref"}   # its own uninterrupted reference: the retrieval run's
    row = bf.kill_colmap(c, tmp_path, "in-process, retrieval:4 + expansion", 3, np.random.default_rng(1))
    assert (row.trials, row.survived, row.lost, row.corrupt, row.tracebacks) == (3, 3, 0, 0, 0), row.details


def test_compare_db_accepts_a_pending_selection_pass_only_on_the_side_named():
    """Right after a kill, a committed geometry may still hold every verdict inlier (tighten / cap run after
    matching): accepted as a superset on the side named, with the same config and matrices; nothing else is."""
    F, H = np.arange(9.0).reshape(3, 3) + 1, np.eye(3)
    big, small = np.array([[0, 1], [2, 3], [4, 5]]), np.array([[0, 1], [4, 5]])
    base = {"integrity": "ok", "error": None, "matches": {}, "features": {}, "ids": {}}
    after = dict(base, geometries={("a", "b"): (3, big, F, H)})
    final = dict(base, geometries={("a", "b"): (3, small, F, H)})
    assert compare_db(after, final, only={("a", "b")})                       # strict by default
    assert compare_db(after, final, only={("a", "b")}, pending_pass="state") == []
    assert compare_db(after, final, only={("a", "b")}, pending_pass="ref")   # the wrong side
    assert compare_db(final, after, only={("a", "b")}, pending_pass="ref") == []
    other = dict(base, geometries={("a", "b"): (3, big, 2 * F + 1, H)})    # another F: never the same pair
    assert compare_db(other, final, only={("a", "b")}, pending_pass="state")
    stray = dict(base, geometries={("a", "b"): (3, np.array([[0, 1], [6, 7]]), F, H)})   # not a superset
    assert compare_db(stray, final, only={("a", "b")}, pending_pass="state")
