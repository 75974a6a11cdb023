"""A/B wall time of ``guidedmatch colmap DB --pairs exhaustive`` for two versions of the code, in alternating fresh
processes (the machine's noise is +-0.1-0.2 s at 2 s, so one run of each says little; medians of 10 alternating
runs move by ~0.03 s).

Each version is a source tree: ``HEAD`` (or any commit) is exported with ``git archive`` into a temporary folder
and byte-compiled; ``.`` is the working tree. Every run gets a fresh copy of the database.

    python tools/ab_collection.py /tmp/lead_coll/default.db --a HEAD --b . --runs 10
    python tools/ab_collection.py DB --a HEAD~1 --b HEAD --runs 10
    python tools/ab_collection.py DB --a . --b . --a-options="--workers 1" --b-options="--workers 2" --runs 3
    python tools/ab_collection.py DB --a . --b . --b-env NUMPY_MADVISE_HUGEPAGE=0 --runs 10

Prints one line per run and the median / min / max of each version. Run it on an idle machine. The first run of
each version compiles Numba's kernels into that tree's cache and is not counted.
"""
from __future__ import annotations

import argparse
import compileall
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def source_tree(rev: str, tmp: Path) -> Path:
    """The ``src`` folder of ``rev`` (``.`` = the working tree), byte-compiled."""
    if rev == ".":
        src = ROOT / "src"
    else:
        dest = tmp
        dest.mkdir(parents=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "src"], check=True, capture_output=True)
        subprocess.run(["tar", "x", "-C", str(dest)], input=archive.stdout, check=True)
        src = dest / "src"
    compileall.compile_dir(str(src), quiet=1)
    return src


def one_run(src: Path, db: Path, work: Path, extra: list[str], more_env: dict | None = None) -> dict:
    """One fresh ``guidedmatch colmap`` process of the tree ``src`` on a fresh copy of ``db``, timed as the collection
    benchmark times its runs (``bench_collection._timed``)."""
    from guidedmatch.evaluation.bench_collection import _timed

    copy = work / "ab.db"
    for p in work.glob("ab.db*"):
        p.unlink()
    shutil.copy(db, copy)
    log = work / "ab.jsonl"
    if log.exists():
        log.unlink()
    env = {**os.environ, **(more_env or {}), "PYTHONPATH": str(src)}
    r = _timed([sys.executable, "-m", "guidedmatch.cli", "colmap", str(copy), "--pairs", "exhaustive", "--no-progress",
                "--log", str(log), *extra], log, env=env)
    return dict(wall=r["wall_s"], first=min(s[1] for s in r["spans"]), inliers=r["summary"]["inliers"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("database", type=Path, help="COLMAP database with features (copied for every run)")
    p.add_argument("--a", default="HEAD", help="version A: a git revision or '.' (working tree); default HEAD")
    p.add_argument("--b", default=".", help="version B; default the working tree")
    p.add_argument("--runs", type=int, default=10, help="runs of each version (default 10)")
    p.add_argument("--a-options", default="", help="more options of guidedmatch colmap for A, e.g. '--workers 1'")
    p.add_argument("--b-options", default="", help="the same for B")
    p.add_argument("--a-env", action="append", default=[], metavar="KEY=VALUE",
                   help="an environment variable of A's processes (repeatable), e.g. NUMBA_NUM_THREADS=1")
    p.add_argument("--b-env", action="append", default=[], metavar="KEY=VALUE", help="the same for B")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="gm-ab-") as tmp:
        tmp = Path(tmp)
        trees = {"A": source_tree(a.a, tmp / "A"), "B": source_tree(a.b, tmp / "B")}
        opts = {"A": a.a_options.split(), "B": a.b_options.split()}
        envs = {"A": dict(e.split("=", 1) for e in a.a_env), "B": dict(e.split("=", 1) for e in a.b_env)}
        work = tmp / "work"
        work.mkdir()
        for tag, src in trees.items():  # Numba compiles each tree's kernels once: not counted
            one_run(src, a.database, work, opts[tag], envs[tag])
        walls: dict[str, list[float]] = {"A": [], "B": []}
        for i in range(a.runs):
            for tag, src in trees.items():
                r = one_run(src, a.database, work, opts[tag], envs[tag])
                walls[tag].append(r["wall"])
                print(f"run {i + 1} {tag}: wall {r['wall']:.3f} s, first pair at {r['first']:.2f} s, "
                      f"inliers {r['inliers']}", flush=True)
    for tag, rev, o in (("A", a.a, " ".join([a.a_options, *a.a_env]).strip()),
                        ("B", a.b, " ".join([a.b_options, *a.b_env]).strip())):
        w = walls[tag]
        print(f"{tag} ({rev}{' ' + o if o else ''}): median {statistics.median(w):.3f} s, min {min(w):.3f}, max {max(w):.3f}, n {len(w)}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
