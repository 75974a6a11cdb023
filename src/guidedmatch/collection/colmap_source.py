"""The COLMAP database source: :class:`ColmapSource` reads a collection's features through ``pycolmap.Database``.

Also the checks behind it, which the sinks and the expansion reuse: :func:`_open_colmap` (an existing database,
refused with a :class:`~guidedmatch.errors.DatabaseError` that says why when it is missing, damaged or another
program's SQLite file; retried while a writer holds it) and the descriptor kinds of COLMAP's descriptor types
(:func:`_descriptor_kind`, :func:`_descriptor_rows`).

Pixel convention: COLMAP puts the centre of the top-left pixel at ``(0.5, 0.5)`` (its keypoints span
``[0, w] x [0, h]``): ``x_cv = x_colmap - 0.5`` on reading (:data:`COLMAP_PIXEL_OFFSET`), ``x_colmap = x_cv + 0.5``
on writing. COLMAP stores float32, so a round trip is exact up to the float32 rounding of ``x + 0.5`` (at most half
an ulp: 6e-5 px below 2048 px).

Descriptors: ``FeatureDescriptors`` of type SIFT (uint8, 128-D; RootSIFT as COLMAP's extractor writes it, or OpenCV
SIFT bytes as :func:`~guidedmatch.collection.sources.images_to_database` writes it) load as ``kind="sift"`` float32
(L2); type UNDEFINED with 128 bytes (databases of COLMAP < 3.12) is read as SIFT too, with another length as packed
binary (ORB 32, AKAZE 61, BRISK 64 bytes; Hamming); other COLMAP types (ALIKED, LoMa) are converted with
``FeatureDescriptors.to_float()`` to float32 (L2).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..errors import DatabaseError, InputError
from ..features import BINARY_KINDS, Features
from .sink_base import open_pycolmap_database, pycolmap_opened
from .source_base import FeatureSource, _check_finite, _examples

__all__ = ["ColmapSource", "COLMAP_PIXEL_OFFSET"]

#: COLMAP pixel coordinate minus OpenCV pixel coordinate of the same point.
COLMAP_PIXEL_OFFSET = 0.5
_BINARY_BY_BYTES = {32: "orb", 61: "akaze", 64: "brisk"}
_SQLITE_MAGIC = b"SQLite format 3\x00"


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
