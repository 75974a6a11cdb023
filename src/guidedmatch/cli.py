"""Command-line interface: ``guidedmatch match | demo | experiment | bench``.

Every error the user can cause (missing or unreadable image, no features, bad option, mismatched
descriptors, ...) prints one line ``guidedmatch: error: ...`` on stderr and exits with status 2 --
never a traceback (``--debug`` shows one). Output files are written atomically.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__

MODES = ("bf", "epi", "so", "so+epi", "so+epi+ia")


class CLIError(Exception):
    """An error reported to the user as one line, exit status 2."""


# --------------------------------------------------------------------------- helpers
def _parse_kv(items: list[str] | None, what: str) -> dict:
    """``["a=1", "b=x"]`` -> ``{"a": 1, "b": "x"}`` (values parsed as JSON when possible)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise CLIError(f"{what} must look like key=value, got {item!r}")
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


def write_matches(path: Path, result, f1, f2) -> None:
    """Write matches as ``.npz`` / ``.csv`` / ``.json`` (by suffix), atomically."""
    from .features import atomic_savez, atomic_write_text

    pairs, dist = result.pairs, result.distances
    p1 = f1.keypoints[pairs[:, 0]] if len(pairs) else np.zeros((0, 2))
    p2 = f2.keypoints[pairs[:, 1]] if len(pairs) else np.zeros((0, 2))
    suffix = path.suffix.lower()
    stats_json = to_json(result.stats)
    if suffix == ".npz":
        atomic_savez(path, pairs=pairs, distances=dist, points1=p1, points2=p2,
                     keypoints1=f1.keypoints, keypoints2=f2.keypoints, stats=np.array(stats_json))
    elif suffix == ".csv":
        lines = ["i1,i2,x1,y1,x2,y2,distance"]
        lines += [f"{a},{b},{x1:.3f},{y1:.3f},{x2:.3f},{y2:.3f},{d:.4f}"
                  for (a, b), (x1, y1), (x2, y2), d in zip(pairs, p1, p2, dist)]
        atomic_write_text(path, "\n".join(lines) + "\n")
    elif suffix == ".json":
        atomic_write_text(path, to_json(dict(pairs=pairs, distances=dist, points1=p1, points2=p2,
                                             stats=result.stats), indent=1))
    else:
        raise CLIError(f"unknown output format {suffix!r}: use .npz, .csv or .json")


def read_matches(path) -> dict:
    """Read back what :func:`write_matches` wrote as ``.npz`` (pairs, distances, points, stats)."""
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["stats"] = json.loads(str(d["stats"]))
    return d


def run_mode(f1, f2, mode: str, config_overrides: dict | None = None, return_models: bool = False):
    """Match two feature sets with ``mode`` (``--config`` keys are :class:`MatcherConfig` fields)."""
    config_overrides = dict(config_overrides or {})
    if mode not in MODES:
        raise CLIError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
    try:
        from . import matcher
    except ImportError:
        matcher = None
    if matcher is None:
        if mode != "bf":
            raise CLIError(f"mode {mode!r} is not available in this build; only 'bf' is")
        from .bruteforce import match_bruteforce

        allowed = {"ratio", "mutual", "max_distance"}
        bad = set(config_overrides) - allowed
        if bad:
            raise CLIError(f"unknown config key(s) for bf: {', '.join(sorted(bad))}")
        res = match_bruteforce(f1, f2, **config_overrides)
        return (res, None) if return_models else res
    try:
        config = matcher.MatcherConfig(**config_overrides)
    except TypeError as exc:
        names = ", ".join(f.name for f in dataclasses.fields(matcher.MatcherConfig))
        raise CLIError(f"bad --config: {exc}. Known keys: {names}") from None
    return matcher.match(f1, f2, mode=mode, config=config, return_models=return_models)


def _detect_both(img1, img2, detector, max_features, options):
    from .features import detect

    f1 = detect(img1, detector, max_features, **options)
    f2 = detect(img2, detector, max_features, **options)
    for name, f in (("IMG1", f1), ("IMG2", f2)):
        if len(f) == 0:
            raise CLIError(f"no features detected in {name} ({detector}); the image may be blank or too small")
    return f1, f2


# --------------------------------------------------------------------------- commands
def cmd_match(args) -> int:
    from .features import load_image

    if args.show_regions and not args.plot:
        raise CLIError("--show-regions needs --plot OUT.png")
    if args.show_regions and args.mode == "bf":
        raise CLIError("--show-regions needs a guided mode (epi, so, so+epi, so+epi+ia), not bf")
    if args.output and Path(args.output).suffix.lower() not in (".npz", ".csv", ".json"):
        raise CLIError(f"unknown output format {Path(args.output).suffix!r}: use .npz, .csv or .json")

    img1 = load_image(args.img1)
    img2 = load_image(args.img2)
    t0 = time.perf_counter()
    f1, f2 = _detect_both(img1, img2, args.detector, args.max_features, _parse_kv(args.detector_option, "--detector-option"))
    t_det = time.perf_counter() - t0
    result, models = run_mode(f1, f2, args.mode, _parse_kv(args.config, "--config"), return_models=True)
    st = result.stats
    print(f"features      : {len(f1)} x {len(f2)} ({args.detector}, detection {t_det:.2f} s)")
    print(f"mode          : {args.mode}")
    print(f"matches       : {len(result)}")
    print(f"comparisons   : {st['comparisons']:,} ({100.0 * st['comparisons'] / max(1, len(f1) * len(f2)):.2f} % of brute force)")
    print(f"matching time : {st['time_s']:.3f} s")
    for fb in st.get("fallbacks", []):
        print(f"fallback      : {fb.get('what')}: {fb.get('reason')}")
    if args.output:
        write_matches(Path(args.output), result, f1, f2)
        print(f"wrote         : {args.output}")
    if args.plot:
        from . import plots

        if args.show_regions:
            if models is None:
                raise CLIError("--show-regions needs a guided mode whose models were fitted (see the fallbacks above)")
            plots.search_regions(args.plot, img1, img2, f1, f2, result, models)
        else:
            plots.motion_field(args.plot, img1, f1.keypoints[result.pairs[:, 0]], f2.keypoints[result.pairs[:, 1]],
                               None, f"{args.mode}: {len(result)} matches")
        print(f"wrote         : {args.plot}")
    return 0


def cmd_demo(args) -> int:
    from . import plots
    from .features import detect
    from .testing.scenes import make_scene

    out = Path(args.out)
    w, h = args.size
    print(f"[1/4] rendering a synthetic two-view scene {w}x{h}, camera roll {args.roll:g} deg (seed {args.seed})")
    scene = make_scene((w, h), roll_deg=args.roll, seed=args.seed)
    print(f"[2/4] detecting {args.detector.upper()} features")
    f1 = detect(scene.image1, args.detector, args.max_features)
    f2 = detect(scene.image2, args.detector, args.max_features)
    print(f"      {len(f1)} x {len(f2)} features")
    modes = MODES if _has_matcher() else ("bf",)
    print(f"[3/4] matching with {', '.join(modes)}")
    rows, panels = [], []
    bf_comp = max(1, len(f1) * len(f2))
    for mode in modes:
        res = run_mode(f1, f2, mode)
        p1, p2 = f1.keypoints[res.pairs[:, 0]], f2.keypoints[res.pairs[:, 1]]
        ok = scene.correct(p1, p2)
        rows.append(dict(mode=mode, comparisons=res.stats["comparisons"], matches=len(res), true=int(ok.sum()),
                         precision=float(ok.mean()) if len(ok) else float("nan"), time_s=res.stats["time_s"],
                         fallbacks=len(res.stats.get("fallbacks", []))))
        panels.append(dict(pts1=p1, pts2=p2, correct=ok,
                           title=f"{mode}: {int(ok.sum())}/{len(res)} correct, {100 * res.stats['comparisons'] / bf_comp:.2f} % comparisons"))
    print()
    print(format_table(rows, bf_comp))
    print()
    print("true = GT within 3 px (exact scene geometry); comparisons = descriptor distances evaluated")
    fig = plots.motion_field_panels(out / "demo_matches.png", scene.image1, panels,
                                    suptitle=f"guidedmatch demo: motion field on image 1 (green = correct, red = wrong), roll {args.roll:g} deg")
    from .features import atomic_write_text

    atomic_write_text(out / "demo_results.json", to_json(dict(rows=rows, features=(len(f1), len(f2)),
                                                              size=(w, h), roll_deg=args.roll, seed=args.seed), indent=1))
    print(f"[4/4] wrote {fig} and {out / 'demo_results.json'}")
    return 0


def format_table(rows: list[dict], bf_comp: int) -> str:
    head = f"{'mode':<10} {'comparisons':>13} {'% of BF':>8} {'matches':>8} {'true':>6} {'precision':>9} {'time (s)':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['mode']:<10} {r['comparisons']:>13,} {100 * r['comparisons'] / bf_comp:>7.2f}% {r['matches']:>8} "
                     f"{r['true']:>6} {100 * r['precision']:>8.2f}% {r['time_s']:>9.3f}")
    return "\n".join(lines)


def _has_matcher() -> bool:
    try:
        from . import matcher  # noqa: F401
    except ImportError:
        return False
    return True


def cmd_experiment(args) -> int:
    if args.which == "alignment":
        try:
            from .evaluation.alignment_sim import run_alignment_experiment
        except ImportError as exc:
            raise CLIError(f"the alignment experiment is not available: {exc}") from None
        summary = run_alignment_experiment(n_pairs=args.pairs, out_dir=Path(args.out), seed=args.seed, progress=True)
        if isinstance(summary, dict) and summary.get("table_md"):
            print(summary["table_md"])
        print(f"wrote results to {args.out}")
        return 0
    raise CLIError(f"unknown experiment {args.which!r}")


def cmd_bench(args) -> int:
    if args.which == "pairs":
        from .evaluation import bench_pairs

        return int(bench_pairs.main(args) or 0)
    try:
        from .evaluation import bench
    except ImportError as exc:
        raise CLIError(f"the benchmark harness is not available: {exc}") from None
    return int(bench.main(args) or 0)


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
    m.add_argument("--detector", default="sift", choices=("sift", "orb", "akaze", "brisk"), help="feature detector (default sift)")
    m.add_argument("--max-features", type=_positive_int, default=None, help="keep at most N strongest features per image")
    m.add_argument("--detector-option", action="append", metavar="KEY=VALUE", help="OpenCV detector option, e.g. contrastThreshold=0.01 (repeatable)")
    m.add_argument("--config", action="append", metavar="KEY=VALUE", help="matcher config override, e.g. ratio=0.9 (repeatable)")
    m.add_argument("-o", "--output", help="write matches to .npz, .csv or .json")
    m.add_argument("--plot", help="write a motion-field PNG")
    m.add_argument("--show-regions", action="store_true", help="with --plot: draw the search regions of a few features instead")
    m.set_defaults(func=cmd_match)

    d = sub.add_parser("demo", help="built-in demo on a rendered scene with known geometry (no data needed)",
                       description="Render a synthetic two-view scene (textured planes, camera roll), match it with "
                       "every mode and print comparisons / matches / true correspondences / precision / time.")
    d.add_argument("--out", default="guidedmatch_demo", help="output folder (default ./guidedmatch_demo)")
    d.add_argument("--size", type=_size, default=(1600, 1200), help="image size WxH (default 1600x1200)")
    d.add_argument("--roll", type=float, default=30.0, help="camera-2 roll in degrees (default 30)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--detector", default="sift", choices=("sift", "orb", "akaze", "brisk"))
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
    b.add_argument("which", choices=("oxford", "synthetic", "real", "alignment", "all", "pairs"))
    b.add_argument("--data", default=None, help="data folder (default: $GUIDEDMATCH_DATA or ../shared/data)")
    b.add_argument("--out", default="reports", help="output folder (default ./reports)")
    b.add_argument("--quick", action="store_true", help="a few pairs per set (minutes, not an hour)")
    b.add_argument("--repeats", type=_positive_int, default=None, help="timing repeats per method (median)")
    b.add_argument("--detector", default="sift", choices=("sift", "orb", "akaze", "brisk"))
    b.add_argument("--seed", type=int, default=0)
    from .evaluation.bench_pairs import add_arguments as _pairs_arguments

    _pairs_arguments(b)  # --features / --dense / --oxford of `bench pairs`
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (CLIError, ValueError, FileNotFoundError, IsADirectoryError, PermissionError, ImportError) as exc:
        if args.debug:
            raise
        print(f"guidedmatch: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("guidedmatch: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # pragma: no cover - last resort, still no traceback without --debug
        if args.debug:
            raise
        print(f"guidedmatch: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
