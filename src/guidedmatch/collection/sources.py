"""Feature sources of a collection: a COLMAP database, an hloc ``features.h5``, or an image folder detected into a
new COLMAP database.

A source is small and picklable (paths plus per-image metadata: names, sizes, feature counts); it opens its file
lazily in the process that calls :meth:`FeatureSource.load`, so Dask workers read features themselves.

Pixel conventions
-----------------
Features are returned in the package's OpenCV convention: ``(0, 0)`` is the **centre** of the top-left pixel.

* COLMAP puts the centre of the top-left pixel at ``(0.5, 0.5)`` (its keypoints span ``[0, w] x [0, h]``):
  ``x_cv = x_colmap - 0.5`` on reading, ``x_colmap = x_cv + 0.5`` on writing. COLMAP stores float32, so a
  round trip is exact up to the float32 rounding of ``x + 0.5`` (at most half an ulp: 6e-5 px below 2048 px).
* hloc's ``features.h5`` keypoints are already in the OpenCV convention (hloc's extract_features rescales with
  ``(x + 0.5) * s - 0.5`` and adds 0.5 when it imports keypoints into COLMAP, hloc/triangulation.py).

Descriptors
-----------
* COLMAP: ``FeatureDescriptors`` of type SIFT (uint8, 128-D; RootSIFT as COLMAP's extractor writes it, or OpenCV
  SIFT bytes as :func:`images_to_database` writes it) load as ``kind="sift"`` float32 (L2). Type UNDEFINED with
  128 bytes (databases of COLMAP < 3.12) is read as SIFT too; UNDEFINED with another length is packed binary
  (ORB 32, AKAZE 61, BRISK 64 bytes; Hamming). Other COLMAP types (ALIKED, LoMa) are converted with
  ``FeatureDescriptors.to_float()`` to float32 (L2).
* hloc: ``descriptors`` stored ``(D, N)`` (float16 or float32) load as ``(N, D)`` float32.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..errors import DatabaseError, ImageReadError, InputError, OutputError
from ..features import BINARY_KINDS, DETECTORS, Features
from .image_folder import IMAGE_EXTENSIONS
from .sink_base import open_pycolmap_database, pycolmap_opened

__all__ = ["FeatureSource", "ColmapSource", "H5Source", "open_source", "images_to_database", "IMAGE_EXTENSIONS",
           "COLMAP_PIXEL_OFFSET"]

#: COLMAP pixel coordinate minus OpenCV pixel coordinate of the same point.
COLMAP_PIXEL_OFFSET = 0.5
_BINARY_BY_BYTES = {32: "orb", 61: "akaze", 64: "brisk"}
_SQLITE_MAGIC = b"SQLite format 3\x00"
_H5_IMAGE_DATASETS = ("descriptors", "image_size", "scores")  # datasets of an hloc image group besides keypoints
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def _examples(items, n: int = 5) -> str:
    items = list(items)
    s = ", ".join(repr(x) for x in items[:n])
    return s + (f" and {len(items) - n} more" if len(items) > n else "")


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


# ====================================================================== COLMAP
def _writer_active(path: Path) -> bool:
    """True while a guidedmatch sink holds the write lock ``<db>.lock`` (a shared flock probe fails)."""
    import fcntl

    lock = path.with_name(path.name + ".lock")
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


#: columns every COLMAP database version has, per table (newer versions add more)
_COLMAP_COLUMNS = {"cameras": {"camera_id", "model", "width", "height", "params"},
                   "images": {"image_id", "name", "camera_id"},
                   "keypoints": {"image_id", "rows", "cols", "data"},
                   "descriptors": {"image_id", "rows", "cols", "data"},
                   "matches": {"pair_id", "rows", "cols", "data"},
                   "two_view_geometries": {"pair_id", "rows", "cols", "data", "config"}}


def _sqlite_problem(path: Path) -> str | None:
    """Why the SQLite file ``path`` is not a usable COLMAP database, read with plain SQLite before COLMAP's schema
    set-up touches it: damaged (truncated, malformed), another program's database (no COLMAP table: COLMAP would
    add its tables to it), or a COLMAP table without COLMAP's columns. None when it looks fine or is busy (a
    writer holds it: the caller retries)."""
    import sqlite3

    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.5)
    except sqlite3.Error:
        return None
    try:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if tables and not tables & {"cameras", "images", "keypoints"}:
            return (f"is an SQLite database but not a COLMAP database (its tables: {_examples(sorted(tables))}); "
                    "nothing was changed")
        for table, need in _COLMAP_COLUMNS.items():
            if table in tables:
                have = {r[1] for r in con.execute(f"PRAGMA table_info({table})")}
                if not need <= have:
                    return (f"is not a COLMAP database of a known layout: table {table!r} lacks the column(s) "
                            f"{', '.join(sorted(need - have))}")
        if "images" in tables:
            con.execute("SELECT count(*) FROM images").fetchone()
    except sqlite3.DatabaseError as exc:
        msg = str(exc)
        if not any(w in msg for w in ("malformed", "not a database", "corrupt")):
            return None  # locked, busy, a WAL file this read-only probe cannot use, ...: pycolmap's open decides
        return f"is damaged or truncated (SQLite: {msg}); restore it or extract the features again"
    finally:
        con.close()
    return None


def _open_colmap(path: Path, busy_timeout: float = 30.0):
    """``pycolmap.Database`` of an existing COLMAP database (DatabaseError when missing or not a database).

    Opening runs COLMAP's schema set-up, which fails while another connection is inside a write transaction
    ("database is locked"). The open is retried: for up to ``busy_timeout`` s while a guidedmatch sink holds the
    database's write lock (its transactions last milliseconds), else for 2 s.
    """
    if not path.exists():
        raise DatabaseError(f"COLMAP database not found: {path}")
    if path.is_dir():
        raise DatabaseError(f"COLMAP database path is a directory: {path}")
    # once pycolmap holds the file in this process, plain open() / sqlite3 probes must not touch it (sink_base)
    probe = not pycolmap_opened(path)
    if probe:
        with open(path, "rb") as fh:
            head = fh.read(16)
        if head != _SQLITE_MAGIC:
            raise DatabaseError(f"{path} is not a COLMAP database (not an SQLite file)")
        problem = _sqlite_problem(path)
        if problem:
            raise DatabaseError(f"{path} {problem}")
    start = time.monotonic()
    delay = 0.02
    while True:
        try:
            return open_pycolmap_database(path)
        except Exception as exc:  # pycolmap raises RuntimeError / ValueError with SQLite's message
            problem = _sqlite_problem(path) if probe else None
            if problem:
                raise DatabaseError(f"{path} {problem}") from None
            waited = time.monotonic() - start
            if waited > (busy_timeout if _writer_active(path) else 2.0):
                raise DatabaseError(f"cannot open COLMAP database {path} (tried for {waited:.1f} s; another "
                                    f"process may be writing it): {exc}") from None
            time.sleep(delay)
            delay = min(0.5, delay * 2)


def _check_finite(xy: np.ndarray, path: Path, name: str) -> None:
    """InputError naming the file and the image when keypoint coordinates are NaN / inf."""
    bad = ~np.isfinite(xy).all(axis=1) if len(xy) else np.zeros(0, bool)
    if bad.any():
        raise InputError(f"{path}: image {name!r} has {int(bad.sum())} of {len(xy)} keypoints with non-finite "
                         f"(NaN / inf) coordinates (first: keypoint {int(np.flatnonzero(bad)[0])}); re-extract its "
                         "features")


def _descriptor_kind(ftype, nbytes: int) -> str:
    """Our descriptor kind for a COLMAP ``FeatureExtractorType`` and row length in bytes."""
    name = getattr(ftype, "name", str(ftype))
    if name == "SIFT" or (name == "UNDEFINED" and nbytes == 128):
        return "sift"
    if name == "UNDEFINED":
        return _BINARY_BY_BYTES.get(nbytes, "binary")
    return name.lower()


def _is_binary(kind: str) -> bool:
    """Packed-bit descriptors (Hamming): ORB / AKAZE / BRISK, or an UNDEFINED row length that is not SIFT's."""
    return kind in BINARY_KINDS or kind == "binary"


def _descriptor_rows(desc, nbytes: int) -> tuple[str, np.ndarray]:
    """``(kind, rows)`` of a ``pycolmap.FeatureDescriptors`` with ``nbytes`` per row: SIFT and packed binary rows as
    stored (uint8, no copy), any other type as float32 (``to_float``)."""
    kind = _descriptor_kind(desc.type, nbytes)
    if kind == "sift" or _is_binary(kind):
        return kind, np.asarray(desc.data)
    return kind, np.asarray(desc.to_float().data, dtype=np.float32)


class ColmapSource(FeatureSource):
    """Features of a COLMAP database (read through ``pycolmap.Database``).

    Raises :class:`DatabaseError` when the database is missing, not a COLMAP database, has no images, or images
    without keypoints or descriptors (or with different counts of each). A mix of descriptor types or lengths
    across images is detected by :meth:`validate` (reads every descriptor blob) and by :meth:`load` (per image,
    against the first image's type).

    Reading while another process writes (the matching sink) is safe: COLMAP opens databases in SQLite WAL mode;
    a transient "database is locked" is retried for up to ``busy_timeout`` seconds.
    """

    kind = "colmap"

    def __init__(self, database_path: str | os.PathLike, *, busy_timeout: float = 30.0) -> None:
        super().__init__(database_path)
        self.busy_timeout = float(busy_timeout)
        db = _open_colmap(self.path, self.busy_timeout)
        try:
            images = sorted(db.read_all_images(), key=lambda im: im.image_id)
            cameras = {c.camera_id: c for c in db.read_all_cameras()}
            if not images:
                raise DatabaseError(f"COLMAP database {self.path} has no images")
            self._ids: dict[str, int] = {}
            no_kp, no_desc, mismatch = [], [], []
            for im in images:
                cam = cameras.get(im.camera_id)
                if cam is None:
                    raise DatabaseError(f"{self.path}: image {im.name!r} refers to missing camera {im.camera_id}")
                n_kp = db.num_keypoints_for_image(im.image_id) if db.exists_keypoints(im.image_id) else 0
                n_desc = db.num_descriptors_for_image(im.image_id) if db.exists_descriptors(im.image_id) else -1
                if not db.exists_keypoints(im.image_id):
                    no_kp.append(im.name)
                if n_desc < 0:
                    no_desc.append(im.name)
                elif n_desc != n_kp:
                    mismatch.append(f"{im.name} ({n_kp} keypoints, {n_desc} descriptors)")
                self._names.append(im.name)
                self._ids[im.name] = int(im.image_id)
                self._sizes[im.name] = (int(cam.width), int(cam.height))
                self._counts[im.name] = int(n_kp)
            if no_kp:
                raise DatabaseError(f"{self.path}: {len(no_kp)} of {len(images)} images have no keypoints "
                                    f"({_examples(no_kp)}); run feature extraction first")
            if no_desc:
                raise DatabaseError(f"{self.path}: {len(no_desc)} of {len(images)} images have no descriptors "
                                    f"({_examples(no_desc)}); run feature extraction first")
            if mismatch:
                raise DatabaseError(f"{self.path}: keypoint and descriptor counts differ for {_examples(mismatch)}")
            self._ref = next((n for n in self._names if self._counts[n] > 0), self._names[0])
            try:
                self._desc = self._read_descriptor_meta(db, self._ref)
            except (ValueError, RuntimeError) as exc:  # a blob that does not hold its rows x cols
                raise DatabaseError(f"{self.path}: the descriptors of image {self._ref!r} cannot be read (damaged "
                                    f"database: {str(exc).strip()})") from None
        finally:
            db.close()

    @property
    def descriptor_kind(self) -> str:
        """Descriptor kind of the first image with features (``"sift"``, ``"orb"``, ...)."""
        return self._desc[0]

    @property
    def descriptor_bytes(self) -> int:
        """Bytes per descriptor row of the first image with features."""
        return self._desc[1]

    def _read_descriptor_meta(self, db, name: str) -> tuple[str, int]:
        d = db.read_descriptors(self._ids[name])
        data = np.asarray(d.data)
        return _descriptor_kind(d.type, int(data.shape[1]) if data.ndim == 2 else 0), (
            int(data.shape[1]) if data.ndim == 2 else 0)

    def _db(self):
        if self._handle is None:
            self._handle = _open_colmap(self.path, self.busy_timeout)
        return self._handle

    def _retry(self, fn):
        deadline = time.monotonic() + self.busy_timeout
        delay = 0.05
        while True:
            try:
                return fn()
            except RuntimeError as exc:  # SQLITE_BUSY surfaces as RuntimeError("... database is locked")
                msg = str(exc).lower()
                if ("locked" not in msg and "busy" not in msg) or time.monotonic() > deadline:
                    raise DatabaseError(f"reading {self.path}: {exc}") from None
                time.sleep(delay)
                delay = min(1.0, delay * 2)

    def add_image(self, name: str, image_id: int, size: tuple[int, int], num_features: int) -> None:
        """Make an image written into the database after this source was opened known to it (its writer, in this
        process, gives the facts: ``guidedmatch sfm`` matching pairs while the extraction still writes images).
        Images are added in the order they were written, so :meth:`names` stays in image id order."""
        if name in self._sizes:
            raise InputError(f"{self.path}: image {name!r} is already known to this source")
        self._ids[name] = int(image_id)
        self._sizes[name] = (int(size[0]), int(size[1]))
        self._counts[name] = int(num_features)
        self._names.append(name)

    def image_id(self, name: str) -> int:
        """COLMAP ``image_id`` of the image."""
        self._check_name(name)
        return self._ids[name]

    def load(self, name: str) -> Features:
        """Keypoints (``x_cv = x_colmap - 0.5``), descriptors and image size of ``name``.

        4- and 6-column COLMAP keypoints also give ``scales`` (OpenCV diameter = 2 x COLMAP scale) and ``angles``
        (degrees of COLMAP's orientation); responses are not stored by COLMAP (None).
        """
        self._check_name(name)
        kp, desc = self._read(name)
        kp = np.asarray(kp, dtype=np.float64).reshape(len(kp), -1) if len(kp) else np.zeros((0, 2))
        _check_finite(kp[:, :2], self.path, name)
        data = np.asarray(desc.data)
        nbytes = int(data.shape[1]) if data.ndim == 2 and len(data) else self._desc[1]
        kind, rows = _descriptor_rows(desc, nbytes)
        if len(data) and (kind, nbytes) != self._desc:
            raise InputError(f"{self.path}: mixed descriptor types: image {name!r} has {kind} ({nbytes} bytes), "
                             f"image {self._ref!r} has {self._desc[0]} ({self._desc[1]} bytes); "
                             "one collection needs one descriptor type")
        if kind == "sift":
            descriptors = rows.astype(np.float32)
            fkind = "sift"
        elif _is_binary(kind):
            descriptors = np.ascontiguousarray(rows, dtype=np.uint8)
            fkind = kind if kind in BINARY_KINDS else "user"
        else:
            descriptors = rows
            fkind = "user"
        scales = angles = None
        # angles in OpenCV's convention, [0, 360) degrees (a negative angle means "no orientation" there)
        if kp.shape[1] == 4:
            scales, angles = 2.0 * kp[:, 2], np.mod(np.rad2deg(kp[:, 3]), 360.0)
        elif kp.shape[1] == 6:
            a11, a12, a21, a22 = kp[:, 2], kp[:, 3], kp[:, 4], kp[:, 5]
            scales = np.hypot(a11, a21) + np.hypot(a12, a22)  # 2 x mean of the two axis scales
            angles = np.mod(np.rad2deg(np.arctan2(a21, a11)), 360.0)
        xy = kp[:, :2] - COLMAP_PIXEL_OFFSET
        if len(descriptors) == 0:
            descriptors = descriptors.reshape(0, nbytes or 128)
        return Features(xy, descriptors, self._sizes[name], fkind, scales=scales, angles=angles)

    def _read(self, name: str):
        """``(keypoints, FeatureDescriptors)`` of ``name``; a blob that does not hold its rows x cols (a damaged
        database) is a DatabaseError naming the database and the image."""
        iid = self._ids[name]
        db = self._db()
        what = "keypoints"
        try:
            kp = self._retry(lambda: db.read_keypoints(iid))
            what = "descriptors"
            desc = self._retry(lambda: db.read_descriptors(iid))
        except (ValueError, RuntimeError) as exc:  # pycolmap's check of a blob's size against rows x cols
            raise DatabaseError(f"{self.path}: the {what} of image {name!r} cannot be read (damaged database: "
                                f"{str(exc).strip()})") from None
        return kp, desc

    def validate(self, names=None) -> None:
        """Read every image's keypoints and descriptors (one image at a time): :class:`DatabaseError` for a blob
        whose size does not match its rows x cols, :class:`InputError` for mixed descriptor types -- each naming the
        database and the image. (NaN / inf keypoint coordinates are refused by :meth:`load`: the pairs of that
        image fail and are reported, the others are matched.)

        Cost: one pass over the keypoint and descriptor tables (~1 MB per 8k SIFT features).
        """
        bad = []
        for name in (self._names if names is None else names):
            self._check_name(name)
            _, d = self._read(name)
            data = np.asarray(d.data)
            nbytes = int(data.shape[1]) if data.ndim == 2 else 0
            meta = (_descriptor_kind(d.type, nbytes), nbytes)
            if self._counts[name] and meta != self._desc:
                bad.append(f"{name} ({meta[0]}, {meta[1]} bytes)")
        if bad:
            raise InputError(f"{self.path}: mixed descriptor types: {self._ref!r} has {self._desc[0]} "
                             f"({self._desc[1]} bytes) but {_examples(bad)}; one collection needs one type")


# ====================================================================== hloc
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


def open_source(path: str | os.PathLike) -> FeatureSource:
    """A :class:`ColmapSource` or :class:`H5Source` by file content (SQLite / HDF5 signature).

    Raises :class:`DatabaseError` for a missing file, a folder (detect images first with
    :func:`images_to_database`) or a file of another kind.
    """
    path = Path(path)
    if not path.exists():
        raise DatabaseError(f"feature source not found: {path}")
    if path.is_dir():
        raise DatabaseError(f"{path} is a folder; detect its images into a database first "
                            "(guidedmatch.collection.images_to_database)")
    if pycolmap_opened(path):  # a COLMAP database this process holds: not opened by Python again (sink_base)
        return ColmapSource(path)
    with open(path, "rb") as fh:
        head = fh.read(16)
    if head == _SQLITE_MAGIC:
        return ColmapSource(path)
    if head[:8] == _HDF5_MAGIC:
        return H5Source(path)
    raise DatabaseError(f"{path} is neither a COLMAP database (SQLite) nor an hloc features file (HDF5)")


# ====================================================================== image folder -> COLMAP database
def images_to_database(image_dir: str | os.PathLike, database_path: str | os.PathLike, *, detector: str = "sift",
                       max_features: int | None = None, max_image_size: int | None = None,
                       camera_model: str = "SIMPLE_RADIAL", single_camera: bool = False, progress: bool = True,
                       detector_options: dict | None = None, resume: bool = False,
                       image_names=None, bad_images: str = "refuse", workers: int = 1) -> ColmapSource:
    """Detect the images of a folder with our detectors and store them in a new COLMAP database.

    Images (``IMAGE_EXTENSIONS``, searched recursively, names relative to ``image_dir`` with ``/``) are decoded
    completely (a truncated or corrupt file is never used) and detected with :func:`guidedmatch.features.detect`
    (:func:`guidedmatch.collection.image_folder.extract_folder`); with ``max_image_size`` the image is first
    downscaled so its longer side is at most that (cv2.INTER_AREA) and keypoints are mapped back to original pixels;
    an image whose estimated detection peak exceeds the available memory is refused (MemoryLimitError naming a
    size). Each image gets, like ``colmap feature_extractor``: a camera (``camera_model``, the EXIF focal length or
    ``1.2 max(w, h)``, principal point at the centre; one shared camera with ``single_camera``), a rig and frame,
    4-column keypoints in COLMAP's convention (x + 0.5, y + 0.5, scale, orientation) and descriptors (SIFT as uint8
    of type SIFT -- OpenCV's SIFT bytes, lossless; binary ORB/AKAZE/BRISK as uint8 of type UNDEFINED).

    ``bad_images="refuse"`` (default): every image is decoded before anything is written and a damaged one raises
    ImageReadError naming it (a blank image, without features, raises InputError when reached); ``"skip"``: such
    images are left out and listed in the returned source's ``skipped_images`` (``[{"name", "reason"}]``).
    ``workers`` > 1 decodes and detects in that many processes.

    Each image is written in one transaction, so an interrupted run leaves a valid database holding the images
    done so far; ``resume=True`` accepts an existing database and detects only the images it lacks.
    ``image_names`` (paths relative to ``image_dir``) restricts the run to those images, in that order.

    Raises:
        OutputError: ``database_path`` exists (without ``resume``) or cannot be written.
        InputError / ImageReadError: no images in the folder / an unreadable image (named).
        ConfigError: unknown detector, detector option or camera model.
    """
    from ..features import check_detector_options
    from ..validation import check_bool, check_choice, check_number
    from .image_folder import ExtractorSpec, check_camera_model, extract_folder, image_names_in

    check_choice("images_to_database", "detector", detector, DETECTORS)
    check_number("images_to_database", "max_features", max_features, lo=1, integer=True, allow_none=True)
    check_number("images_to_database", "max_image_size", max_image_size, lo=16, integer=True, allow_none=True)
    check_number("images_to_database", "workers", workers, lo=1, integer=True)
    check_choice("images_to_database", "bad_images", bad_images, ("skip", "refuse"))
    for n, v in (("single_camera", single_camera), ("progress", progress), ("resume", resume)):
        check_bool("images_to_database", n, v)
    options = check_detector_options(detector, dict(detector_options or {}))
    check_camera_model(camera_model)
    image_dir, database_path = Path(image_dir), Path(database_path)
    names = image_names_in(image_dir, image_names)
    if database_path.exists() and not resume:
        raise OutputError(f"database {database_path} exists; pass it as the feature source, delete it, "
                          "or resume=True to complete it")
    if database_path.is_dir():
        raise OutputError(f"database path is a directory: {database_path}")
    parent = database_path.parent if str(database_path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"folder of the database does not exist: {parent}")
    if not os.access(parent, os.W_OK) or (database_path.exists() and not os.access(database_path, os.W_OK)):
        raise OutputError(f"cannot write the COLMAP database {database_path} (read-only)")
    # cheap signature check of every file before any work
    unreadable = [n for n in names if not _have_reader(image_dir / n)]
    if unreadable and bad_images == "refuse":
        raise ImageReadError(f"{len(unreadable)} file(s) in {image_dir} are not readable images: "
                             f"{_examples(unreadable)}")
    skipped = [{"name": n, "reason": f"not a readable image: {image_dir / n}"} for n in unreadable]
    names = [n for n in names if n not in set(unreadable)]
    spec = ExtractorSpec(detector="ours:" + detector, max_features=max_features, max_image_size=max_image_size,
                         detector_options=tuple(sorted(options.items())))
    if names:
        out = extract_folder(image_dir, database_path, names, spec, camera_model=camera_model,
                             single_camera=single_camera, workers=workers, bad_images=bad_images, progress=progress)
        skipped += out["skipped"]
    src = ColmapSource(database_path)
    src.skipped_images = skipped
    return src


def _have_reader(path: Path) -> bool:
    import cv2

    try:
        return bool(cv2.haveImageReader(str(path)))
    except cv2.error:
        return False
