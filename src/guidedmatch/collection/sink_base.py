"""What every match sink shares: the exclusive write lock, the checks of a writable file and of a pair's matches,
the free-space check, and the :class:`MatchSink` interface (:mod:`guidedmatch.collection.sinks` has the COLMAP sink,
:mod:`guidedmatch.collection.hloc_sink` the hloc one)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DatabaseBusyError, InputError, OutputError

__all__ = ["WriteLock", "MatchSink", "SPACE_MARGIN"]


# ====================================================================== lock
class WriteLock:
    """Exclusive, non-blocking ``fcntl.flock`` on ``<target>.lock`` (released on close or process death).

    ``reentrant=True``: a holder that lets later acquisitions in the same process share its lock (``guidedmatch sfm``
    holds it for its whole run and its stages open sinks on the same database); the lock is released when that
    outer holder releases it. Without it, a second acquisition is refused even within one process."""

    #: resolved lock path -> [fd, holders, pid] of the re-entrant locks this process holds
    _HELD: dict = {}

    def __init__(self, target: str | os.PathLike, *, reentrant: bool = False) -> None:
        self.target = Path(target)
        self.reentrant = reentrant
        self.path = self.target.with_name(self.target.name + ".lock")
        self._fd: int | None = None
        self._key = ""

    def acquire(self) -> "WriteLock":
        import fcntl

        self._key = key = str(self.path.resolve())
        held = WriteLock._HELD.get(key)
        if held is not None and held[2] == os.getpid():  # this process holds it already: one more holder
            held[1] += 1
            self._fd = held[0]
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise OutputError(f"cannot create the lock file {self.path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            finally:
                os.close(fd)
            raise DatabaseBusyError(f"{self.target} is being written by another process (pid {holder}, lock "
                                    f"{self.path}); wait for it to finish or stop it, then rerun (finished pairs "
                                    "are kept)") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        if self.reentrant:
            WriteLock._HELD[key] = [fd, 1, os.getpid()]
        return self

    def release(self) -> None:
        import fcntl

        fd, self._fd = self._fd, None
        if fd is None:
            return
        held = WriteLock._HELD.get(self._key)
        if held is not None and held[0] == fd and held[1] > 1:  # an outer holder keeps it
            held[1] -= 1
            return
        WriteLock._HELD.pop(self._key, None)
        try:
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def __enter__(self) -> "WriteLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    @property
    def held(self) -> bool:
        return self._fd is not None


def _check_writable(path: Path, what: str) -> None:
    """OutputError when ``path`` (existing) or its folder cannot be written by this process."""
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise OutputError(f"{what} path is a directory: {path}")
    if not parent.is_dir():
        raise OutputError(f"folder of the {what} does not exist: {parent}")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputError(f"{what} {path} is read-only; make it writable or work on a copy")
    if not os.access(parent, os.W_OK):
        raise OutputError(f"folder {parent} of the {what} is read-only (SQLite / HDF5 need to create files "
                          "beside it)")


def _check_pairs(name1: str, name2: str, pairs, scores, n1: int | None, n2: int | None):
    if name1 == name2:
        raise InputError(f"cannot store a self-pair ({name1!r})")
    p = np.asarray(pairs)
    if p.size == 0:
        p = p.reshape(0, 2)
    if p.ndim != 2 or p.shape[1] != 2 or not (np.issubdtype(p.dtype, np.integer) or p.size == 0):
        raise InputError(f"pairs of {name1} / {name2} must be an (M, 2) integer array, got {p.dtype} {p.shape}")
    p = p.astype(np.int64)
    if len(p) and p.min() < 0:
        raise InputError(f"pairs of {name1} / {name2} contain negative feature indices")
    for col, (name, n) in enumerate(((name1, n1), (name2, n2))):
        if n is not None and len(p) and p[:, col].max() >= n:
            raise InputError(f"pairs of {name1} / {name2}: feature index {int(p[:, col].max())} out of range for "
                             f"{name!r} ({n} features)")
    if scores is None:
        s = np.zeros(len(p), np.float32)
    else:
        s = np.asarray(scores, np.float32).reshape(-1)
        if len(s) != len(p):
            raise InputError(f"{len(s)} scores for {len(p)} matches ({name1} / {name2})")
    return p, s


#: free space every COLMAP database transaction asks for beyond twice its own bytes: SQLite writes a committed
#: transaction's pages to the WAL and, at an automatic checkpoint, copies up to ~1000 WAL pages (~4 MB) into the
#: database file -- both need room on the disk
SPACE_MARGIN = 8 << 20


def _space_problem(paths, folder: Path, need: int, kept: str = "finished pairs are kept") -> str | None:
    """Why writing ``need`` more bytes into ``paths`` (files in ``folder``) would fail, or None: too little free
    space on the filesystem, or a per-process file size limit (``RLIMIT_FSIZE``) below a file's size plus it.
    ``kept`` ends the message: what a rerun keeps."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    free = st.f_bavail * st.f_frsize
    if free < need:
        return (f"disk full: {free / 2**20:.1f} MB free on the filesystem of {folder}, a write needs up to "
                f"{need / 2**20:.1f} MB; free some space and rerun ({kept})")
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):
        return None
    if soft != resource.RLIM_INFINITY:
        for f in paths:
            size = f.stat().st_size if f.exists() else 0
            if size + need > soft:
                return (f"file size limit: {f.name} ({size / 2**20:.1f} MB) may not grow past {soft / 2**20:.1f} MB "
                        f"in this process (ulimit -f); raise the limit and rerun ({kept})")
    return None


class MatchSink:
    """Base class: a locked, resumable destination of per-pair matches (a context manager)."""

    kind = ""

    def done_pairs(self, candidates=None) -> set[frozenset[str]]:
        """Pairs already complete in the sink (resume: skip them). Pass the pair list as ``candidates`` for an
        exact answer restricted to it (ColmapSink: see its note on pairs with zero matches)."""
        raise NotImplementedError

    def write(self, name1: str, name2: str, pairs: np.ndarray, scores: np.ndarray | None,
              geometry=None) -> None:
        """Store the matches of one pair atomically (``pairs (M, 2)`` indices into name1's / name2's features,
        ``scores (M,)`` per-match values (the engine's descriptor distances), ``geometry`` a
        :class:`~guidedmatch.geometry.TwoViewGeometry` or None)."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_database_space(database_path: Path, nbytes: int, kept: str = "the images already extracted are kept"
                         ) -> None:
    """OutputError naming the database when a transaction of ``nbytes`` might not fit on its disk (or under the
    process's file size limit); ``kept`` says what a rerun keeps. pycolmap commits in a C++ destructor, where
    SQLite's "database or disk is full" aborts the whole process instead of raising, so every writer checks the room
    before each transaction."""
    database_path = Path(database_path)
    folder = database_path.parent if str(database_path.parent) else Path(".")
    problem = _space_problem([database_path, database_path.with_name(database_path.name + "-wal")], folder,
                             2 * int(nbytes) + SPACE_MARGIN, kept=kept)
    if problem:
        raise OutputError(f"cannot write the COLMAP database {database_path}: {problem}")


# ------------------------------------------------------------------------------ one SQLite library per database file
#: (device, inode) of every database file this process has opened with pycolmap. SQLite's locks are POSIX advisory
#: locks, held per *process*, and closing *any* descriptor of a file drops all of the process's locks on it. SQLite
#: guards its own connections against that, but pycolmap bundles its own SQLite: a plain ``open()`` of the file or
#: a Python ``sqlite3`` connection closed while pycolmap holds the database silently drops pycolmap's locks, and
#: another process (a Dask worker closing its reader) may then checkpoint and delete the write-ahead log under the
#: writer's feet -- a malformed database. Seen on a 220-image collection; so after the first pycolmap open of a file
#: in a process, nothing but pycolmap touches that file in it (:func:`pycolmap_opened`).
_PYCOLMAP_FILES: set = set()


def _file_key(path) -> tuple | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def note_pycolmap_open(path) -> None:
    """Record that this process has opened the database file ``path`` with pycolmap (module comment above)."""
    key = _file_key(path)
    if key is not None:
        _PYCOLMAP_FILES.add(key)


def pycolmap_opened(path) -> bool:
    """True when this process has opened ``path`` with pycolmap: from then on, reading it with Python's ``open`` or
    ``sqlite3`` could drop pycolmap's locks (module comment above), so callers use pycolmap instead."""
    key = _file_key(path)
    return key is not None and key in _PYCOLMAP_FILES


def open_pycolmap_database(path):
    """``pycolmap.Database.open(path)``, recorded by :func:`note_pycolmap_open`."""
    import pycolmap

    db = pycolmap.Database.open(str(path))
    note_pycolmap_open(path)
    return db
