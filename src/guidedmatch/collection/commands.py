"""The collection commands of the CLI: ``guidedmatch colmap DATABASE`` and ``guidedmatch hloc FEATURES PAIRS MATCHES``.

Both check everything they can before matching (options, the database / feature file, the pair list, the write
lock), run :func:`~guidedmatch.collection.engine.match_collection`, print its summary and exit with status 2 and one
line when pairs failed (they are not written: rerunning the same command retries exactly them).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import GuidedMatchError

COLMAP_EXAMPLES = """examples:
  guidedmatch colmap project/database.db                       # every pair (exhaustive), our two-view geometry
  guidedmatch colmap db.db --pairs sequential:10               # video: each image with the next 10
  guidedmatch colmap db.db --pairs pairs.txt --workers 2       # a COLMAP / hloc pairs file, 2 local processes
  guidedmatch colmap db.db --scheduler tcp://10.0.0.1:8786     # a running Dask cluster (shared storage)
  guidedmatch colmap db.db --geometry colmap                   # raw matches, then COLMAP's own verification
  colmap mapper --database_path db.db --image_path images --output_path sparse   # then map as usual

Interrupted? Run the same command again: pairs already in the database are skipped.
"""

HLOC_EXAMPLES = """examples:
  guidedmatch hloc outputs/feats-sift.h5 outputs/pairs-netvlad.txt outputs/matches-guided.h5
  guidedmatch hloc feats.h5 exhaustive matches.h5 --workers 2 --config band_px=3

Then use MATCHES.h5 wherever hloc expects a matches file (e.g. hloc.reconstruction.main(..., matches=...)).
Interrupted? Run the same command again: pairs already in MATCHES.h5 (or its .parts folder) are skipped.
"""


def _nonneg_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {v}")
    return v


def _common(p: argparse.ArgumentParser, modes) -> None:
    p.add_argument("--mode", default="so+epi+ia", choices=modes, help="matching mode (default so+epi+ia)")
    p.add_argument("--config", action="append", metavar="KEY=VALUE",
                   help="matcher config override, e.g. band_px=3 (repeatable)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_nonneg_int, default=None, metavar="N",
                       help="N local single-threaded worker processes (0: in this process; default: auto -- "
                            "in-process for small jobs, else one per core)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="address of a running Dask scheduler (tcp://host:8786); workers need the files")
    p.add_argument("--retries", type=_nonneg_int, default=1, help="retries of a failed pair (default 1)")
    p.add_argument("--log", default=None, metavar="PATH",
                   help="per-pair JSON lines + a summary line (default: next to the output, .guidedmatch.jsonl; "
                        "'none' for no log)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_collection_commands(sub) -> None:
    """Add ``colmap`` and ``hloc`` to the CLI's subparsers."""
    from ..config import MODES

    c = sub.add_parser("colmap", help="match the images of a COLMAP database (writes matches + two-view geometries)",
                       description="Match image pairs of a COLMAP database (features from colmap feature_extractor, "
                       "pycolmap.extract_features or guidedmatch) and write their matches and two-view geometries "
                       "into it, ready for colmap mapper / pycolmap.incremental_mapping. Resumable.",
                       epilog=COLMAP_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("database", help="COLMAP database (.db) with images, keypoints and descriptors")
    c.add_argument("--pairs", default="exhaustive", metavar="SPEC",
                   help="exhaustive | sequential[:K[:quadratic]] | PAIRS.txt ('name1 name2' lines); default exhaustive")
    c.add_argument("--geometry", default="ours", choices=("ours", "colmap"),
                   help="ours: our two-view verdict per pair (no separate verification); colmap: raw matches, then "
                        "pycolmap's geometric verification (default ours)")
    _common(c, MODES)
    c.set_defaults(func=cmd_colmap)

    h = sub.add_parser("hloc", help="match the pairs of an hloc features.h5 into an hloc matches.h5",
                       description="Match the image pairs of a pairs file with the features of an hloc features.h5 "
                       "and write an hloc matches.h5 (matches0 / matching_scores0). Resumable.",
                       epilog=HLOC_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    h.add_argument("features", help="hloc features.h5 (keypoints, descriptors D x N)")
    h.add_argument("pairs", help="pairs file ('name1 name2' lines), or exhaustive | sequential[:K]")
    h.add_argument("matches", help="output matches.h5 (created, or completed when it exists)")
    _common(h, MODES)
    h.set_defaults(func=cmd_hloc)


def _collection_config(args, log_default: Path):
    """The validated CollectionConfig of the options (ConfigError before any work)."""
    from ..cli import _parse_kv
    from .engine import CollectionConfig

    log = args.log if args.log is not None else str(log_default)
    return CollectionConfig(mode=args.mode, matcher=_parse_kv(args.config, "--config"), workers=args.workers,
                            scheduler=args.scheduler, retries=args.retries, progress=not args.no_progress,
                            log_path=None if str(log).lower() == "none" else log)


def _print_pairs(pairs) -> None:
    """Say what the pair list normalization dropped (duplicates, reversed duplicates, self-pairs), if anything."""
    if any(isinstance(v, dict) and v.get("count") for v in pairs.report.values()):
        print(f"pairs      : {pairs.summary()}")


def _finish(report, log_path) -> int:
    print(report.summary())
    if log_path:
        print(f"log        : {log_path}")
    if report.failed:
        (a, b), reason = report.failed[0]
        n = report.done + len(report.failed)
        raise GuidedMatchError(f"{len(report.failed)} of {n} pairs failed and were not written (first: {a} {b}: "
                               f"{reason}); run the same command again to retry them"
                               + (f"; details in {log_path}" if log_path else ""))
    return 0


def _setup(args, output: Path, open_source, spec: str):
    """Everything checked before matching: options -> config, the source, the pair list, descriptor types."""
    from .pairs import pairs_from_spec

    try:
        cfg = _collection_config(args, output.with_name(output.name + ".guidedmatch.jsonl"))
    except GuidedMatchError as exc:
        raise type(exc)(f"bad option: {exc}") from None
    source = open_source()
    pairs = pairs_from_spec(spec, source.names())
    _print_pairs(pairs)
    source.validate(pairs.names())
    return cfg, source, pairs


def cmd_colmap(args) -> int:
    from .engine import match_collection
    from .sinks import ColmapSink
    from .sources import ColmapSource

    db = Path(args.database)
    cfg, source, pairs = _setup(args, db, lambda: ColmapSource(db), args.pairs)
    with ColmapSink(db, geometry=args.geometry) as sink:
        report = match_collection(source, pairs, sink, cfg)
        if args.geometry == "colmap" and report.done:
            n = sink.verify()
            print(f"verified   : {n} pairs with COLMAP's geometric verification (pycolmap.verify_matches)")
    return _finish(report, cfg.log_path)


def cmd_hloc(args) -> int:
    from .engine import match_collection
    from .sinks import H5MatchesSink
    from .sources import H5Source

    out = Path(args.matches)
    cfg, source, pairs = _setup(args, out, lambda: H5Source(args.features), args.pairs)
    with H5MatchesSink(out, source) as sink:
        report = match_collection(source, pairs, sink, cfg)
    return _finish(report, cfg.log_path)
