"""An image folder into a COLMAP database: every image decoded once, completely, and its features extracted from
those pixels.

Each image is read by the package's strict reader (:func:`guidedmatch.features.read_image_strict`): a truncated or
corrupt file (libjpeg's "Premature end of JPEG file", a PNG without ``IEND``, a CRC error, ...) is never used,
whatever the extractor would have made of it. The decoded pixels go straight to the extractor:

* ``"colmap"``: pycolmap's SIFT (``pycolmap.FeatureExtractor``, the extractor of ``colmap feature_extractor``) on
  COLMAP's own grey conversion of the RGB pixels (``Bitmap.clone_as_grey``), downscaled as COLMAP does
  (``Bitmap.thumbnail(max_image_size)``, keypoints rescaled to the original pixels like COLMAP's
  ``ScaleKeypoints``): the same keypoints and descriptors as ``pycolmap.extract_features`` on the same file;
* ``"ours:<detector>"``: :func:`guidedmatch.features.detect` on the decoder's grey image (SIFT as uint8 of type
  SIFT, binary descriptors as uint8 of type UNDEFINED).

Cameras as COLMAP's image reader makes them: ``camera_model`` with the EXIF focal length when the file has one
(``pycolmap.infer_camera_from_image``; a prior focal length) or ``1.2 max(w, h)`` otherwise; images of the same EXIF
camera (make, model, focal length, size) share a camera; ``single_camera`` shares one camera; ``camera=(model,
params)`` gives every image that known camera. One rig and one frame per camera/image, like COLMAP. (Not copied
from COLMAP's reader: GPS pose priors from EXIF and masks.)

Workers: pycolmap's extractor holds the GIL, so images are decoded and extracted in worker processes (``spawn``;
one image each at a time, at most ``2 x workers`` results waiting; in this process when there are fewer than
:data:`IN_PROCESS_MAX_MP` megapixels to extract) and written by this process, one transaction
per image, in name order: an interrupted run leaves a valid database with the images done so far, and a rerun
extracts only the images without keypoints.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DatabaseError, GuidedMatchError, ImageReadError, InputError, MemoryLimitError
from .sink_base import check_database_space, open_pycolmap_database

__all__ = ["IMAGE_EXTENSIONS", "ExtractorSpec", "list_images", "decode_image", "extract_image", "extract_folder",
           "COLMAP_MAX_IMAGE_SIZE"]

#: File suffixes taken as images (case-insensitive).
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".jp2")
#: ``colmap feature_extractor``'s longest image side, used when ``max_image_size`` is not given for ``"colmap"``.
COLMAP_MAX_IMAGE_SIZE = 3200
#: Our detectors, as ``detector="ours:<name>"``.
OUR_DETECTORS = ("sift", "orb", "akaze", "brisk")
_EXIF_FOCAL_TAGS = (37386, 41989)  # FocalLength, FocalLengthIn35mmFilm (Exif IFD)


@dataclass(frozen=True)
class ExtractorSpec:
    """What determines an image's features (picklable; sent to the workers)."""

    detector: str = "colmap"             # "colmap" (pycolmap SIFT) or "ours:sift|orb|akaze|brisk"
    max_features: int | None = None      # features per image; None = the detector's default (8192 for COLMAP SIFT)
    max_image_size: int | None = None    # longest side before extraction; None = 3200 for COLMAP, none for ours
    peak_threshold: float | None = None  # COLMAP SIFT peak threshold; None = COLMAP's default
    detector_options: tuple = ()         # ours: sorted (name, value) OpenCV factory options

    def __post_init__(self) -> None:
        det = self.detector
        if det != "colmap" and not (det.startswith("ours:") and det[5:] in OUR_DETECTORS):
            raise ConfigError(f"detector must be 'colmap' or one of {', '.join('ours:' + d for d in OUR_DETECTORS)}; "
                              f"got {det!r}")
        if self.peak_threshold is not None and det != "colmap":
            raise ConfigError(f"peak_threshold applies to the COLMAP SIFT detector only (detector={det!r})")


def list_images(image_dir: str | os.PathLike) -> list[str]:
    """Image files under ``image_dir`` (recursive, by suffix, hidden folders included), as sorted POSIX paths
    relative to it -- the names COLMAP gives them. Other files (e.g. a ``K.txt``) are ignored."""
    root = Path(image_dir)
    names = []
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for f in files:
            if f.lower().endswith(IMAGE_EXTENSIONS) and Path(folder, f).is_file():
                names.append(Path(folder, f).relative_to(root).as_posix())
    return sorted(names)


def image_names_in(image_dir: str | os.PathLike, image_names=None, *, allow_empty: bool = False) -> list[str]:
    """The images to use from ``image_dir``: all of them (:func:`list_images`) when ``image_names`` is None, else
    ``image_names`` as POSIX paths, each checked to be a file there and none repeated. InputError when the folder is
    missing, a name is not a file or repeats, or there is no image (an explicit empty list is allowed with
    ``allow_empty``)."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise InputError(f"image folder not found: {image_dir}")
    if image_names is None:
        names = list_images(image_dir)
    else:
        names = [Path(str(n)).as_posix() for n in image_names]
        missing = [n for n in names if not (image_dir / n).is_file()]
        if missing:
            raise InputError(f"{len(missing)} of the image_names are not files in {image_dir}: "
                             f"{', '.join(missing[:5])}" + (" ..." if len(missing) > 5 else ""))
        if len(set(names)) != len(names):
            raise InputError("image_names has repeated names")
    if not names and not (allow_empty and image_names is not None):
        raise InputError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {image_dir}")
    return names


def decode_image(path: str | os.PathLike, rgb: bool) -> np.ndarray:
    """The whole image, decoded strictly (ImageReadError naming the file otherwise): ``(h, w, 3)`` RGB uint8 when
    ``rgb`` (COLMAP's extractor input), else the decoder's ``(h, w)`` grey. EXIF orientation is not applied (COLMAP
    does not rotate the pixels either: keypoints stay in the file's pixel frame)."""
    import cv2

    from ..features import read_image_strict

    flags = (cv2.IMREAD_COLOR if rgb else cv2.IMREAD_GRAYSCALE) | cv2.IMREAD_IGNORE_ORIENTATION
    img = read_image_strict(path, flags)
    if img.size == 0 or min(img.shape[:2]) == 0:
        raise ImageReadError(f"empty image: {path}")
    if img.dtype != np.uint8:   # decoders give 8 bits for these flags; be explicit if a build does not
        img = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img[:, :, ::-1]) if rgb else img


def decode_check(image_dir: str | os.PathLike, names: list[str]) -> None:
    """Decode every image of ``names`` completely (grey); raise one ImageReadError naming each damaged one."""
    bad = []
    for n in names:
        try:
            decode_image(Path(image_dir) / n, rgb=False)
        except ImageReadError as exc:
            bad.append(str(exc))
    if bad:
        raise ImageReadError(f"{len(bad)} damaged image(s): " + "; ".join(bad[:5])
                             + ("" if len(bad) <= 5 else f"; ... {len(bad) - 5} more"))


_EXTRACTORS: dict = {}  # one pycolmap extractor per process and settings


def _colmap_extractor(spec: ExtractorSpec):
    import pycolmap

    key = (spec.max_features, spec.peak_threshold)
    if key not in _EXTRACTORS:
        opts = pycolmap.FeatureExtractionOptions()
        opts.num_threads = 1
        opts.use_gpu = False
        if spec.max_features:
            opts.sift.max_num_features = int(spec.max_features)
        if spec.peak_threshold is not None:
            opts.sift.peak_threshold = float(spec.peak_threshold)
        _EXTRACTORS[key] = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
    return _EXTRACTORS[key]


def extract_image(pixels: np.ndarray, spec: ExtractorSpec) -> tuple[np.ndarray, np.ndarray, str]:
    """Features of decoded pixels in COLMAP's database layout: ``(keypoints (N, 4|6) float32`` in COLMAP's pixel
    convention, ``descriptors (N, D) uint8``, COLMAP descriptor type name ``"SIFT" | "UNDEFINED")``."""
    if spec.detector == "colmap":
        import pycolmap

        h, w = pixels.shape[:2]
        bitmap = pycolmap.Bitmap.from_array(pixels).clone_as_grey()
        bitmap.thumbnail(int(spec.max_image_size or COLMAP_MAX_IMAGE_SIZE))
        kps, desc = _colmap_extractor(spec).extract(bitmap)
        kp = np.array([(k.x, k.y, k.a11, k.a12, k.a21, k.a22) for k in kps], np.float32).reshape(-1, 6)
        if (bitmap.width, bitmap.height) != (w, h):   # COLMAP's ScaleKeypoints: float32 factors, x / y columns
            sx, sy = np.float32(w) / np.float32(bitmap.width), np.float32(h) / np.float32(bitmap.height)
            kp *= np.array([sx, sy, sx, sy, sx, sy], np.float32)
        return kp, np.ascontiguousarray(desc.data, dtype=np.uint8), "SIFT"
    from ..features import detect

    f = detect(pixels, spec.detector[5:], spec.max_features, max_image_size=spec.max_image_size,
               **dict(spec.detector_options))
    d = _colmap_descriptors(f)
    return _colmap_keypoints(f), np.ascontiguousarray(d.data, dtype=np.uint8), d.type.name


def _colmap_keypoints(f) -> np.ndarray:
    """``(N, 4) float32``: COLMAP x, y (+0.5), scale (= OpenCV diameter / 2), orientation (radians)."""
    n = len(f)
    out = np.zeros((n, 4), np.float32)
    out[:, :2] = f.keypoints + 0.5   # COLMAP's pixel convention (sources.COLMAP_PIXEL_OFFSET)
    out[:, 2] = (f.scales / 2.0) if f.scales is not None else 1.0
    out[:, 3] = np.deg2rad(f.angles) if f.angles is not None else 0.0
    return out


def _colmap_descriptors(f):
    import pycolmap

    d = f.descriptors
    if f.kind == "sift":
        # OpenCV's float SIFT values are integers 0..255 (x512 normalized, clipped): uint8 is lossless
        u = np.clip(np.rint(d), 0, 255).astype(np.uint8)
        return pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, u)
    if d.dtype != np.uint8:
        raise InputError(f"cannot store float {f.kind} descriptors in a COLMAP database (SIFT or binary only)")
    return pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.UNDEFINED, np.ascontiguousarray(d))


def _exif_camera(path: Path, w: int, h: int) -> tuple[str | None, bool]:
    """``(COLMAP's EXIF camera key "make-model-focal-WxH" or None, whether the file has an EXIF focal length)`` --
    header only (Pillow), no pixels."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
    except Exception:  # noqa: BLE001 - no readable EXIF: COLMAP's default focal length
        return None, False
    focal = next((float(sub[t]) for t in (41989, 37386) if t in sub and float(sub[t] or 0) > 0), None)
    make, model = exif.get(271), exif.get(272)
    key = f"{make}-{model}-{focal:.6f}-{w}x{h}" if make and model and focal else None
    return key, any(t in sub for t in _EXIF_FOCAL_TAGS)


def _work(task: tuple) -> dict:
    """One image in a worker: decode strictly, extract, read the EXIF camera. Errors of the image itself come back
    as ``{"error": reason}``; other user errors (e.g. the memory guard) as ``{"fatal": exception}``."""
    path, name, spec, camera_model, verify_only = task
    t0 = time.perf_counter()
    try:
        pixels = decode_image(path, rgb=spec.detector == "colmap")
    except ImageReadError as exc:
        return {"name": name, "error": str(exc)}
    h, w = pixels.shape[:2]
    if verify_only:
        return {"name": name, "width": w, "height": h}
    try:
        kp, desc, dtype = extract_image(pixels, spec)
    except GuidedMatchError as exc:
        return {"name": name, "fatal": exc}
    del pixels
    key, has_focal = _exif_camera(path, w, h)
    focal, prior = 1.2 * max(w, h), False
    if has_focal:   # COLMAP's own EXIF rules (35 mm equivalent, focal plane resolution, sensor database)
        import pycolmap

        opts = pycolmap.ImageReaderOptions()
        opts.camera_model = camera_model
        cam = pycolmap.infer_camera_from_image(str(path), opts)
        focal, prior = float(cam.mean_focal_length()), bool(cam.has_prior_focal_length)
    return {"name": name, "width": w, "height": h, "keypoints": kp, "descriptors": desc, "type": dtype,
            "exif_key": key, "focal": focal, "prior": prior, "time_s": time.perf_counter() - t0}


def _init_worker(log_level: int) -> None:
    import pycolmap

    from .._runtime import plain_sigterm

    pycolmap.logging.minloglevel = log_level   # COLMAP's log level of the parent (its INFO lines silenced or not)
    plain_sigterm()   # the pool's SIGTERM ends a worker at once (no glog stack dump, no deadlock in its handler)


def _megapixels(paths) -> float:
    """Total image area (header only, Pillow); an image whose header Pillow cannot read counts as 12 MP."""
    from PIL import Image

    total = 0.0
    for p in paths:
        try:
            with Image.open(p) as im:
                total += im.size[0] * im.size[1] / 1e6
        except Exception:  # noqa: BLE001 - the strict decode reports it later
            total += 12.0
    return total


#: Below this many megapixels to extract, images are extracted in this process: starting a worker process (imports
#: of pycolmap and OpenCV) costs ~2 s, about what COLMAP's SIFT takes on 2 MP with one core.
IN_PROCESS_MAX_MP = 8.0


def _results(tasks: list, workers: int):
    """The worker results in task order (a process pool when ``workers > 1``, bounded look-ahead)."""
    if workers <= 1 or len(tasks) <= 1:
        for t in tasks:
            yield _work(t)
        return
    import pycolmap
    from concurrent.futures.process import BrokenProcessPool

    try:
        yield from pool_results(_work, tasks, workers, _init_worker, (int(pycolmap.logging.minloglevel),))
    except BrokenProcessPool:
        raise MemoryLimitError("an extraction worker process died: killed by the system (out of memory?) -- the "
                               "images written so far are kept: rerun with fewer processes (--threads 1) or a "
                               "smaller --max-image-size -- or, from a Python script, the script lacks an "
                               "`if __name__ == \"__main__\":` guard (worker processes are spawned)") from None


def pool_results(fn, tasks: list, workers: int, initializer=None, initargs: tuple = ()):
    """``fn(task)`` for each task in a pool of ``workers`` spawned processes, yielded in task order with at most
    ``2 * workers`` tasks in flight. When a worker dies the pool is broken (``BrokenProcessPool``) and every other
    worker is killed with SIGKILL before the error leaves: the pool's own SIGTERM can hang a worker for ever,
    because pycolmap installs glog's failure signal handler, which symbolizes a stack trace inside the handler and
    can deadlock when the signal lands while the worker holds the allocator's or the loader's lock (measured: 1 of 60
    processes sent SIGTERM at a random moment of importing pycolmap and OpenCV never ended) -- and the pool's exit
    would wait for it."""
    import multiprocessing
    from collections import deque
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=initializer,
                               initargs=initargs)
    procs = getattr(pool, "_processes", None)   # the pool's {pid: Process}, the one its manager thread joins
    pending = deque()
    try:
        for t in tasks:
            pending.append(pool.submit(fn, t))
            if len(pending) >= 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    except BrokenProcessPool:
        for p in list((procs or {}).values()):
            p.kill()
        raise
    finally:
        for f in pending:
            f.cancel()
        pool.shutdown(wait=True)


def check_camera_model(camera_model: str, what: str = "") -> None:
    """ConfigError unless ``camera_model`` is a COLMAP camera model name (``what``: the field, for the message)."""
    import pycolmap

    try:
        pycolmap.Camera.create_from_model_name(1, camera_model, 100.0, 100, 100)
    except Exception:  # noqa: BLE001 - pycolmap raises a bare exception type for an unknown name
        raise ConfigError(f"{what + ': ' if what else ''}unknown COLMAP camera model {camera_model!r} "
                          "(e.g. SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)") from None


def extract_folder(image_dir: str | os.PathLike, database: str | os.PathLike, names: list[str],
                   spec: ExtractorSpec, *, camera_model: str = "SIMPLE_RADIAL",
                   camera: tuple[str, list[float]] | None = None, single_camera: bool = False,
                   workers: int = 1, bad_images: str = "skip", progress: bool = True) -> dict:
    """Extract the features of ``names`` (relative to ``image_dir``) into the COLMAP ``database`` (created when
    missing); images that already have keypoints and descriptors there are not read again.

    ``bad_images="skip"``: an image that does not decode completely, or gives no features, is left out and listed
    in the returned ``skipped`` (name and reason); ``"refuse"``: every image to extract is decoded first and any
    damaged one raises ImageReadError naming each, before anything is written.

    Returns ``{"extracted", "reused", "skipped": [{"name", "reason"}], "time_s", "workers"}``.
    """
    import pycolmap
    from tqdm.auto import tqdm

    if bad_images not in ("skip", "refuse"):
        raise ConfigError(f"bad_images must be 'skip' or 'refuse', got {bad_images!r}")
    check_camera_model(camera_model)
    t0 = time.perf_counter()
    root, database = Path(image_dir), Path(database)
    check_database_space(database, 0)  # opening a new database writes its schema
    db = open_pycolmap_database(database)
    try:
        existing = {im.name: im for im in db.read_all_images()}
        done = {n for n, im in existing.items() if db.exists_keypoints(im.image_id) and db.exists_descriptors(im.image_id)}
        todo = [n for n in names if n not in done]
        workers = max(1, min(int(workers), len(todo)))
        if workers > 1 and _megapixels(root / n for n in todo) < IN_PROCESS_MAX_MP:
            workers = 1
        skipped: list[dict] = []
        if todo and bad_images == "refuse":
            bad = [r for r in _results([(root / n, n, spec, camera_model, True) for n in todo], workers)
                   if "error" in r]
            if bad:
                raise ImageReadError(f"{len(bad)} damaged image(s): " + "; ".join(r["error"] for r in bad[:5])
                                     + ("" if len(bad) <= 5 else f"; ... {len(bad) - 5} more"))
        shared = None   # (camera, rig_id) every new image uses: single_camera / a known camera
        by_exif: dict[str, tuple] = {}
        if (single_camera or camera is not None) and db.num_cameras() > 0:
            cam0 = db.read_all_cameras()[0]
            shared = (cam0, next((r.rig_id for r in db.read_all_rigs() if r.has_sensor(cam0.sensor_id)), None))
        tasks = [(root / n, n, spec, camera_model, False) for n in todo]
        bar = tqdm(total=len(todo), desc="extract", unit="img", disable=not progress)
        extracted = 0
        for r in _results(tasks, workers):
            bar.update(1)
            name = r["name"]
            if "fatal" in r:
                raise r["fatal"]
            if "error" not in r and shared is not None and (shared[0].width, shared[0].height) != (r["width"], r["height"]):
                r["error"] = (f"single_camera: {root / name} is {r['width']}x{r['height']}, but the shared camera is "
                              f"{shared[0].width}x{shared[0].height}")
            if "error" in r:
                if bad_images == "refuse":
                    raise InputError(r["error"])
                skipped.append({"name": name, "reason": r["error"]})
                continue
            w, h = r["width"], r["height"]
            check_database_space(database, np.asarray(r["keypoints"]).nbytes + 160 * len(r["keypoints"]))
            with pycolmap.DatabaseTransaction(db):   # one image: camera, rig, image, frame, keypoints, descriptors
                im = existing.get(name)
                if im is None:
                    cam_rig = shared or by_exif.get(r["exif_key"])
                    if cam_rig is None:
                        if camera is not None:
                            cam = pycolmap.Camera(model=camera[0], width=w, height=h, params=camera[1])
                            cam.has_prior_focal_length = True
                        else:
                            cam = pycolmap.Camera.create_from_model_name(0, camera_model, r["focal"], w, h)
                            cam.has_prior_focal_length = r["prior"]
                        cam.camera_id = db.write_camera(cam)
                        rig = pycolmap.Rig()
                        rig.add_ref_sensor(cam.sensor_id)
                        cam_rig = (cam, db.write_rig(rig))
                        if single_camera or camera is not None:
                            shared = cam_rig
                        elif r["exif_key"]:
                            by_exif[r["exif_key"]] = cam_rig
                    iid = db.write_image(pycolmap.Image(name=name, camera_id=cam_rig[0].camera_id))
                    frame = pycolmap.Frame()
                    frame.rig_id = cam_rig[1]
                    frame.add_data_id(db.read_image(iid).data_id)
                    db.write_frame(frame)
                else:
                    iid = im.image_id
                    cam = db.read_camera(im.camera_id)
                    if (cam.width, cam.height) != (w, h):
                        raise InputError(f"{name} is {w}x{h} but its camera in {database} is {cam.width}x{cam.height}")
                if db.exists_keypoints(iid):
                    db.update_keypoints(iid, r["keypoints"])
                else:
                    db.write_keypoints(iid, r["keypoints"])
                if db.exists_descriptors(iid):   # keypoints without descriptors are never written here
                    raise DatabaseError(f"{database}: image {name!r} has descriptors but no keypoints; remove the "
                                        "image from the database and rerun")
                db.write_descriptors(iid, _descriptors(r))
            extracted += 1
        bar.close()
    finally:
        db.close()
    return {"extracted": extracted, "reused": len(names) - len(todo), "skipped": skipped,
            "time_s": time.perf_counter() - t0, "workers": workers}


def _descriptors(r: dict):
    import pycolmap

    return pycolmap.FeatureDescriptors(getattr(pycolmap.FeatureExtractorType, r["type"]), r["descriptors"])
