"""The first pass's unguided starts, kept for the second look: the pairs it may match again are matched faster.

The second look (:mod:`guidedmatch.collection.second_look`) matches again the weak and rejected pairs of the first
pass, with a prior draw order. Its unguided start searches image 1's features against all of image 2 again, and
most of the features it draws the first pass had searched already, with the same index: the same results. Each
pair the first pass leaves rejected or weak returns its :class:`~guidedmatch.prepared.StartMemo` (the 2-NN and the
comparisons of every feature it searched); :class:`StartMemos` keeps them in the process that runs the stages, within
a memory bound, and the second look sends each pair's memo with its task. The matches are bit-identical with or
without (tests/test_collection_memos.py); only the time changes. fox (67 images, 2,211 pairs, one thread): the
second look 21.5 -> 14.9 s, fox's two-view geometries identical (collection history, twenty-first round).
"""
from __future__ import annotations

import pickle

__all__ = ["StartMemos", "dump", "load"]


def dump(memo) -> bytes:
    """A :class:`~guidedmatch.prepared.StartMemo` as bytes (compact: the features it holds)."""
    return pickle.dumps(memo, protocol=pickle.HIGHEST_PROTOCOL)


def load(blob):
    """The :class:`~guidedmatch.prepared.StartMemo` of :func:`dump`'s bytes (a memo object is returned as it is)."""
    return pickle.loads(blob) if isinstance(blob, bytes) else blob


class StartMemos:
    """Start memos of a run's pairs, in compact (pickled) form within ``max_mb``.

    Args:
        keep_below: the pairs whose memo the workers return: verdict not "verified", or fewer inliers than this (the
            second look's ``weak_below``).
        max_mb: memory for the memos; a memo that would exceed it is not kept (counted in :meth:`summary`: those
            pairs are searched again, with the same result).
    """

    def __init__(self, keep_below: int, max_mb: float = 512.0):
        self.keep_below = int(keep_below)
        self.max_bytes = int(max_mb * 2**20)
        self._store: dict = {}
        self.bytes = 0
        self.kept = self.dropped = self.taken = self.hits = 0
        self.recording = True  # runs given this store return their rejected and weak pairs' memos into it

    def add(self, pair: tuple, memo) -> None:
        """Keep ``memo`` (a StartMemo or its pickle, :func:`dump`) of the oriented ``pair`` (a later one of the same
        pair replaces it)."""
        blob = memo if isinstance(memo, bytes) else dump(memo)
        old = self._store.pop(tuple(pair), None)
        if old is not None:
            self.bytes -= len(old)
        if self.bytes + len(blob) > self.max_bytes:
            self.dropped += 1
            return
        self._store[tuple(pair)] = blob
        self.bytes += len(blob)
        self.kept += 1

    def take(self, pair: tuple) -> bytes | None:
        """The memo of the oriented ``pair`` as its pickle (removed from the store; :func:`load`), or None."""
        blob = self._store.pop(tuple(pair), None)
        if blob is None:
            return None
        self.bytes -= len(blob)
        self.taken += 1
        return blob

    def for_task(self, task) -> dict | None:
        """``{pair: pickled memo}`` of the task's pairs that have one (taken), or None."""
        out = {}
        for p in task:
            m = self.take(tuple(p))
            if m is not None:
                out[tuple(p)] = m
        return out or None

    def __len__(self) -> int:
        return len(self._store)

    def summary(self) -> dict:
        """``kept`` / ``dropped`` (over the memory bound) / ``taken`` memos, ``hits`` (features not searched again),
        ``mb`` held now."""
        return dict(kept=self.kept, dropped=self.dropped, taken=self.taken, hits=self.hits,
                    mb=round(self.bytes / 2**20, 1), max_mb=round(self.max_bytes / 2**20, 1))
