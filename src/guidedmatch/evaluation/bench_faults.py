"""Fault injection: ``kill -9`` at random moments, a full disk, two writers, corrupt inputs and fuzzed arguments.

``python -m guidedmatch.evaluation.bench_faults --out benchmarks/results`` writes ``faults.md`` (one row per fault
class: trials / survived / finished work lost / corrupt outputs / tracebacks, then the details of each class) and
``faults.json`` (run metadata and every trial). Everything runs on a rendered multi-view collection made by the
bench itself (no data needed); each trial runs ``guidedmatch`` in a fresh process, as a user would.

What "survived" means per class:

* **kill -9** of ``guidedmatch colmap`` (in-process and ``--workers 2``) at a moment drawn uniformly from the
  uninterrupted run's wall time, and of ``guidedmatch sfm`` inside each stage (extraction / matching / mapping,
  the stage windows taken from the uninterrupted run's stage lines): right after the kill every stored pair is
  complete and equal to the uninterrupted run's and ``PRAGMA integrity_check`` says ok; the rerun exits 0, skips
  every pair (and image) stored before the kill -- a finished one redone counts as *finished work lost* -- and
  leaves the same match tables (pairs, matches, inlier sets, F, H) as the uninterrupted run.
* **disk full** (a tmpfs of a chosen size; ``RLIMIT_FSIZE`` where mounting is not permitted) while writing the
  database, ``matches.h5``, the sfm model and its report: exit 2 with a message naming the path, no half-written
  file (the database passes ``integrity_check`` with only complete pairs, h5 files open, the old model and report
  still read), and the rerun with space exits 0 with the uninterrupted run's result.
* **two writers** on one database / ``matches.h5`` / sfm project, and a foreign SQLite transaction held open: the
  second refuses with a clear message (exit 2) or both finish -- the result equal to the uninterrupted run's.
* **corrupt inputs** and **fuzzed arguments**: :mod:`guidedmatch.evaluation.faults_inputs`.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .faults_common import (Row, Run, SmallFS, compare_db, db_state, fill, make_collection, parse_skipped,
                            partial_rows, reordered_pairs, run_and_kill, run_cli, table_markdown)
from .meta import cpu_label

SFM_STAGES = (("extraction", "[1/3]"), ("matching", "[2/3]"), ("mapping", "[3/3]"))
SFM_END = "done in"


def add_arguments(parser) -> None:
    """Options of the faults bench (besides ``--out``, ``--seed``, ``--quick`` of the ``bench`` command)."""
    parser.add_argument("--kill-trials", type=int, default=None, metavar="N",
                        help="faults: kill -9 trials of guidedmatch colmap per backend (default 30; --quick 4)")
    parser.add_argument("--sfm-kill-trials", type=int, default=None, metavar="N",
                        help="faults: kill -9 trials of guidedmatch sfm per stage (default 4; --quick 1)")
    parser.add_argument("--fuzz-examples", type=int, default=None, metavar="N",
                        help="faults: fuzzed argument lists per subcommand (default 150; --quick 25)")
    parser.add_argument("--kill-backends", default=None, metavar="LIST",
                        help="faults: '|'-separated runs of guidedmatch colmap to kill (default all: "
                             + " | ".join(KILL_BACKENDS) + ")")
    parser.add_argument("--faults", default=None, metavar="LIST",
                        help="faults: comma-separated subset of kill, sfm-kill, disk, writers, inputs, fuzz")
    parser.add_argument("--work", default=None, metavar="DIR",
                        help="faults: scratch folder (default: a temporary folder, removed afterwards)")
    parser.add_argument("--merge-faults", action="store_true",
                        help="faults: keep the rows of an existing OUT/faults.json that this run does not produce "
                             "(their run metadata is kept under merged_runs)")


FAULT_CLASSES = ("kill", "sfm-kill", "disk", "writers", "inputs", "fuzz")


# ============================================================================================ helpers
def _fresh(path: Path, src: Path | None = None) -> Path:
    """Remove ``path`` and its SQLite / lock / log side files; copy ``src`` there when given."""
    for suffix in ("", "-wal", "-shm", "-journal", ".lock", ".guidedmatch.jsonl", ".retrieval.npz",
                   ".expansion.json"):
        p = path.with_name(path.name + suffix)
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    if src is not None:
        shutil.copy(src, path)
    return path


#: the kill trials' runs of ``guidedmatch colmap``: backend name -> extra arguments (the retrieval run has the
#: retrieval stage (vocabulary + shortlist), the shortlist's pairs and the expansion rounds to be killed in)
KILL_BACKENDS = {"in-process": ["--workers", "0"], "dask": ["--workers", "2"],
                 "in-process, retrieval:4 + expansion": ["--workers", "0", "--pairs", "retrieval:4"]}


def _colmap_args(db: Path, backend: str) -> list:
    return ["colmap", db, "--no-progress", *KILL_BACKENDS[backend]]


def _skipped(text: str) -> int | None:
    """Pairs a rerun skipped as already done: the one summary line, or the sum over a staged run's stages
    (shortlist, expansion rounds)."""
    parsed = parse_skipped(text)
    if parsed is not None:
        return parsed[1]
    stages = re.findall(r"(\d+) matched, (\d+) skipped", text)
    return sum(int(b) for _, b in stages) if stages else None


def _names_path(text: str, path) -> bool:
    return str(path) in text or Path(path).name in text


# ============================================================================================ kill -9
def _log_lines(db: Path, n: int):
    """A ``kill_when`` trigger: the run's per-pair log (beside the database) has at least ``n`` lines."""
    log = db.with_name(db.name + ".guidedmatch.jsonl")

    def ready() -> bool:
        try:
            with open(log, "rb") as fh:
                return fh.read().count(b"\n") >= n
        except OSError:
            return False
    return ready


def kill_colmap(coll: dict, work: Path, backend: str, trials: int, rng: np.random.Generator, *,
                after_pairs=None) -> Row:
    """``kill -9`` of ``guidedmatch colmap`` at uniform random moments of its run, then a rerun.
    ``after_pairs``: per trial, kill when the run's log has that many pair lines instead (a kill mid-matching
    whatever the machine's speed; the tests use it)."""
    row = Row(f"kill -9: guidedmatch colmap ({backend})")
    if after_pairs is None or "ref" not in coll:
        ref_db = _fresh(work / f"ref-{backend}.db", coll["db"])
        ref_run, _ = run_and_kill(_colmap_args(ref_db, backend), float("inf"))
        if ref_run.rc != 0:
            raise RuntimeError(f"the uninterrupted run failed: {ref_run.tail()}")
        ref = db_state(ref_db)
        duration = ref_run.wall_s
        row.notes.append(f"uninterrupted run {duration:.2f} s wall, {len(ref['geometries'])} pairs; kill times "
                         f"uniform in [0, {duration:.2f}] s")
    else:  # the tests: killed after a number of logged pairs, compared with the given uninterrupted tables
        ref, duration = coll["ref"], float("inf")
    orphans = 0
    for k in range(trials):
        t = float(rng.uniform(0.0, duration)) if after_pairs is None else float("inf")
        db = _fresh(work / f"kill-{backend}.db", coll["db"])
        trigger = None if after_pairs is None else _log_lines(db, after_pairs[k])
        run, info = run_and_kill(_colmap_args(db, backend), t, kill_when=trigger)
        after = db_state(db)
        committed = set(after["geometries"])
        broken = compare_db(after, ref, only=committed, pending_pass="state")
        if partial_rows(after):
            broken.append(f"{partial_rows(after)} half-stored pairs")
        rerun = run_cli(_colmap_args(db, backend))
        final = db_state(db)
        diffs = compare_db(final, ref)
        parsed = _skipped(rerun.stdout)
        skipped = parsed or 0
        lost = max(0, len(committed) - skipped)
        orphans += bool(info["orphans"])
        ok = rerun.rc == 0 and not diffs and not broken and lost == 0 and parsed is not None
        t = t if np.isfinite(t) else run.wall_s
        row.add(ok, lost=lost, corrupt=bool(broken or diffs), bug=rerun.bug or run.bug, kill_at_s=round(t, 3),
                killed=info["killed"], committed_before=len(committed), rerun_rc=rerun.rc, rerun_skipped=skipped,
                after_kill=broken, after_rerun=diffs, orphans=len(info["orphans"]),
                rerun_tail="" if ok else rerun.tail(), killed_run_traceback=run.bug_text(),
                rerun_traceback=rerun.bug_text())
        print(f"  {row.fault} {k + 1}/{trials}: kill at {t:.2f} s, {len(committed)} pairs stored, rerun rc "
              f"{rerun.rc} skipped {skipped}{'' if ok else ' FAILED'}", flush=True)
    if orphans:
        row.notes.append(f"{orphans} of {trials} kills left processes of the run alive 3 s later (killed by the "
                         "bench)")
    return row


def _sfm_args(images: Path, out: Path) -> list:
    return ["sfm", images, out, "--workers", "0", "--max-features", "2000", "--threads", "2"]


def _sfm_report(out: Path) -> dict | None:
    import json

    try:
        return json.loads((out / "report.json").read_text())
    except (OSError, ValueError):
        return None


def _model_ok(path: Path) -> int | None:
    """Registered images of the model at ``path`` (None when it cannot be read)."""
    import pycolmap

    try:
        return int(pycolmap.Reconstruction(str(path)).num_reg_images())
    except Exception:  # noqa: BLE001 - anything unreadable
        return None


def kill_sfm(coll: dict, work: Path, per_stage: int, rng: np.random.Generator) -> list[Row]:
    """``kill -9`` of ``guidedmatch sfm`` inside each stage, then a rerun."""
    import re

    ref_out = work / "sfm-ref"
    shutil.rmtree(ref_out, ignore_errors=True)
    markers = [m for _, m in SFM_STAGES] + [SFM_END]
    ref_run, _ = run_and_kill(_sfm_args(coll["images"], ref_out), float("inf"), stage_markers=markers)
    if ref_run.rc != 0 or len(ref_run.stage_times) != len(markers):
        raise RuntimeError(f"the uninterrupted sfm run failed: {ref_run.tail()}")
    ref = db_state(ref_out / "database.db")
    bounds = [ref_run.stage_times[m] for m in markers]
    rows = []
    for s, (stage, _) in enumerate(SFM_STAGES):
        lo, hi = bounds[s], bounds[s + 1]
        row = Row(f"kill -9: guidedmatch sfm, {stage}")
        row.notes.append(f"stage window of the uninterrupted run {lo:.2f}-{hi:.2f} s (of {ref_run.wall_s:.2f} s)")
        for k in range(per_stage):
            t = float(rng.uniform(lo, hi))
            out = work / f"sfm-kill-{stage}-{k}"
            shutil.rmtree(out, ignore_errors=True)
            run, info = run_and_kill(_sfm_args(coll["images"], out), t, stage_markers=markers)
            after = db_state(out / "database.db")
            have_db = after["error"] != "missing"
            extracted = sum(1 for kp, d in after["features"].values() if kp is not None and d is not None)
            committed = set(after["geometries"])
            broken = (compare_db(after, ref, only=committed, skip=reordered_pairs(after, ref), pending_pass="state")
                      if have_db else [])
            if have_db and after["integrity"] not in (None, "ok"):
                broken.append("integrity")
            rerun = run_cli(_sfm_args(coll["images"], out))
            m = re.search(r"(\d+) image\(s\) to extract, (\d+) reused", rerun.stderr)
            reused = int(m.group(2)) if m else 0
            rep = _sfm_report(out) or {}
            coll_rep = rep.get("stages", {}).get("matching", {}).get("collection", {})
            skipped = int(coll_rep.get("skipped", 0))
            final = db_state(out / "database.db")
            # pycolmap numbers the images in the order its threads finish them: a pair numbered the other way
            # round is matched in the other direction (the matcher is not symmetric), in any two runs
            reordered = reordered_pairs(final, ref)
            diffs = compare_db(final, ref, features=True, skip=reordered)
            if have_db:  # what was stored before the kill is what the rerun kept
                diffs += [f"{d} (vs the state after the kill)" for d in
                          compare_db(final, after, only=committed, pending_pass="ref")]
                lost_imgs = [n for n, f in after["features"].items()
                             if None not in f and final["features"].get(n) != f]
                if lost_imgs:
                    diffs.append(f"features of {len(lost_imgs)} images extracted before the kill changed")
            reg = _model_ok(out / "sparse" / "0")
            lost = max(0, extracted - reused) + max(0, len(committed) - skipped)
            ok = rerun.rc == 0 and not diffs and not broken and lost == 0 and reg is not None
            row.add(ok, lost=lost, corrupt=bool(broken or diffs), bug=rerun.bug or run.bug, kill_at_s=round(t, 3),
                    killed=info["killed"], images_extracted_before=extracted, pairs_stored_before=len(committed),
                    rerun_rc=rerun.rc, rerun_images_reused=reused, rerun_pairs_skipped=skipped,
                    registered=reg, registered_uninterrupted=_model_ok(ref_out / "sparse" / "0"),
                    pairs_numbered_otherwise=len(reordered),
                    after_kill=broken, after_rerun=diffs, rerun_tail="" if ok else rerun.tail())
            print(f"  {row.fault} {k + 1}/{per_stage}: kill at {t:.2f} s ({extracted} images, {len(committed)} "
                  f"pairs stored), rerun rc {rerun.rc}{'' if ok else ' FAILED: ' + '; '.join(broken + diffs)}",
                  flush=True)
            if ok:  # a failed trial's project stays in the work folder for a look
                shutil.rmtree(out, ignore_errors=True)
        n_re = [d["pairs_numbered_otherwise"] for d in row.details]
        if any(n_re):
            row.notes.append(f"{sum(1 for n in n_re if n)} of {len(n_re)} reruns numbered some images otherwise than "
                             f"the uninterrupted run ({max(n_re)} pairs at most): pycolmap's extraction numbers "
                             "images in the order its threads finish, such a pair is matched in the other direction "
                             "(different matches, in any two runs); their content is compared with the state after "
                             "the kill only")
        rows.append(row)
    return rows


# ============================================================================================ disk full
def _expect_exit2(run: Run, path) -> list[str]:
    problems = []
    if run.rc != 2:
        problems.append(f"exit {run.rc}, not 2")
    if not _names_path(run.stderr, path):
        problems.append(f"message does not name {Path(path).name}")
    return problems


def disk_full_colmap(coll: dict, folder: Path, ref: dict, size: int, *, log: bool = True,
                     grown: int = 0) -> tuple[bool, dict]:
    """``guidedmatch colmap`` on a copy of the collection's database in a ``size``-byte filesystem: exit 0, or
    exit 2 naming the database with only complete pairs stored; then the rerun with space gives the uninterrupted
    run's tables (``ref``) without redoing a stored pair. Returns ``(survived, details for Row.add)``."""
    with SmallFS(folder, size) as fs:
        db = _fresh(fs.folder / "database.db", coll["db"])
        args = _colmap_args(db, "in-process") + ([] if log else ["--log", "none"])
        run = run_cli(args, preexec_fn=fs.preexec())
        after = db_state(db)
        committed = set(after["geometries"])
        broken = (compare_db(after, ref, only=committed, pending_pass="state")
                  + ([f"{partial_rows(after)} half-stored pairs"] if partial_rows(after) else []))
        problems = _expect_exit2(run, db) if run.rc != 0 else []
        fs.resize(max(grown, size) * 3 + (16 << 20))
        if fs.method == "rlimit":
            fs.size = 1 << 40
        rerun = run_cli(args, preexec_fn=fs.preexec())
        final = db_state(db)
        diffs = compare_db(final, ref)
        parsed = parse_skipped(rerun.stdout)
        lost = max(0, len(committed) - (parsed[1] if parsed else 0))
        ok = not problems and not broken and not diffs and rerun.rc == 0 and lost == 0
        return ok, dict(lost=lost, corrupt=bool(broken or diffs), bug=run.bug or rerun.bug,
                        case=f"colmap database ({'with' if log else 'no'} log), {size // 1024} KiB filesystem",
                        method=fs.method, rc=run.rc, message=run.tail(), problems=problems, after_fault=broken,
                        pairs_stored=len(committed), rerun_rc=rerun.rc, after_rerun=diffs)


def disk_full(coll: dict, work: Path, ref_h5: dict | None = None) -> Row:
    """The database, ``matches.h5``, the sfm database, model and report on a filesystem that fills up."""
    row = Row("disk full")
    base_size = coll["db"].stat().st_size
    ref_db = _fresh(work / "ref-disk.db", coll["db"])
    run_cli(_colmap_args(ref_db, "in-process"))
    ref = db_state(ref_db)
    grown = ref_db.stat().st_size + sum(p.stat().st_size for p in ref_db.parent.glob(ref_db.name + "-wal"))
    methods = set()

    # -- 1. guidedmatch colmap: the database (and its log beside it) fill the disk
    from ..collection.sinks import SPACE_MARGIN

    # room for the sink's margin plus a few hundred KiB (each commit appends a few 4 KiB pages to the WAL):
    # refused mid-run; without the margin: refused at the start
    for extra, margin, log in ((256 << 10, True, True), (1 << 20, True, False), (1 << 20, False, True)):
        size = base_size + (SPACE_MARGIN if margin else 0) + extra
        ok, detail = disk_full_colmap(coll, work / "fs-db", ref, size, log=log, grown=grown)
        methods.add(detail["method"])
        row.add(ok, **detail)

    # -- 2. guidedmatch hloc: matches.h5 (segments and the merge) fill the disk
    if ref_h5 is not None:
        from .faults_inputs import h5_pairs

        for frac in (0.3, 0.8):
            size = max(int(frac * ref_h5["bytes"]), 4096)
            with SmallFS(work / "fs-h5", size) as fs:
                methods.add(fs.method)
                out = fs.folder / "matches.h5"
                args = ["hloc", ref_h5["features"], "exhaustive", out, "--workers", "0", "--no-progress",
                        "--log", "none"]
                run = run_cli(args, preexec_fn=fs.preexec())
                problems = _expect_exit2(run, out) if run.rc != 0 else []
                broken = []
                for f in [out, *sorted((fs.folder / "matches.h5.parts").glob("*.h5"))]:
                    if f.exists() and h5_pairs(f) is None:
                        broken.append(f"{f.name} is not a readable HDF5 file")
                fs.resize(ref_h5["bytes"] * 4 + (8 << 20))
                rerun = run_cli(args, preexec_fn=fs.preexec())
                got = h5_pairs(out) if out.exists() else None
                diffs = [] if got == ref_h5["pairs"] else ["matches.h5 differs from the uninterrupted run"]
                ok = not problems and not broken and not diffs and rerun.rc == 0
                row.add(ok, corrupt=bool(broken or diffs), bug=run.bug or rerun.bug,
                        case=f"hloc matches.h5, {size // 1024} KiB filesystem", method=fs.method, rc=run.rc,
                        message=run.tail(), problems=problems, after_fault=broken, rerun_rc=rerun.rc,
                        after_rerun=diffs)

    # -- 3. guidedmatch sfm: the database during extraction; the model and the report of a rerun
    ref_out = work / "sfm-ref"
    if (ref_out / "report.json").exists():
        ext_db = sum(len(kp or b"") + len(d or b"") for kp, d in db_state(ref_out / "database.db")["features"]
                     .values())
        with SmallFS(work / "fs-sfm", max(ext_db // 2, 1 << 16)) as fs:
            methods.add(fs.method)
            out = fs.folder / "project"
            args = _sfm_args(coll["images"], out)
            run = run_cli(args, preexec_fn=fs.preexec())
            problems = _expect_exit2(run, out / "database.db") if run.rc != 0 else ["exit 0 on a full disk"]
            after = db_state(out / "database.db")
            broken = [] if after["error"] == "missing" or after["integrity"] == "ok" else ["database integrity"]
            fs.resize(64 << 20)
            rerun = run_cli(args, preexec_fn=fs.preexec())
            ok = not problems and not broken and rerun.rc == 0 and _model_ok(out / "sparse" / "0") is not None
            row.add(ok, corrupt=bool(broken), bug=run.bug or rerun.bug,
                    case=f"sfm: the database during extraction, {max(ext_db // 2, 1 << 16) // 1024} KiB filesystem",
                    method=fs.method, rc=run.rc, message=run.tail(), problems=problems, after_fault=broken,
                    rerun_rc=rerun.rc)
        outputs = sum(p.stat().st_size for p in (ref_out / "sparse" / "0").iterdir()) + sum(
            (ref_out / n).stat().st_size for n in ("report.json", "report.md", "reconstruction.png"))
        for frac in (0.1, 0.5, 0.9):
            leave = int(frac * outputs)
            with SmallFS(work / "fs-map", 64 << 20) as fs:
                methods.add(fs.method)
                out = fs.folder / "project"
                shutil.copytree(ref_out, out)
                if fs.method == "tmpfs":
                    filler = fill(fs.folder, leave)
                else:  # a per-file limit: the largest output file is refused
                    filler = None
                    fs.size = max(leave // 4, 4096)
                run = run_cli(_sfm_args(coll["images"], out), preexec_fn=fs.preexec())
                named = next((p for p in ("sparse", "report.json", "report.md", "reconstruction.png", "database.db")
                              if p in run.stderr), None)
                problems = [] if run.rc == 0 else _expect_exit2(run, out)
                if run.rc == 0:
                    problems.append("exit 0 with too little space (the outputs fit?)")
                broken = []
                if _model_ok(out / "sparse" / "0") is None:
                    broken.append("sparse/0 unreadable")
                if _sfm_report(out) is None:
                    broken.append("report.json unreadable")
                if filler is not None:
                    filler.unlink()
                fs.size = 64 << 20
                rerun = run_cli(_sfm_args(coll["images"], out), preexec_fn=fs.preexec())
                ok = (not problems or problems == ["exit 0 with too little space (the outputs fit?)"]) and \
                    not broken and rerun.rc == 0
                row.add(ok, corrupt=bool(broken), bug=run.bug or rerun.bug,
                        case=f"sfm rerun: model / report with {leave // 1024} KiB free (of {outputs // 1024} KiB "
                             "written)", method=fs.method, rc=run.rc, message=run.tail(), path_named=named,
                        problems=problems, after_fault=broken, rerun_rc=rerun.rc)
    row.notes.append("filesystem: " + ", ".join(sorted(methods)) +
                     (" (RLIMIT_FSIZE: mounting a tmpfs is not permitted here)" if "rlimit" in methods else ""))
    return row


# ============================================================================================ two writers
def _concurrent(argvs, offsets, preexec=None) -> list[Run]:
    """Start each argv at its offset (s) and wait for all."""
    runs: list = [None] * len(argvs)
    t0 = time.perf_counter()

    def go(i: int) -> None:
        time.sleep(max(0.0, offsets[i] - (time.perf_counter() - t0)))
        runs[i] = run_cli(argvs[i])

    threads = [threading.Thread(target=go, args=(i,)) for i in range(len(argvs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return runs


def _refused_clearly(run: Run) -> bool:
    return run.rc == 2 and ("being written by another process" in run.stderr or "another process" in run.stderr)


def two_writers(coll: dict, work: Path, trials: int, rng: np.random.Generator, ref_h5: dict | None) -> Row:
    row = Row("two writers at once")
    ref_db = _fresh(work / "ref-writers.db", coll["db"])
    ref_run = run_cli(_colmap_args(ref_db, "in-process"))
    ref = db_state(ref_db)
    for k in range(trials):
        db = _fresh(work / "writers.db", coll["db"])
        backend = ("in-process", "dask")[k % 2]
        dt = float(rng.uniform(0.0, 0.8 * ref_run.wall_s))
        runs = _concurrent([_colmap_args(db, backend), _colmap_args(db, "in-process")], [0.0, dt])
        final = db_state(db)
        diffs = compare_db(final, ref)
        outcome = [("ok" if r.rc == 0 else "refused" if _refused_clearly(r) else f"exit {r.rc}") for r in runs]
        ok = all(o in ("ok", "refused") for o in outcome) and "ok" in outcome and not diffs
        row.add(ok, corrupt=bool(diffs), bug=any(r.bug for r in runs), case=f"colmap ({backend}) + colmap "
                f"{dt:.2f} s later", outcomes=outcome, messages=[r.tail() for r in runs if r.rc], after=diffs)
    if ref_h5 is not None:
        from .faults_inputs import h5_pairs

        for dt in (0.0, 0.5):
            out = work / "writers.h5"
            for p in (out, out.with_name(out.name + ".lock")):
                p.unlink(missing_ok=True)
            shutil.rmtree(out.with_name(out.name + ".parts"), ignore_errors=True)
            argv = ["hloc", ref_h5["features"], "exhaustive", out, "--workers", "0", "--no-progress", "--log", "none"]
            runs = _concurrent([argv, argv], [0.0, dt])
            got = h5_pairs(out) if out.exists() else None
            diffs = [] if got == ref_h5["pairs"] else ["matches.h5 differs from the uninterrupted run"]
            outcome = [("ok" if r.rc == 0 else "refused" if _refused_clearly(r) else f"exit {r.rc}") for r in runs]
            ok = all(o in ("ok", "refused") for o in outcome) and "ok" in outcome and not diffs
            row.add(ok, corrupt=bool(diffs), bug=any(r.bug for r in runs), case=f"hloc + hloc {dt:.2f} s later",
                    outcomes=outcome, messages=[r.tail() for r in runs if r.rc], after=diffs)
    # a foreign SQLite writer (COLMAP's GUI, a script) holds a write transaction while guidedmatch starts
    for hold in (1.0, 6.0):
        db = _fresh(work / "foreign.db", coll["db"])
        code = ("import sqlite3, sys, time; c = sqlite3.connect(sys.argv[1], isolation_level=None); "
                "c.execute('BEGIN IMMEDIATE'); print('held', flush=True); time.sleep(float(sys.argv[2])); "
                "c.execute('ROLLBACK')")
        holder = subprocess.Popen([sys.executable, "-c", code, str(db), str(hold)], stdout=subprocess.PIPE, text=True)
        holder.stdout.readline()
        run = run_cli(_colmap_args(db, "in-process"))
        holder.wait()
        if run.rc != 0:
            rerun = run_cli(_colmap_args(db, "in-process"))
        else:
            rerun = run
        diffs = compare_db(db_state(db), ref)
        clear = run.rc == 0 or (run.rc == 2 and _names_path(run.stderr, db))
        ok = clear and rerun.rc == 0 and not diffs
        row.add(ok, corrupt=bool(diffs), bug=run.bug or rerun.bug, case=f"a foreign SQLite write transaction held "
                f"{hold:g} s", outcomes=[f"exit {run.rc}"], messages=[run.tail()] if run.rc else [], after=diffs)
    # two sfm runs on one project folder
    out = work / "sfm-writers"
    shutil.rmtree(out, ignore_errors=True)
    runs = _concurrent([_sfm_args(coll["images"], out)] * 2, [0.0, 2.0])
    outcome = [("ok" if r.rc == 0 else "refused" if _refused_clearly(r) else f"exit {r.rc}") for r in runs]
    final = db_state(out / "database.db")
    ref_sfm = work / "sfm-ref" / "database.db"
    if ref_sfm.exists():
        ref_state = db_state(ref_sfm)
        diffs = compare_db(final, ref_state, features=True, skip=reordered_pairs(final, ref_state))
    else:
        diffs = []
    ok = all(o in ("ok", "refused") for o in outcome) and "ok" in outcome and not diffs and \
        _model_ok(out / "sparse" / "0") is not None
    row.add(ok, corrupt=bool(diffs), bug=any(r.bug for r in runs), case="sfm + sfm 2 s later, one project folder",
            outcomes=outcome, messages=[r.tail() for r in runs if r.rc], after=diffs)
    return row


# ============================================================================================ main
def _details_markdown(rows) -> str:
    lines = []
    for r in rows:
        lines += ["", f"### {r.fault}", ""]
        lines += [f"- {n}" for n in r.notes]
        failed = [d for d in r.details if not d.get("ok", True)]
        cases = [d for d in r.details if "case" in d]
        commands = [d for d in r.details if "command" in d]
        if commands:  # the fuzzer: one line per subcommand
            lines += ["", "| subcommand | argument lists | failed | stopped after 30 s | exit codes |",
                      "|---|---:|---:|---:|---|"]
            lines += [f"| {d['command']} | {d['examples']} | {d['failed']} | {d['timeouts']} | "
                      f"{', '.join(d['exit_codes'])} |" for d in commands]
        elif cases:
            lines += ["", "| case | result | exit | message |", "|---|---|---:|---|"]
            for d in cases:
                msg = str(d.get("message") or "; ".join(d.get("messages", [])) or "").replace("\n", " / ")
                msg = msg.replace("|", "\\|")[:220]
                res = "ok" if d["ok"] else "FAILED: " + "; ".join(map(str, d.get("problems", []) + d.get("after_fault", [])
                                                                    + d.get("after", []) + d.get("after_rerun", [])
                                                                    + d.get("after_kill", [])))[:200]
                rc = d.get("rc", "/".join(d.get("outcomes", [])))
                lines.append(f"| {d['case']} | {res} | {rc} | {msg} |")
        elif failed:
            lines += ["", f"{len(failed)} failed trial(s):"]
            for d in failed[:8]:
                lines.append(f"- kill at {d.get('kill_at_s')} s: rerun exit {d.get('rerun_rc')}; "
                             + "; ".join(map(str, d.get("after_kill", []) + d.get("after_rerun", [])))
                             + (f"; {d.get('rerun_tail', '')}".replace("\n", " / ") if d.get("rerun_tail") else ""))
    return "\n".join(lines)


def main(args) -> int:
    import os
    import tempfile

    from ..features import atomic_write_text, writable_folder
    from .meta import run_metadata, write_json

    out = writable_folder(args.out)
    out.mkdir(parents=True, exist_ok=True)
    quick = bool(getattr(args, "quick", False))
    seed = int(getattr(args, "seed", 0) or 0)
    kills = getattr(args, "kill_trials", None) or (4 if quick else 30)
    sfm_kills = getattr(args, "sfm_kill_trials", None) or (1 if quick else 4)
    fuzz_n = getattr(args, "fuzz_examples", None) or (25 if quick else 150)
    which = [w.strip() for w in (getattr(args, "faults", None) or ",".join(FAULT_CLASSES)).split(",") if w.strip()]
    unknown = set(which) - set(FAULT_CLASSES)
    from ..errors import ConfigError

    if unknown:
        raise ConfigError(f"--faults: unknown fault class(es) {sorted(unknown)}; choose from {FAULT_CLASSES}")
    chosen = getattr(args, "kill_backends", None)
    backends = [b.strip() for b in chosen.split("|")] if chosen else list(KILL_BACKENDS)
    if set(backends) - set(KILL_BACKENDS):
        raise ConfigError(f"--kill-backends: unknown {sorted(set(backends) - set(KILL_BACKENDS))}; choose from "
                          f"{list(KILL_BACKENDS)}")
    meta = run_metadata(seed)
    t_start = time.perf_counter()
    rng = np.random.default_rng(seed)
    own_work = getattr(args, "work", None) is None
    work = Path(tempfile.mkdtemp(prefix="guidedmatch-faults-")) if own_work else Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    errors: list[str] = []
    state = {"coll": None}
    kept: list[Row] = []
    if getattr(args, "merge_faults", False) and (out / "faults.json").exists():
        import json

        old = json.loads((out / "faults.json").read_text())
        kept = [_row_from_dict(r) for r in old.get("rows", [])]
        meta["merged_runs"] = [old.get("meta")] + old.get("meta", {}).get("merged_runs", [])

    def write(final: bool) -> None:
        """faults.md + faults.json with the rows so far (rewritten after each class: a crash keeps the rest)."""
        wall = time.perf_counter() - t_start
        mine = {r.fault for r in rows}
        all_rows = [r for r in kept if r.fault not in mine] + rows
        meta["load_average_end"] = os.getloadavg()[0]
        n_img = len(state["coll"]["names"]) if state["coll"] else 0
        md = ["# Fault injection", "",
              "`python -m guidedmatch.evaluation.bench_faults --out benchmarks/results` (`guidedmatch bench faults`): "
              f"{n_img} rendered 800x600 views, 2000 SIFT features each; every trial a fresh `guidedmatch` process. "
              "Survived = the output is correct after the fault and after a rerun (see "
              "`guidedmatch.evaluation.bench_faults` for the exact checks per class).", "",
              table_markdown(all_rows), "",
              f"Run: {wall / 60:.1f} min{'' if final else ' (in progress)'}, commit {meta.get('git_commit')}"
              f"{' (dirty)' if meta.get('git_dirty') else ''}, {cpu_label(meta)}, load average "
              f"{meta.get('load_average'):.2f} at the start, {meta['load_average_end']:.2f} at the end "
              f"(other jobs shared the 2 cores); seed {seed}."
              + (f" Rows of {len(meta['merged_runs'])} earlier run(s) kept (--merge-faults; their metadata in "
                 "faults.json, merged_runs)." if kept else "")]
        md += [f"\nBench error: {e}" for e in errors]
        md += [_details_markdown(all_rows), ""]
        atomic_write_text(out / "faults.md", "\n".join(md))
        write_json(out / "faults.json", {"meta": meta, "wall_s": wall, "complete": final, "kill_trials": kills,
                                         "sfm_kill_trials_per_stage": sfm_kills, "fuzz_examples": fuzz_n,
                                         "errors": errors, "rows": [r.to_dict() for r in all_rows]})

    def step(name: str, fn) -> None:
        try:
            got = fn()
        except Exception as exc:  # noqa: BLE001 - one class failing must not lose the others' results
            import traceback

            errors.append(f"{name}: {type(exc).__name__}: {exc}")
            print(traceback.format_exc(), file=sys.stderr, flush=True)
            got = []
        rows.extend(got if isinstance(got, list) else [got])
        write(False)

    try:
        coll = make_collection(work / "collection", n_images=14, size=(800, 600), max_features=2000, seed=seed)
        state["coll"] = coll
        from .faults_inputs import corrupt_inputs, fuzz_arguments, make_h5_reference

        ref_h5 = make_h5_reference(coll, work) if {"disk", "writers"} & set(which) else None
        print(f"faults bench: {len(coll['names'])} images in {work}", flush=True)
        if "kill" in which:
            for backend in backends:
                step(f"kill {backend}", lambda b=backend: kill_colmap(coll, work, b, kills, rng))
        if {"sfm-kill", "disk", "writers"} & set(which):
            step("sfm kill", lambda: [r for r in kill_sfm(coll, work, sfm_kills if "sfm-kill" in which else 0, rng)
                                      if r.trials])
        if "disk" in which:
            step("disk", lambda: disk_full(coll, work, ref_h5))
        if "writers" in which:
            step("writers", lambda: two_writers(coll, work, 4 if quick else 8, rng, ref_h5))
        if "inputs" in which:
            step("inputs", lambda: corrupt_inputs(work / "inputs"))
        if "fuzz" in which:
            step("fuzz", lambda: fuzz_arguments(work / "fuzz", fuzz_n, seed))
    finally:
        if own_work:
            shutil.rmtree(work, ignore_errors=True)
    write(True)
    print(table_markdown(rows))
    print(f"wrote {out / 'faults.md'} and {out / 'faults.json'}")
    return 0


def _row_from_dict(d: dict) -> Row:
    return Row(d["fault"], d["trials"], d["survived"], d["finished_work_lost"], d["corrupt_outputs"], d["tracebacks"],
               list(d.get("notes", [])), list(d.get("details", [])))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.bench_faults", description=__doc__.split("\n")[0])
    p.add_argument("--out", default="benchmarks/results", help="output folder (default benchmarks/results)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="a few trials per class (minutes)")
    add_arguments(p)
    return p


if __name__ == "__main__":  # pragma: no cover
    from ..errors import GuidedMatchError

    try:
        sys.exit(main(build_parser().parse_args()))
    except GuidedMatchError as exc:
        print(f"bench_faults: error: {exc}", file=sys.stderr)
        sys.exit(2)
