"""The base class of a collection's feature sources (:class:`FeatureSource`) and the helpers every source uses.

A source is small and picklable (paths plus per-image metadata: names, sizes, feature counts); it opens its file
lazily in the process that calls :meth:`FeatureSource.load`, so Dask workers read features themselves. The sources:
:class:`~guidedmatch.collection.colmap_source.ColmapSource` (a COLMAP database),
:class:`~guidedmatch.collection.hloc_source.H5Source` (an hloc ``features.h5``); :mod:`guidedmatch.collection.sources`
opens either by file content and re-exports them.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..features import Features

__all__ = ["FeatureSource"]


def _examples(items, n: int = 5) -> str:
    items = list(items)
    s = ", ".join(repr(x) for x in items[:n])
    return s + (f" and {len(items) - n} more" if len(items) > n else "")


def _check_finite(xy: np.ndarray, path: Path, name: str) -> None:
    """InputError naming the file and the image when keypoint coordinates are NaN / inf."""
    bad = ~np.isfinite(xy).all(axis=1) if len(xy) else np.zeros(0, bool)
    if bad.any():
        raise InputError(f"{path}: image {name!r} has {int(bad.sum())} of {len(xy)} keypoints with non-finite "
                         f"(NaN / inf) coordinates (first: keypoint {int(np.flatnonzero(bad)[0])}); re-extract its "
                         "features")


class FeatureSource:
    """Base class: the features of a collection, image by image.

    Attributes:
        kind: ``"colmap"`` or ``"h5"``.
        path: the file the features live in.

    Subclasses keep only paths and small metadata in their state (picklable) and open files lazily.
    """

    kind: str = ""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._handle = None
        self._names: list[str] = []
        self._sizes: dict[str, tuple[int, int]] = {}
        self._counts: dict[str, int] = {}

    # ------------------------------------------------------------------ metadata (no file access)
    def names(self) -> list[str]:
        """Image names in source order (COLMAP image name / hloc group path)."""
        return list(self._names)

    def _check_name(self, name: str) -> None:
        if name not in self._sizes:
            raise InputError(f"image {name!r} is not in {self.kind} source {self.path}")

    def image_size(self, name: str) -> tuple[int, int]:
        """``(w, h)`` of the image, pixels."""
        self._check_name(name)
        return self._sizes[name]

    def num_features(self, name: str) -> int:
        """Number of keypoints of the image."""
        self._check_name(name)
        return self._counts[name]

    def __len__(self) -> int:
        return len(self._names)

    def __contains__(self, name) -> bool:
        return name in self._sizes

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, {len(self)} images)"

    # ------------------------------------------------------------------ features
    def load(self, name: str) -> Features:
        """The image's :class:`~guidedmatch.features.Features` (OpenCV pixel convention)."""
        raise NotImplementedError

    def validate(self, names=None) -> None:
        """Check that every image (or ``names``) has descriptors of one type and length; InputError if not.

        Call it before matching: sources check what is cheap at construction; this may read more.
        """

    def close(self) -> None:
        """Close the file handle of this process (reopened by the next :meth:`load`)."""
        h, self._handle = self._handle, None
        if h is not None:
            h.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_handle"] = None  # never ship an open file to another process
        return state

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
