"""Command-line interface: ``guidedmatch match | demo | experiment | bench | colmap | hloc | sfm``.

Every error the user can cause is a :class:`~guidedmatch.errors.GuidedMatchError` (missing or unreadable image,
no features, bad option or config value, mismatched descriptors, ...): it prints one line ``guidedmatch: error:
...`` on stderr and exits with status 2, checked before any detection where possible. Any other exception is a
bug: one line ``guidedmatch: internal error: ...``, exit status 1. ``--debug`` shows the traceback of either.
Output files are written atomically.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from ._runtime import freeze_gc_at_exit, mark_own_process
from .config import MODES, MatcherConfig
from .errors import ConfigError, GuidedMatchError, InputError, OutputError
from .features import writable_folder

OUTPUT_FORMATS = (".npz", ".csv", ".json")


# --------------------------------------------------------------------------- helpers
def _parse_kv(items: list[str] | None, what: str) -> dict:
    """``["a=1", "b=x"]`` -> ``{"a": 1, "b": "x"}`` (values parsed as JSON when possible)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"{what} must look like key=value, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            low = v.strip().lower()
            out[k.strip()] = None if low in ("none", "null") else (low == "true" if low in ("true", "false") else v)
    return out


def to_json(obj, **kw) -> str:
    from .evaluation.meta import json_default

    return json.dumps(obj, default=json_default, **kw)


def write_matches(path: Path, result, f1, f2, geometry=None, verified=None) -> None:
    """Write matches as ``.npz`` / ``.csv`` / ``.json`` (by suffix), atomically.

    ``geometry``: the pair's :class:`~guidedmatch.geometry.TwoViewGeometry` (stored as ``stats["geometry"]``);
    ``verified``: optional ``(M,) bool`` per match (``--keep-unverified``: a ``verified`` array / column).
    """
    from .features import atomic_savez, atomic_write_text

    pairs, dist = result.pairs, result.distances
    p1 = f1.keypoints[pairs[:, 0]] if len(pairs) else np.zeros((0, 2))
    p2 = f2.keypoints[pairs[:, 1]] if len(pairs) else np.zeros((0, 2))
    suffix = path.suffix.lower()
    stats = result.stats.to_dict()
    if geometry is not None:
        stats["geometry"] = geometry.to_dict()
    stats_json = to_json(stats)
    extra = {} if verified is None else {"verified": np.asarray(verified, bool)}
    if suffix == ".npz":
        atomic_savez(path, pairs=pairs, distances=dist, points1=p1, points2=p2,
                     keypoints1=f1.keypoints, keypoints2=f2.keypoints, stats=np.array(stats_json), **extra)
    elif suffix == ".csv":
        v = extra.get("verified")
        lines = ["i1,i2,x1,y1,x2,y2,distance" + (",verified" if v is not None else "")]
        lines += [f"{a},{b},{x1:.3f},{y1:.3f},{x2:.3f},{y2:.3f},{d:.4f}" + ("" if v is None else f",{int(v[k])}")
                  for k, ((a, b), (x1, y1), (x2, y2), d) in enumerate(zip(pairs, p1, p2, dist))]
        atomic_write_text(path, "\n".join(lines) + "\n")
    elif suffix == ".json":
        atomic_write_text(path, to_json(dict(pairs=pairs, distances=dist, points1=p1, points2=p2,
                                             stats=stats, **extra), indent=1))
    else:
        raise OutputError(f"unknown output format {suffix!r}: use .npz, .csv or .json")


def read_matches(path) -> dict:
    """Read back what :func:`write_matches` wrote as ``.npz`` (pairs, distances, points, stats)."""
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["stats"] = json.loads(str(d["stats"]))
    return d


def matcher_config(items: list[str] | None) -> MatcherConfig:
    """``--config KEY=VALUE`` items -> a validated :class:`MatcherConfig` (ConfigError naming the valid keys)."""
    from .validation import config_from

    try:
        return config_from(MatcherConfig, _parse_kv(items, "--config"))
    except ConfigError as exc:
        raise ConfigError(f"bad --config: {exc}") from None


def _check_detect_memory_both(img1, img2, detector, max_image_size=None, names=("IMG1", "IMG2")) -> None:
    """MemoryLimitError (with a suggested --max-image-size) when detecting either image would not fit, before any
    detection (or compilation) starts."""
    from .features import check_detect_memory

    for img, name in zip((img1, img2), names):
        h, w = img.shape[:2]
        if max_image_size and max(w, h) > max_image_size:
            s = max_image_size / max(w, h)
            w, h = max(1, round(w * s)), max(1, round(h * s))
        check_detect_memory(w, h, detector, name)


def _detect_both(img1, img2, detector, max_features, options, max_image_size=None, names=("IMG1", "IMG2")):
    from .features import detect

    feats = [detect(img, detector, max_features, max_image_size=max_image_size, **options) for img in (img1, img2)]
    for name, f in zip(names, feats):
        if len(f) == 0:
            raise InputError(f"no features detected in {name} ({detector}); the image may be blank or too small")
    return feats[0], feats[1]


def _check_input_image(path: str, what: str) -> None:
    from .errors import ImageReadError
    from .features import ImageNotFoundError

    p = Path(path)
    if not p.exists():
        raise ImageNotFoundError(f"{what} not found: {p}")
    if p.is_dir():
        raise ImageReadError(f"{what} is a folder, not an image: {p}")


def fallback_lines(fallbacks) -> list[str]:
    """Each distinct fallback once, with how often it occurred: ``"what: reason (x3)"``."""
    counts: dict[tuple, int] = {}
    for fb in fallbacks or ():
        key = (fb.what, fb.reason) if hasattr(fb, "what") else (fb.get("what"), fb.get("reason"))
        counts[key] = counts.get(key, 0) + 1
    return [f"{w}: {r}" + (f" (x{n})" if n > 1 else "") for (w, r), n in counts.items()]


def _subset_result(result, keep: np.ndarray):
    import dataclasses

    return dataclasses.replace(result, pairs=result.pairs[keep], distances=result.distances[keep],
                               flags={k: np.asarray(v)[keep] for k, v in result.flags.items()})


def timed_match(f1, f2, mode, config=None, *, return_models=False, warm: bool = True):
    """``match`` with its Numba kernels warmed up first (untimed; ``warm=False``: the caller already did); returns
    ``(match's return value, matching_seconds, compile_seconds)`` -- ``match`` itself reports any compilation left
    in the timed run apart from ``stats.time_s`` (``stats.details["jit_compile_s"]``)."""
    from .jit import warm_up
    from .matcher import match

    compile_s = warm_up(f1, f2, mode, config) if warm else 0.0
    out = match(f1, f2, mode, config, return_models=return_models)
    st = (out[0] if return_models else out).stats
    return out, st.time_s, compile_s + st.details.get("jit_compile_s", 0.0)


def jit_summary(compile_s: float, bg) -> str:
    """``"1.2 s"`` -- or, when helper processes compiled (:func:`guidedmatch.jit.background_compile`), how long
    they took and how much of it this run waited for."""
    if not bg.helpers:
        return f"{compile_s:.1f} s"
    took = "" if bg.helper_seconds is None else f"{bg.helper_seconds:.1f} CPU-s in "
    return (f"{took}{bg.helpers} helper process{'es' if bg.helpers > 1 else ''} during reading and detection, "
            f"{compile_s:.1f} s waited for")


# --------------------------------------------------------------------------- commands
def cmd_match(args) -> int:
    from .features import check_detector_options, check_output_path, load_image

    # every argument and path problem is found here, before any image is read
    config = matcher_config(args.config)
    detector_options = check_detector_options(args.detector, _parse_kv(args.detector_option, "--detector-option"))
    if args.show_regions and not args.plot:
        raise ConfigError("--show-regions needs --plot OUT.png")
    if args.show_regions and args.mode == "bf":
        raise ConfigError("--show-regions needs a guided mode (epi, so, so+epi, so+epi+ia), not bf")
    if args.output and Path(args.output).suffix.lower() not in OUTPUT_FORMATS:
        raise OutputError(f"unknown output format {Path(args.output).suffix!r}: use .npz, .csv or .json")
    if args.keep_unverified and not args.output:
        raise ConfigError("--keep-unverified needs -o OUT")
    if args.keep_unverified:  # the matcher then returns the matches of a no-overlap pair too (unverified="keep")
        config = config.replace(unverified="keep")
    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".pdf", ".svg", ".jpg"):
        raise OutputError(f"unknown plot format {Path(args.plot).suffix!r}: use .png, .pdf, .svg or .jpg")
    _check_input_image(args.img1, "IMG1")
    _check_input_image(args.img2, "IMG2")
    if args.output:
        check_output_path(args.output, "-o/--output")
    if args.plot:
        check_output_path(args.plot, "--plot")

    from .jit import background_compile, guided_kernels_needed

    # the images are read (strict decode) and their detection memory checked before the first-run compile starts:
    # a corrupt or too large image is one error line, with no compile note before it and no helper started
    img1 = load_image(args.img1)
    img2 = load_image(args.img2)
    _check_detect_memory_both(img1, img2, args.detector, args.max_image_size, (args.img1, args.img2))
    with background_compile(args.detector, (args.mode,)) as bg:  # first run: kernels compile on both cores meanwhile
        t0 = time.perf_counter()
        f1, f2 = _detect_both(img1, img2, args.detector, args.max_features, detector_options, args.max_image_size,
                              (args.img1, args.img2))
        t_det = time.perf_counter() - t0
        if bg and not guided_kernels_needed(f1, f2, (args.mode,), config):
            bg.cancel()  # brute force at these feature counts: the helpers' kernels are not needed
        waited = bg.wait()
    (result, models), time_s, compile_s = timed_match(f1, f2, args.mode, config, return_models=True)
    compile_s += waited
    st = result.stats
    geo = result.geometry  # every matcher result carries its two-view verdict (issue 11)
    scaled = ""
    if args.max_image_size and max(max(f.image_size) for f in (f1, f2)) > args.max_image_size:
        scaled = f", detected at long side <= {args.max_image_size} px, coordinates in original pixels"
    print(f"features      : {len(f1)} x {len(f2)} ({args.detector}, detection {t_det:.2f} s{scaled})")
    print(f"mode          : {args.mode}")
    print(f"matches       : {len(result)}")
    if geo:
        print(f"verdict       : verified ({geo.model}): {geo.num_inliers} of {len(result)} matches geometrically verified")
    else:
        label = "no overlap" if geo.verdict == "no-overlap" else "too few matches"
        print(f"verdict       : {label}: 0 geometrically verified matches ({geo.reason})")
    print(f"comparisons   : {st.comparisons:,} ({100.0 * st.comparison_ratio:.2f} % of brute force)")
    jit_note = f" (Numba compilation excluded: {jit_summary(compile_s, bg)}, first run only)" \
        if compile_s or bg.helpers else ""
    print(f"matching time : {time_s:.3f} s{jit_note}")
    for line in fallback_lines(st.fallbacks):
        print(f"fallback      : {line}")
    inl = np.asarray(geo.inliers, bool) if len(geo.inliers) == len(result) else np.zeros(len(result), bool)
    if args.output:
        out = result if args.keep_unverified else _subset_result(result, inl)
        write_matches(Path(args.output), out, f1, f2, geometry=geo, verified=inl if args.keep_unverified else None)
        what = f"{len(out)} matches, {int(inl.sum())} verified" if args.keep_unverified else \
            f"{len(out)} verified matches" + ("" if geo else "; --keep-unverified writes the unverified ones")
        print(f"wrote         : {args.output} ({what})")
    if args.plot:
        from . import plots

        if args.show_regions:
            if models is None:
                raise InputError("--show-regions needs a guided mode whose models were fitted (see the fallbacks above)")
            plots.search_regions(args.plot, img1, img2, f1, f2, result, models)
        else:
            verdict = (f"{geo.num_inliers} verified ({geo.model})" if geo else
                       ("no overlap" if geo.verdict == "no-overlap" else "too few matches") + ": 0 verified")
            plots.match_pair(args.plot, img1, img2, f1.keypoints[result.pairs[:, 0]], f2.keypoints[result.pairs[:, 1]],
                             inl, f"{args.mode}: {len(result)} matches, {verdict}")
        print(f"wrote         : {args.plot}")
    return 0


def cmd_demo(args) -> int:
    from . import plots
    from .features import detect
    from .features import check_output_path
    from .testing.scenes import make_scene

    out = Path(args.out)
    for name in ("demo_matches.png", "demo_results.json"):
        check_output_path(out / name, "--out")
    w, h = args.size
    from .jit import background_compile, guided_kernels_needed, warm_up

    with background_compile(args.detector, MODES) as bg:  # first run: kernels compile on both cores meanwhile
        print(f"[1/4] rendering a synthetic two-view scene {w}x{h}, camera roll {args.roll:g} deg (seed {args.seed})")
        scene = make_scene((w, h), roll_deg=args.roll, seed=args.seed)
        print(f"[2/4] detecting {args.detector.upper()} features")
        f1 = detect(scene.image1, args.detector, args.max_features)
        f2 = detect(scene.image2, args.detector, args.max_features)
        print(f"      {len(f1)} x {len(f2)} features")
        compile_s, warmed = 0.0, []
        if bg and not guided_kernels_needed(f1, f2, MODES):
            bg.cancel()  # every mode is brute force at these feature counts: the helpers' kernels are not needed
        if bg:  # first run: untimed work the demo does anyway while the helpers compile -- import Matplotlib, then
            # warm each mode up as soon as the helper compiling its kernels has finished
            plots._plt()
            for group, modes in (("guided", ("bf", "epi")), ("order", ("so",))):
                compile_s += bg.wait(group)
                for mode in modes:
                    compile_s += warm_up(f1, f2, mode)
                    warmed.append(mode)
        compile_s += bg.wait()
    print(f"[3/4] matching with {', '.join(MODES)}")
    rows, panels = [], []
    bf_comp = max(1, len(f1) * len(f2))
    for mode in MODES:
        # kernels warmed up first: no compilation in the times
        res, time_s, c_s = timed_match(f1, f2, mode, warm=mode not in warmed)
        compile_s += c_s
        p1, p2 = f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]]
        ok = scene.correct(p1, p2)
        rows.append(dict(mode=mode, comparisons=res.stats.comparisons, matches=len(res), true=int(ok.sum()),
                         precision=float(ok.mean()) if len(ok) else float("nan"), time_s=time_s,
                         fallbacks=len(res.stats.fallbacks)))
        panels.append(dict(pts1=p1, pts2=p2, correct=ok,
                           title=f"{mode}: {int(ok.sum())}/{len(res)} correct, {100 * res.stats.comparisons / bf_comp:.2f} % comparisons"))
    print()
    print(format_table(rows, bf_comp))
    print()
    print("true = GT within 3 px (exact scene geometry); comparisons = descriptor distances evaluated")
    if compile_s or bg.helpers:
        print(f"Numba compilation (first run only, not in the times above): {jit_summary(compile_s, bg)}")
    fig = plots.motion_field_panels(out / "demo_matches.png", scene.image1, panels,
                                    suptitle=f"guidedmatch demo: motion field on image 1 (green = correct, red = wrong), roll {args.roll:g} deg")
    from .features import atomic_write_text

    atomic_write_text(out / "demo_results.json", to_json(dict(rows=rows, features=(len(f1), len(f2)),
                                                              size=(w, h), roll_deg=args.roll, seed=args.seed,
                                                              jit_compile_s=compile_s,
                                                              jit_helpers_s=bg.helper_seconds if bg.helpers else 0.0),
                                                         indent=1))
    print(f"[4/4] wrote {fig} and {out / 'demo_results.json'}")
    return 0


def format_table(rows: list[dict], bf_comp: int) -> str:
    head = f"{'mode':<10} {'comparisons':>13} {'% of BF':>8} {'matches':>8} {'true':>6} {'precision':>9} {'time (s)':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['mode']:<10} {r['comparisons']:>13,} {100 * r['comparisons'] / bf_comp:>7.2f}% {r['matches']:>8} "
                     f"{r['true']:>6} {100 * r['precision']:>8.2f}% {r['time_s']:>9.3f}")
    return "\n".join(lines)


def cmd_experiment(args) -> int:
    if args.which == "alignment":
        from .evaluation.alignment_sim import run_alignment_experiment

        summary = run_alignment_experiment(n_pairs=args.pairs, out_dir=writable_folder(args.out), seed=args.seed,
                                           progress=True)
        if isinstance(summary, dict) and summary.get("table_md"):
            print(summary["table_md"])
        print(f"wrote results to {args.out}")
        return 0
    raise ConfigError(f"unknown experiment {args.which!r}")


def cmd_bench(args) -> int:
    writable_folder(args.out)
    if args.which == "sfm":
        from .evaluation import bench_sfm

        return int(bench_sfm.main(args) or 0)
    if args.which == "pairs":
        from .evaluation import bench_pairs

        return int(bench_pairs.main(args) or 0)
    from .evaluation.bench import run_benchmarks

    if args.which == "collection":  # issue 12: guidedmatch colmap vs pycolmap.match_exhaustive on Herz-Jesus-P8
        from .datasets import data_root
        from .evaluation.bench_collection import DATA_REL, main as bench_collection

        root = data_root(args.data)
        if root is None or not (root / DATA_REL).is_dir():
            raise InputError(f"no Herz-Jesus-P8 images under {root}/{DATA_REL}: pass --data DIR or set GUIDEDMATCH_DATA")
        return bench_collection(["--data", str(root), "--out", str(Path(args.out) / "collection")]
                                + (["--repeats", str(args.repeats)] if args.repeats else []))
    run_benchmarks(args.which, data=args.data, out=args.out, quick=args.quick, repeats=args.repeats,
                   detector=args.detector, seed=args.seed)
    return 0


def cmd_sfm(args) -> int:
    from .sfm import SfmConfig, run_sfm

    conf = SfmConfig(detector=args.detector, max_features=args.max_features, max_image_size=args.max_image_size,
                     peak_threshold=args.peak_threshold, camera_model=args.camera_model, camera=args.camera,
                     single_camera=args.single_camera, pairs=args.pairs, mode=args.mode,
                     matcher=_parse_kv(args.config, "--config") or None, geometry=args.geometry,
                     max_inliers_per_pair=args.max_inliers_per_pair, workers=args.workers,
                     scheduler=args.scheduler, num_threads=args.threads, seed=args.seed, progress=not args.quiet)
    report = run_sfm(args.image_dir, args.out_dir, conf, command="guidedmatch " + " ".join(sys.argv[1:]),
                     colmap_log=args.colmap_log)
    if report["registered"] < 2:
        print(f"guidedmatch: no reconstruction: the mapper registered {report['registered']} of {report['num_images']} "
              f"images (too few verified pairs; see {Path(args.out_dir) / 'report.md'})", file=sys.stderr)
        return 1
    return 0


# --------------------------------------------------------------------------- collections: colmap, hloc (issue 12)
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
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="in-process runs: pairs matched at once on N threads (default: one per core)")
    p.add_argument("--retries", type=_nonneg_int, default=1, help="retries of a failed pair (default 1)")
    p.add_argument("--cache-mb", type=_positive_int, default=1024, metavar="MB",
                   help="per process (each worker, or this one in-process): loaded images kept, MB (default 1024: "
                        "~100 images of 8192 SIFT features, ~12 of 70k); a collection that does not fit is matched "
                        "in sweeps that load each image more than once")
    p.add_argument("--log", default=None, metavar="PATH",
                   help="per-pair JSON lines + a summary line (default: next to the output, .guidedmatch.jsonl; "
                        "'none' for no log)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--timeline", default=None, metavar="PNG",
                   help="also draw when each pair of this run ran, on which worker or thread (a PNG figure)")


def add_collection_commands(sub) -> None:
    """Add ``colmap`` and ``hloc`` to the CLI's subparsers."""
    c = sub.add_parser("colmap", help="match the images of a COLMAP database (writes matches + two-view geometries)",
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
                        "(default 0 = all; guidedmatch sfm uses 1000: the mapper's time follows its observations; "
                        "below 100 COLMAP's mapper cannot pick an initial pair)")
    _common(c, MODES)
    _expansion_options(c)
    c.set_defaults(func=cmd_colmap)

    h = sub.add_parser("hloc", help="match the pairs of an hloc features.h5 into an hloc matches.h5",
                       description="Match the image pairs of a pairs file with the features of an hloc features.h5 "
                       "and write an hloc matches.h5 (matches0 / matching_scores0). Resumable.",
                       epilog=HLOC_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    h.add_argument("features", help="hloc features.h5 (keypoints, descriptors D x N)")
    h.add_argument("pairs", help="pairs file ('name1 name2' lines), or exhaustive | sequential[:K] | retrieval[:K] "
                                "| several joined by '+'")
    h.add_argument("matches", help="output matches.h5 (created, or completed when it exists)")
    _common(h, MODES)
    h.set_defaults(func=cmd_hloc)


def _collection_config(args, log_default: Path):
    """The validated CollectionConfig of the options (ConfigError before any work)."""
    from .collection.engine import CollectionConfig

    log = args.log if args.log is not None else str(log_default)
    if args.threads is not None and (args.workers or args.scheduler):
        raise ConfigError("--threads is for in-process runs; with --workers N / --scheduler each worker runs one pair "
                          "at a time")
    from .collection.engine import collection_matcher_config

    try:
        matcher = collection_matcher_config(_parse_kv(args.config, "--config"))
    except ConfigError as exc:
        raise ConfigError(f"bad --config: {exc}") from None
    return CollectionConfig(mode=args.mode, matcher=matcher, workers=args.workers,
                            threads=args.threads, scheduler=args.scheduler, retries=args.retries, progress=not args.no_progress,
                            cache_mb=float(args.cache_mb), log_path=None if str(log).lower() == "none" else log)


def _print_pairs(pairs) -> None:
    """Say what the pair list normalization dropped (duplicates, reversed duplicates, self-pairs), if anything."""
    if any(isinstance(v, dict) and v.get("count") for v in pairs.report.values()):
        print(f"pairs      : {pairs.summary()}")


def _finish(report, log_path, timeline: str | None = None) -> int:
    print(report.summary())
    if log_path:
        print(f"log        : {log_path}")
    if timeline:
        from .plots import collection_timeline

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
    from .collection.pairs import pairs_from_spec

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


def cmd_colmap(args) -> int:
    from .collection.engine import match_collection
    from .collection.sinks import ColmapSink
    from .collection.sources import ColmapSource

    db = Path(args.database)
    if args.max_inliers_per_pair < 0:
        raise ConfigError(f"--max-inliers-per-pair must be >= 0 (0 = all inliers); got {args.max_inliers_per_pair}")
    expand = _expansion_wanted(args)
    cfg, source, pairs = _setup(args, db, lambda: ColmapSource(db), args.pairs)
    with ColmapSink(db, geometry=args.geometry) as sink:
        if expand is not None:
            from .collection.expansion import match_collection_expanded

            report = match_collection_expanded(source, pairs, sink, cfg, expand)
        else:
            report = match_collection(source, pairs, sink, cfg)
        if args.geometry == "colmap" and report.done:
            n = sink.verify()
            print(f"verified   : {n} pairs with COLMAP's geometric verification (pycolmap.verify_matches)")
        if args.max_inliers_per_pair:
            cap = sink.cap_inliers(args.max_inliers_per_pair)
            print(f"mapper     : {cap['inliers_after']:,} of {cap['inliers_before']:,} inliers kept (at most "
                  f"{cap['max_inliers']} per pair, spread; {cap['pairs_capped']} pairs capped, {cap['time_s']:.2f} s)")
    return _finish(report, cfg.log_path, args.timeline)


def cmd_hloc(args) -> int:
    from .collection.engine import match_collection
    from .collection.sinks import H5MatchesSink
    from .collection.sources import H5Source

    out = Path(args.matches)
    cfg, source, pairs = _setup(args, out, lambda: H5Source(args.features), args.pairs)
    with H5MatchesSink(out, source) as sink:
        report = match_collection(source, pairs, sink, cfg)
    return _finish(report, cfg.log_path, args.timeline)


# --------------------------------------------------------------------------- parser
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1600x1200, got {text!r}") from None
    if w < 64 or h < 64:
        raise argparse.ArgumentTypeError("size must be at least 64x64")
    return w, h


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    from .evaluation.bench import BENCHMARKS
    from .features import DETECTORS

    p = argparse.ArgumentParser(prog="guidedmatch", description="Guided image feature matching with feature spatial "
                                "order and epipolar geometry (Teng & Dong).")
    p.add_argument("--version", action="version", version=f"guidedmatch {__version__}")
    p.add_argument("--debug", action="store_true", help="show Python tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    m = sub.add_parser("match", help="match the features of two images", description="Detect features in two "
                       "images and match them; prints a summary and optionally writes matches and a plot.")
    m.add_argument("img1")
    m.add_argument("img2")
    m.add_argument("--mode", default="so+epi+ia", choices=MODES, help="matching mode (default: so+epi+ia)")
    m.add_argument("--detector", default="sift", choices=DETECTORS, help="feature detector (default sift)")
    m.add_argument("--max-features", type=_positive_int, default=None, help="keep at most N strongest features per image")
    m.add_argument("--detector-option", action="append", metavar="KEY=VALUE", help="OpenCV detector option, e.g. contrastThreshold=0.01 (repeatable)")
    m.add_argument("--config", action="append", metavar="KEY=VALUE", help="matcher config override, e.g. ratio=0.9 (repeatable)")
    m.add_argument("--max-image-size", type=_positive_int, default=None, metavar="PX",
                   help="detect on a copy downscaled to this long side (keypoints still in original pixels); "
                        "needed for very large images (the memory check suggests a size)")
    m.add_argument("-o", "--output", help="write the geometrically verified matches to .npz, .csv or .json")
    m.add_argument("--keep-unverified", action="store_true",
                   help="with -o: write every match, with a 'verified' flag, also when the images do not overlap")
    m.add_argument("--plot", help="write a PNG of both images with the matches (inliers / outliers of the verdict)")
    m.add_argument("--show-regions", action="store_true", help="with --plot: draw the search regions of a few features instead")
    m.set_defaults(func=cmd_match)

    d = sub.add_parser("demo", help="built-in demo on a rendered scene with known geometry (no data needed)",
                       description="Render a synthetic two-view scene (textured planes, camera roll), match it with "
                       "every mode and print comparisons / matches / true correspondences / precision / time.")
    d.add_argument("--out", default="guidedmatch_demo", help="output folder (default ./guidedmatch_demo)")
    d.add_argument("--size", type=_size, default=(1600, 1200), help="image size WxH (default 1600x1200)")
    d.add_argument("--roll", type=float, default=30.0, help="camera-2 roll in degrees (default 30)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--detector", default="sift", choices=DETECTORS)
    d.add_argument("--max-features", type=_positive_int, default=None)
    d.set_defaults(func=cmd_demo)

    e = sub.add_parser("experiment", help="run a paper experiment", description="Run one of the paper's experiments.")
    e.add_argument("which", choices=("alignment",), help="alignment: K-hat ratio vs viewing angle for the four alignment approaches")
    e.add_argument("--pairs", type=_positive_int, default=3000, help="number of simulated view pairs (default 3000)")
    e.add_argument("--out", default="out/alignment", help="output folder")
    e.add_argument("--seed", type=int, default=0)
    e.set_defaults(func=cmd_experiment)

    b = sub.add_parser("bench", help="reproduce the paper's tables side by side with the paper and peers",
                       description="Benchmark harness: Oxford, synthetic, real (Strecha) and the alignment simulation.")
    b.add_argument("which", choices=(*BENCHMARKS, "collection", "pairs", "sfm"),
                   help="pairs: every pair of Herz-Jesus-P8 + unrelated pairs vs COLMAP-style IVF, faiss, FLANN; "
                   "sfm: COLMAP's matcher vs guidedmatch inside COLMAP's mapper, GT poses (Herz-Jesus-P8)")
    b.add_argument("--data", default=None, help="data folder (default: $GUIDEDMATCH_DATA or ../shared/data)")
    b.add_argument("--out", default="reports", help="output folder (default ./reports)")
    b.add_argument("--quick", action="store_true", help="a few pairs per set (minutes, not an hour)")
    b.add_argument("--repeats", type=_positive_int, default=None,
                   help="timing repeats per method (median); sfm: runs of each end-to-end pipeline (median, "
                        "alternating order); collection: runs of COLMAP vs ours and of 1 vs 2 workers (alternating)")
    b.add_argument("--detector", default="sift", choices=DETECTORS)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--scene", default=None, help="sfm: scene folder with images/ and gt_dense_cameras/ (Strecha "
                   "layout; default: Herz-Jesus-P8 in the data folder)")
    b.add_argument("--methods", default=None, help="sfm: comma-separated subset of colmap, colmap_guided, "
                   "so+epi+ia+ours, so+epi+ia+colmap, epi+ours, epi+colmap, colmap+cap, so+epi+ia+ours+cap (+cap: at "
                   "most 1000 inliers per pair to the mapper, as guidedmatch sfm does)")
    b.add_argument("--threads", type=_positive_int, default=2, help="sfm: CPU threads for COLMAP (default 2)")
    b.add_argument("--work", default=None, help="sfm: folder for the databases and models (default OUT/work; "
                   "extracted features are reused by a rerun)")
    b.add_argument("--merge", action="store_true", help="sfm: keep the rows of an existing OUT/sfm.json that this run "
                   "does not redo (e.g. after --methods X)")
    b.add_argument("--no-e2e", action="store_true", help="sfm: skip the end-to-end comparison (guidedmatch sfm vs "
                   "the pycolmap pipeline with COLMAP's matcher)")
    from .evaluation.bench_pairs import add_arguments as _pairs_arguments

    _pairs_arguments(b)  # --features / --dense / --oxford of `bench pairs`
    b.set_defaults(func=cmd_bench)

    s = sub.add_parser("sfm", help="photos -> COLMAP sparse model (extraction, guided matching, incremental mapping)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Structure from motion with guidedmatch as the matcher: pycolmap SIFT extraction "
                       "(or our detectors), collection matching into OUT_DIR/database.db, pycolmap.incremental_mapping "
                       "into OUT_DIR/sparse/0, report.json / report.md / reconstruction.png. Resumable: a rerun "
                       "reuses extracted features and matched pairs and redoes the mapping.",
                       epilog="examples:\n"
                       "  guidedmatch sfm photos/ project/\n"
                       "  guidedmatch sfm photos/ project/ --pairs sequential:10 --workers 4\n"
                       "  guidedmatch sfm photos/ project/ --camera PINHOLE:2759.5,2764.2,1520.7,1006.8\n"
                       "  guidedmatch sfm photos/ project/ --detector ours:orb --max-features 4000\n"
                       "  colmap gui --database_path project/database.db --image_path photos/ --import_path project/sparse/0")
    s.add_argument("image_dir", help="folder of images (searched recursively; names relative to it)")
    s.add_argument("out_dir", help="project folder (created; database.db, sparse/, report.*)")
    s.add_argument("--detector", default="colmap", help="colmap (pycolmap SIFT, default) or ours:sift|orb|akaze|brisk")
    s.add_argument("--max-features", type=_positive_int, default=None, help="features per image (default: "
                   "8192 for COLMAP SIFT, unlimited for ours)")
    s.add_argument("--max-image-size", type=_positive_int, default=None, help="downscale so the longer side is at "
                   "most this before extraction (default: 3200 for COLMAP, none for ours)")
    s.add_argument("--peak-threshold", type=float, default=None, help="COLMAP SIFT peak threshold (default "
                   "0.0067; 0.002 gives ~5x more features)")
    s.add_argument("--camera", default=None, metavar="MODEL:PARAMS", help="known intrinsics for every image, e.g. "
                   "PINHOLE:fx,fy,cx,cy (held fixed in bundle adjustment)")
    s.add_argument("--single-camera", action="store_true", help="all images share one (estimated) camera")
    s.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model when intrinsics are "
                   "estimated (default SIMPLE_RADIAL)")
    s.add_argument("--pairs", default="exhaustive", help="exhaustive (default), sequential, sequential:K, or a "
                   "file of 'name1 name2' lines")
    s.add_argument("--mode", default="so+epi+ia", choices=MODES, help="matching mode (default so+epi+ia)")
    s.add_argument("--config", action="append", metavar="KEY=VALUE", help="matcher config override (repeatable)")
    s.add_argument("--geometry", default="ours", choices=("ours", "colmap"), help="two-view geometry: ours "
                   "(the matcher's verdict, default) or colmap (pycolmap's verification)")
    s.add_argument("--max-inliers-per-pair", type=int, default=1000, metavar="K", help="inlier matches "
                   "per pair handed to the mapper, spread over the image, best first (default 1000; 0 = all): the "
                   "mapper's time follows its observations, and on Herz-Jesus-P8 1000 gave poses at least as good as "
                   "all of them (docs/collections.md)")
    s.add_argument("--workers", type=int, default=None, help="matching worker processes (default: auto; 0 = in this process)")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS", help="match on a running Dask cluster")
    s.add_argument("--threads", type=int, default=-1, help="COLMAP extraction/mapping threads (default -1 = all)")
    s.add_argument("--seed", type=int, default=0, help="mapper random seed (default 0)")
    s.add_argument("--quiet", action="store_true", help="no progress output")
    s.add_argument("--colmap-log", action="store_true", help="show COLMAP's INFO log lines (extraction, mapping)")
    s.set_defaults(func=cmd_sfm)
    add_collection_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    freeze_gc_at_exit()  # a cheap interpreter shutdown (guidedmatch._runtime)
    mark_own_process()   # Numba's set-up may skip its SciPy BLAS probe (guidedmatch._runtime)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except GuidedMatchError as exc:  # the user's input or configuration: one line, exit 2
        if args.debug:
            raise
        print(f"guidedmatch: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("guidedmatch: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: one line, exit 1 (--debug: the traceback)
        if args.debug:
            raise
        print(f"guidedmatch: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)", file=sys.stderr)
        return 1


# --------------------------------------------------------------------------- colmap: verified expansion
def _expansion_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--expand", action=argparse.BooleanOptionalAction, default=None,
                   help="after the pairs, also match the pairs closing a triangle of verified pairs (a-b and b-c "
                        "verified, a-c not tried), in rounds, until a round verifies nothing new (default: on "
                        "when --pairs has a retrieval part, off otherwise)")
    p.add_argument("--expand-rounds", type=_nonneg_int, default=None, metavar="N",
                   help="at most N expansion rounds (default 10; 0 = none)")


def _expansion_wanted(args):
    """ExpansionConfig fields (dict) when the verified expansion runs, else None."""
    parts = [x.strip() for x in str(args.pairs).split("+")] if not Path(args.pairs).exists() else []
    on = args.expand if args.expand is not None else any(x.split(":")[0] == "retrieval" for x in parts)
    if args.expand_rounds is not None and not on:
        raise ConfigError("--expand-rounds needs the expansion (--expand, or a retrieval --pairs spec)")
    if not on:
        return None
    return {} if args.expand_rounds is None else dict(max_rounds=args.expand_rounds)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
