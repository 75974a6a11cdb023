"""Small shared pieces of a guided run: the matches accepted per batch and collected over the phases, and the
detector orientations the verdict's second search uses."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..config import MatcherConfig


def _has_frames(c: MatcherConfig, f1, f2) -> bool:
    """The verdict's second search can run: ``frame_hypotheses`` on and both images have detector orientations."""
    return bool(c.frame_hypotheses) and f1.angles is not None and f2.angles is not None


def _frames(c: MatcherConfig, f1, f2, q: np.ndarray, j: np.ndarray):
    """``(angles1[q], angles2[j])`` for the verdict's second search (``frame_hypotheses``), or None when off or
    either image has no detector orientations."""
    if not _has_frames(c, f1, f2):
        return None
    return np.asarray(f1.angles)[q], np.asarray(f2.angles)[j]



class _Accepted(NamedTuple):
    """Matches accepted from one batch of queries: image-1 index, image-2 index, distance, single-candidate flag."""

    q: np.ndarray
    j: np.ndarray
    d: np.ndarray
    single: np.ndarray


class _Collected:
    """Matches accumulated over the phases of a run (with the phase each was made in)."""

    def __init__(self):
        self.parts: list[tuple[_Accepted, int]] = []

    def add(self, acc: _Accepted, phase: int) -> None:
        self.parts.append((acc, phase))

    def pairs_so_far(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([a.q for a, _ in self.parts]), np.concatenate([a.j for a, _ in self.parts])

    def arrays(self):
        cat = lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt)  # noqa: E731
        q = cat([a.q for a, _ in self.parts], np.int64)
        j = cat([a.j for a, _ in self.parts], np.int64)
        d = cat([a.d for a, _ in self.parts], np.float32)
        single = cat([a.single for a, _ in self.parts], bool)
        phase = cat([np.full(len(a.q), p, np.int64) for a, p in self.parts], np.int64)
        return q, j, d, single, phase
