"""The hloc source: :class:`H5Source` reads a collection's features from an hloc ``features.h5``, and
:func:`write_features_h5` writes one.

Keypoints in ``features.h5`` are already in the package's OpenCV convention (hloc's extract_features rescales with
``(x + 0.5) * s - 0.5`` and adds 0.5 when it imports keypoints into COLMAP, hloc/triangulation.py). Descriptors are
stored ``(D, N)`` (float16 or float32) and load as ``(N, D)`` float32.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DatabaseError, InputError
from ..features import Features
from .source_base import FeatureSource, _check_finite, _examples

__all__ = ["H5Source", "write_features_h5"]

_H5_IMAGE_DATASETS = ("descriptors", "image_size", "scores")  # datasets of an hloc image group besides keypoints
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


class H5Source(FeatureSource):
    """Features of an hloc ``features.h5``: one group per image (its name; ``/`` in a name nests groups) with
    ``keypoints (N, 2)`` (OpenCV convention), ``descriptors (D, N)`` (float16/float32), ``image_size`` (w, h) and
    optional ``scores (N,)`` (loaded as ``responses``)."""

    kind = "h5"

    def __init__(self, features_h5: str | os.PathLike) -> None:
        super().__init__(features_h5)
        import h5py

        if not self.path.exists():
            raise DatabaseError(f"features file not found: {self.path}")
        try:
            fh = h5py.File(self.path, "r")
        except OSError as exc:
            raise DatabaseError(f"{self.path} is not an HDF5 features file: {exc}") from None
        try:
            groups: list[str] = []
            no_kp: list[str] = []   # an image group (it has an image's datasets) that lost its keypoints

            def visit(n, obj) -> None:
                if isinstance(obj, h5py.Group):
                    if "keypoints" in obj:
                        groups.append(n)
                    elif any(k in obj and isinstance(obj[k], h5py.Dataset) for k in _H5_IMAGE_DATASETS):
                        no_kp.append(n)
            fh.visititems(visit)
            if not groups:
                raise DatabaseError(f"{self.path}: no image groups with 'keypoints' (not an hloc features.h5?)")
            if no_kp:
                raise DatabaseError(f"{self.path}: {len(no_kp)} image group(s) have no 'keypoints' dataset "
                                    f"({_examples(no_kp)})")
            no_desc, bad = [], []
            dims = {}
            for g in groups:
                grp = fh[g]
                kp = grp["keypoints"]
                if not isinstance(kp, h5py.Dataset) or kp.dtype.kind not in "fiu":
                    bad.append(f"{g}: keypoints of type {getattr(kp, 'dtype', 'group')} (expected float)")
                    continue
                if kp.ndim != 2 or kp.shape[1] != 2:
                    bad.append(f"{g}: keypoints shape {kp.shape}")
                    continue
                if "descriptors" not in grp:
                    no_desc.append(g)
                    continue
                d = grp["descriptors"]
                if not isinstance(d, h5py.Dataset) or d.dtype.kind not in "fiu":
                    bad.append(f"{g}: descriptors of type {getattr(d, 'dtype', 'group')} (expected float16 / "
                               "float32, or uint8)")
                    continue
                if d.ndim != 2 or d.shape[1] != kp.shape[0]:
                    bad.append(f"{g}: descriptors shape {d.shape} for {kp.shape[0]} keypoints (hloc stores D x N)")
                    continue
                if "image_size" not in grp:
                    bad.append(f"{g}: no image_size")
                    continue
                dims.setdefault((int(d.shape[0]), str(d.dtype.kind)), []).append(g)
                w, h = (int(v) for v in np.asarray(grp["image_size"]).reshape(-1)[:2])
                self._names.append(g)
                self._sizes[g] = (w, h)
                self._counts[g] = int(kp.shape[0])
            if no_desc:
                raise DatabaseError(f"{self.path}: {len(no_desc)} of {len(groups)} images have no descriptors "
                                    f"({_examples(no_desc)})")
            if bad:
                raise DatabaseError(f"{self.path}: malformed image groups: {_examples(bad)}")
            if len(dims) > 1:
                desc = "; ".join(f"{d} x {'float' if k == 'f' else k} in {len(v)} images (e.g. {v[0]!r})"
                                 for (d, k), v in dims.items())
                raise InputError(f"{self.path}: mixed descriptor types: {desc}")
            (self._dim, self._dkind), = dims.keys()
        finally:
            fh.close()

    def _file(self):
        if self._handle is None:
            import h5py

            self._handle = h5py.File(self.path, "r")
        return self._handle

    def _keypoints(self, name: str) -> np.ndarray:
        try:
            kp = np.asarray(self._file()[name]["keypoints"], dtype=np.float64)
        except (OSError, ValueError, TypeError) as exc:
            raise DatabaseError(f"{self.path}: the keypoints of image {name!r} cannot be read: {exc}") from None
        _check_finite(kp, self.path, name)
        return kp


    def load(self, name: str) -> Features:
        self._check_name(name)
        grp = self._file()[name]
        kp = self._keypoints(name)
        try:
            d = np.asarray(grp["descriptors"])
        except (OSError, ValueError, TypeError) as exc:
            raise DatabaseError(f"{self.path}: the descriptors of image {name!r} cannot be read: {exc}") from None
        desc = d.T.astype(np.uint8 if d.dtype == np.uint8 else np.float32)
        scores = np.asarray(grp["scores"], dtype=np.float32) if "scores" in grp else None
        if scores is not None and scores.shape != (len(kp),):
            scores = None
        if len(kp) == 0:
            desc = desc.reshape(0, self._dim)
        return Features(kp, desc, self._sizes[name], "user", responses=scores)


def write_features_h5(path: str | os.PathLike, features: dict, *, as_half: bool = True) -> None:
    """Write ``{name: Features}`` as an hloc ``features.h5`` (keypoints (N,2) float32, descriptors D x N, float16
    when ``as_half`` like hloc's default, ``image_size``, ``scores`` from ``responses``). Written to a temp file and
    renamed (no partial file)."""
    import tempfile

    import h5py

    from ..features import publish

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp.h5", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as fh:
            for name, f in features.items():
                grp = fh.create_group(name)
                grp.create_dataset("keypoints", data=f.keypoints.astype(np.float32))
                d = f.descriptors.T
                if d.dtype != np.uint8:
                    d = d.astype(np.float16 if as_half else np.float32)
                grp.create_dataset("descriptors", data=d)
                grp.create_dataset("image_size", data=np.array(f.image_size, np.int64))
                if f.responses is not None:
                    grp.create_dataset("scores", data=f.responses.astype(np.float16 if as_half else np.float32))
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
