"""Skip markers for tests that read the evaluation data (``GUIDEDMATCH_DATA``, see :mod:`guidedmatch.datasets`).

A test that needs data files names them; it is skipped -- with a reason listing what is missing -- whenever the
data root is not found *or* any of the named files is absent (e.g. ``GUIDEDMATCH_DATA`` pointing at an empty or
partial folder), so a missing file is never a test failure.

>>> import pytest
>>> mark = needs_data("no/such/file.png", root="/nonexistent")
>>> mark.kwargs["reason"].startswith("evaluation data missing")
True
"""
from __future__ import annotations

import os
from pathlib import Path

from ..datasets import OXFORD_ALL_SEQUENCES, data_root

__all__ = ["missing_data", "needs_data", "OXFORD_FILES", "STRECHA_FILES", "PHOTO_FILES", "DATA_FOLDERS"]

#: the Oxford images and plain-text homographies of every sequence (``oxford_pairs`` with any targets)
OXFORD_FILES = tuple(f"oxford/{s}/img{k}.png" for s in OXFORD_ALL_SEQUENCES for k in range(1, 7)) + tuple(
    f"oxford/{s}/H1to{k}p" for s in OXFORD_ALL_SEQUENCES for k in range(2, 7))
#: the Strecha pairs file and the Herz-Jesus-P8 images it lists
STRECHA_FILES = ("pose_pairs/strecha/strecha_pairs_with_gt.txt", "pose_pairs/strecha/Herz-Jesus-P8/images/*.jpg")
#: the photos of the synthetic sets (at least one)
PHOTO_FILES = ("photos/unsplash/*",)


def missing_data(*patterns: str, root: str | os.PathLike | None = None) -> list[str]:
    """The entries of ``patterns`` (paths relative to the data root; globs need >= 1 match) that are absent.

    Returns ``["<data root>"]`` when no data root is found at all.
    """
    r = data_root(root)
    if r is None or not Path(r).is_dir():
        return [f"<data root {r}>" if r is not None else "<data root>"]
    r = Path(r)
    out = []
    for pat in patterns:
        if any(ch in pat for ch in "*?["):
            if not any(r.glob(pat)):
                out.append(pat)
        elif not (r / pat).exists():
            out.append(pat)
    return out


#: what a bare ``@needs_data`` (no files named) requires: the three data folders, each non-empty
DATA_FOLDERS = ("oxford/*", "pose_pairs/*", "photos/*")


def needs_data(*patterns, root: str | os.PathLike | None = None):
    """``pytest.mark.skipif`` that skips unless every file of ``patterns`` exists under the data root.

    Used bare (``@needs_data`` on a test function) it requires :data:`DATA_FOLDERS`; name the files a test reads
    to make it skip whenever one of them is missing.
    """
    import pytest

    if len(patterns) == 1 and callable(patterns[0]):
        return needs_data(*DATA_FOLDERS, root=root)(patterns[0])
    miss = missing_data(*patterns, root=root)
    shown = ", ".join(miss[:3]) + (f" (+{len(miss) - 3} more)" if len(miss) > 3 else "")
    return pytest.mark.skipif(bool(miss), reason=f"evaluation data missing: {shown} (set GUIDEDMATCH_DATA)")
