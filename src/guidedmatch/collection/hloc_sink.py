"""The hloc sink: matches written into an hloc ``matches.h5`` (``matches0`` / ``matching_scores0`` per pair)."""
from __future__ import annotations

import io
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import DatabaseError, InputError, OutputError

from .sink_base import MatchSink, WriteLock, _check_pairs, _check_writable, _space_problem

__all__ = ["H5MatchesSink", "names_to_pair"]


# ====================================================================== hloc
def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's key of a pair in ``matches.h5`` (hloc/utils/parsers.py): ``/`` in names becomes ``-``.

    >>> names_to_pair("seq/a.jpg", "b.jpg")
    'seq-a.jpg/b.jpg'
    """
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


class H5MatchesSink(MatchSink):
    """Write matches as an hloc ``matches.h5``: group ``names_to_pair(name1, name2)`` with ``matches0 (N1,) int32``
    (index into name2's features, -1 = unmatched; int32 holds any keypoint count, hloc's own int16 stops at
    32,767) and ``matching_scores0 (N1,) float32`` (the scores given to :meth:`write`, 0 where unmatched).

    Crash safety: writes are buffered and flushed every ``flush_every`` pairs (and on close) as a complete new
    segment file in ``<matches>.parts/`` (temp file + rename); :meth:`close` merges the existing ``matches.h5``
    and all segments into a temp file renamed over ``matches.h5``. A kill at any moment leaves the old
    ``matches.h5`` plus complete segments; the next run counts their pairs as done and merges them. Pairs still in
    the buffer at a crash are simply matched again.

    Args:
        matches_h5: output path.
        source: the :class:`~guidedmatch.collection.sources.FeatureSource` (or ``{name: num_features}``) giving
            ``N1`` -- ``matches0`` then has exactly one entry per keypoint of name1, as hloc writes it. Without
            it ``matches0`` ends at the last matched index (hloc's readers only use entries != -1);
            ``report["matches0_length"]`` says which.
        flush_every: pairs per segment file.
        overwrite: start over (existing pairs are not reported as done and are replaced at close).
    """

    kind = "h5"

    def __init__(self, matches_h5: str | os.PathLike, source=None, *, flush_every: int = 64,
                 overwrite: bool = False) -> None:
        from ..validation import check_bool, check_number

        check_number("H5MatchesSink", "flush_every", flush_every, lo=1, integer=True)
        check_bool("H5MatchesSink", "overwrite", overwrite)
        self.path = Path(matches_h5)
        self.parts = self.path.with_name(self.path.name + ".parts")
        self.flush_every = int(flush_every)
        self.overwrite = overwrite
        self._buffer: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._segments = 0
        self._closed = False
        if source is None:
            self._nf, names = None, []
        elif isinstance(source, dict):
            self._nf, names = {str(k): int(v) for k, v in source.items()}, list(source)
        else:
            names = source.names()
            self._nf = {n: source.num_features(n) for n in names}
        self._unsanitize = {n.replace("/", "-"): n for n in names}
        self.report = {"matches0_length": "num_features" if self._nf is not None else "last matched index + 1"}
        _check_writable(self.path, "matches file")
        if self.path.exists():
            self._check_h5(self.path)
        self._lock = WriteLock(self.path).acquire()
        try:
            self.parts.mkdir(exist_ok=True)
            for f in self.parts.iterdir():
                if f.name.endswith(".tmp"):
                    f.unlink()  # an interrupted segment write: never renamed, so incomplete
            if overwrite:
                for f in self.parts.glob("*.h5"):
                    f.unlink()
        except BaseException:
            self._lock.release()
            raise
        self._done = set() if overwrite else self._stored_keys()

    @staticmethod
    def _check_h5(path: Path) -> None:
        import h5py

        try:
            with h5py.File(path, "r"):
                pass
        except OSError as exc:
            raise DatabaseError(f"{path} exists but is not an HDF5 file ({exc}); move it away") from None

    def _keys_of(self, path: Path) -> set[str]:
        import h5py

        keys: set[str] = set()
        with h5py.File(path, "r") as fh:
            fh.visititems(lambda n, obj: keys.add(n) if isinstance(obj, h5py.Group) and "matches0" in obj else None)
        return keys

    def _segment_files(self) -> list[Path]:
        return sorted(self.parts.glob("*.h5"))

    def _stored_keys(self) -> set[str]:
        keys: set[str] = set()
        if self.path.exists():
            keys |= self._keys_of(self.path)
        for seg in self._segment_files():
            keys |= self._keys_of(seg)
        return keys

    def _key_names(self, key: str) -> frozenset[str] | None:
        parts = key.split("/")
        if len(parts) != 2:
            return None
        a, b = (self._unsanitize.get(x, x) for x in parts)
        return frozenset((a, b))

    def done_pairs(self, candidates=None) -> set[frozenset[str]]:
        """Pairs in ``matches.h5``, in complete segments, or written in this session (either key order);
        restricted to ``candidates`` (pairs of names) when given."""
        keys = set(self._done) | set(self._buffer)
        if candidates is not None:
            return {frozenset((a, b)) for a, b in candidates
                    if names_to_pair(a, b) in keys or names_to_pair(b, a) in keys}
        return {s for s in map(self._key_names, keys) if s is not None}

    def write(self, name1: str, name2: str, pairs: np.ndarray, scores: np.ndarray | None = None,
              geometry=None) -> None:
        """Buffer one pair under ``names_to_pair(name1, name2)`` (``matches0`` over name1's features).

        ``scores`` are stored as given in ``matching_scores0`` (0 where unmatched). hloc's learned matchers store
        confidences there (higher = better); the collection engine passes descriptor distances (lower = better).
        hloc's own pipeline reads them only through ``import_matches(min_match_score=...)``, off by default -- do
        not set it on our files. ``geometry`` is not stored (hloc verifies in COLMAP at import). A pair already
        stored (either order) is replaced at close.
        """
        if self._closed:
            raise OutputError(f"H5MatchesSink({self.path}) is closed")
        n1 = n2 = None
        if self._nf is not None:
            for n in (name1, name2):
                if n not in self._nf:
                    raise InputError(f"image {n!r} is not in the feature source of {self.path}")
            n1, n2 = self._nf[name1], self._nf[name2]
        p, s = _check_pairs(name1, name2, pairs, scores, n1, n2)
        if len(np.unique(p[:, 0])) != len(p):
            raise InputError(f"matches0 holds one match per feature of {name1!r}; got repeated indices")
        length = n1 if n1 is not None else (int(p[:, 0].max()) + 1 if len(p) else 0)
        m0 = np.full(length, -1, np.int32)
        s0 = np.zeros(length, np.float32)
        m0[p[:, 0]] = p[:, 1]
        s0[p[:, 0]] = s
        key = names_to_pair(name1, name2)
        rkey = names_to_pair(name2, name1)
        self._buffer.pop(rkey, None)  # the later write of a pair wins, whatever its order
        self._buffer[key] = (m0, s0)
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        """Write the buffered pairs as one new segment file (temp file + rename: complete or absent)."""
        import h5py

        if not self._buffer:
            return
        # built in memory, then written with plain file I/O: HDF5's own writes hitting a full disk (or the file size
        # limit) end in errors raised from finalizers and can crash the process; a plain write is one OSError
        mem = io.BytesIO()
        with h5py.File(mem, "w") as fh:
            for key, (m0, s0) in self._buffer.items():
                grp = fh.create_group(key)
                grp.create_dataset("matches0", data=m0)
                grp.create_dataset("matching_scores0", data=s0)
        data = mem.getbuffer()
        tmp = None
        try:
            fd, tmp = tempfile.mkstemp(prefix=f"seg-{os.getpid()}-", suffix=".tmp", dir=self.parts)
            with os.fdopen(fd, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
            final = self.parts / f"seg-{time.time_ns():020d}-{os.getpid()}.h5"
            os.replace(tmp, final)
        except OSError as exc:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
            raise OutputError(f"cannot write the matches file {self.path} (a segment in {self.parts}): "
                              f"{exc.strerror or exc}; free some space and rerun (finished pairs are kept)") from None
        except BaseException:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
            raise
        self._done |= set(self._buffer)
        self._buffer.clear()
        self._segments += 1

    def _merge(self) -> None:
        """``matches.h5`` + segments (later ones win) -> temp file -> rename; then delete the segments."""
        import h5py

        from ..features import publish

        segments = self._segment_files()
        if not segments and self.path.exists() and not self.overwrite:
            return
        # the merged copy needs about the space of its sources: refused before HDF5 writes a byte (see flush)
        need = sum(f.stat().st_size for f in segments) + (self.path.stat().st_size if self.path.exists() else 0)
        problem = _space_problem([self.path], self.path.parent if str(self.path.parent) else Path("."),
                                 int(1.25 * need) + (1 << 20))
        if problem:
            raise OutputError(f"cannot write the matches file {self.path}: {problem} (the matched pairs wait in "
                              f"{self.parts})")
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp.h5", dir=self.path.parent)
        os.close(fd)
        try:
            with h5py.File(tmp, "w") as out:
                sources = ([] if (self.overwrite or not self.path.exists()) else [self.path]) + segments
                for src in sources:
                    with h5py.File(src, "r") as fh:
                        for key in sorted(self._keys_of(src)):
                            rkey = "/".join(key.split("/")[::-1])
                            if key in out:
                                del out[key]
                            if rkey in out and src != self.path:  # a later segment stored the other order
                                del out[rkey]
                            fh.copy(fh[key], out, name=key)
            publish(tmp, self.path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        for seg in segments:
            seg.unlink()

    def close(self) -> None:
        """Flush, merge into ``matches.h5`` (atomic rename), remove the segments, release the lock."""
        if self._closed:
            return
        try:
            self.flush()
            self._merge()
            try:
                self.parts.rmdir()
            except OSError:
                pass
        finally:
            self._closed = True
            self._lock.release()

    def __del__(self) -> None:
        try:
            if not getattr(self, "_closed", True):
                self._lock.release()  # no merge from a finalizer: segments stay for the next run
                self._closed = True
        except Exception:
            pass
