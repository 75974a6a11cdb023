"""SIFT features of a folder of photos into a COLMAP database, on all cores: :func:`extract_to_database`.

Two extractors write the same kind of database (what ``colmap feature_extractor`` writes, readable by
``pycolmap.incremental_mapping``, ``colmap mapper`` and :class:`guidedmatch.collection.ColmapSource`):

* ``"opencv"`` -- OpenCV's SIFT (``cv2.SIFT``, one image per thread: OpenCV and Pillow's decoder release the GIL),
  made to look like COLMAP's SIFT:

  - the image is read once with Pillow, fully decoded as 8-bit grey (a truncated or damaged file raises and is
    reported by name -- OpenCV's ``imread`` would return the decoded part with only a warning), downscaled with
    ``cv2.INTER_AREA`` when its longer side exceeds ``max_image_size`` (COLMAP's 3200), and handed to SIFT;
  - COLMAP's scale space: the image upsampled once (``first_octave=-1``, OpenCV's precise upscale so keypoints
    are not shifted by a quarter pixel), ``num_octaves`` octaves of 3 levels, peak threshold 0.0067 (COLMAP's
    ``peak_threshold`` = OpenCV's ``contrastThreshold / nOctaveLayers``), edge threshold 10, at most 2 orientations
    per detection;
  - COLMAP's choice of ``max_features``: whole scale levels are kept from the coarsest down until the detections
    (orientations not counted) exceed ``max_features`` -- the level that crosses the limit is kept whole, so an
    image can have more rows than ``max_features``, as in COLMAP (``selection="scale"``: exactly the
    ``max_features`` largest-scale rows instead);
  - COLMAP's descriptor: RootSIFT (L1-normalised, square root) times 512, rounded, saturated to uint8 -- OpenCV's
    and COLMAP's bins are in the same order (checked against pycolmap on a shared image: correlation 0.87 for the
    same keypoint, < 0.4 for any of COLMAP's VLFeat reorderings);
  - keypoints in COLMAP's convention: pixel centres at +0.5 (x + 0.5, y + 0.5 of OpenCV's), multiplied by the
    original / detected size ratio, scale = OpenCV's diameter / 2 (COLMAP's sigma: ratio 0.498 measured),
    orientation = OpenCV's angle in radians (the same direction as COLMAP's, measured).

* ``"pycolmap"`` -- ``pycolmap.extract_features`` (COLMAP's VLFeat SIFT) with the options of
  :class:`ExtractionConfig` (``first_octave``, ``max_image_size``, ``max_features``, ``num_threads``).

Cameras are made as COLMAP's image reader makes them (one camera per image, ``camera_model``, principal point at
the centre): the focal length from EXIF when the photo has it (35 mm equivalent: ``f35 / 43.27 x diagonal``, or
``FocalLength x FocalPlaneXResolution``; prior focal flag set) else ``1.2 x max(width, height)`` (no prior).
COLMAP's third EXIF rule (a sensor-width table by camera make and model) is not reproduced: such photos get the
1.2 x guess. ``single_camera`` shares one camera among all images (they must have one size).

Resumable: an image already in the database with keypoints and descriptors is not read again. Each image is written
in one transaction (camera, rig, image, frame, keypoints, descriptors), so an interrupted run leaves a valid
database of the images done. Memory is bounded: at most ``2 x workers`` images are decoded or detected at once.
A damaged image is skipped and named in the report (``on_error="skip"``, the default) or stops the run before
anything of it is written (``on_error="raise"``).

:func:`iter_features` is the same extraction as a generator that yields each image's features as soon as they
exist (completion order), for a consumer that starts work on an image before the others are done.
"""
from __future__ import annotations

import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from .collection.sink_base import check_database_space, open_pycolmap_database
from .errors import ConfigError, ImageReadError, InputError, OutputError
from .validation import check_bool, check_choice, check_number, config_from

__all__ = ["ExtractionConfig", "ImageFeatures", "EXTRACTORS", "read_grey", "exif_focal_px", "sift_opencv",
           "colmap_level_selection", "rootsift_uint8", "extract_image", "iter_features", "extract_to_database",
           "OrderedImageWriter", "extract_pycolmap", "database_keypoint_counts"]

#: Extractors of :class:`ExtractionConfig`.
EXTRACTORS = ("opencv", "pycolmap")
#: COLMAP's pixel convention: the centre of the top-left pixel is (0.5, 0.5); OpenCV's is (0, 0).
COLMAP_PIXEL_OFFSET = 0.5
#: COLMAP's focal-length guess without EXIF, times the longer image side.
DEFAULT_FOCAL_FACTOR = 1.2
#: OpenCV's SIFT levels per octave (COLMAP's ``octave_resolution``).
OCTAVE_RESOLUTION = 3


@dataclass(frozen=True)
class ExtractionConfig:
    """Settings of :func:`extract_to_database` (checked on construction)."""

    extractor: str = "opencv"          # "opencv" (OpenCV SIFT, COLMAP's conventions) | "pycolmap" (COLMAP's own SIFT)
    max_features: int = 8192           # COLMAP's max_num_features (see selection)
    max_image_size: int = 3200         # longest side before detection (COLMAP's default); larger images downscaled
    first_octave: int = -1             # -1: image upsampled x2 first (COLMAP's default); 0: native resolution (pycolmap only)
    num_octaves: int = 4               # octaves from first_octave (COLMAP's 4: scales up to 2^2 of the image)
    peak_threshold: float = 0.02 / 3   # DoG peak threshold on [0, 1] intensities (COLMAP's 0.0067)
    edge_threshold: float = 10.0       # ratio of principal curvatures (COLMAP's and OpenCV's 10)
    max_orientations: int = 2          # orientations kept per detection (COLMAP's 2)
    selection: str = "levels"          # "levels": COLMAP's whole-level rule; "scale": exactly the largest max_features
    camera_model: str = "SIMPLE_RADIAL"  # camera model of each image's camera (COLMAP's default)
    single_camera: bool = False        # one camera for all images (same size required)
    workers: int | None = None         # images detected at once; None = os.cpu_count(); pycolmap: its num_threads
    on_error: str = "skip"             # damaged image: "skip" (named in the report) | "raise" (ImageReadError)
    progress: bool = True              # progress bar with images/s and ETA on stderr

    def __post_init__(self) -> None:
        o = "ExtractionConfig"
        check_choice(o, "extractor", self.extractor, EXTRACTORS)
        check_number(o, "max_features", self.max_features, lo=1, integer=True)
        check_number(o, "max_image_size", self.max_image_size, lo=16, integer=True)
        check_choice(o, "first_octave", self.first_octave, (-1, 0))
        if self.extractor == "opencv" and self.first_octave != -1:
            raise ConfigError(f"{o}.first_octave=0 needs extractor='pycolmap' (OpenCV's SIFT always upsamples the "
                              "image once); for a cheaper OpenCV extraction lower max_image_size")
        check_number(o, "num_octaves", self.num_octaves, lo=1, hi=16, integer=True)
        check_number(o, "peak_threshold", self.peak_threshold, lo=0, lo_open=True)
        check_number(o, "edge_threshold", self.edge_threshold, lo=1, lo_open=True)
        check_number(o, "max_orientations", self.max_orientations, lo=1, hi=4, integer=True)
        check_choice(o, "selection", self.selection, ("levels", "scale"))
        if self.extractor == "pycolmap" and self.selection != "levels":
            raise ConfigError(f"{o}.selection='scale' is for extractor='opencv' (pycolmap applies COLMAP's rule)")
        from .collection.image_folder import check_camera_model

        check_camera_model(self.camera_model, f"{o}.camera_model")
        check_bool(o, "single_camera", self.single_camera)
        check_number(o, "workers", self.workers, lo=1, integer=True, allow_none=True)
        check_choice(o, "on_error", self.on_error, ("skip", "raise"))
        check_bool(o, "progress", self.progress)

    @property
    def num_workers(self) -> int:
        return int(self.workers or os.cpu_count() or 1)


@dataclass(frozen=True)
class ImageFeatures:
    """One image's features in COLMAP's conventions (what goes into the database)."""

    name: str                 # path relative to the image folder, "/"-separated (COLMAP's image name)
    width: int                # original image size (px)
    height: int
    keypoints: np.ndarray     # (N, 4) float32: x, y (COLMAP pixel convention, original pixels), scale, orientation (rad)
    descriptors: np.ndarray   # (N, 128) uint8 RootSIFT x 512 (COLMAP's SIFT rows)
    focal_px: float | None    # focal length from EXIF (px), None without
    timing: dict = field(default_factory=dict, repr=False)  # read_s, detect_s (seconds of the worker)


# --------------------------------------------------------------------------- reading
def exif_focal_px(exif, width: int, height: int) -> float | None:
    """Focal length in pixels from EXIF tags as COLMAP computes it, or None.

    ``exif``: a mapping of EXIF tag numbers (Pillow's ``Image.getexif().get_ifd(0x8769)`` merged with the base IFD).
    Rules: ``FocalLengthIn35mmFilm`` (0xA405) ``/ 43.27 x sqrt(w^2 + h^2)``; else ``FocalLength`` (0x920A) x
    ``FocalPlaneXResolution`` (0xA20E) in pixels per mm (unit 0xA210: 2 inch, 3 cm, 4 mm, 5 um).

    >>> round(exif_focal_px({0xA405: 28}, 4000, 3000), 1)
    3235.5
    >>> exif_focal_px({0x920A: 4.3, 0xA20E: 1000.0, 0xA210: 4}, 100, 100)
    4300.0
    >>> exif_focal_px({}, 100, 100) is None
    True
    """
    def num(tag):
        v = exif.get(tag)
        try:
            v = float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return v if np.isfinite(v) and v > 0 else None

    f35 = num(0xA405)
    if f35:
        return f35 / 43.27 * float(np.hypot(width, height))
    f_mm, xres, unit = num(0x920A), num(0xA20E), exif.get(0xA210)
    per_mm = {2: 1 / 25.4, 3: 0.1, 4: 1.0, 5: 1000.0}.get(unit if isinstance(unit, int) else -1)
    if f_mm and xres and per_mm:
        return f_mm * xres * per_mm
    return None


def read_grey(path: str | os.PathLike) -> tuple[np.ndarray, float | None]:
    """The whole image as 8-bit grey ``(H, W) uint8`` (JPEG: the decoder's luma, others: Pillow's ``L``) and the
    EXIF focal length in pixels (:func:`exif_focal_px`) or None. Pixels as stored (no EXIF rotation), as COLMAP.

    Raises:
        ImageReadError: the file is missing, not an image, or damaged (truncated, corrupt data) -- Pillow decodes
            every byte and raises; nothing partial is returned.
    """
    from PIL import Image, ImageFile, UnidentifiedImageError

    if ImageFile.LOAD_TRUNCATED_IMAGES:  # a process-wide switch another library may have set: never accept it
        raise ImageReadError("PIL.ImageFile.LOAD_TRUNCATED_IMAGES is True in this process: truncated images would "
                             "be decoded partially; set it to False")
    path = Path(path)
    try:
        with Image.open(path) as im:
            try:
                exif = dict(im.getexif())
                exif.update(im.getexif().get_ifd(0x8769))
            except Exception:  # noqa: BLE001 - damaged EXIF: no focal length, like COLMAP
                exif = {}
            if im.format == "JPEG" and im.mode in ("RGB", "L", "YCbCr"):
                im.draft("L", im.size)     # decode the luma channel only (no colour conversion)
            if im.mode not in ("L", "RGB", "RGBA", "P", "LA", "I;16", "I", "F", "CMYK", "YCbCr", "1"):
                raise ImageReadError(f"{path}: unsupported image mode {im.mode!r}")
            im.load()
            if im.mode in ("I;16", "I", "F"):  # 16-bit / float: scale to 8 bits by the type's range
                arr = np.asarray(im, dtype=np.float64)
                top = 65535.0 if im.mode != "F" else max(float(arr.max()), 1e-12)
                grey = np.clip(np.rint(arr * (255.0 / top)), 0, 255).astype(np.uint8)
            else:
                grey = np.asarray(im if im.mode == "L" else im.convert("L"), dtype=np.uint8)
            w, h = im.size
    except FileNotFoundError:
        raise ImageReadError(f"{path}: no such file") from None
    except UnidentifiedImageError:
        raise ImageReadError(f"{path}: not an image file Pillow can read") from None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise ImageReadError(f"image file is truncated or corrupt: {path} ({exc})") from None
    if grey.shape != (h, w) or grey.size == 0:
        raise ImageReadError(f"{path}: decoded {grey.shape} pixels for a {w}x{h} image")
    return np.ascontiguousarray(grey), exif_focal_px(exif, w, h)


# --------------------------------------------------------------------------- OpenCV SIFT, COLMAP's way
def _octave_layer(octave_field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's packed ``KeyPoint.octave`` -> (octave relative to the input image, layer).

    >>> _octave_layer(np.array([255 + (2 << 8), 1 + (3 << 8)]))
    (array([-1,  1]), array([2, 3]))
    """
    o = octave_field & 255
    return np.where(o >= 128, o - 256, o), (octave_field >> 8) & 255


def colmap_level_selection(octave: np.ndarray, layer: np.ndarray, xy: np.ndarray, scale: np.ndarray,
                           max_features: int, max_orientations: int = 2, selection: str = "levels") -> np.ndarray:
    """Sorted indices of the rows COLMAP would keep.

    Rows with the same level and position are one detection with several orientations; at most
    ``max_orientations`` of them are kept (the first ones). ``"levels"``: levels (octave, layer) are taken from the
    coarsest down until the number of detections exceeds ``max_features`` (that level kept whole; COLMAP's
    ``SiftCPUFeatureExtractor``). ``"scale"``: the ``max_features`` rows of largest scale.

    >>> octv = np.array([0, 0, 0, 1, 1]); lay = np.array([1, 1, 2, 1, 1])
    >>> xy = np.array([[0, 0], [0, 0], [5, 5], [1, 1], [2, 2]], float)
    >>> sc = np.array([1., 1, 2, 3, 4])
    >>> [sorted(colmap_level_selection(octv, lay, xy, sc, m).tolist()) for m in (1, 2, 3)]
    [[3, 4], [2, 3, 4], [0, 1, 2, 3, 4]]
    >>> sorted(colmap_level_selection(octv, lay, xy, sc, 3, max_orientations=1).tolist())
    [0, 2, 3, 4]
    """
    n = len(octave)
    if n == 0:
        return np.zeros(0, np.int64)
    level = octave.astype(np.int64) * 64 + layer.astype(np.int64)
    order = np.lexsort((np.arange(n), xy[:, 1], xy[:, 0], level))
    lv, x, y = level[order], xy[order, 0], xy[order, 1]
    new_det = np.ones(n, bool)
    new_det[1:] = (lv[1:] != lv[:-1]) | (x[1:] != x[:-1]) | (y[1:] != y[:-1])
    det_id = np.cumsum(new_det) - 1
    first = np.flatnonzero(new_det)
    rank = np.arange(n) - first[det_id]
    keep = order[rank < max_orientations]
    if selection == "scale":
        if len(keep) > max_features:
            keep = keep[np.argsort(-scale[keep], kind="stable")[:max_features]]
        return np.sort(keep)
    # detections per level, coarsest level first
    kept_level = level[keep]
    is_det = new_det[np.argsort(order)][keep]       # one row of each detection counts
    levels = np.unique(kept_level)[::-1]
    count = 0
    cut = levels[-1]
    for lvl in levels:
        count += int(np.count_nonzero(is_det & (kept_level == lvl)))
        cut = lvl
        if count > max_features:
            break
    return np.sort(keep[kept_level >= cut])


def rootsift_uint8(desc: np.ndarray) -> np.ndarray:
    """SIFT rows (any positive scale, e.g. OpenCV's 0..255 floats) -> COLMAP's stored RootSIFT rows:
    ``min(255, round(512 sqrt(d / |d|_1)))`` as uint8 (all-zero rows stay zero).

    >>> rootsift_uint8(np.array([[4.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])).tolist()   # 512 x 0.5 saturates
    [[255, 0, 0, 0], [255, 255, 255, 255]]
    >>> rootsift_uint8(np.full((1, 16), 3.0)).tolist() == [[128] * 16]
    True
    """
    d = np.asarray(desc, np.float32)
    l1 = d.sum(axis=1, keepdims=True)
    root = np.sqrt(d / np.where(l1 > 0, l1, 1.0))
    return np.minimum(np.rint(root * 512.0), 255.0).astype(np.uint8)


def sift_opencv(grey: np.ndarray, conf: ExtractionConfig) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP-style SIFT of an 8-bit grey image with OpenCV: ``(keypoints (N, 4) float32, descriptors (N, 128)
    uint8)``, keypoints in COLMAP's convention in the pixels of ``grey`` (x + 0.5, y + 0.5, sigma, angle rad)."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=0, nOctaveLayers=OCTAVE_RESOLUTION,
                           contrastThreshold=float(conf.peak_threshold) * OCTAVE_RESOLUTION,
                           edgeThreshold=float(conf.edge_threshold), sigma=1.6, descriptorType=cv2.CV_32F,
                           enable_precise_upscale=True)
    kps, desc = sift.detectAndCompute(grey, None)   # one scale space; rows not kept are dropped below
    if not kps:
        return np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8)
    packed = np.fromiter((k.octave for k in kps), np.int64, len(kps))
    octave, layer = _octave_layer(packed)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    size = np.fromiter((k.size for k in kps), np.float64, len(kps))
    ok = np.flatnonzero(octave <= conf.first_octave + conf.num_octaves - 1)   # COLMAP's coarsest octave
    keep = ok[colmap_level_selection(octave[ok], layer[ok], xy[ok], size[ok], conf.max_features,
                                     conf.max_orientations, conf.selection)]
    kps = [kps[i] for i in keep]
    desc = np.asarray(desc).reshape(-1, 128)[keep]
    n = len(kps)
    out = np.empty((n, 4), np.float32)
    out[:, :2] = np.array([k.pt for k in kps], np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET
    out[:, 2] = np.fromiter((k.size for k in kps), np.float64, n) / 2.0
    out[:, 3] = np.deg2rad(np.fromiter((k.angle for k in kps), np.float64, n))
    return out, rootsift_uint8(desc)


def extract_image(image_dir: str | os.PathLike, name: str, conf: ExtractionConfig) -> ImageFeatures:
    """Read (once), downscale to ``max_image_size`` if larger, detect (:func:`sift_opencv`); keypoints scaled back to
    the original pixels (COLMAP's convention makes that a multiplication). Raises ImageReadError (named)."""
    import cv2

    t0 = time.perf_counter()
    grey, focal = read_grey(Path(image_dir) / name)
    h, w = grey.shape
    t1 = time.perf_counter()
    s = min(1.0, conf.max_image_size / max(w, h))
    img = grey
    if s < 1.0:
        img = cv2.resize(grey, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
        del grey
    kp, desc = sift_opencv(img, conf)
    if img.shape != (h, w):
        kp[:, 0] *= w / img.shape[1]
        kp[:, 1] *= h / img.shape[0]
        kp[:, 2] *= 0.5 * (w / img.shape[1] + h / img.shape[0])
    return ImageFeatures(name, w, h, kp, desc, focal, {"read_s": t1 - t0, "detect_s": time.perf_counter() - t1})


# --------------------------------------------------------------------------- the parallel loop
def iter_features(image_dir: str | os.PathLike, names: Iterable[str], conf: ExtractionConfig | dict | None = None,
                  ) -> Iterator[ImageFeatures | tuple[str, ImageReadError]]:
    """Yield each image's :class:`ImageFeatures` as soon as it exists (completion order), or ``(name, error)`` for
    an image that could not be read. ``conf.num_workers`` threads, at most twice that many images in flight (decoded
    or being detected), so memory stays bounded whatever the number of images. OpenCV is limited to one thread per
    call inside (the images give the parallelism) and restored afterwards."""
    import cv2

    conf = config_from(ExtractionConfig, conf)
    if conf.extractor != "opencv":
        raise ConfigError("iter_features runs the 'opencv' extractor; use extract_pycolmap for pycolmap")
    names = list(names)
    nw = conf.num_workers
    old_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(nw, thread_name_prefix="guidedmatch-sift") as pool:
            pending: dict = {}
            it = iter(names)
            for name in it:
                pending[pool.submit(extract_image, image_dir, name, conf)] = name
                if len(pending) >= 2 * nw:
                    break
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    name = pending.pop(fut)
                    try:
                        yield fut.result()
                    except ImageReadError as exc:
                        yield name, exc
                    nxt = next(it, None)
                    if nxt is not None:
                        pending[pool.submit(extract_image, image_dir, nxt, conf)] = nxt
    finally:
        cv2.setNumThreads(old_threads)


# --------------------------------------------------------------------------- database
def database_keypoint_counts(database_path: str | os.PathLike) -> dict[str, int]:
    """``{image name: keypoints}`` of the images of a COLMAP database that have keypoints *and* descriptors
    (an image without either counts 0)."""
    import pycolmap

    db = open_pycolmap_database(database_path)
    try:
        return {im.name: (int(db.num_keypoints_for_image(im.image_id))
                          if db.exists_keypoints(im.image_id) and db.exists_descriptors(im.image_id) else 0)
                for im in db.read_all_images()}
    finally:
        db.close()


def _check_database_path(database_path: Path) -> None:
    if database_path.is_dir():
        raise OutputError(f"database path is a directory: {database_path}")
    parent = database_path.parent
    if not parent.is_dir():
        raise OutputError(f"folder of the database does not exist: {parent}")
    if not os.access(parent, os.W_OK) or (database_path.exists() and not os.access(database_path, os.W_OK)):
        raise OutputError(f"cannot write the COLMAP database {database_path}")


class _Writer:
    """Writes one image per transaction (camera, rig, image, frame, keypoints, descriptors) into an open database."""

    def __init__(self, db, conf: ExtractionConfig, path: Path) -> None:
        self.db, self.conf, self.path = db, conf, path
        self.shared = self.shared_rig = None
        if conf.single_camera and db.num_cameras() > 0:
            self.shared = db.read_all_cameras()[0]
            self.shared_rig = next((r.rig_id for r in db.read_all_rigs() if r.has_sensor(self.shared.sensor_id)),
                                   None)

    def write(self, f: ImageFeatures) -> int:
        """Write ``f`` (one transaction); returns its image id."""
        import pycolmap

        db = self.db
        if self.shared is not None and (self.shared.width, self.shared.height) != (f.width, f.height):
            raise InputError(f"single_camera: {f.name} is {f.width}x{f.height} but the shared camera is "
                             f"{self.shared.width}x{self.shared.height}")
        desc = pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, np.ascontiguousarray(f.descriptors))
        check_database_space(self.path, np.asarray(f.keypoints).nbytes + np.asarray(f.descriptors).nbytes)
        with pycolmap.DatabaseTransaction(db):
            old = db.read_image_with_name(f.name)
            if old is None:
                if self.shared is not None:
                    cam_id, rig_id = self.shared.camera_id, self.shared_rig
                else:
                    focal = f.focal_px or DEFAULT_FOCAL_FACTOR * max(f.width, f.height)
                    cam = pycolmap.Camera.create_from_model_name(0, self.conf.camera_model, focal, f.width, f.height)
                    cam.has_prior_focal_length = f.focal_px is not None
                    cam.camera_id = db.write_camera(cam)
                    rig = pycolmap.Rig()
                    rig.add_ref_sensor(cam.sensor_id)
                    rig_id = db.write_rig(rig)
                    cam_id = cam.camera_id
                    if self.conf.single_camera:
                        self.shared, self.shared_rig = cam, rig_id
                iid = db.write_image(pycolmap.Image(name=f.name, camera_id=cam_id))
                frame = pycolmap.Frame()
                frame.rig_id = rig_id
                frame.add_data_id(db.read_image(iid).data_id)
                db.write_frame(frame)
            else:
                iid = old.image_id
                cam = db.read_camera(old.camera_id)
                if (cam.width, cam.height) != (f.width, f.height):
                    raise InputError(f"{f.name} is {f.width}x{f.height} but its camera in the database is "
                                     f"{cam.width}x{cam.height}")
            kp = np.ascontiguousarray(f.keypoints, np.float32)
            if db.exists_keypoints(iid):
                db.update_keypoints(iid, kp)
            else:
                db.write_keypoints(iid, kp)
            if db.exists_descriptors(iid):
                db.update_descriptors(iid, desc)
            else:
                db.write_descriptors(iid, desc)
        return int(iid)


class OrderedImageWriter:
    """Writes finished images into an open database in the order of ``todo`` (image ids follow the names, as with
    COLMAP's extractor), whatever order they finish in: an image waits in memory until every image before it is
    written or has failed. One transaction per image (:class:`_Writer`), so a kill leaves complete images only.

    :meth:`add` takes what :func:`iter_features` yields (features, or ``(name, ImageReadError)``) and returns the
    images resolved by it, in ``todo`` order: ``(name, image id, features)`` for a written one, ``(name, None, None)``
    for a damaged one (listed in ``failed`` with the reason; with ``on_error="raise"`` its error is raised instead).
    """

    def __init__(self, db, conf: ExtractionConfig, path: Path, todo: list[str], bar=None) -> None:
        self._writer = _Writer(db, conf, path)
        self.conf, self.todo, self.bar = conf, list(todo), bar
        self.ready: dict = {}     # finished out of order, waiting for the images before them
        self.next = 0             # todo[:next] are resolved
        self.failed: list[dict] = []
        self.read_s = self.detect_s = 0.0

    @property
    def waiting(self) -> int:
        """Images finished but not yet written (held in memory)."""
        return len(self.ready)

    def add(self, item: "ImageFeatures | tuple[str, ImageReadError]") -> list[tuple]:
        if isinstance(item, tuple):
            name, exc = item
            if self.conf.on_error == "raise":
                raise exc
            self.failed.append({"name": name, "reason": str(exc)})
            if self.conf.progress and self.bar is not None:  # (otherwise the caller reports the returned "failed")
                self.bar.write(f"skipping {name}: {exc}", file=sys.stderr)
            self.ready[name] = None
        else:
            self.ready[item.name] = item
        out = []
        while self.next < len(self.todo) and self.todo[self.next] in self.ready:
            name = self.todo[self.next]
            f = self.ready.pop(name)
            self.next += 1
            if f is None:
                out.append((name, None, None))
                continue
            iid = self._writer.write(f)
            self.read_s += f.timing["read_s"]
            self.detect_s += f.timing["detect_s"]
            out.append((name, iid, f))
        return out


def extract_to_database(image_dir: str | os.PathLike, database_path: str | os.PathLike,
                        conf: ExtractionConfig | dict | None = None, *, image_names: Iterable[str] | None = None,
                        on_image: Callable[[ImageFeatures], None] | None = None) -> dict:
    """SIFT features of the images of ``image_dir`` (or ``image_names``, relative to it) into the COLMAP database
    ``database_path`` (created if missing; images already there with features are reused). See the module
    docstring for the conventions. Images are written in ``image_names`` order (image ids follow it, as with COLMAP's extractor); ``on_image(features)``
    is called (in this thread) after each image is written.

    Returns ``{"extractor", "config", "time_s", "extracted", "reused", "failed": [{"name", "reason"}],
    "keypoints": {"total", "min", "median", "max"}, "per_image": {name: keypoints}, "read_s", "detect_s"}``
    (``read_s`` / ``detect_s``: summed over the workers).

    Raises before any work: InputError (missing folder, no images, unknown names), OutputError (database path not
    writable), ConfigError. During: ImageReadError for a damaged image with ``on_error="raise"`` (the images written
    before it stay, each complete).
    """
    conf = config_from(ExtractionConfig, conf)
    image_dir, database_path = Path(image_dir), Path(database_path)
    from .collection.image_folder import image_names_in

    names = image_names_in(image_dir, image_names, allow_empty=True)
    _check_database_path(database_path)
    t0 = time.perf_counter()
    before = database_keypoint_counts(database_path) if database_path.exists() else {}
    todo = [n for n in names if before.get(n, 0) == 0]
    failed: list[dict] = []
    read_s = detect_s = 0.0
    if todo and conf.extractor == "pycolmap":
        extract_pycolmap(image_dir, database_path, todo, conf)
    elif todo:
        import pycolmap
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="SIFT", unit="img", disable=not conf.progress, file=sys.stderr,
                   dynamic_ncols=True)
        check_database_space(database_path, 0)  # opening a new database writes its schema
        db = open_pycolmap_database(database_path)
        try:
            writer = OrderedImageWriter(db, conf, database_path, todo, bar=bar)
            gen = iter_features(image_dir, todo, conf)
            try:
                for item in gen:
                    bar.update(1)
                    for _name, _iid, f in writer.add(item):
                        if on_image is not None and f is not None:
                            on_image(f)
            finally:
                gen.close()
        finally:
            db.close()
            bar.close()
        failed, read_s, detect_s = writer.failed, writer.read_s, writer.detect_s
    after = database_keypoint_counts(database_path)
    if conf.extractor == "pycolmap":   # COLMAP logs and skips an image it cannot read
        failed = [{"name": n, "reason": "COLMAP's reader could not read it (see its log)"}
                  for n in todo if after.get(n, 0) == 0 and n not in after]
    counts = [after[n] for n in names if after.get(n, 0) > 0]
    return {"extractor": conf.extractor, "config": asdict(conf), "time_s": time.perf_counter() - t0,
            "extracted": sum(1 for n in todo if after.get(n, 0) > 0), "reused": len(names) - len(todo),
            "failed": failed,
            "keypoints": {"total": int(sum(counts)), "min": int(min(counts, default=0)),
                          "median": float(np.median(counts)) if counts else 0.0, "max": int(max(counts, default=0))},
            "per_image": {n: after.get(n, 0) for n in names}, "read_s": read_s, "detect_s": detect_s}


def extract_pycolmap(image_dir: str | os.PathLike, database_path: str | os.PathLike, names: list[str],
                     conf: ExtractionConfig) -> None:
    """``pycolmap.extract_features`` (COLMAP's CPU SIFT) with ``conf``'s options (``workers`` -> ``num_threads``)."""
    import pycolmap

    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = conf.workers or -1
    ext.use_gpu = False
    ext.max_image_size = conf.max_image_size
    ext.sift.max_num_features = conf.max_features
    ext.sift.first_octave = conf.first_octave
    ext.sift.num_octaves = conf.num_octaves
    ext.sift.peak_threshold = conf.peak_threshold
    ext.sift.edge_threshold = conf.edge_threshold
    ext.sift.max_num_orientations = conf.max_orientations
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = conf.camera_model
    mode = pycolmap.CameraMode.SINGLE if conf.single_camera else pycolmap.CameraMode.AUTO
    # COLMAP's extractor writes in its own threads, where a full disk aborts the process: room for every image at
    # its feature budget (keypoints 24 + descriptor 128 bytes a feature) is checked before it starts
    check_database_space(Path(database_path), len(names) * conf.max_features * 152)
    pycolmap.extract_features(str(database_path), str(image_dir), image_names=list(names), camera_mode=mode,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)

