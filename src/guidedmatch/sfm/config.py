"""Settings and paths of the structure-from-motion stages (:class:`SfmConfig`, :class:`SfmPaths`)."""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

from ..collection.image_folder import COLMAP_MAX_IMAGE_SIZE, IMAGE_EXTENSIONS, OUR_DETECTORS
from ..base import DEFAULT_INLIER_PX, DEFAULT_REFIT_DEG
from ..config import MODES
from ..errors import ConfigError
from ..validation import check_bool, check_choice, check_number, config_from

__all__ = ["SfmConfig", "SfmPaths", "parse_camera", "IMAGE_EXTENSIONS", "COLMAP_MAX_IMAGE_SIZE", "OUR_DETECTORS",
           "CAMERA_MODELS", "MAPPERS", "AUTO_GLOBAL_ABOVE", "resolve_mapper",
           "mapper_label", "MIN_MAPPER_INLIERS", "VERIFIED_CONFIGS"]

#: Camera models accepted by ``camera=`` and their parameter counts (COLMAP's names and parameter order).
CAMERA_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}
#: COLMAP's ``IncrementalMapperOptions.init_min_num_inliers``: fewer inliers per pair and the mapper cannot start.
MIN_MAPPER_INLIERS = 100
#: ``max_inliers_per_pair`` applies only when the database holds more verified inliers than this in all. The cap is
#: a time measure -- the mapper's bundle adjustments cost what its observations cost -- and it costs pose accuracy
#: where the mapper is cheap anyway: on COLMAP's features, 3 mapper seeds (benchmarks/results/accuracy), median
#: error without / with a cap of 1000 per pair: Herz-Jesus-P8 (60k inliers, 3.7 s of mapping) 0.205 / 0.229 deg
#: (COLMAP's matches 0.213), P25 (406k) 0.361 / 0.362, buddha (186k) 0.206 / 0.211, fox (760k) 0.487 / 0.483;
#: `guidedmatch sfm` on P8 (51k, OpenCV SIFT): 0.213 / 0.241 (COLMAP 0.214). 100,000 inliers map in about 5 s on
#: 2 cores: a handful of images keeps every inlier, a collection of dozens is capped as before. The value was set
#: with Herz-Jesus-P8 in view (the one scene here below it); it is not tuned further.
CAP_ABOVE_INLIERS = 100_000
#: Two-view geometry configurations the mapper uses (COLMAP ``TwoViewGeometry::ConfigurationType``).
VERIFIED_CONFIGS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC", "MULTIPLE")
#: Mappers: ``pycolmap.incremental_mapping`` and ``pycolmap.global_mapping`` (COLMAP's global SfM).
MAPPERS = ("incremental", "global")
#: ``mapper="auto"``: the global mapper above this many images, the incremental one up to it (:func:`resolve_mapper`)
AUTO_GLOBAL_ABOVE = 100


def resolve_mapper(mapper: str, num_images: int) -> tuple[str, str]:
    """``(mapper that runs, why)``: ``"auto"`` picks by the number of images in the database; the others stay.

    Measured (docs/sfm.md#the-mapper): on Herz-Jesus-P8 and P25 (8 and 25 images) the incremental mapper was faster
    and more accurate; on the 220-image collection the global one mapped 1.6x faster, registered a scene the
    incremental one left out (lund: 21 + 8 of 29 images vs none) and kept Herz-Jesus-P25's poses better than COLMAP's
    pipeline; in between nothing was measured, so the switch sits at :data:`AUTO_GLOBAL_ABOVE`.

    >>> resolve_mapper("auto", 67)[0], resolve_mapper("auto", 220)[0], resolve_mapper("global", 8)
    ('incremental', 'global', ('global', 'mapper=global'))
    """
    if mapper != "auto":
        return mapper, f"mapper={mapper}"
    if num_images > AUTO_GLOBAL_ABOVE:
        return "global", f"auto: {num_images} images > {AUTO_GLOBAL_ABOVE}: global"
    return "incremental", f"auto: {num_images} images <= {AUTO_GLOBAL_ABOVE}: incremental"


def mapper_label(mapping: dict) -> str:
    """``"global mapper (auto: 220 images > 100: global)"`` -- the mapper of a mapping record, with the auto rule
    that picked it (a mapper given by name: just its name).

    >>> mapper_label({"mapper": "global", "mapper_rule": "auto: 220 images > 100: global"})
    'global mapper (auto: 220 images > 100: global)'
    >>> mapper_label({"mapper": "incremental", "mapper_rule": "mapper=incremental"}), mapper_label({})
    ('incremental mapper', 'incremental mapper')
    """
    rule = str(mapping.get("mapper_rule") or "")
    return f"{mapping.get('mapper', 'incremental')} mapper" + (f" ({rule})" if rule.startswith("auto") else "")


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
    """Settings of the stages / ``guidedmatch extract | map | sfm`` (every field checked on construction)."""

    detector: str = "sift"             # "sift" = OpenCV SIFT written as COLMAP's (3.7x less CPU, same conventions);
                                       # "colmap" = pycolmap SIFT (colmap feature_extractor); "ours:sift|orb|akaze|brisk"
    max_features: int | None = None    # features per image; None = the detector's default (8192 for COLMAP SIFT)
    max_image_size: int | None = None  # longest side before extraction; None = the detector's default (3200 for COLMAP)
    peak_threshold: float | None = None  # COLMAP SIFT peak threshold; None = COLMAP's 0.0067 (0.002: ~5x more features)
    camera_model: str = "SIMPLE_RADIAL"  # camera model when intrinsics are estimated (COLMAP's default)
    camera: str | None = None          # known intrinsics "MODEL:params" for every image (held fixed in bundle adjustment)
    single_camera: bool = False        # all images share one camera (intrinsics estimated jointly)
    bad_images: str = "skip"           # a damaged image: "skip" (left out, listed in the report) | "refuse" (error)
    pairs: str = "auto"                # "auto" (exhaustive up to 60 images, else retrieval:20 + verified expansion) |
                                       # "exhaustive" | "sequential[:K]" | "retrieval[:K]" | "a+b" | a pairs file
    mode: str = "so+epi+ia"            # matcher mode (guidedmatch.matcher.match)
    matcher: dict | None = None        # MatcherConfig overrides, e.g. {"alignment": "c_inplane"}
    geometry: str = "ours"             # two-view geometry: "ours" (matcher's verdict written) | "colmap" (pycolmap verifies)
    inlier_px: float = DEFAULT_INLIER_PX  # geometry "ours": the mapper gets the inliers within this many px of their
                                       # pair's F / H (at least 15; the verdict decides at 3 px); 0 = all of them
    refit_below_deg: float = DEFAULT_REFIT_DEG  # ...the F of pairs whose median triangulation angle is below this fitted
                                       # again on its inliers first (small baselines); 0 = never
    max_inliers_per_pair: int = 1000   # inliers per pair handed to the mapper (spread over the image, best first); 0 = all
    cap_above: int = CAP_ABOVE_INLIERS  # ...but only when the database holds more inliers than this in all (0: always)
    second_look: bool | None = None    # weak pairs, and rejected ones that verified neighbours tie by chained matches, are
                                       # matched again, their chained keypoints drawn first (collection.second_look);
                                       # None: on with geometry "ours" (it reads our verdicts back), off with "colmap"
    workers: int | None = None         # matching worker processes; None = automatic, 0 = in this process (collection engine)
    scheduler: str | None = None       # address of a running Dask scheduler for matching
    mapper: str = "auto"               # "incremental" (pycolmap.incremental_mapping) | "global" (pycolmap.global_mapping)
                                       # | "auto": global above AUTO_GLOBAL_ABOVE (100) images, else incremental
    num_threads: int = -1              # extraction processes and COLMAP verification / mapping threads; -1 = all cores
    seed: int = 0                      # mapper random seed (COLMAP's RANSAC and initial pair trials)
    pipeline: str = "off"              # match pairs while extracting: "off" (measured no faster on 2 cores) | "auto"
                                       # (where the pairs allow: not retrieval) | "on" (refused where they do not)
    progress: bool = True              # print stage lines and progress bars

    def __post_init__(self) -> None:
        o = "SfmConfig"
        det = self.detector
        if det not in ("sift", "colmap") and not (det.startswith("ours:") and det[5:] in OUR_DETECTORS):
            raise ConfigError(f"{o}.detector must be 'sift', 'colmap' or one of "
                              f"{', '.join('ours:' + d for d in OUR_DETECTORS)}; got {det!r}")
        check_number(o, "max_features", self.max_features, lo=1, integer=True, allow_none=True)
        check_number(o, "max_image_size", self.max_image_size, lo=16, integer=True, allow_none=True)
        check_number(o, "peak_threshold", self.peak_threshold, lo=0, lo_open=True, allow_none=True)
        if self.peak_threshold is not None and det not in ("sift", "colmap"):
            raise ConfigError(f"{o}.peak_threshold applies to the COLMAP SIFT detector only (detector={det!r})")
        check_choice(o, "camera_model", self.camera_model, CAMERA_MODELS)
        parse_camera(self.camera)
        check_bool(o, "single_camera", self.single_camera)
        check_choice(o, "bad_images", self.bad_images, ("skip", "refuse"))
        if not isinstance(self.pairs, str) or not self.pairs:
            raise ConfigError(f"{o}.pairs must be 'auto', 'exhaustive', 'sequential[:K]', 'retrieval[:K]' or a "
                              f"pairs file; got {self.pairs!r}")
        check_choice(o, "mode", self.mode, MODES)
        if self.matcher is not None and not isinstance(self.matcher, dict):
            raise ConfigError(f"{o}.matcher must be a dict of MatcherConfig fields or None; got {self.matcher!r}")
        if self.matcher:
            from ..config import MatcherConfig

            config_from(MatcherConfig, self.matcher)
        check_choice(o, "geometry", self.geometry, ("ours", "colmap"))
        check_number(o, "inlier_px", self.inlier_px, lo=0)
        object.__setattr__(self, "inlier_px", float(self.inlier_px))
        check_number(o, "refit_below_deg", self.refit_below_deg, lo=0, hi=180)
        object.__setattr__(self, "refit_below_deg", float(self.refit_below_deg))
        check_number(o, "max_inliers_per_pair", self.max_inliers_per_pair, lo=0, integer=True)
        if 0 < self.max_inliers_per_pair < MIN_MAPPER_INLIERS:
            raise ConfigError(f"{o}.max_inliers_per_pair must be 0 (all) or >= {MIN_MAPPER_INLIERS}: COLMAP's mapper "
                              f"needs {MIN_MAPPER_INLIERS} inliers in its initial pair (init_min_num_inliers); got "
                              f"{self.max_inliers_per_pair}")
        check_number(o, "cap_above", self.cap_above, lo=0, integer=True)
        if self.second_look is not None:
            check_bool(o, "second_look", self.second_look)
        check_number(o, "workers", self.workers, lo=0, integer=True, allow_none=True)
        check_choice(o, "mapper", self.mapper, (*MAPPERS, "auto"))
        check_number(o, "num_threads", self.num_threads, lo=-1, integer=True)
        if self.num_threads == 0:
            raise ConfigError(f"{o}.num_threads must be -1 (all cores) or >= 1; got 0")
        check_number(o, "seed", self.seed, lo=0, integer=True)
        check_choice(o, "pipeline", self.pipeline, ("auto", "on", "off"))
        check_bool(o, "progress", self.progress)

    def extraction_settings(self) -> dict:
        """What determines the database's features (a rerun with other values is refused)."""
        return {k: getattr(self, k) for k in ("detector", "max_features", "max_image_size", "peak_threshold",
                                               "camera_model", "camera", "single_camera")}

    def matcher_for(self, num_images: int) -> dict:
        """The matcher settings the matching runs with over ``num_images`` images: ``matcher``, and when the global
        mapper will run (:func:`resolve_mapper`) ``nonplanar_as_F=False`` unless ``matcher`` sets it: the global
        mapper takes each pair's relative pose from its two-view geometry, and an F fitted to a scene with a dominant
        plane gives an unstable one (fox alone, OpenCV SIFT, global mapper: 0.529 deg with it off, 0.748 deg on;
        the incremental mapper triangulates the off-plane inliers and gains: docs/sfm.md).

        >>> SfmConfig(mapper="global").matcher_for(8), SfmConfig(mapper="auto").matcher_for(8)
        ({'nonplanar_as_F': False}, {})
        >>> SfmConfig(mapper="global", matcher={"nonplanar_as_F": True}).matcher_for(8)
        {'nonplanar_as_F': True}
        """
        m = dict(self.matcher or {})
        if resolve_mapper(self.mapper, num_images)[0] == "global":
            m.setdefault("nonplanar_as_F", False)
        return m

    def matching_settings(self) -> dict:
        """What determines the matched pairs (a rerun with other values is refused while pairs exist)."""
        return {"mode": self.mode, "matcher": dict(self.matcher or {}), "geometry": self.geometry,
                "max_inliers_per_pair": self.max_inliers_per_pair, "cap_above": self.cap_above,
                "inlier_px": self.inlier_px, "refit_below_deg": self.refit_below_deg}

    def mapping_settings(self) -> dict:
        """What determines the model given the database (a rerun with the same values and database reuses it)."""
        return {"mapper": self.mapper, "seed": self.seed, "camera": self.camera}


@dataclass(frozen=True)
class SfmPaths:
    """Where the stages read and write. ``guidedmatch sfm``: everything under ``out_dir`` (``database.db``,
    ``sparse/``, reports); the staged commands name the database (``database``) and the model folder (``sparse``)
    themselves."""

    image_dir: Path
    out_dir: Path
    database_path: Path | None = None   # default out_dir/database.db
    sparse_path: Path | None = None     # default out_dir/sparse

    def __post_init__(self) -> None:
        for k in ("image_dir", "out_dir", "database_path", "sparse_path"):
            if getattr(self, k) is not None:
                object.__setattr__(self, k, Path(getattr(self, k)).expanduser().resolve())

    database = property(lambda self: self.database_path or self.out_dir / "database.db")
    sparse = property(lambda self: self.sparse_path or self.out_dir / "sparse")
    project = property(lambda self: self.out_dir / "sfm_project.json")
    report_json = property(lambda self: self.out_dir / "report.json")
    report_md = property(lambda self: self.out_dir / "report.md")
    figure = property(lambda self: self.out_dir / "reconstruction.png")
    pair_log = property(lambda self: self.out_dir / "pairs.jsonl")
    mapping_record = property(lambda self: self.sparse / "mapping.json")


def say(conf: SfmConfig, text: str) -> None:
    """A progress line on stderr (unless ``conf.progress`` is off)."""
    if conf.progress:
        print(text, file=sys.stderr, flush=True)
