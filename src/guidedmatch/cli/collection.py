"""``guidedmatch colmap`` (a COLMAP database) and ``guidedmatch hloc`` (hloc features.h5 -> matches.h5): collection
matching with the collection engine."""
from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from ..base import DEFAULT_INLIER_PX, DEFAULT_REFIT_DEG
from ..config import MODES
from ..errors import ConfigError, GuidedMatchError, InputError
from ..features import writable_folder
from .common import add_cap_above_option, nonneg_int, parse_kv, positive_int

__all__ = ["add_commands", "cmd_colmap", "cmd_hloc", "add_matching_options"]


COLMAP_EXAMPLES = """examples:
  guidedmatch colmap project/database.db                       # every pair (exhaustive), our two-view geometry
  guidedmatch colmap db.db --pairs sequential:10               # video: each image with the next 10
  guidedmatch colmap db.db --pairs pairs.txt --workers 2       # a COLMAP / hloc pairs file, 2 local processes
  guidedmatch colmap db.db --pairs retrieval:20                # hundreds of photos: each image's 20 most similar
                                                               # (own visual words), then the verified expansion
  guidedmatch colmap db.db --pairs sequential:5+retrieval:10   # a walk or video: neighbours and look-alikes
  guidedmatch colmap db.db --scheduler tcp://10.0.0.1:8786     # a running Dask cluster (shared storage)
  guidedmatch colmap db.db --geometry colmap                   # raw matches, then COLMAP's own verification
  guidedmatch colmap db.db --workers 2 --timeline run.png      # and a figure of when each pair ran, per worker
  guidedmatch colmap db.db --max-inliers-per-pair 1000         # at most 1000 spread, best-first inliers per pair
                                                               # for the mapper: faster mapping (docs/collections.md)
  guidedmatch colmap db.db --config max_unguided=0.005         # many unrelated 50k+-feature images: rejects them
                                                               # ~3x sooner, loses pairs verified late (docs/collections.md)
  guidedmatch map db.db images/ sparse/                        # then map with pycolmap (pip only), or with
  colmap mapper --database_path db.db --image_path images --output_path sparse   # the COLMAP program

Interrupted? Run the same command again: pairs already in the database are skipped.
"""

HLOC_EXAMPLES = """examples:
  guidedmatch hloc outputs/feats-sift.h5 outputs/pairs-netvlad.txt outputs/matches-guided.h5
  guidedmatch hloc feats.h5 exhaustive matches.h5 --workers 2 --config band_px=3

Then use MATCHES.h5 wherever hloc expects a matches file (e.g. hloc.reconstruction.main(..., matches=...)).
Interrupted? Run the same command again: pairs already in MATCHES.h5 (or its .parts folder) are skipped.
"""



def add_matching_options(p: argparse.ArgumentParser, modes) -> None:
    p.add_argument("--mode", default="so+epi+ia", choices=modes, help="matching mode (default so+epi+ia)")
    p.add_argument("--config", action="append", metavar="KEY=VALUE",
                   help="matcher config override, e.g. band_px=3 (repeatable)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=nonneg_int, default=None, metavar="N",
                       help="N local single-threaded worker processes (0: in this process; default: auto -- "
                            "in-process for small jobs, else one per core)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="address of a running Dask scheduler (tcp://host:8786); workers need the files")
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="in-process runs: pairs matched at once on N threads (default: one per core)")
    p.add_argument("--retries", type=nonneg_int, default=1, help="retries of a failed pair (default 1)")
    p.add_argument("--shared-quantizer", choices=("auto", "on", "off"), default="off",
                   help="one IVF coarse quantizer for every image, so each image's cells are computed once, not once "
                        "per pair (auto: from 16 images; default off: every image its own k-means, each pair as "
                        "guidedmatch.match gives it -- on was 8 %% faster on fox, with worse poses there; "
                        "docs/collections.md)")
    p.add_argument("--cache-mb", type=positive_int, default=1024, metavar="MB",
                   help="per process (each worker, or this one in-process): loaded images kept, MB (default 1024: "
                        "~100 images of 8192 SIFT features, ~12 of 70k); a collection that does not fit is matched "
                        "in sweeps that load each image more than once")
    p.add_argument("--log", default=None, metavar="PATH",
                   help="per-pair JSON lines + a summary line (default: next to the output, .guidedmatch.jsonl; "
                        "'none' for no log)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--timeline", default=None, metavar="PNG",
                   help="also draw when each pair of this run ran, on which worker or thread (a PNG figure)")


def add_commands(sub, parents) -> None:
    """Add ``colmap`` and ``hloc`` to the CLI's subparsers."""
    c = sub.add_parser("colmap", parents=parents, help="match the images of a COLMAP database (writes matches + two-view geometries)",
                       description="Match image pairs of a COLMAP database (features from colmap feature_extractor, "
                       "pycolmap.extract_features or guidedmatch) and write their matches and two-view geometries "
                       "into it, ready for colmap mapper / pycolmap.incremental_mapping. Resumable.",
                       epilog=COLMAP_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("database", help="COLMAP database (.db) with images, keypoints and descriptors")
    c.add_argument("--pairs", default="exhaustive", metavar="SPEC",
                   help="exhaustive | sequential[:K[:quadratic]] | retrieval[:K] (the K most similar images of each "
                        "image by the collection's own visual words; K default 20) | PAIRS.txt ('name1 name2' lines) "
                        "| several joined by '+', e.g. sequential:5+retrieval:20; default exhaustive")
    c.add_argument("--geometry", default="ours", choices=("ours", "colmap"),
                   help="ours: our two-view verdict per pair (no separate verification); colmap: raw matches, then "
                        "pycolmap's geometric verification (default ours)")
    c.add_argument("--max-inliers-per-pair", type=int, default=0, metavar="K",
                   help="then keep at most K inliers per pair for the mapper, spread over the image, best first "
                        "(keypoints in the most verified pairs, then the smallest error to the pair's F / H; default 0 = all; guidedmatch sfm uses 1000: the mapper's time follows its observations; only above --cap-above inliers in all; "
                        "below 100 COLMAP's mapper cannot pick an initial pair)")
    add_cap_above_option(c)
    c.add_argument("--inlier-px", type=float, default=DEFAULT_INLIER_PX, metavar="PX",
                   help="with --geometry ours: the mapper gets the inliers within PX of their pair's F / H, at least "
                        f"15 per pair (default {DEFAULT_INLIER_PX:g}; the verdict decides at 3 px; 0 = all of them; "
                        "docs/collections.md)")
    c.add_argument("--refit-below-deg", type=float, default=DEFAULT_REFIT_DEG, metavar="DEG",
                   help="with --inlier-px: first fit F again on its own inliers for the pairs whose median "
                        f"triangulation angle is below DEG (small baselines, e.g. video frames; default "
                        f"{DEFAULT_REFIT_DEG:g}; 0 = never; docs/collections.md)")
    add_matching_options(c, MODES)
    add_expansion_options(c)
    add_second_look_option(c)
    c.set_defaults(func=cmd_colmap)

    h = sub.add_parser("hloc", parents=parents, help="match the pairs of an hloc features.h5 into an hloc matches.h5",
                       description="Match the image pairs of a pairs file with the features of an hloc features.h5 "
                       "and write an hloc matches.h5 (matches0 / matching_scores0). Resumable.",
                       epilog=HLOC_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    h.add_argument("features", help="hloc features.h5 (keypoints, descriptors D x N)")
    h.add_argument("pairs", help="pairs file ('name1 name2' lines), or exhaustive | sequential[:K] | retrieval[:K] "
                                "| several joined by '+'")
    h.add_argument("matches", help="output matches.h5 (created, or completed when it exists)")
    add_matching_options(h, MODES)
    h.set_defaults(func=cmd_hloc)


def _collection_config(args, log_default: Path):
    """The validated CollectionConfig of the options (ConfigError before any work)."""
    from ..collection.engine import CollectionConfig

    log = args.log if args.log is not None else str(log_default)
    if args.threads is not None and (args.workers or args.scheduler):
        raise ConfigError("--threads is for in-process runs; with --workers N / --scheduler each worker runs one pair "
                          "at a time")
    from ..collection.engine import collection_matcher_config

    try:
        matcher = collection_matcher_config(parse_kv(args.config, "--config"))
    except ConfigError as exc:
        raise ConfigError(f"bad --config: {exc}") from None
    return CollectionConfig(mode=args.mode, matcher=matcher, workers=args.workers,
                            threads=args.threads, scheduler=args.scheduler, retries=args.retries, progress=not args.no_progress,
                            cache_mb=float(args.cache_mb), log_path=None if str(log).lower() == "none" else log,
                            shared_quantizer=args.shared_quantizer)


def _print_pairs(pairs) -> None:
    """Say what the pair list normalization dropped (duplicates, reversed duplicates, self-pairs), if anything."""
    if any(isinstance(v, dict) and v.get("count") for v in pairs.report.values()):
        print(f"pairs      : {pairs.summary()}")


def _finish(report, log_path, timeline: str | None = None) -> int:
    print(report.summary())
    if log_path:
        print(f"log        : {log_path}")
    if timeline:
        from ..plots import collection_timeline

        drawn = collection_timeline(timeline, report.per_pair, title=report.totals.get("backend", ""))
        print(f"timeline   : {drawn if drawn else 'no pair was matched in this run: no figure'}")
    if report.failed:
        (a, b), reason = report.failed[0]
        n = report.done + len(report.failed)
        raise GuidedMatchError(f"{len(report.failed)} of {n} pairs failed and were not written (first: {a} {b}: "
                               f"{reason}); run the same command again to retry them"
                               + (f"; details in {log_path}" if log_path else ""))
    return 0


def _setup(args, output: Path, open_source, spec: str):
    """Everything checked before matching: options -> config, the source, the pair list, descriptor types."""
    from ..collection.pairs import pairs_from_spec

    for path, what in ((output, "the output"), *([(Path(args.features), "--features")] if getattr(args, "features", None)
                                                 is not None else [])):
        if str(path) in ("", ".") or not path.name:
            raise InputError(f"{what} path is empty or a folder ({str(path)!r}): give a file path")
    cfg = _collection_config(args, output.with_name(output.name + ".guidedmatch.jsonl"))
    if args.timeline is not None:
        if Path(args.timeline).suffix.lower() != ".png":
            raise ConfigError(f"--timeline writes a PNG figure; give a .png path, got {args.timeline}")
        writable_folder(Path(args.timeline).parent, "--timeline")
    source = open_source()
    pairs = pairs_from_spec(spec, source.names(), source, retrieval=dict(progress=cfg.progress),
                            retrieval_cache=Path(str(output) + ".retrieval.npz"))
    _print_pairs(pairs)
    source.validate(pairs.names())
    return cfg, source, pairs


def add_expansion_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--expand", action=argparse.BooleanOptionalAction, default=None,
                   help="after the pairs, also match the pairs closing a triangle of verified pairs (a-b and b-c "
                        "verified, a-c not tried), in rounds, until a round verifies nothing new (default: on "
                        "when --pairs has a retrieval part, off otherwise)")
    p.add_argument("--expand-rounds", type=nonneg_int, default=None, metavar="N",
                   help="at most N expansion rounds (default 10; 0 = none)")


def add_second_look_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--second-look", action=argparse.BooleanOptionalAction, default=None,
                   help="after matching, match again the weak verified pairs (< 64 inliers) and the rejected pairs "
                        "that verified neighbours tie together by >= 16 chained matches -- the wide-baseline pairs an "
                        "exhaustive matcher verifies -- drawing the keypoints the chains point to first (default: on "
                        "with --geometry ours, which it reads back; --no-second-look: off; docs/collections.md)")
    p.add_argument("--second-look-config", action="append", metavar="KEY=VALUE",
                   help="a setting of the second look (SecondLookConfig), e.g. weak_below=0 or min_chained=32 "
                        "(repeatable; docs/collections.md)")


def second_look_settings(args) -> dict | None:
    """The second look's settings from ``--second-look`` / ``--second-look-config`` (validated before any work), or
    None when it does not run."""
    from ..collection.second_look import SecondLookConfig
    from ..sfm.stages import second_look_on
    from ..validation import config_from

    items = getattr(args, "second_look_config", None)
    on = second_look_on(args.second_look, args.geometry)
    if items and not on:
        raise ConfigError("--second-look-config needs the second look (--geometry ours, without --no-second-look)")
    kv = parse_kv(items, "--second-look-config")
    try:
        config_from(SecondLookConfig, kv)
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"bad --second-look-config: {exc}") from None
    return kv if on else None


def expansion_wanted(spec: str, expand: bool | None, rounds: int | None) -> dict | None:
    """ExpansionConfig fields (dict) when the verified expansion runs, else None: on by default when the pair spec
    has a retrieval part."""
    from ..collection.pairs import has_retrieval

    on = expand if expand is not None else has_retrieval(spec)
    if rounds is not None and not on:
        raise ConfigError("--expand-rounds needs the expansion (--expand, or a retrieval --pairs spec)")
    if not on:
        return None
    return {} if rounds is None else dict(max_rounds=rounds)


def cmd_colmap(args) -> int:
    from ..collection.sources import ColmapSource
    from ..sfm.stages import describe_cap, describe_tightening, match_into_database

    db = Path(args.database)
    if args.max_inliers_per_pair < 0:
        raise ConfigError(f"--max-inliers-per-pair must be >= 0 (0 = all inliers); got {args.max_inliers_per_pair}")
    if not args.inlier_px >= 0:
        raise ConfigError(f"--inlier-px must be >= 0 (0 = all inliers); got {args.inlier_px}")
    if not 0 <= args.refit_below_deg <= 180:
        raise ConfigError(f"--refit-below-deg must be in [0, 180] (0 = never); got {args.refit_below_deg}")
    expand = expansion_wanted(args.pairs, args.expand, args.expand_rounds)
    look_settings = second_look_settings(args)
    from ..collection.sink_base import WriteLock

    # another writer of this database is refused here, before this run opens it: opening it (COLMAP's schema set-up
    # takes SQLite's write lock for a moment) could make the running writer's next commit fail with "database is
    # locked" (the fault bench's two-writers case); the run's sinks share this lock
    with WriteLock(db, reentrant=True) if db.is_file() else contextlib.nullcontext():
        cfg, source, pairs = _setup(args, db, lambda: ColmapSource(db), args.pairs)
        done = match_into_database(source, pairs, db, cfg, geometry=args.geometry,
                                   max_inliers_per_pair=args.max_inliers_per_pair, expand=expand,
                                   second_look=look_settings,
                                   inlier_px=args.inlier_px, refit_below_deg=args.refit_below_deg,
                                   cap_above=args.cap_above)
    if args.second_look is True and args.geometry != "ours":
        print("second look: not run (it reads our two-view geometries back: --geometry ours)")
    if (look := done["second_look"]) is not None:
        from ..collection.second_look import describe

        print(f"second look: {describe(look)}")
    if done["verified"] is not None:
        print(f"verified   : {done['verified']} pairs with COLMAP's geometric verification (pycolmap.verify_matches)")
    if (tight := done["inlier_px"]) is not None:
        print(f"mapper     : {describe_tightening(tight)}")
    if (cap := done["inlier_cap"]) is not None:
        print(f"mapper     : {describe_cap(cap)}")
    status = _finish(done["report"], cfg.log_path, args.timeline)
    print(f"next       : guidedmatch map {db} IMAGE_DIR OUT_DIR   (pycolmap's mapper; or colmap mapper "
          f"--database_path {db} --image_path IMAGE_DIR --output_path OUT_DIR)")
    return status


def cmd_hloc(args) -> int:
    from ..collection.engine import match_collection
    from ..collection.sinks import H5MatchesSink
    from ..collection.sources import H5Source

    out = Path(args.matches)
    cfg, source, pairs = _setup(args, out, lambda: H5Source(args.features), args.pairs)
    with H5MatchesSink(out, source) as sink:
        report = match_collection(source, pairs, sink, cfg)
    return _finish(report, cfg.log_path, args.timeline)


