"""guidedmatch sfm with extraction and matching overlapped (sfm/overlap.py, SfmConfig.pipeline): when it overlaps
and why not; the pairs it computes early are final; the database equals the staged run's (features byte for byte,
matches and two-view geometries) with a damaged image among the views; kill -9 at any moment then a rerun gives the
uninterrupted run's database; the report says what ran."""
from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from guidedmatch.errors import ConfigError
from guidedmatch.sfm import SfmConfig
from guidedmatch.sfm.overlap import _spec_parts, overlap_plan, prefix_pairs

SRC = str(Path(__file__).resolve().parents[1] / "src")


# --------------------------------------------------------------------------- when it overlaps
def test_overlap_plan_says_when_and_why_not(tmp_path):
    names = [f"{i:03d}.jpg" for i in range(8)]
    assert overlap_plan(SfmConfig(), names) == (False, "pipeline=off", None)   # the default (measured)
    assert overlap_plan(SfmConfig(pipeline="auto"), names)[2] == "exhaustive"
    assert overlap_plan(SfmConfig(pipeline="off"), names) == (False, "pipeline=off", None)
    ok, why, _ = overlap_plan(SfmConfig(pairs="sequential:3+retrieval:5", pipeline="auto"), names)
    assert not ok and "retrieval part" in why
    many = [f"{i:03d}.jpg" for i in range(61)]
    ok, why, _ = overlap_plan(SfmConfig(pipeline="auto"), many)
    assert not ok and "61 images > 60" in why
    assert overlap_plan(SfmConfig(pairs="sequential:3", pipeline="auto"), many)[:3:2] == (True, "sequential:3")
    for kw, needle in ((dict(detector="colmap"), "detector 'colmap'"), (dict(workers=2), "worker processes"),
                       (dict(scheduler="tcp://x:1"), "Dask")):
        ok, why, _ = overlap_plan(SfmConfig(pipeline="auto", **kw), names)
        assert not ok and needle in why
        with pytest.raises(ConfigError, match="pipeline='on' but .*" + needle.split()[0]):
            overlap_plan(SfmConfig(pipeline="on", **kw), names)
    assert overlap_plan(SfmConfig(workers=0, pipeline="auto"), names)[0] is True
    with pytest.raises(ConfigError, match="pipeline"):
        SfmConfig(pipeline="yes")


@pytest.mark.parametrize("spec", ["exhaustive", "sequential:2", "sequential:3:quadratic", "file",
                                  "sequential:1+file+exhaustive"])
def test_pairs_of_a_prefix_are_final_and_oriented_as_the_final_list(tmp_path, spec):
    """Images resolved in name order, some damaged, some written by an earlier run (smaller image ids): every pair
    computed on a resolved prefix is in the final pair list with the same orientation."""
    from guidedmatch.collection.pairs import pairs_from_spec

    rng = np.random.default_rng(0)
    names = [f"im{i:02d}.jpg" for i in range(12)]
    # the file names 9 of the 12 (a pairs file naming a damaged image is refused by the staged pass, and by ours)
    (tmp_path / "pairs.txt").write_text("".join(f"{names[a]} {names[b]}\n" for a, b in rng.integers(0, 9, (30, 2))))
    has_file = "file" in spec
    spec = spec.replace("file", str(tmp_path / "pairs.txt"))
    for trial in range(20):
        bad = set(rng.choice(names[9:] if has_file else names, 2, replace=False)) if trial else set()
        ids = {n: i for i, n in enumerate(rng.permutation(names), 1)} if trial % 2 else \
            {n: i for i, n in enumerate(names, 1)}
        good = [n for n in names if n not in bad]
        final = pairs_from_spec(spec, sorted(good, key=ids.get)).pairs
        parts = _spec_parts(spec)
        seen = set()
        for k in range(len(names) + 1):
            usable = sorted((n for n in names[:k] if n not in bad), key=ids.get)
            got = prefix_pairs(parts, usable)
            seen |= {frozenset(p) for p in got}
            # the first orientation of each pair (PairStream keeps the first one added)
            first = {}
            for p in got:
                first.setdefault(frozenset(p), p)
            assert set(first.values()) <= set(final), (spec, trial, k)
        assert seen == {frozenset(p) for p in final}


# --------------------------------------------------------------------------- same database as the staged path
@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """6 rendered views (640x480) with an unreadable file between two of them in name order."""
    mv = pytest.importorskip("guidedmatch.testing.multiview")
    scene = mv.make_multiview(n_views=6, size=(640, 480), seed=1, isolated=False, spacing=1.6)
    folder = tmp_path_factory.mktemp("ov") / "images"
    mv.write_views(scene, folder)
    (folder / "view_02b.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 64)   # damaged, between 02 and 03
    return scene, folder


def db_dump(path: Path) -> dict:
    """Everything the stages write: images (ids, cameras), keypoint and descriptor blobs, matches and two-view
    geometries (configuration, inlier matches, F, H), by image names."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        names = dict(con.execute("SELECT image_id, name FROM images"))
        out = {"images": sorted(con.execute("SELECT image_id, name, camera_id FROM images")),
               "cameras": sorted(con.execute("SELECT * FROM cameras")),
               "keypoints": {names[i]: (r, c, bytes(d)) for i, r, c, d in
                             con.execute("SELECT image_id, rows, cols, data FROM keypoints")},
               "descriptors": {names[i]: (r, c, bytes(d)) for i, r, c, d in
                               con.execute("SELECT image_id, rows, cols, data FROM descriptors")}}

        def by_names(pid):
            i2 = pid % 2147483647
            i1 = (pid - i2) // 2147483647
            return names[i1], names[i2]

        out["matches"] = {by_names(p): (r, c, bytes(d) if d is not None else b"") for p, r, c, d in
                          con.execute("SELECT pair_id, rows, cols, data FROM matches")}
        out["geometries"] = {by_names(p): (r, cfg, bytes(d) if d is not None else b"",
                                           bytes(F) if F is not None else b"", bytes(H) if H is not None else b"")
                             for p, r, cfg, d, F, H in
                             con.execute("SELECT pair_id, rows, config, data, F, H FROM two_view_geometries")}
        return out
    finally:
        con.close()


@pytest.mark.parametrize("pairs", ["auto", "sequential:2"])
def test_overlapped_database_equals_the_staged_one(views, tmp_path, pairs):
    """The same images, settings and pairs with pipeline on and off: the same image ids, cameras, keypoint and
    descriptor bytes, the same matches and two-view geometries byte for byte (inlier cap applied); the damaged image
    is skipped and named either way; the report says whether the stages overlapped and why."""
    from guidedmatch.sfm import run_sfm

    scene, folder = views
    conf = {"pairs": pairs, "workers": 0, "num_threads": 2, "progress": False, "max_inliers_per_pair": 200,
            "cap_above": 0}
    on = run_sfm(folder, tmp_path / "on", {**conf, "pipeline": "on"})
    off = run_sfm(folder, tmp_path / "off", {**conf, "pipeline": "off"})
    a, b = db_dump(tmp_path / "on" / "database.db"), db_dump(tmp_path / "off" / "database.db")
    assert len(a["images"]) == 6 and len(a["keypoints"]) == 6 and min(r for r, _, _ in a["keypoints"].values()) > 100
    n_pairs = 15 if pairs == "auto" else 9
    assert len(a["matches"]) == len(a["geometries"]) == n_pairs
    for key in ("images", "cameras", "keypoints", "descriptors", "matches", "geometries"):
        assert a[key] == b[key], key
    assert sum(g[0] > 0 for g in a["geometries"].values()) >= 5      # verified pairs with inliers
    assert max(g[0] for g in a["geometries"].values()) == 200        # the cap ran on the overlapped pairs too
    for rep in (on, off):
        assert [s["name"] for s in rep["skipped_images"]] == ["view_02b.png"]
        assert rep["registered"] == 6
    assert on["stages"]["matching"]["collection"]["done"] == n_pairs == off["stages"]["matching"]["collection"]["done"]
    assert on["pipeline"]["overlapped"] is True and on["pipeline"]["not_in_final_list"] == 0
    assert on["pipeline"]["pairs_matched_overlapped"] == n_pairs and on["stages"]["extraction"]["extracted"] == 6
    assert off["pipeline"] == {"setting": "off", "overlapped": False, "why": "pipeline=off"}
    md = (tmp_path / "on" / "report.md").read_text()
    assert "Extraction and matching overlapped" in md and "pairs during the extraction" in on["summary"]
    assert "not overlapped (pipeline=off)" in (tmp_path / "off" / "report.md").read_text()
    # a rerun of the overlapped run: nothing extracted or matched again
    again = run_sfm(folder, tmp_path / "on", {**conf, "pipeline": "on"})
    assert again["stages"]["extraction"]["extracted"] == 0 and again["stages"]["matching"]["collection"]["done"] == 0
    assert again["stages"]["matching"]["collection"]["skipped"] == n_pairs
    assert db_dump(tmp_path / "on" / "database.db") == a


def test_retrieval_pairs_run_staged_and_say_why(views, tmp_path):
    from guidedmatch.sfm import run_sfm

    scene, folder = views
    rep = run_sfm(folder, tmp_path / "r", {"pairs": "retrieval:3", "workers": 0, "num_threads": 2, "pipeline": "auto",
                                           "progress": False})
    assert rep["pipeline"]["overlapped"] is False and "retrieval part" in rep["pipeline"]["why"]
    assert "not overlapped (pairs 'retrieval:3' has a retrieval part" in (tmp_path / "r" / "report.md").read_text()
    assert "overlap" not in rep["stages"]["matching"] and rep["registered"] >= 5


# --------------------------------------------------------------------------- kill -9, then a rerun
def _images_in(db: Path) -> int:
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.2)
        try:
            return con.execute("SELECT COUNT(*) FROM images").fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return 0


def _sfm_cmd(folder, out):
    return [sys.executable, "-m", "guidedmatch.cli", "sfm", str(folder), str(out), "--pipeline", "on",
            "--workers", "0", "--threads", "2", "--quiet"]


ENV = {"PYTHONPATH": SRC, "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1",
       "OPENBLAS_NUM_THREADS": "1"}


@pytest.mark.parametrize("when", ["images", "pairs"])
def test_kill_9_then_rerun_equals_an_uninterrupted_run(views, tmp_path, when):
    """``guidedmatch sfm --pipeline on`` killed (SIGKILL) once 2 images are in the database (extraction running),
    or once its first pair is logged; the rerun completes it, and the database equals an uninterrupted run's."""
    scene, folder = views
    out = tmp_path / "killed"
    err = tmp_path / "run1.stderr"
    with open(err, "wb") as err_file:
        proc = subprocess.Popen(_sfm_cmd(folder, out), env=ENV, start_new_session=True, stdout=subprocess.DEVNULL,
                                stderr=err_file)
    try:
        deadline = time.monotonic() + 180
        db, log = out / "database.db", out / "pairs.jsonl"
        while time.monotonic() < deadline and proc.poll() is None:
            if when == "images" and db.exists() and _images_in(db) >= 2:
                break
            if when == "pairs" and log.exists() and '"event": "pair"' in log.read_text():
                break
            time.sleep(0.005)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, (f"the run ended by itself (exit {proc.returncode}) before it could be "
                                                f"killed; its stderr: {err.read_text(errors='replace')[-2000:]}")
    killed = db_dump(out / "database.db")
    assert len(killed["images"]) < 6 or len(killed["geometries"]) < 15      # interrupted for real
    r2 = subprocess.run(_sfm_cmd(folder, out), env=ENV, capture_output=True, text=True, timeout=600)
    assert r2.returncode == 0, r2.stderr
    ref = tmp_path / "ref"
    r3 = subprocess.run(_sfm_cmd(folder, ref), env=ENV, capture_output=True, text=True, timeout=600)
    assert r3.returncode == 0, r3.stderr
    assert db_dump(out / "database.db") == db_dump(ref / "database.db")
    rep = json.loads((out / "report.json").read_text())
    assert rep["pipeline"]["overlapped"] and [s["name"] for s in rep["skipped_images"]] == ["view_02b.png"]
    ex = rep["stages"]["extraction"]
    assert ex["extracted"] + ex["reused"] == 6 and ex["reused"] == len(killed["keypoints"])
    col = rep["stages"]["matching"]["collection"]
    assert col["done"] + col["skipped"] == 15 and col["skipped"] == len(killed["geometries"])


def test_pipeline_on_where_it_cannot_overlap_is_refused_before_any_work(views, tmp_path):
    scene, folder = views
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "guidedmatch.cli", "sfm", str(folder), str(out), "--pipeline", "on",
                           "--pairs", "retrieval:3", "--quiet"], env=ENV, capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "pipeline='on' but extraction and matching cannot overlap" in lines[0] and "retrieval" in lines[0]
    assert not out.exists()
