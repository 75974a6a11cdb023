"""Shared pieces of the fault-injection benchmark (:mod:`guidedmatch.evaluation.bench_faults`) and its tests:
running the CLI in a fresh process, a small rendered collection, reading a COLMAP database's match tables with
plain SQLite, a small filesystem (tmpfs, or ``RLIMIT_FSIZE`` where mounting is not permitted), and the row of
the faults table.
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: a fresh ``guidedmatch`` process (whatever module layout the CLI has: ``guidedmatch.cli.main``)
CLI = [sys.executable, "-c", "import sys; from guidedmatch.cli import main; sys.exit(main())"]
#: what a traceback or a bug looks like on stderr
BUG_MARKERS = ("Traceback (most recent call last)", "internal error")


@dataclass
class Run:
    """One finished (or killed) CLI process."""

    argv: list
    rc: int | None
    stdout: str
    stderr: str
    wall_s: float
    stage_times: dict = field(default_factory=dict)   # first stderr line starting with a marker -> seconds

    @property
    def bug(self) -> bool:
        """A traceback or an internal error on stderr."""
        return any(m in self.stderr for m in BUG_MARKERS)

    def bug_text(self, n: int = 1500) -> str:
        """The stderr from the first traceback / internal error on (empty when there is none)."""
        at = min((self.stderr.find(m) for m in BUG_MARKERS if m in self.stderr), default=-1)
        return "" if at < 0 else self.stderr[at:at + n]

    def tail(self, n: int = 300) -> str:
        text = (self.stderr.strip() or self.stdout.strip()).replace("\r", "\n")
        lines = [ln for ln in text.splitlines() if ln.strip() and "it/s]" not in ln and "%|" not in ln]
        return "\n".join(lines[-3:])[-n:]


def run_cli(args, *, timeout: float = 900, cwd=None, preexec_fn=None, env=None) -> Run:
    """Run ``guidedmatch ARGS`` in a fresh process and wait for it."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                           preexec_fn=preexec_fn, env=env)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as exc:
        rc, out, err = None, _text(exc.stdout), _text(exc.stderr) + f"\n[timeout after {timeout} s]"
    return Run(list(map(str, args)), rc, out, err, time.perf_counter() - t0)


def _text(b) -> str:
    if b is None:
        return ""
    return b.decode(errors="replace") if isinstance(b, bytes) else b


def session_pids(sid: int) -> list[int]:
    """Live processes of session ``sid`` (a process started with ``start_new_session``: its workers too)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if fields[0] != "Z" and int(fields[3]) == sid:   # state, ppid, pgrp, session
            out.append(int(d.name))
    return out


def run_and_kill(args, kill_at: float, *, stage_markers=(), timeout: float = 900, cwd=None,
                 kill_when=None) -> tuple[Run, dict]:
    """Start ``guidedmatch ARGS`` in a new session, ``kill -9`` its main process ``kill_at`` s after the start
    (``inf``: never) or as soon as ``kill_when()`` (polled every 10 ms) returns True, and report ``{"killed": bool, "orphans": [pids still alive 3 s after the kill]}`` -- the
    orphans (e.g. Dask worker processes) are then killed. ``stage_markers``: stderr line prefixes whose first
    arrival time is recorded in ``Run.stage_times``."""
    import threading

    t0 = time.perf_counter()
    proc = subprocess.Popen([*CLI, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=cwd, start_new_session=True, errors="replace")
    err_lines: list[str] = []
    out_chunks: list[str] = []
    stage_times: dict[str, float] = {}

    def read_err() -> None:
        for line in proc.stderr:
            err_lines.append(line)
            for m in stage_markers:
                if line.startswith(m) and m not in stage_times:
                    stage_times[m] = time.perf_counter() - t0

    def read_out() -> None:
        out_chunks.append(proc.stdout.read())

    readers = [threading.Thread(target=read_err, daemon=True), threading.Thread(target=read_out, daemon=True)]
    for r in readers:
        r.start()
    killed = False
    deadline = t0 + (kill_at if np.isfinite(kill_at) else timeout)
    triggered = False
    while proc.poll() is None and time.perf_counter() < deadline:
        if kill_when is not None and kill_when():
            triggered = True
            break
        time.sleep(0.01)
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        killed = bool(np.isfinite(kill_at)) or triggered
    rc = proc.wait()
    wall = time.perf_counter() - t0
    orphans: list[int] = []
    if killed:
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            orphans = session_pids(proc.pid)
            if not orphans:
                break
            time.sleep(0.2)
    left = session_pids(proc.pid)
    if left:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        end = time.monotonic() + 5.0
        while session_pids(proc.pid) and time.monotonic() < end:
            time.sleep(0.1)
    for r in readers:
        r.join(timeout=5)
    run = Run(list(map(str, args)), rc, "".join(out_chunks), "".join(err_lines), wall, stage_times)
    return run, {"killed": killed, "orphans": orphans}


# ---------------------------------------------------------------------------------------------- collection
def make_collection(work: Path, n_images: int = 14, size=(800, 600), max_features: int = 2000,
                    seed: int = 0) -> dict:
    """A rendered multi-view collection (``work/images``) and a COLMAP database of its SIFT features without
    matches (``work/base.db``). Returns ``{"images", "db", "names"}``."""
    from ..collection.sources import images_to_database
    from ..testing.multiview import make_multiview, write_views

    work.mkdir(parents=True, exist_ok=True)
    images, db = work / "images", work / "base.db"
    mv = make_multiview(n_images, tuple(size), seed=seed, isolated=False)
    if not db.exists():
        write_views(mv, images)
        tmp = work / "base.tmp.db"
        if tmp.exists():
            tmp.unlink()
        images_to_database(images, tmp, max_features=max_features, progress=False)
        os.replace(tmp, db)
    return {"images": images, "db": db, "names": list(mv.names)}


# ---------------------------------------------------------------------------------------------- database
_MAX_IMAGE_ID = 2147483647  # COLMAP: pair_id = image_id1 * 2147483647 + image_id2, image_id1 < image_id2


def _blob(b, dtype, cols: int) -> np.ndarray:
    return np.frombuffer(bytes(b or b""), dtype).reshape(-1, cols)


def db_state(path: Path) -> dict:
    """What is on disk in a COLMAP database, read with plain SQLite (no pycolmap), keyed by image names so that two
    runs that numbered the images differently compare equal: ``{"integrity", "matches": {(name1, name2): (M, 2)
    uint32}, "geometries": {(name1, name2): (config, inliers (K, 2), F (3, 3) or None, H or None)}, "features":
    {name: (keypoint bytes, descriptor bytes)}, "error"}``, pairs in name order (``name1 < name2``; columns
    swapped, F transposed and H inverted where COLMAP stored them the other way round). A database that cannot be
    read gives ``error``."""
    out = {"integrity": None, "matches": {}, "geometries": {}, "features": {}, "ids": {}, "error": None}
    if not Path(path).exists():
        out["error"] = "missing"
        return out
    try:
        con = sqlite3.connect(f"file:{path}?mode=rw", uri=True, timeout=30)
        try:
            out["integrity"] = "; ".join(r[0] for r in con.execute("PRAGMA integrity_check"))
            names = {int(i): n for i, n in con.execute("SELECT image_id, name FROM images")}
            out["ids"] = {n: i for i, n in names.items()}

            def key(pid: int):
                i2 = pid % _MAX_IMAGE_ID
                i1 = (pid - i2) // _MAX_IMAGE_ID
                a, b = names.get(i1, f"#{i1}"), names.get(i2, f"#{i2}")
                return ((a, b), False) if a <= b else ((b, a), True)

            for pid, data in con.execute("SELECT pair_id, data FROM matches"):
                k, swap = key(int(pid))
                m = _blob(data, np.uint32, 2)
                out["matches"][k] = m[:, ::-1].copy() if swap else m
            for pid, cfg, data, F, H in con.execute("SELECT pair_id, config, data, F, H FROM two_view_geometries"):
                k, swap = key(int(pid))
                m = _blob(data, np.uint32, 2)
                F = _blob(F, np.float64, 3) if F else None
                H = _blob(H, np.float64, 3) if H else None
                if swap:
                    m = m[:, ::-1].copy()
                    F = None if F is None else F.T
                    H = None if H is None or abs(np.linalg.det(H)) < 1e-300 else np.linalg.inv(H)
                out["geometries"][k] = (int(cfg), m, F, H)
            kps = {names.get(int(i), f"#{i}"): bytes(d or b"") for i, d in
                   con.execute("SELECT image_id, data FROM keypoints")}
            descs = {names.get(int(i), f"#{i}"): bytes(d or b"") for i, d in
                     con.execute("SELECT image_id, data FROM descriptors")}
            out["features"] = {n: (kps.get(n), descs.get(n)) for n in set(kps) | set(descs)}
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        out["error"] = str(exc)
    return out


def _same_matrix(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return bool(min(np.abs(a - b).max(), np.abs(a + b).max()) < 1e-9)


def _same_row(table: str, x, y, pending_pass: str | None = None) -> bool:
    """Rows equal; ``pending_pass`` "state" / "ref": a geometry whose inlier set is a superset of the other's is
    also accepted on that side (same configuration and matrices) -- the mapper's selection passes (tighten, cap)
    run after matching, so a kill between them leaves committed pairs whose inliers the rerun narrows."""
    if table == "matches":
        return x.shape == y.shape and bool(np.array_equal(x, y))
    same = x[0] == y[0] and _same_matrix(x[2], y[2]) and _same_matrix(x[3], y[3])
    if x[1].shape == y[1].shape and bool(np.array_equal(x[1], y[1])):
        return same
    if pending_pass is None:
        return False
    big, small = (x[1], y[1]) if pending_pass == "state" else (y[1], x[1])
    return same and set(map(tuple, np.asarray(small).tolist())) <= set(map(tuple, np.asarray(big).tolist()))


def reordered_pairs(state: dict, ref: dict) -> set:
    """Pairs whose two images are numbered in the other order than in ``ref`` (COLMAP stores a pair under the
    smaller image id first; the collection pair lists follow the database's image order, so such a pair was
    matched in the other direction -- the matcher is not symmetric)."""
    a, b = state.get("ids", {}), ref.get("ids", {})
    out = set()
    for k in set(state["geometries"]) | set(state["matches"]):
        n1, n2 = k
        if n1 in a and n2 in a and n1 in b and n2 in b and (a[n1] < a[n2]) != (b[n1] < b[n2]):
            out.add(k)
    return out


def compare_db(state: dict, ref: dict, *, only=None, features: bool = False, skip=(),
               pending_pass: str | None = None) -> list[str]:
    """Differences of ``state`` from ``ref`` in the match tables (pairs, matches, inlier sets, config, F, H up to
    scale); with ``only`` (pairs) just those pairs of ``state``, which must all be as in ``ref``; ``features``: also
    every image's keypoint and descriptor blobs; ``skip``: pairs whose content is not compared (their presence
    is); ``pending_pass`` ("state" / "ref"): that side may hold a superset of the other's inliers in a geometry
    (the state right after a kill, before the selection passes that follow matching ran on its pairs)."""
    diffs = []
    skip = set(skip)
    if state["error"]:
        return [f"unreadable: {state['error']}"]
    if state["integrity"] != "ok":
        diffs.append(f"integrity_check: {state['integrity'][:200]}")
    for table in ("matches", "geometries"):
        got, want = state[table], ref[table]
        keys = set(got) if only is None else set(got) & set(only)
        if only is None and set(got) != set(want):
            diffs.append(f"{table}: {len(set(got) - set(want))} extra, {len(set(want) - set(got))} missing pairs")
        bad = [k for k in (keys & set(want)) - skip if not _same_row(table, got[k], want[k], pending_pass)]
        extra = keys - set(want)
        if bad:
            diffs.append(f"{table}: {len(bad)} pairs differ from the uninterrupted run (e.g. {sorted(bad)[0]})")
        if extra and only is not None:
            diffs.append(f"{table}: {len(extra)} pairs the uninterrupted run does not have")
    if only is None and set(state["matches"]) != set(state["geometries"]) and ref["geometries"]:
        diffs.append("pairs with matches but no two-view geometry (or the reverse)")
    if features:
        bad = sorted(n for n in set(state["features"]) | set(ref["features"])
                     if state["features"].get(n) != ref["features"].get(n))
        if bad:
            diffs.append(f"keypoints / descriptors of {len(bad)} images differ from the uninterrupted run "
                         f"(e.g. {bad[0]})")
    return diffs


def partial_rows(state: dict) -> int:
    """Pairs stored half: a matches row without its two-view geometry or the reverse (``geometry="ours"``)."""
    return len(set(state["matches"]) ^ set(state["geometries"]))


SKIPPED_RE = re.compile(r"(\d+) matched, (\d+) skipped as already done, (\d+) failed")


def parse_skipped(text: str) -> tuple[int, int, int] | None:
    """``(matched, skipped, failed)`` from a collection report's summary line."""
    m = SKIPPED_RE.search(text)
    return tuple(int(v) for v in m.groups()) if m else None


# ---------------------------------------------------------------------------------------------- small filesystem
class SmallFS:
    """A folder whose filesystem holds ``size`` bytes: a tmpfs mount (root, where permitted); otherwise
    ``method == "rlimit"`` and :meth:`preexec` sets ``RLIMIT_FSIZE`` (the largest file a child may write) instead.
    """

    def __init__(self, folder: Path, size: int, *, allow_mount: bool = True) -> None:
        self.folder = Path(folder)
        self.size = int(size)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.method = "rlimit"
        if allow_mount and _try(["mount", "-t", "tmpfs", "-o", f"size={self._kib(size)}k", "tmpfs",
                                 str(self.folder)]):
            self.method = "tmpfs"

    @staticmethod
    def _kib(size: int) -> int:
        return max(4, (int(size) + 4095) // 4096 * 4)

    def resize(self, size: int) -> None:
        self.size = int(size)
        if self.method == "tmpfs":
            _try(["mount", "-o", f"remount,size={self._kib(size)}k", str(self.folder)], check=True)

    def preexec(self):
        """``preexec_fn`` for the child: ``RLIMIT_FSIZE`` under the ``rlimit`` method, else None."""
        if self.method != "rlimit":
            return None
        size = self.size

        def limit() -> None:
            import resource

            resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
        return limit

    def free(self) -> int:
        st = os.statvfs(self.folder)
        return st.f_bavail * st.f_frsize

    def close(self) -> None:
        if self.method == "tmpfs":
            _try(["umount", "-l", str(self.folder)])
            self.method = "closed"

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _try(cmd, check: bool = False) -> bool:
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return False
    if check and p.returncode:
        raise RuntimeError(f"{' '.join(cmd)}: {p.stderr.strip()}")
    return p.returncode == 0


def mount_permitted(scratch: Path) -> bool:
    """True when a tmpfs can be mounted here (root in a container that allows it)."""
    fs = SmallFS(scratch / "probe-mount", 1 << 20)
    ok = fs.method == "tmpfs"
    fs.close()
    return ok


def fill(folder: Path, leave: int) -> Path:
    """Write a filler file into ``folder`` so that about ``leave`` bytes stay free on its filesystem."""
    path = Path(folder) / "filler.bin"
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    n = max(0, free - int(leave))
    with open(path, "wb") as fh:
        chunk = b"\0" * (1 << 20)
        while n > 0:
            k = min(n, len(chunk))
            try:
                fh.write(chunk[:k])
                fh.flush()
            except OSError:
                break
            n -= k
    return path


# ---------------------------------------------------------------------------------------------- table
@dataclass
class Row:
    """One line of the faults table, with per-trial details for the JSON."""

    fault: str
    trials: int = 0
    survived: int = 0
    lost: int = 0          # finished units (pairs, images) redone or gone after the fault
    corrupt: int = 0       # outputs that are unreadable, fail integrity_check, or differ from the clean run
    tracebacks: int = 0
    notes: list = field(default_factory=list)
    details: list = field(default_factory=list)

    def add(self, ok: bool, *, lost: int = 0, corrupt: bool = False, bug: bool = False, **detail) -> None:
        self.trials += 1
        self.survived += bool(ok)
        self.lost += int(lost)
        self.corrupt += bool(corrupt)
        self.tracebacks += bool(bug)
        self.details.append(dict(ok=bool(ok), lost=int(lost), corrupt=bool(corrupt), traceback=bool(bug), **detail))

    def to_dict(self) -> dict:
        return dict(fault=self.fault, trials=self.trials, survived=self.survived, finished_work_lost=self.lost,
                    corrupt_outputs=self.corrupt, tracebacks=self.tracebacks, notes=self.notes,
                    details=self.details)


def table_markdown(rows) -> str:
    head = ["| fault class | trials | survived | finished work lost | corrupt outputs | tracebacks |",
            "|---|---:|---:|---:|---:|---:|"]
    body = [f"| {r.fault} | {r.trials} | {r.survived} | {r.lost} | {r.corrupt} | {r.tracebacks} |" for r in rows]
    return "\n".join(head + body)
