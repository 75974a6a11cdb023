"""Feature sources of a collection: a COLMAP database, an hloc ``features.h5``, or an image folder detected into a
new COLMAP database -- :func:`open_source` opens either file by its content, :func:`images_to_database` detects a
folder of images into a new COLMAP database.

Features are returned in the package's OpenCV pixel convention: ``(0, 0)`` is the **centre** of the top-left pixel
(COLMAP's ``(0.5, 0.5)`` is converted on reading and writing; hloc's keypoints already follow it).

What lives where (every public name is importable from here):

* :mod:`~guidedmatch.collection.source_base` -- :class:`FeatureSource`, the base class: small and picklable (paths
  plus per-image metadata: names, sizes, feature counts); it opens its file lazily in the process that calls
  :meth:`FeatureSource.load`, so Dask workers read features themselves;
* :mod:`~guidedmatch.collection.colmap_source` -- :class:`ColmapSource` (a COLMAP database; its pixel convention,
  :data:`COLMAP_PIXEL_OFFSET`, and descriptor types) and the database checks the sinks reuse;
* :mod:`~guidedmatch.collection.hloc_source` -- :class:`H5Source` (an hloc ``features.h5``) and
  :func:`write_features_h5`;
* here -- :func:`open_source` and :func:`images_to_database` (decoding and detection in
  :mod:`guidedmatch.collection.image_folder`).
"""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import DatabaseError, ImageReadError, OutputError
from ..features import DETECTORS
from .colmap_source import _SQLITE_MAGIC, COLMAP_PIXEL_OFFSET, ColmapSource
from .hloc_source import _HDF5_MAGIC, H5Source, write_features_h5  # noqa: F401 -- re-exported
from .image_folder import IMAGE_EXTENSIONS
from .sink_base import pycolmap_opened
from .source_base import FeatureSource, _examples

__all__ = ["FeatureSource", "ColmapSource", "H5Source", "open_source", "images_to_database", "IMAGE_EXTENSIONS",
           "COLMAP_PIXEL_OFFSET"]


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
