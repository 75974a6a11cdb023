"""``guidedmatch match`` (two images) and ``guidedmatch demo`` (a rendered scene with known geometry)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..config import MODES
from ..errors import ConfigError, InputError, OutputError
from .common import OUTPUT_FORMATS, fallback_lines, jit_summary, matcher_config, parse_kv, positive_int, size_arg, \
    timed_match, to_json

__all__ = ["add_commands", "cmd_match", "cmd_demo", "write_matches", "read_matches", "format_table"]


def write_matches(path: Path, result, f1, f2, geometry=None, verified=None) -> None:
    """Write matches as ``.npz`` / ``.csv`` / ``.json`` (by suffix), atomically.

    ``geometry``: the pair's :class:`~guidedmatch.geometry.TwoViewGeometry` (stored as ``stats["geometry"]``);
    ``verified``: optional ``(M,) bool`` per match (``--keep-unverified``: a ``verified`` array / column).
    """
    from ..features import atomic_savez, atomic_write_text

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



def _check_detect_memory_both(img1, img2, detector, max_image_size=None, names=("IMG1", "IMG2")) -> None:
    """MemoryLimitError (with a suggested --max-image-size) when detecting either image would not fit, before any
    detection (or compilation) starts."""
    from ..features import check_detect_memory

    for img, name in zip((img1, img2), names):
        h, w = img.shape[:2]
        if max_image_size and max(w, h) > max_image_size:
            s = max_image_size / max(w, h)
            w, h = max(1, round(w * s)), max(1, round(h * s))
        check_detect_memory(w, h, detector, name)


def _detect_both(img1, img2, detector, max_features, options, max_image_size=None, names=("IMG1", "IMG2")):
    from ..features import detect

    feats = [detect(img, detector, max_features, max_image_size=max_image_size, **options) for img in (img1, img2)]
    for name, f in zip(names, feats):
        if len(f) == 0:
            raise InputError(f"no features detected in {name} ({detector}); the image may be blank or too small")
    return feats[0], feats[1]


def _check_input_image(path: str, what: str) -> None:
    from ..errors import ImageReadError
    from ..features import ImageNotFoundError

    p = Path(path)
    if not p.exists():
        raise ImageNotFoundError(f"{what} not found: {p}")
    if p.is_dir():
        raise ImageReadError(f"{what} is a folder, not an image: {p}")



def _subset_result(result, keep: np.ndarray):
    import dataclasses

    return dataclasses.replace(result, pairs=result.pairs[keep], distances=result.distances[keep],
                               flags={k: np.asarray(v)[keep] for k, v in result.flags.items()})



def cmd_match(args) -> int:
    from ..features import check_detector_options, check_output_path, load_image

    # every argument and path problem is found here, before any image is read
    config = matcher_config(args.config)
    detector_options = check_detector_options(args.detector, parse_kv(args.detector_option, "--detector-option"))
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

    from .. import matcher  # noqa: F401 - registers the matcher's warm-ups with ..jit
    from ..jit import background_compile, guided_kernels_needed

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
    geo = result.geometry  # every matcher result carries its two-view verdict
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
        from .. import plots

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
    from .. import plots
    from ..features import detect
    from ..features import check_output_path
    from ..testing.scenes import make_scene

    out = Path(args.out)
    for name in ("demo_matches.png", "demo_results.json"):
        check_output_path(out / name, "--out")
    w, h = args.size
    from .. import matcher  # noqa: F401 - registers the matcher's warm-ups with ..jit
    from ..jit import background_compile, guided_kernels_needed, warm_up

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
    from ..features import atomic_write_text

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




def add_commands(sub, parents) -> None:
    """Add ``match`` and ``demo`` to the CLI's subparsers."""
    from ..features import DETECTORS

    m = sub.add_parser("match", parents=parents, help="match the features of two images", description="Detect features in two "
                       "images and match them; prints a summary and optionally writes matches and a plot.")
    m.add_argument("img1")
    m.add_argument("img2")
    m.add_argument("--mode", default="so+epi+ia", choices=MODES, help="matching mode (default: so+epi+ia)")
    m.add_argument("--detector", default="sift", choices=DETECTORS, help="feature detector (default sift)")
    m.add_argument("--max-features", type=positive_int, default=None, help="keep at most N strongest features per image")
    m.add_argument("--detector-option", action="append", metavar="KEY=VALUE", help="OpenCV detector option, e.g. contrastThreshold=0.01 (repeatable)")
    m.add_argument("--config", action="append", metavar="KEY=VALUE", help="matcher config override, e.g. ratio=0.9 (repeatable)")
    m.add_argument("--max-image-size", type=positive_int, default=None, metavar="PX",
                   help="detect on a copy downscaled to this long side (keypoints still in original pixels); "
                        "needed for very large images (the memory check suggests a size)")
    m.add_argument("-o", "--output", help="write the geometrically verified matches to .npz, .csv or .json")
    m.add_argument("--keep-unverified", action="store_true",
                   help="with -o: write every match, with a 'verified' flag, also when the images do not overlap")
    m.add_argument("--plot", help="write a PNG of both images with the matches (inliers / outliers of the verdict)")
    m.add_argument("--show-regions", action="store_true", help="with --plot: draw the search regions of a few features instead")
    m.set_defaults(func=cmd_match)

    d = sub.add_parser("demo", parents=parents, help="built-in demo on a rendered scene with known geometry (no data needed)",
                       description="Render a synthetic two-view scene (textured planes, camera roll), match it with "
                       "every mode and print comparisons / matches / true correspondences / precision / time.")
    d.add_argument("--out", default="guidedmatch_demo", help="output folder (default ./guidedmatch_demo)")
    d.add_argument("--size", type=size_arg, default=(1600, 1200), help="image size WxH (default 1600x1200)")
    d.add_argument("--roll", type=float, default=30.0, help="camera-2 roll in degrees (default 30)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--detector", default="sift", choices=DETECTORS)
    d.add_argument("--max-features", type=positive_int, default=None)
    d.set_defaults(func=cmd_demo)
