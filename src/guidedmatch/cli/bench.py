"""``guidedmatch bench`` (benchmark harness) and ``guidedmatch experiment`` (the paper's experiments)."""
from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError, InputError
from ..features import writable_folder
from .common import positive_int

__all__ = ["add_commands", "cmd_bench", "cmd_experiment", "DELEGATED", "delegated_bench"]

#: benchmarks with options of their own: ``guidedmatch bench NAME ...`` hands the rest of the command line to the
#: module's ``add_arguments(parser)`` / ``main(args)`` (the same as ``python -m MODULE ...``)
DELEGATED = {
    "faults": ("guidedmatch.evaluation.bench_faults", "kill -9, disk full, two writers, corrupt inputs, fuzzed "
               "arguments: what survives, written to faults.md / faults.json"),
    "accuracy": ("guidedmatch.evaluation.bench_accuracy", "pose accuracy per scene: COLMAP's matcher vs ours on the "
                 "same features and mapper, mapper seeds, wrong inliers, drift figure"),
    "large": ("guidedmatch.evaluation.bench_large", "the 220-image multi-scene collection: COLMAP exhaustive / "
              "vocabulary tree vs ours exhaustive / retrieval / retrieval + expansion (time, recall, across-scene pairs)"),
    "extract": ("guidedmatch.evaluation.bench_extract", "extraction options (OpenCV SIFT, pycolmap) and mappers "
                "end to end on Herz-Jesus-P8 / P25: time and pose accuracy"),
}


#: ``bench sfm --set large``: the pycolmap pipelines' matchers (and ours with retrieval + expansion, which
#: ``guidedmatch sfm`` picks on this many images) on the 220-image collection, then their mapper and guidedmatch sfm
LARGE_SFM_METHODS = "colmap_exhaustive,colmap_vocabtree,ours_retrieval_expand"


def delegated_bench(argv: list[str]):
    """``(namespace, module)`` when ``argv`` is ``[--debug] bench NAME ...`` with NAME in :data:`DELEGATED`, else None."""
    import argparse
    import importlib

    rest = [a for a in argv if a != "--debug"]
    if len(rest) < 2 or rest[0] != "bench" or rest[1] not in DELEGATED:
        return None
    import inspect

    module = importlib.import_module(DELEGATED[rest[1]][0])
    if "argv" in inspect.signature(module.main).parameters:   # main(argv) parses its own command line
        args = argparse.Namespace(debug="--debug" in argv, command="bench")
        args.func = lambda _args, _argv=rest[2:]: module.main(_argv)
        return args
    if hasattr(module, "build_parser"):  # the module's own command line (python -m MODULE), under our name
        parser = module.build_parser()
        parser.prog = f"guidedmatch bench {rest[1]}"
    else:
        parser = argparse.ArgumentParser(prog=f"guidedmatch bench {rest[1]}", description=DELEGATED[rest[1]][1])
        if "standalone" in inspect.signature(module.add_arguments).parameters:
            module.add_arguments(parser, standalone=True)
        else:
            module.add_arguments(parser)
    args = parser.parse_args(rest[2:])
    args.debug, args.command = "--debug" in argv, "bench"
    args.func = module.main
    return args


def cmd_experiment(args) -> int:
    if args.which == "alignment":
        from ..evaluation.alignment_sim import run_alignment_experiment

        summary = run_alignment_experiment(n_pairs=args.pairs, out_dir=writable_folder(args.out), seed=args.seed,
                                           progress=True)
        if isinstance(summary, dict) and summary.get("table_md"):
            print(summary["table_md"])
        print(f"wrote results to {args.out}")
        return 0
    raise ConfigError(f"unknown experiment {args.which!r}")


def cmd_bench(args) -> int:
    writable_folder(args.out)
    if args.which == "sfm" and args.set == "large":  # the 220-image collection: bench large's photos -> model rows
        from ..evaluation import bench_large

        return int(bench_large.main([*(["--data", args.data] if args.data else []),
                                     *(["--work", args.work] if args.work else []),
                                     "--out", str(Path(args.out) / "large"), "--methods", LARGE_SFM_METHODS,
                                     "--map", "colmap_exhaustive,colmap_vocabtree", "--sfm",
                                     "--sfm-mappers", "incremental,global"]) or 0)
    if args.which == "sfm":
        from ..evaluation import bench_sfm

        return int(bench_sfm.main(args) or 0)
    if args.which == "pairs":
        from ..evaluation import bench_pairs

        return int(bench_pairs.main(args) or 0)
    from ..evaluation.bench import run_benchmarks

    if args.which == "collection":  # guidedmatch colmap vs pycolmap.match_exhaustive on Herz-Jesus-P8
        from ..datasets import data_root
        from ..evaluation.bench_collection import DATA_REL, main as bench_collection

        root = data_root(args.data)
        if root is None or not (root / DATA_REL).is_dir():
            raise InputError(f"no Herz-Jesus-P8 images under {root}/{DATA_REL}: pass --data DIR or set GUIDEDMATCH_DATA")
        return bench_collection(["--data", str(root), "--out", str(Path(args.out) / "collection")]
                                + (["--repeats", str(args.repeats)] if args.repeats else []))
    run_benchmarks(args.which, data=args.data, out=args.out, quick=args.quick, repeats=args.repeats,
                   detector=args.detector, seed=args.seed)
    return 0




def add_commands(sub, parents) -> None:
    """Add ``experiment`` and ``bench`` to the CLI's subparsers."""
    from ..evaluation.bench import BENCHMARKS
    from ..features import DETECTORS

    e = sub.add_parser("experiment", parents=parents, help="run a paper experiment", description="Run one of the paper's experiments.")
    e.add_argument("which", choices=("alignment",), help="alignment: K-hat ratio vs viewing angle for the four alignment approaches")
    e.add_argument("--pairs", type=positive_int, default=3000, help="number of simulated view pairs (default 3000)")
    e.add_argument("--out", default="out/alignment", help="output folder")
    e.add_argument("--seed", type=int, default=0)
    e.set_defaults(func=cmd_experiment)

    b = sub.add_parser("bench", parents=parents, help="reproduce the paper's tables side by side with the paper and peers",
                       description="Benchmark harness: Oxford, synthetic, real (Strecha) and the alignment simulation.")
    b.add_argument("which", choices=(*BENCHMARKS, "collection", "pairs", "sfm", *DELEGATED),
                   help="; ".join(f"{k}: {v[1]} (own options: guidedmatch bench {k} --help)" for k, v in DELEGATED.items())
                   + "; pairs: every pair of Herz-Jesus-P8 + unrelated pairs vs COLMAP-style IVF, faiss, FLANN; "
                   "sfm: COLMAP's matcher vs guidedmatch inside COLMAP's mapper, GT poses (Herz-Jesus-P8)")
    b.add_argument("--data", default=None, help="data folder (default: $GUIDEDMATCH_DATA or ../shared/data)")
    b.add_argument("--out", default="reports", help="output folder (default ./reports)")
    b.add_argument("--quick", action="store_true", help="a few pairs per set (minutes, not an hour)")
    b.add_argument("--repeats", type=positive_int, default=None,
                   help="timing repeats per method (median); sfm: runs of each end-to-end pipeline (median, "
                        "alternating order); collection: runs of COLMAP vs ours and of 1 vs 2 workers (alternating)")
    b.add_argument("--detector", default="sift", choices=DETECTORS)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--scene", default=None, help="sfm: scene folder with images/ and gt_dense_cameras/ (Strecha "
                   "layout; default: Herz-Jesus-P8 in the data folder)")
    b.add_argument("--methods", default=None, help="sfm: comma-separated subset of colmap, colmap_guided, "
                   "so+epi+ia+ours, so+epi+ia+colmap, epi+ours, epi+colmap, colmap+cap, so+epi+ia+ours+cap (+cap: at "
                   "most 1000 inliers per pair to the mapper, as guidedmatch sfm does)")
    b.add_argument("--set", default="p8", choices=("p8", "large"),
                   help="sfm: p8 = Herz-Jesus-P8 (or --scene), median of --repeats alternating runs; large = the "
                   "220-image collection (data/collections + Herz-Jesus-P8 + the Unsplash photos): guidedmatch sfm (each mapper) vs "
                   "the pycolmap pipeline with exhaustive and with vocabulary-tree matching, one run each, per-scene "
                   "registration, models and poses (bench large --sfm; cached in --work, default ~/.cache/guidedmatch/"
                   "large; COLMAP exhaustive takes ~16 min there)")
    b.add_argument("--threads", type=positive_int, default=2, help="sfm: CPU threads for COLMAP (default 2)")
    b.add_argument("--work", default=None, help="sfm: folder for the databases and models (default OUT/work; "
                   "extracted features are reused by a rerun)")
    b.add_argument("--merge", action="store_true", help="sfm: keep the rows of an existing OUT/sfm.json that this run "
                   "does not redo (e.g. after --methods X)")
    b.add_argument("--no-e2e", action="store_true", help="sfm: skip the end-to-end comparison (guidedmatch sfm vs "
                   "the pycolmap pipeline with COLMAP's matcher)")
    from ..evaluation.bench_pairs import add_arguments as _pairs_arguments

    _pairs_arguments(b)  # --features / --dense / --oxford of `bench pairs`
    b.set_defaults(func=cmd_bench)
