"""From a folder of photos to a COLMAP sparse model in one call: ``guidedmatch sfm IMAGE_DIR OUT_DIR``.

Three resumable stages in the style of hloc (each a ``main(conf, paths)`` that reuses what a previous run left):

1. **extraction** (:func:`extract_main`): pycolmap's SIFT by default -- the same features ``colmap
   feature_extractor`` writes, so the result is comparable with COLMAP's own pipeline -- or one of our OpenCV
   detectors (``detector="ours:sift|orb|akaze|brisk"``, through :func:`guidedmatch.collection.sources.images_to_database`).
   Images already in the database with keypoints are not extracted again.
2. **matching** (:func:`match_main`): :func:`guidedmatch.collection.engine.match_collection` over the pair list
   (exhaustive by default, ``sequential[:K]`` or a pairs file), writing matches and two-view geometries into the
   database (``geometry="ours"``: the matcher's own verdict; ``"colmap"``: pycolmap's verification afterwards),
   then at most ``max_inliers_per_pair`` inliers of each pair are kept for the mapper (spread over the image, best
   first: :meth:`guidedmatch.collection.ColmapSink.cap_inliers`; ``0`` keeps all). Pairs already complete in the
   database are skipped.
3. **mapping** (:func:`map_main`): ``pycolmap.incremental_mapping`` into ``OUT_DIR/sparse/<k>/`` (always redone;
   written to a temporary folder and moved into place when complete).

``OUT_DIR`` receives ``database.db``, ``sparse/0`` (readable by ``colmap gui`` and ``pycolmap.Reconstruction``),
``report.json`` + ``report.md`` (time per stage, per-pair matches / inliers / verdicts, registered images,
3-D points, mean track length, reprojection error) and ``reconstruction.png`` (cameras and sparse points, top and
side view). ``OUT_DIR/sfm_project.json`` records the image folder and the extraction / matching settings: a rerun
with other settings, or an ``OUT_DIR`` holding a database of another project, is refused before any work.

Coordinates: COLMAP's ``cam_from_world`` (``X_cam = R X_world + t``); keypoints in the database use COLMAP's
pixel convention (the feature sources convert to OpenCV's).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import MODES
from .errors import ConfigError, DatabaseError, InputError, OutputError
from .validation import check_bool, check_choice, check_number, config_from

__all__ = ["SfmConfig", "SfmPaths", "IMAGE_EXTENSIONS", "list_images", "check_images", "parse_camera",
           "extract_main", "match_main", "map_main", "main", "run_sfm", "database_pair_stats",
           "verified_inliers", "run_mapping", "reconstruction_stats", "plot_reconstruction",
           "extract_colmap_sift", "colmap_log_level"]

#: File suffixes taken as images (case-insensitive), as COLMAP's image reader accepts them.
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp")
#: ``colmap feature_extractor``'s longest image side, used when ``max_image_size`` is not given.
COLMAP_MAX_IMAGE_SIZE = 3200
#: Our detectors, as ``detector="ours:<name>"``.
OUR_DETECTORS = ("sift", "orb", "akaze", "brisk")
#: Camera models accepted by ``camera=`` and their parameter counts (COLMAP's names and parameter order).
CAMERA_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}
#: COLMAP's ``IncrementalMapperOptions.init_min_num_inliers``: fewer inliers per pair and the mapper cannot start.
MIN_MAPPER_INLIERS = 100
#: Two-view geometry configurations the mapper uses (COLMAP ``TwoViewGeometry::ConfigurationType``).
VERIFIED_CONFIGS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC", "MULTIPLE")


def parse_camera(spec: str | None) -> tuple[str, list[float]] | None:
    """``"PINHOLE:fx,fy,cx,cy"`` -> ``("PINHOLE", [fx, fy, cx, cy])`` (COLMAP model name and parameter order).

    >>> parse_camera("PINHOLE:1000,1000,320,240")
    ('PINHOLE', [1000.0, 1000.0, 320.0, 240.0])
    >>> parse_camera(None) is None
    True
    """
    if spec is None:
        return None
    model, sep, rest = str(spec).partition(":")
    model = model.strip().upper()
    if not sep or model not in CAMERA_MODELS:
        raise ConfigError(f"camera must look like MODEL:p1,p2,... with MODEL one of {', '.join(CAMERA_MODELS)} "
                          f"(e.g. PINHOLE:fx,fy,cx,cy); got {spec!r}")
    try:
        params = [float(v) for v in rest.split(",")]
    except ValueError:
        raise ConfigError(f"camera parameters must be numbers, got {rest!r}") from None
    if len(params) != CAMERA_MODELS[model] or not all(math.isfinite(v) for v in params):
        raise ConfigError(f"camera model {model} takes {CAMERA_MODELS[model]} finite parameters, got {rest!r}")
    if params[0] <= 0 or (model in ("PINHOLE", "RADIAL", "OPENCV") and model != "RADIAL" and params[1] <= 0):
        raise ConfigError(f"camera focal length must be > 0, got {rest!r}")
    return model, params


@dataclass(frozen=True)
class SfmConfig:
    """Settings of :func:`run_sfm` / ``guidedmatch sfm`` (every field checked on construction)."""

    detector: str = "colmap"           # "colmap" = pycolmap SIFT (colmap feature_extractor), or "ours:sift|orb|akaze|brisk"
    max_features: int | None = None    # features per image; None = the detector's default (8192 for COLMAP SIFT)
    max_image_size: int | None = None  # longest side before extraction; None = the detector's default (3200 for COLMAP)
    peak_threshold: float | None = None  # COLMAP SIFT peak threshold; None = COLMAP's 0.0067 (0.002: ~5x more features)
    camera_model: str = "SIMPLE_RADIAL"  # camera model when intrinsics are estimated (COLMAP's default)
    camera: str | None = None          # known intrinsics "MODEL:params" for every image (held fixed in bundle adjustment)
    single_camera: bool = False        # all images share one camera (intrinsics estimated jointly)
    pairs: str = "exhaustive"          # "exhaustive" | "sequential" | "sequential:K" | path of a "name1 name2" file
    mode: str = "so+epi+ia"            # matcher mode (guidedmatch.matcher.match)
    matcher: dict | None = None        # MatcherConfig overrides, e.g. {"alignment": "c_inplane"}
    geometry: str = "ours"             # two-view geometry: "ours" (matcher's verdict written) | "colmap" (pycolmap verifies)
    max_inliers_per_pair: int = 1000   # inliers per pair handed to the mapper (spread over the image, best first); 0 = all
    workers: int | None = None         # matching worker processes; None = automatic, 0 = in this process (collection engine)
    scheduler: str | None = None       # address of a running Dask scheduler for matching
    num_threads: int = -1              # COLMAP extraction / verification / mapping threads; -1 = all cores
    seed: int = 0                      # mapper random seed (COLMAP's RANSAC and initial pair trials)
    progress: bool = True              # print stage lines and progress bars

    def __post_init__(self) -> None:
        o = "SfmConfig"
        det = self.detector
        if det != "colmap" and not (det.startswith("ours:") and det[5:] in OUR_DETECTORS):
            raise ConfigError(f"{o}.detector must be 'colmap' or one of "
                              f"{', '.join('ours:' + d for d in OUR_DETECTORS)}; got {det!r}")
        check_number(o, "max_features", self.max_features, lo=1, integer=True, allow_none=True)
        check_number(o, "max_image_size", self.max_image_size, lo=16, integer=True, allow_none=True)
        check_number(o, "peak_threshold", self.peak_threshold, lo=0, lo_open=True, allow_none=True)
        if self.peak_threshold is not None and det != "colmap":
            raise ConfigError(f"{o}.peak_threshold applies to the COLMAP SIFT detector only (detector={det!r})")
        check_choice(o, "camera_model", self.camera_model, CAMERA_MODELS)
        parse_camera(self.camera)
        check_bool(o, "single_camera", self.single_camera)
        if not isinstance(self.pairs, str) or not self.pairs:
            raise ConfigError(f"{o}.pairs must be 'exhaustive', 'sequential[:K]' or a pairs file; got {self.pairs!r}")
        check_choice(o, "mode", self.mode, MODES)
        if self.matcher is not None and not isinstance(self.matcher, dict):
            raise ConfigError(f"{o}.matcher must be a dict of MatcherConfig fields or None; got {self.matcher!r}")
        if self.matcher:
            from .config import MatcherConfig

            config_from(MatcherConfig, self.matcher)
        check_choice(o, "geometry", self.geometry, ("ours", "colmap"))
        check_number(o, "max_inliers_per_pair", self.max_inliers_per_pair, lo=0, integer=True)
        if 0 < self.max_inliers_per_pair < MIN_MAPPER_INLIERS:
            raise ConfigError(f"{o}.max_inliers_per_pair must be 0 (all) or >= {MIN_MAPPER_INLIERS}: COLMAP's mapper "
                              f"needs {MIN_MAPPER_INLIERS} inliers in its initial pair (init_min_num_inliers); got "
                              f"{self.max_inliers_per_pair}")
        check_number(o, "workers", self.workers, lo=0, integer=True, allow_none=True)
        check_number(o, "num_threads", self.num_threads, lo=-1, integer=True)
        if self.num_threads == 0:
            raise ConfigError(f"{o}.num_threads must be -1 (all cores) or >= 1; got 0")
        check_number(o, "seed", self.seed, lo=0, integer=True)
        check_bool(o, "progress", self.progress)

    def extraction_settings(self) -> dict:
        """What determines the database's features (a rerun with other values is refused)."""
        return {k: getattr(self, k) for k in ("detector", "max_features", "max_image_size", "peak_threshold",
                                               "camera_model", "camera", "single_camera")}

    def matching_settings(self) -> dict:
        """What determines the matched pairs (a rerun with other values is refused while pairs exist)."""
        return {"mode": self.mode, "matcher": dict(self.matcher or {}), "geometry": self.geometry,
                "max_inliers_per_pair": self.max_inliers_per_pair}


@dataclass(frozen=True)
class SfmPaths:
    """Where the stages read and write (all under ``out_dir`` except the images)."""

    image_dir: Path
    out_dir: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "image_dir", Path(self.image_dir).expanduser().resolve())
        object.__setattr__(self, "out_dir", Path(self.out_dir).expanduser().resolve())

    database = property(lambda self: self.out_dir / "database.db")
    sparse = property(lambda self: self.out_dir / "sparse")
    project = property(lambda self: self.out_dir / "sfm_project.json")
    report_json = property(lambda self: self.out_dir / "report.json")
    report_md = property(lambda self: self.out_dir / "report.md")
    figure = property(lambda self: self.out_dir / "reconstruction.png")
    pair_log = property(lambda self: self.out_dir / "pairs.jsonl")


def _say(conf: SfmConfig, text: str) -> None:
    if conf.progress:
        print(text, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- inputs
def list_images(image_dir: str | os.PathLike) -> list[str]:
    """Image files under ``image_dir`` (recursive, by suffix), as sorted POSIX paths relative to it -- the names
    COLMAP gives them. Other files (e.g. a ``K.txt``) are ignored."""
    root = Path(image_dir)
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def _image_readable(path: Path) -> bool:
    """Whether ``path`` looks like an image the extractors can read: its header parses (Pillow, no pixels decoded:
    ~2 ms per file), or else OpenCV decodes it at 1/8 resolution (formats Pillow does not know). Truncated or
    otherwise damaged pixel data is left to the extractor, which reports the image as failed."""
    try:
        from PIL import Image, UnidentifiedImageError

        with Image.open(path) as im:
            im.verify()
        return True
    except (ImportError, UnidentifiedImageError):
        pass
    except (OSError, ValueError, SyntaxError):  # a known format whose header is damaged
        return False
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    return img is not None and img.size > 0


def check_images(image_dir: str | os.PathLike) -> tuple[list[str], list[dict]]:
    """Split the folder's images into readable names and skipped ``{"name", "reason"}`` entries.

    Each image's header is parsed (:func:`_image_readable`; decoding every photo even at 1/8 resolution took 0.2 s
    for the 8 Herz-Jesus-P8 photos, i.e. ~25 ms per 6-Mpixel JPEG: half a minute before any work for a thousand);
    a file that does not parse is skipped.

    Raises:
        InputError: the folder is missing, holds no image files, or fewer than 2 readable images.
    """
    import cv2

    root = Path(image_dir)
    if not root.is_dir():
        raise InputError(f"image folder not found: {root}")
    names = list_images(root)
    if not names:
        raise InputError(f"no images in {root} (looked for {', '.join(IMAGE_EXTENSIONS)})")
    good, skipped = [], []
    try:   # the reason goes into the report; OpenCV's own decoder messages on stderr would only add noise
        old_level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - OpenCV builds without the logging module
        old_level = None
    try:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1))) as pool:  # file reads overlap
            ok = list(pool.map(lambda n: _image_readable(root / n), names))
        for n, r in zip(names, ok):
            if r:
                good.append(n)
            else:
                skipped.append({"name": n, "reason": "unreadable (not an image file its format's reader can parse)"})
    finally:
        if old_level is not None:
            cv2.utils.logging.setLogLevel(old_level)
    if len(good) < 2:
        extra = f" ({len(skipped)} unreadable: {', '.join(s['name'] for s in skipped[:3])})" if skipped else ""
        raise InputError(f"structure from motion needs at least 2 readable images; {root} has {len(good)}{extra}")
    return good, skipped


def _read_project(paths: SfmPaths) -> dict | None:
    if not paths.project.is_file():
        return None
    try:
        return json.loads(paths.project.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise OutputError(f"{paths.project} is unreadable ({exc}); use a new OUT_DIR") from None


def _write_project(paths: SfmPaths, project: dict) -> None:
    from .evaluation.meta import write_json

    write_json(paths.project, project)


def _db_image_names(db_path: Path) -> dict[str, int]:
    """``{name: number of keypoints}`` of the images in a COLMAP database."""
    import pycolmap

    try:
        db = pycolmap.Database.open(str(db_path))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError subclasses for any SQLite problem
        raise DatabaseError(f"{db_path}: not a readable COLMAP database ({exc})") from None
    try:
        return {img.name: int(db.num_keypoints_for_image(img.image_id)) if db.exists_keypoints(img.image_id) else 0
                for img in db.read_all_images()}
    finally:
        db.close()


def check_output(conf: SfmConfig, paths: SfmPaths, names: list[str]) -> dict:
    """Refuse an ``OUT_DIR`` that belongs to another project or was made with other settings (before any work).

    Returns the project record to write (image folder, extraction and matching settings).

    Raises:
        OutputError: OUT_DIR is a file or not writable, its database.db was not made by ``guidedmatch sfm`` for this
            image folder (or names images that are not in it), or the settings differ from the recorded ones.
    """
    out = paths.out_dir
    if out.exists() and not out.is_dir():
        raise OutputError(f"OUT_DIR {out} exists and is not a folder")
    probe = out if out.exists() else next(p for p in out.parents if p.exists())
    if not os.access(probe, os.W_OK):
        raise OutputError(f"OUT_DIR {out} is not writable")
    project = {"format": "guidedmatch-sfm/1", "image_dir": str(paths.image_dir),
               "extraction": conf.extraction_settings(), "matching": conf.matching_settings()}
    old = _read_project(paths)
    if paths.database.exists():
        if old is None:
            raise OutputError(f"{paths.database} exists but was not made by `guidedmatch sfm` (no {paths.project.name}); "
                              "refusing to touch another project's database: use a new OUT_DIR")
        if old.get("image_dir") != str(paths.image_dir):
            raise OutputError(f"{paths.database} belongs to the images in {old.get('image_dir')}, not {paths.image_dir}; "
                              "use a new OUT_DIR")
        in_db = _db_image_names(paths.database)
        foreign = sorted(set(in_db) - set(list_images(paths.image_dir)))
        if foreign:
            raise OutputError(f"{paths.database} holds {len(foreign)} image(s) not in {paths.image_dir} "
                              f"(e.g. {foreign[0]!r}); it belongs to another project: use a new OUT_DIR")
        if in_db and old.get("extraction") != project["extraction"]:
            raise OutputError(f"the features in {paths.database} were extracted with {old.get('extraction')}, not "
                              f"{project['extraction']}; rerun with the same options or use a new OUT_DIR")
        # projects from before max_inliers_per_pair handed the mapper every inlier: they read as 0
        old_matching = {"max_inliers_per_pair": 0, **old["matching"]} if isinstance(old.get("matching"), dict) else None
        if _num_matched_pairs(paths.database) and old_matching != project["matching"]:
            raise OutputError(f"the pairs in {paths.database} were matched with {old.get('matching')}, not "
                              f"{project['matching']}; rerun with the same options or use a new OUT_DIR")
    return project


def _num_matched_pairs(db_path: Path) -> int:
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        return int(db.num_matched_image_pairs())
    finally:
        db.close()


# --------------------------------------------------------------------------- stage 1: extraction
def extract_colmap_sift(database: str | os.PathLike, image_dir: str | os.PathLike, image_names: list[str], *,
                        max_features: int | None = None, max_image_size: int | None = None,
                        peak_threshold: float | None = None, camera_model: str = "SIMPLE_RADIAL",
                        camera: str | None = None, single_camera: bool = False, num_threads: int = -1) -> None:
    """``pycolmap.extract_features`` (CPU SIFT, as ``colmap feature_extractor``) for ``image_names`` of ``image_dir``.

    ``camera="MODEL:params"`` gives every image that camera (one shared camera); ``single_camera`` shares one
    estimated camera; otherwise COLMAP's AUTO mode (one camera per image size / EXIF focal length).
    """
    import pycolmap

    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = num_threads
    ext.use_gpu = False
    ext.max_image_size = int(max_image_size) if max_image_size else COLMAP_MAX_IMAGE_SIZE
    if max_features:
        ext.sift.max_num_features = int(max_features)
    if peak_threshold is not None:
        ext.sift.peak_threshold = float(peak_threshold)
    reader = pycolmap.ImageReaderOptions()
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
    reader.camera_model = camera_model
    cam = parse_camera(camera)
    if cam is not None:
        reader.camera_model = cam[0]
        reader.camera_params = ",".join(f"{v:.10g}" for v in cam[1])
        mode = pycolmap.CameraMode.SINGLE
    pycolmap.extract_features(str(database), str(image_dir), image_names=list(image_names), camera_mode=mode,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)


def extract_main(conf: SfmConfig, paths: SfmPaths, names: list[str]) -> dict:
    """Stage 1: features of every image in ``names`` not yet in the database. Returns the stage's record
    (``time_s``, ``extracted``, ``reused``, ``failed`` = images the extractor could not use, keypoint stats)."""
    t0 = time.perf_counter()
    before = _db_image_names(paths.database) if paths.database.exists() else {}
    todo = [n for n in names if before.get(n, 0) == 0]
    _say(conf, f"[1/3] extraction ({conf.detector}): {len(todo)} image(s) to extract, {len(names) - len(todo)} reused")
    if todo:
        if conf.detector == "colmap":
            extract_colmap_sift(paths.database, paths.image_dir, todo, max_features=conf.max_features,
                                max_image_size=conf.max_image_size, peak_threshold=conf.peak_threshold,
                                camera_model=conf.camera_model, camera=conf.camera, single_camera=conf.single_camera,
                                num_threads=conf.num_threads)
        else:
            _extract_ours(conf, paths, todo)
    after = _db_image_names(paths.database)
    failed = [n for n in names if after.get(n, 0) == 0]
    counts = [after[n] for n in names if after.get(n, 0) > 0]
    return {"time_s": time.perf_counter() - t0, "detector": conf.detector, "extracted": len(todo) - len(failed),
            "reused": len(names) - len(todo), "failed": failed,
            "keypoints": {"total": int(sum(counts)), "min": int(min(counts, default=0)),
                          "median": float(np.median(counts)) if counts else 0.0, "max": int(max(counts, default=0))}}


def _extract_ours(conf: SfmConfig, paths: SfmPaths, names: list[str]) -> None:
    """Our OpenCV detector through the collection's image-folder source (a COLMAP database with cameras, like
    ``colmap feature_extractor`` writes). ``images_to_database`` takes a whole folder; when some of its images
    are to be left out (unreadable), it is given a folder of symbolic links to ``names`` under the same relative
    names (``OUT_DIR/.images``), so the database names still refer to ``IMAGE_DIR``."""
    from .collection.sources import images_to_database

    folder = paths.image_dir
    if set(names) != set(list_images(paths.image_dir)):
        folder = paths.out_dir / ".images"
        if folder.exists():
            shutil.rmtree(folder)
        for n in names:
            link = folder / n
            link.parent.mkdir(parents=True, exist_ok=True)
            os.symlink(paths.image_dir / n, link)
    cam = parse_camera(conf.camera)
    try:
        src = images_to_database(folder, paths.database, detector=conf.detector[5:], max_features=conf.max_features,
                                 max_image_size=conf.max_image_size,
                                 camera_model=cam[0] if cam else conf.camera_model,
                                 single_camera=conf.single_camera or cam is not None, progress=conf.progress,
                                 resume=True)
        src.close()
    finally:
        if folder != paths.image_dir:
            shutil.rmtree(folder, ignore_errors=True)
    if cam is not None:
        _set_known_camera(paths.database, cam)


def _set_known_camera(db_path: Path, cam: tuple[str, list[float]]) -> None:
    """Give every camera of the database the known model and parameters (prior focal length flag set)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        for c in db.read_all_cameras():
            new = pycolmap.Camera(model=cam[0], width=c.width, height=c.height, params=cam[1], camera_id=c.camera_id)
            new.has_prior_focal_length = True
            db.update_camera(new)
    finally:
        db.close()


# --------------------------------------------------------------------------- stage 2: matching
def match_main(conf: SfmConfig, paths: SfmPaths, names: list[str]) -> dict:
    """Stage 2: match the pair list with the collection engine into the database (pairs already there skipped);
    with ``geometry="colmap"`` pycolmap's verification runs afterwards on the pairs without a geometry."""
    import pycolmap

    from .collection.engine import CollectionConfig, match_collection
    from .collection.pairs import pairs_from_spec
    from .collection.sinks import ColmapSink
    from .collection.sources import ColmapSource

    t0 = time.perf_counter()
    source = ColmapSource(paths.database)
    try:
        pair_list = pairs_from_spec(conf.pairs, [n for n in source.names() if n in set(names)])
        _say(conf, f"[2/3] matching ({conf.mode}, geometry {conf.geometry}): {len(pair_list.pairs)} pairs ({conf.pairs})")
        cconf = CollectionConfig(mode=conf.mode, matcher=dict(conf.matcher or {}), workers=conf.workers,
                                 scheduler=conf.scheduler, progress=conf.progress, log_path=str(paths.pair_log))
        with ColmapSink(paths.database, geometry=conf.geometry) as sink:
            report = match_collection(source, pair_list.pairs, sink, cconf)
            t_match = time.perf_counter() - t0
            t_verify = 0.0
            if conf.geometry == "colmap":
                t1 = time.perf_counter()
                sink.verify(pycolmap.TwoViewGeometryOptions())   # COLMAP's default verification
                t_verify = time.perf_counter() - t1
            # the mapper's bundle adjustments cost what its observations cost: hand it at most K inliers per pair
            # (spread, best first; weaker pairs whole). Idempotent, so a resumed run caps only the new pairs.
            cap = sink.cap_inliers(conf.max_inliers_per_pair) if conf.max_inliers_per_pair else None
    finally:
        source.close()
    pairs = database_pair_stats(paths.database)
    if cap is not None:
        _say(conf, f"      mapper's inliers: {cap['inliers_after']:,} of {cap['inliers_before']:,} (at most "
                   f"{cap['max_inliers']} per pair; {cap['pairs_capped']} pairs capped)")
    return {"time_s": time.perf_counter() - t0, "match_time_s": t_match, "verify_time_s": t_verify,
            "inlier_cap": cap,
            "pairs": len(pair_list.pairs), "pair_list_report": pair_list.report, "collection": report.to_dict(),
            "verified_pairs": sum(p["verified"] for p in pairs), "verified_inliers": sum(p["inliers"] for p in pairs),
            "raw_matches": sum(p["matches"] for p in pairs)}


def database_pair_stats(database: str | os.PathLike) -> list[dict]:
    """Per image pair of a COLMAP database: ``name1, name2, matches`` (raw), ``config`` (two-view geometry
    configuration name or None), ``inliers`` (inlier matches of a verified geometry, else 0), ``verified``."""
    import pycolmap

    rows = []
    db = pycolmap.Database.open(str(database))
    try:   # counts in bulk; each geometry read alone (its inlier matches), so memory stays one pair's worth
        names = {img.image_id: img.name for img in db.read_all_images()}
        raw = {int(pid): int(n) for pid, n in zip(*db.read_num_matches())}
        geo = {int(pid): int(n) for pid, n in zip(*db.read_two_view_geometry_num_inliers())}
        for pid in sorted(set(raw) | set(geo)):
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            config = None
            if pid in geo:
                config = pycolmap.TwoViewGeometryConfiguration(int(db.read_two_view_geometry(i1, i2).config)).name
            verified = config in VERIFIED_CONFIGS
            rows.append({"name1": names.get(i1, str(i1)), "name2": names.get(i2, str(i2)), "matches": raw.get(pid, 0),
                         "config": config, "inliers": geo[pid] if verified else 0, "verified": bool(verified)})
    finally:
        db.close()
    return rows


def verified_inliers(database: str | os.PathLike) -> tuple[int, int]:
    """``(verified pairs, total inlier matches of verified pairs)`` of a COLMAP database."""
    rows = database_pair_stats(database)
    return sum(r["verified"] for r in rows), sum(r["inliers"] for r in rows)


# --------------------------------------------------------------------------- stage 3: mapping
def run_mapping(database: str | os.PathLike, image_dir: str | os.PathLike, sparse_dir: str | os.PathLike, *,
                num_threads: int = -1, seed: int = 0, fixed_intrinsics: bool = False) -> dict:
    """``pycolmap.incremental_mapping`` into ``sparse_dir/<k>`` (a temporary sibling folder moved into place when
    complete, so an interrupted run leaves the previous model). Returns ``{"time_s", "models": [stats per model,
    largest first], "best": index of the model with most registered images or None}``."""
    import pycolmap

    sparse_dir = Path(sparse_dir)
    tmp = sparse_dir.with_name(sparse_dir.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    if fixed_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(database), str(image_dir), str(tmp), options=opts)
    elapsed = time.perf_counter() - t0
    models = sorted(((int(k), r) for k, r in recs.items()), key=lambda kr: -kr[1].num_reg_images())
    # COLMAP numbers models in the order it found them; renumber so that sparse/0 is the largest
    final = sparse_dir.with_name(sparse_dir.name + ".new")
    if final.exists():
        shutil.rmtree(final)
    final.mkdir()
    stats = []
    for new_idx, (_, rec) in enumerate(models):
        d = final / str(new_idx)
        d.mkdir()
        rec.write(str(d))
        stats.append(dict(reconstruction_stats(rec), path=str(sparse_dir / str(new_idx))))
    shutil.rmtree(tmp)
    if sparse_dir.exists():
        shutil.rmtree(sparse_dir)
    os.replace(final, sparse_dir)
    return {"time_s": elapsed, "models": stats, "best": 0 if stats else None}


def reconstruction_stats(rec: Any) -> dict:
    """Registered images, 3-D points, observations, mean track length, mean reprojection error (px) of a model."""
    return {"registered": int(rec.num_reg_images()), "images": int(rec.num_images()),
            "points3D": int(rec.num_points3D()), "observations": int(rec.compute_num_observations()),
            "mean_track_length": float(rec.compute_mean_track_length()),
            "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "registered_names": sorted(rec.image(i).name for i in rec.reg_image_ids())}


def map_main(conf: SfmConfig, paths: SfmPaths) -> dict:
    """Stage 3: incremental mapping from the database (always redone; the previous model is replaced when done)."""
    _say(conf, "[3/3] mapping (pycolmap.incremental_mapping)")
    return run_mapping(paths.database, paths.image_dir, paths.sparse, num_threads=conf.num_threads, seed=conf.seed,
                       fixed_intrinsics=conf.camera is not None)


# --------------------------------------------------------------------------- figure and report
def plot_reconstruction(path: str | os.PathLike, rec: Any, title: str = "", max_points: int = 30000,
                        seed: int = 0) -> Path:
    """Cameras (centres + viewing directions) and sparse points, top view and side view.

    The axes follow the cameras: "up" = the mean of the cameras' image-up directions (``-y`` of each camera),
    "forward" = the mean viewing direction made orthogonal to it, "right" = forward x up. Points beyond the
    1st-99th percentile box are left out of the axis limits."""
    from .plots import _plt, save_figure

    plt = _plt()
    centres, dirs, ups = [], [], []
    for i in rec.reg_image_ids():
        pose = rec.image(i).cam_from_world()
        R = pose.rotation.matrix()
        centres.append(-R.T @ np.asarray(pose.translation))
        dirs.append(R[2])
        ups.append(-R[1])
    centres = np.array(centres).reshape(-1, 3)
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    up = np.mean(ups, axis=0) if ups else np.array([0.0, -1.0, 0.0])
    up /= max(np.linalg.norm(up), 1e-12)
    fwd = np.mean(dirs, axis=0) if dirs else np.array([0.0, 0.0, 1.0])
    fwd = fwd - up * np.dot(fwd, up)
    if np.linalg.norm(fwd) < 1e-9:
        fwd = np.cross(up, [1.0, 0.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    B = np.stack([right, fwd, up])
    c, p = centres @ B.T, pts @ B.T
    d = np.array(dirs).reshape(-1, 3) @ B.T
    span = np.ptp(np.vstack([c, np.percentile(p, [1, 99], axis=0)]) if len(p) else c, axis=0).max() if len(c) else 1.0
    arrow = 0.08 * max(span, 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    size = 4.0 if len(p) < 5000 else 0.6
    for ax, (a, b, la, lb, name) in zip(axes, ((0, 1, "right", "forward", "top view"),
                                                 (1, 2, "forward", "up", "side view"))):
        if len(p):
            ax.scatter(p[:, a], p[:, b], s=size, c="0.35", alpha=0.5, linewidths=0)
        ax.scatter(c[:, a], c[:, b], s=25, c="tab:red", zorder=3, label="cameras")
        for ci, di in zip(c, d):
            ax.plot([ci[a], ci[a] + arrow * di[a]], [ci[b], ci[b] + arrow * di[b]], c="tab:red", lw=1.2)
        xy = np.vstack([np.percentile(p[:, [a, b]], [1, 99], axis=0), c[:, [a, b]]]) if len(p) else c[:, [a, b]]
        lo, hi = xy.min(0), xy.max(0)
        half = 0.55 * max(float((hi - lo).max()), 1e-9)          # square box: equal scales on both axes
        mid = (lo + hi) / 2
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.set_title(f"{name}: {len(c)} cameras, {rec.num_points3D()} points" + (f" (showing {len(p)})" if
                                                                                 len(p) < rec.num_points3D() else ""))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def _fmt_s(v: float) -> str:
    return f"{v:.2f}"


def report_markdown(report: dict) -> str:
    """The human-readable ``report.md`` of a run."""
    st = report["stages"]
    lines = [f"# guidedmatch sfm: {report['image_dir']}", "",
             f"Command: `{report.get('command', '')}`  ", f"Finished: {report['meta'].get('timestamp_utc')}", "",
             "| stage | time (s) | details |", "|---|---|---|"]
    ex = st["extraction"]
    lines.append(f"| extraction ({ex['detector']}) | {_fmt_s(ex['time_s'])} | {ex['extracted']} extracted, {ex['reused']} "
                 f"reused, keypoints median {ex['keypoints']['median']:.0f} (total {ex['keypoints']['total']:,}) |")
    ma = st["matching"]
    coll = ma["collection"]
    lines.append(f"| matching ({report['config']['mode']}, geometry {report['config']['geometry']}) | "
                 f"{_fmt_s(ma['time_s'])} | {ma['pairs']} pairs: {coll['done']} matched now, {coll['skipped']} reused, "
                 f"{len(coll['failed'])} failed; "
                 f"{ma['verified_pairs']} verified pairs, {ma['verified_inliers']:,} inlier matches"
                 + (f" (COLMAP verification {_fmt_s(ma['verify_time_s'])} s)" if report['config']['geometry'] == 'colmap' else "")
                 + (f"; the mapper gets at most {ic['max_inliers']} per pair ({ic['pairs_capped']} pairs capped "
                    f"this run: {ic['inliers_before']:,} -> {ic['inliers_after']:,})" if (ic := ma.get("inlier_cap")) else "")
                 + " |")
    mp = st["mapping"]
    best = mp["models"][mp["best"]] if mp.get("best") is not None else None
    lines.append(f"| mapping | {_fmt_s(mp['time_s'])} | {len(mp['models'])} model(s) |")
    lines.append(f"| total | {_fmt_s(report['total_time_s'])} | |")
    lines += ["", "## Reconstruction (sparse/0)", ""]
    if best is None:
        lines.append("No model: the mapper could not initialise (too few verified pairs).")
    else:
        lines += ["| registered | 3D points | observations | mean track length | mean reprojection error (px) |",
                  "|---|---|---|---|---|",
                  f"| {best['registered']}/{report['num_images']} | {best['points3D']:,} | {best['observations']:,} | "
                  f"{best['mean_track_length']:.2f} | {best['mean_reprojection_error_px']:.3f} |", "",
                  f"![cameras and points]({Path(report['figure']).name})" if report.get("figure") else ""]
        unreg = report.get("unregistered", [])
        if unreg:
            lines += ["", f"Not registered: {', '.join(unreg)}"]
    if report.get("skipped_images"):
        lines += ["", "## Skipped images", ""] + [f"* {s['name']}: {s['reason']}" for s in report["skipped_images"]]
    if coll.get("failed"):
        lines += ["", "## Failed pairs", ""] + [f"* {' '.join(f['pair'])}: {f['reason']}" for f in coll["failed"]]
    rows = report["pairs"]
    lines += ["", f"## Pairs ({len(rows)} with matches; verdict = COLMAP two-view configuration)", "",
              "| image 1 | image 2 | matches | verdict | inliers |", "|---|---|---|---|---|"]
    cap = 300
    for r in rows[:cap]:
        lines.append(f"| {r['name1']} | {r['name2']} | {r['matches']} | {r['config'] or 'none'} | {r['inliers']} |")
    if len(rows) > cap:
        lines.append(f"| ... {len(rows) - cap} more in report.json | | | | |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- the pipeline
def main(conf: SfmConfig, paths: SfmPaths, command: str = "") -> dict:
    """Run (or resume) the three stages; write ``report.json``, ``report.md`` and the figure. Returns the report.

    Raises before any work: InputError (no / one readable image), OutputError (OUT_DIR of another project or made
    with other settings; a process where zlib cannot be used, :func:`guidedmatch._runtime.zlib_shadowed`),
    ConfigError (bad settings)."""
    from ._runtime import require_zlib
    from .evaluation.meta import run_metadata, write_json
    from .features import atomic_write_text

    conf = config_from(SfmConfig, conf)
    require_zlib(paths.figure)  # a process where the figure's PNG encoder would abort: say so before any work
    t_start = time.perf_counter()
    names, skipped = check_images(paths.image_dir)
    project = check_output(conf, paths, names)
    from .collection.pairs import pairs_from_spec

    pairs_from_spec(conf.pairs, names)   # a bad spec, a missing pairs file or unknown names fail here, before any work
    paths.out_dir.mkdir(parents=True, exist_ok=True)
    _write_project(paths, project)
    if skipped:
        _say(conf, f"skipping {len(skipped)} unreadable image(s): " + ", ".join(s["name"] for s in skipped))

    # No matching set-up in a thread during the extraction (session 20 had one): pycolmap's extractor keeps both cores
    # busy, and 8 alternating fresh runs on Herz-Jesus-P8 showed the thread's 0.65-0.89 s of imports and kernel loads
    # costing the extraction 0.14-2.0 s (median ~0.75) for 0.3-0.5 s saved in matching: extraction + matching was
    # 0.35 s longer with it (median; 7 of 8 rounds longer). docs/collections.md, session 21.
    extraction = extract_main(conf, paths, names)
    for n in extraction["failed"]:
        skipped.append({"name": n, "reason": "the feature extractor could not read it or found no features"})
    names = [n for n in names if n not in set(extraction["failed"])]
    if len(names) < 2:
        raise InputError(f"fewer than 2 images with features in {paths.image_dir}; nothing to match")
    matching = match_main(conf, paths, names)
    # the report's bookkeeping (run metadata, per-pair table, the plotting library's import: ~0.5 s) runs in a thread
    # while the mapper works -- pycolmap releases the GIL and its mapping does not keep both cores busy
    side: dict = {}

    def bookkeeping() -> None:
        try:
            side["meta"] = run_metadata(conf.seed)
            side["pairs"] = database_pair_stats(paths.database)
            from .plots import _plt

            _plt()
        except Exception as exc:  # noqa: BLE001 - redone (and raised) in the main thread below
            side["error"] = exc

    helper = threading.Thread(target=bookkeeping, name="guidedmatch-sfm-report", daemon=True)
    helper.start()
    try:
        mapping = map_main(conf, paths)
    finally:
        helper.join()
    best = mapping["models"][0] if mapping["models"] else None
    report = {"image_dir": str(paths.image_dir), "out_dir": str(paths.out_dir), "command": command,
              "config": dataclasses.asdict(conf), "num_images": len(names), "skipped_images": skipped,
              "stages": {"extraction": extraction, "matching": matching, "mapping": mapping},
              "total_time_s": time.perf_counter() - t_start,
              "registered": best["registered"] if best else 0, "points3D": best["points3D"] if best else 0,
              "unregistered": sorted(set(names) - set(best["registered_names"])) if best else names,
              "pairs": side["pairs"] if "pairs" in side else database_pair_stats(paths.database),
              "database": str(paths.database), "sparse": str(paths.sparse / "0") if best else None, "figure": None,
              "meta": side["meta"] if "meta" in side else run_metadata(conf.seed)}
    if best:
        import pycolmap

        rec = pycolmap.Reconstruction(str(paths.sparse / "0"))
        report["figure"] = str(plot_reconstruction(paths.figure, rec, title=f"{paths.image_dir.name}: "
                                                   f"{best['registered']}/{len(names)} images, {best['points3D']:,} points"))
    write_json(paths.report_json, report)
    atomic_write_text(paths.report_md, report_markdown(report))
    _say(conf, f"done in {report['total_time_s']:.1f} s: {report['registered']}/{len(names)} images registered, "
               f"{report['points3D']:,} points -> {paths.sparse / '0'}; report {paths.report_md}")
    return report


def run_sfm(image_dir: str | os.PathLike, out_dir: str | os.PathLike, config: SfmConfig | dict | None = None,
            command: str = "", colmap_log: bool = False) -> dict:
    """``guidedmatch sfm IMAGE_DIR OUT_DIR`` as a function: :func:`main` with :class:`SfmPaths`.

    COLMAP's own INFO log lines (thousands for a mapping run) are silenced unless ``colmap_log``; its warnings and
    errors still show."""
    with colmap_log_level(0 if colmap_log else 1):
        return main(config_from(SfmConfig, config), SfmPaths(image_dir, out_dir), command=command)


@contextlib.contextmanager
def colmap_log_level(level: int = 1):
    """COLMAP's (glog) minimum log level inside the block: 0 INFO, 1 WARNING, 2 ERROR; restored afterwards."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
