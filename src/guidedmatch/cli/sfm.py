"""``guidedmatch extract`` -> ``guidedmatch colmap`` -> ``guidedmatch map``, and ``guidedmatch sfm`` (the three stages
in one process): photos to a COLMAP sparse model with pycolmap only (no COLMAP program needed)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..base import DEFAULT_INLIER_PX, DEFAULT_REFIT_DEG
from ..config import MODES
from .common import add_cap_above_option, parse_kv, positive_int

__all__ = ["add_commands", "cmd_extract", "cmd_map", "cmd_sfm", "add_extraction_options", "add_mapping_options"]

BAD_IMAGES_HELP = ("what to do with an image that does not decode completely (truncated, corrupt, not an image): "
                   "skip (default: left out, named with the reason in the output and in sfm's report) or refuse (exit 2 "
                   "naming it, before any feature is written; every image is decoded once more for that check)")


def add_extraction_options(p: argparse.ArgumentParser) -> None:
    """The options that determine the features (``extract`` and ``sfm``)."""
    p.add_argument("--detector", default="sift", help="sift (default: OpenCV SIFT written as COLMAP's own, ~3.7x less "
                   "CPU than COLMAP's), colmap (pycolmap's SIFT, as colmap feature_extractor) or ours:sift|orb|akaze|brisk")
    p.add_argument("--max-features", type=positive_int, default=None, help="features per image (default: "
                   "8192 for COLMAP SIFT, unlimited for ours)")
    p.add_argument("--max-image-size", type=positive_int, default=None, help="downscale so the longer side is at "
                   "most this before extraction (default: 3200 for COLMAP, none for ours)")
    p.add_argument("--peak-threshold", type=float, default=None, help="COLMAP SIFT peak threshold (default "
                   "0.0067; 0.002 gives ~5x more features)")
    p.add_argument("--camera", default=None, metavar="MODEL:PARAMS", help="known intrinsics for every image, e.g. "
                   "PINHOLE:fx,fy,cx,cy (held fixed in bundle adjustment)")
    p.add_argument("--single-camera", action="store_true", help="all images share one (estimated) camera")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model when intrinsics are "
                   "estimated (default SIMPLE_RADIAL)")
    p.add_argument("--bad-images", default="skip", choices=("skip", "refuse"), help=BAD_IMAGES_HELP)


def add_mapping_options(p: argparse.ArgumentParser) -> None:
    """The mapper's options (``map`` and ``sfm``)."""
    p.add_argument("--mapper", default="auto", choices=("auto", "incremental", "global"),
                   help="incremental (pycolmap.incremental_mapping), global (pycolmap.global_mapping, COLMAP's "
                        "global SfM) or auto (default: global above 100 images, else incremental; docs/sfm.md)")
    # 100 = guidedmatch.sfm.AUTO_GLOBAL_ABOVE, written out: importing guidedmatch.sfm here would add ~0.16 s to the
    # start-up of every command (tests/test_sfm.py checks the two agree)
    p.add_argument("--seed", type=int, default=0, help="mapper random seed (default 0)")


def _common_run_options(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--threads", type=int, default=-1, help=f"{what} (default -1 = all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--colmap-log", action="store_true", help="show COLMAP's INFO log lines")


def _conf(args, **extra):
    """The SfmConfig of the parsed options (those a subcommand does not have keep their defaults)."""
    from ..sfm import SfmConfig

    names = ("detector", "max_features", "max_image_size", "peak_threshold", "camera_model", "camera",
             "single_camera", "bad_images", "pairs", "mode", "geometry", "max_inliers_per_pair", "cap_above", "inlier_px", "refit_below_deg",
             "workers", "scheduler", "mapper", "seed", "second_look", "pipeline")
    kw = {k: getattr(args, k) for k in names if hasattr(args, k)}
    if getattr(args, "config", None):
        kw["matcher"] = parse_kv(args.config, "--config") or None
    return SfmConfig(**kw, num_threads=args.threads, progress=not args.quiet, **extra)


def _skipped_lines(skipped) -> None:
    for s in skipped:
        print(f"skipped    : {s['name']}: {s['reason']}")


def _peak(rec: dict) -> str:
    m = rec.get("peak_rss_mb") or {}
    kids = f" (largest worker process {m['children']:,.0f} MB)" if m.get("children") else ""
    return f"peak memory {m.get('self', 0):,.0f} MB{kids}"


def cmd_extract(args) -> int:
    from ..sfm import run_extract

    rec = run_extract(args.image_dir, args.database, _conf(args), colmap_log=args.colmap_log)
    print(f"extracted  : {rec['extracted']} image(s), {rec['reused']} already in {args.database}, "
          f"{len(rec['skipped'])} skipped; keypoints median {rec['keypoints']['median']:.0f} "
          f"({rec['time_s']:.1f} s, {rec['workers']} process(es), {_peak(rec)})")
    _skipped_lines(rec["skipped"])
    print(f"next       : guidedmatch colmap {args.database} --max-inliers-per-pair 1000   "
          f"(then: guidedmatch map {args.database} {args.image_dir} OUT_DIR)")
    return 0


def _models_lines(rec: dict, out: Path) -> None:
    for k, m in enumerate(rec["models"]):
        print(f"model      : {out / str(k)}: {m['registered']} images, {m['points3D']:,} points"
              + (f" ({', '.join(m['registered_names'][:6])}{', ...' if m['registered'] > 6 else ''})"
                 if len(rec["models"]) > 1 else ""))


def cmd_map(args) -> int:
    from ..sfm import run_map

    out = Path(args.out)
    rec = run_map(args.database, args.image_dir, out, _conf(args), colmap_log=args.colmap_log,
                  fixed_intrinsics=args.fixed_intrinsics)
    how = "reused (same database and settings)" if rec.get("reused") else f"{rec['time_s']:.1f} s"
    from ..sfm.config import mapper_label

    print(f"mapping    : {mapper_label(rec)}, {how}, {len(rec['models'])} model(s), {_peak(rec)}")
    _models_lines(rec, out)
    if not rec["models"] or rec["models"][0]["registered"] < 2:
        print("guidedmatch: no reconstruction: the mapper could not register 2 images (too few verified pairs)",
              file=sys.stderr)
        return 2  # the photos give no model: an answer about the input (exit 1 is reserved for bugs)
    print(f"next       : colmap gui --database_path {args.database} --image_path {args.image_dir} --import_path "
          f"{out / '0'}   (or pycolmap.Reconstruction('{out / '0'}'))")
    return 0


def cmd_sfm(args) -> int:
    from ..sfm import run_sfm

    report = run_sfm(args.image_dir, args.out_dir, _conf(args), command="guidedmatch " + " ".join(sys.argv[1:]),
                     colmap_log=args.colmap_log)
    if args.quiet:   # the summary line went to stderr with the progress; say the essentials once
        print(report["summary"])
    _skipped_lines(report["skipped_images"])
    if report["registered"] < 2:
        print(f"guidedmatch: no reconstruction: the mapper registered {report['registered']} of {report['num_images']} "
              f"images (too few verified pairs; see {Path(args.out_dir) / 'report.md'})", file=sys.stderr)
        return 2  # the photos give no model: an answer about the input (exit 1 is reserved for bugs)
    print(f"next       : colmap gui --database_path {report['database']} --image_path {args.image_dir} "
          f"--import_path {report['sparse']}   (or pycolmap.Reconstruction('{report['sparse']}'))")
    return 0


def add_commands(sub, parents) -> None:
    """Add ``extract``, ``map`` and ``sfm`` to the CLI's subparsers."""
    x = sub.add_parser("extract", parents=parents, help="images -> COLMAP database of features (stage 1 of sfm)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Decode every image of IMAGE_DIR completely and extract its features into a "
                       "COLMAP database (the extractor of guidedmatch sfm: OpenCV SIFT written as COLMAP writes its own by default, --detector colmap for pycolmap's; the database "
                       "works with guidedmatch colmap, colmap mapper and pycolmap). Resumable: a rerun extracts only "
                       "the images not yet in the database.",
                       epilog="examples:\n"
                       "  guidedmatch extract photos/ project/database.db\n"
                       "  guidedmatch colmap project/database.db --max-inliers-per-pair 1000\n"
                       "  guidedmatch map project/database.db photos/ project/sparse\n")
    x.add_argument("image_dir", help="folder of images (searched recursively; names relative to it)")
    x.add_argument("database", help="COLMAP database to create or complete (.db)")
    add_extraction_options(x)
    _common_run_options(x, "extraction processes")
    x.set_defaults(func=cmd_extract)

    m = sub.add_parser("map", parents=parents, help="COLMAP database -> sparse model(s) with pycolmap (stage 3 of sfm)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Run pycolmap's mapper on a matched COLMAP database (e.g. after guidedmatch "
                       "colmap) and write the models into OUT/0, OUT/1, ... (largest first) with OUT/mapping.json. "
                       "A rerun on an unchanged database with the same options reuses the model.",
                       epilog="examples:\n"
                       "  guidedmatch map project/database.db photos/ project/sparse\n"
                       "  guidedmatch map project/database.db photos/ project/sparse-global --mapper global\n")
    m.add_argument("database", help="COLMAP database with features, matches and two-view geometries")
    m.add_argument("image_dir", help="the image folder of the database (the mapper reads point colours from it)")
    m.add_argument("out", help="output folder of the models (created)")
    add_mapping_options(m)
    m.add_argument("--fixed-intrinsics", action="store_true", help="hold the cameras' intrinsics fixed in bundle "
                   "adjustment (as guidedmatch sfm --camera does)")
    _common_run_options(m, "mapper threads")
    m.set_defaults(func=cmd_map)

    s = sub.add_parser("sfm", parents=parents, help="photos -> COLMAP sparse model(s): extract, colmap and map in one process",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Structure from motion with guidedmatch as the matcher -- the stages of guidedmatch "
                       "extract, colmap and map in one process: every image decoded completely and its features "
                       "extracted (OpenCV SIFT in COLMAP's conventions by default) into OUT_DIR/database.db, collection matching, pycolmap's "
                       "mapper (--mapper auto: incremental up to 100 images, global beyond) into OUT_DIR/sparse/0 (sparse/1, ... when the images "
                       "form several models), report.json / report.md / reconstruction.png with the time and peak "
                       "memory of each stage. A damaged image is skipped and named (--bad-images refuse: exit 2). "
                       "Resumable: a rerun reuses extracted features, matched pairs and an up-to-date model.",
                       epilog="examples:\n"
                       "  guidedmatch sfm photos/ project/\n"
                       "  guidedmatch sfm photos/ project/ --pairs sequential:10 --workers 4\n"
                       "  guidedmatch sfm photos/ project/ --camera PINHOLE:2759.5,2764.2,1520.7,1006.8\n"
                       "  guidedmatch sfm photos/ project/ --detector ours:orb --max-features 4000\n"
                       "  guidedmatch sfm photos/ project/ --mapper global --bad-images refuse\n"
                       "  colmap gui --database_path project/database.db --image_path photos/ --import_path project/sparse/0")
    s.add_argument("image_dir", help="folder of images (searched recursively; names relative to it)")
    s.add_argument("out_dir", help="project folder (created; database.db, sparse/, report.*)")
    add_extraction_options(s)
    s.add_argument("--pairs", default="auto", help="auto (default: exhaustive up to 60 images, else retrieval:20 "
                   "followed by the verified expansion), exhaustive, sequential[:K], retrieval[:K], specs joined by "
                   "'+', or a file of 'name1 name2' lines")
    s.add_argument("--mode", default="so+epi+ia", choices=MODES, help="matching mode (default so+epi+ia)")
    s.add_argument("--config", action="append", metavar="KEY=VALUE", help="matcher config override (repeatable)")
    s.add_argument("--geometry", default="ours", choices=("ours", "colmap"), help="two-view geometry: ours "
                   "(the matcher's verdict, default) or colmap (pycolmap's verification)")
    s.add_argument("--max-inliers-per-pair", type=int, default=1000, metavar="K", help="inlier matches "
                   "per pair handed to the mapper, spread over the image, best first: keypoints in the most verified pairs, "
                   "then the smallest error to the pair's F / H (default 1000; 0 = all), when the database holds more "
                   "than --cap-above inliers in all: the mapper's time follows its observations (docs/sfm.md)")
    add_cap_above_option(s)
    s.add_argument("--inlier-px", type=float, default=DEFAULT_INLIER_PX, metavar="PX", help="with --geometry ours: "
                   "the mapper gets the inliers within PX of their pair's F / H, at least 15 per pair (default "
                   f"{DEFAULT_INLIER_PX:g}; the verdict decides at 3 px; 0 = all: docs/collections.md)")
    s.add_argument("--refit-below-deg", type=float, default=DEFAULT_REFIT_DEG, metavar="DEG", help="with --inlier-px: "
                   "first fit F again on its own inliers for the pairs whose median triangulation angle is below DEG "
                   f"(small baselines; default {DEFAULT_REFIT_DEG:g}; 0 = never: docs/collections.md)")
    s.add_argument("--second-look", action=argparse.BooleanOptionalAction, default=None,
                   help="match again the weak pairs and the rejected pairs that verified neighbours tie together by "
                        "chained matches, their chained keypoints drawn first (default: on with --geometry ours; "
                        "guidedmatch colmap --help)")
    s.add_argument("--workers", type=int, default=None, help="matching worker processes (default: auto; 0 = in this process)")
    s.add_argument("--pipeline", default="off", choices=("auto", "on", "off"), help="match each pair as soon as both "
                   "its images' features are written, while the others are extracted: off (default: extraction, "
                   "then matching; the overlap was no faster on Herz-Jesus-P8 on 2 cores, docs/sfm.md), auto (where "
                   "the pairs allow it: exhaustive, sequential, a pairs file; not retrieval), on (refused where they "
                   "do not); the report says which ran and why")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS", help="match on a running Dask cluster")
    add_mapping_options(s)
    _common_run_options(s, "extraction processes and COLMAP verification / mapping threads")
    s.set_defaults(func=cmd_sfm)
