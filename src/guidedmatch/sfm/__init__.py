"""From a folder of photos to a COLMAP sparse model: ``guidedmatch sfm IMAGE_DIR OUT_DIR``, or the same three
stages one command at a time (``guidedmatch extract`` -> ``guidedmatch colmap`` -> ``guidedmatch map``).

Three resumable stages in the style of hloc (each a ``main(conf, paths)`` that reuses what a previous run left):

1. **extraction** (:func:`extract_main`): every image decoded once and completely (a truncated or corrupt file is
   skipped and listed in the report by name and reason, or refused with ``bad_images="refuse"``), then by default
   OpenCV SIFT written as COLMAP writes its own (``detector="sift"``, :func:`guidedmatch.extraction.extract_to_database`:
   COLMAP's image size, octaves, thresholds and feature selection, RootSIFT uint8, pixel-centre keypoints), or
   pycolmap's SIFT (``detector="colmap"``: the keypoints and descriptors ``colmap feature_extractor`` writes), or one
   of our OpenCV detectors (``detector="ours:sift|orb|akaze|brisk"``)
   (:func:`guidedmatch.collection.image_folder.extract_folder`). Images already in the database are not read again.
2. **matching** (:func:`match_main`): :func:`guidedmatch.collection.engine.match_collection` over the pair list
   (``pairs="auto"``: exhaustive up to 60 images, else ``retrieval:20`` followed by the verified expansion;
   ``exhaustive``, ``sequential[:K]``, ``retrieval[:K]`` or a pairs file), writing matches and two-view geometries into the
   database (``geometry="ours"``: the matcher's own verdict; ``"colmap"``: pycolmap's verification afterwards),
   then at most ``max_inliers_per_pair`` inliers of each pair are kept for the mapper (spread over the image, best
   first: :meth:`guidedmatch.collection.ColmapSink.cap_inliers`; ``0`` keeps all). Pairs already complete in the
   database are skipped.
3. **mapping** (:func:`map_main`): ``pycolmap.incremental_mapping`` (default) or ``pycolmap.global_mapping``
   (``mapper="global"``) into ``OUT_DIR/sparse/<k>/``, the largest model first (written to a temporary folder and
   moved into place when complete; reused when the database and the mapper settings are unchanged).

``OUT_DIR`` receives ``database.db``, ``sparse/0`` (readable by ``colmap gui`` and ``pycolmap.Reconstruction``;
``sparse/1``, ... when the images form several models), ``report.json`` + ``report.md`` (time and peak memory per
stage, per-pair matches / inliers / verdicts, each model's images and points, skipped images) and
``reconstruction.png`` (cameras and sparse points of ``sparse/0``, top and side view). ``OUT_DIR/sfm_project.json``
records the image folder and the extraction / matching settings: a rerun with other settings, or an ``OUT_DIR``
holding a database of another project, is refused before any work.

Coordinates: COLMAP's ``cam_from_world`` (``X_cam = R X_world + t``); keypoints in the database use COLMAP's
pixel convention (the feature sources convert to OpenCV's).
"""
from __future__ import annotations

from .config import (CAMERA_MODELS, COLMAP_MAX_IMAGE_SIZE, IMAGE_EXTENSIONS, MAPPERS, MIN_MAPPER_INLIERS,
                     OUR_DETECTORS, VERIFIED_CONFIGS, SfmConfig, SfmPaths, parse_camera)
from .pipeline import colmap_log_level, image_names, list_images, main, run_extract, run_map, run_sfm
from .report import plot_reconstruction, report_markdown
from .stages import (_db_image_names, check_output,  # noqa: F401 - _db_image_names: the benchmark's peer
                     database_pair_stats, database_summary, extract_colmap_sift,
                     extract_main, map_main, match_main, reconstruction_stats, run_mapping, verified_inliers)

__all__ = ["SfmConfig", "SfmPaths", "IMAGE_EXTENSIONS", "MAPPERS", "list_images", "parse_camera",
           "extract_main", "match_main", "map_main", "main", "run_sfm", "run_extract", "run_map",
           "database_pair_stats", "database_summary", "verified_inliers", "run_mapping", "reconstruction_stats",
           "plot_reconstruction", "report_markdown", "extract_colmap_sift", "colmap_log_level", "check_output",
           "image_names", "CAMERA_MODELS", "COLMAP_MAX_IMAGE_SIZE", "MIN_MAPPER_INLIERS", "OUR_DETECTORS",
           "VERIFIED_CONFIGS"]
