"""Helpers shared by the subcommands: option parsing, JSON output, the matching timer, argparse types."""
from __future__ import annotations

import argparse
import json

from ..config import MatcherConfig
from ..errors import ConfigError

OUTPUT_FORMATS = (".npz", ".csv", ".json")


# --------------------------------------------------------------------------- helpers
def parse_kv(items: list[str] | None, what: str) -> dict:
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
    from ..evaluation.meta import json_default

    return json.dumps(obj, default=json_default, **kw)


def matcher_config(items: list[str] | None) -> MatcherConfig:
    """``--config KEY=VALUE`` items -> a validated :class:`MatcherConfig` (ConfigError naming the valid keys)."""
    from ..validation import config_from

    try:
        return config_from(MatcherConfig, parse_kv(items, "--config"))
    except ConfigError as exc:
        raise ConfigError(f"bad --config: {exc}") from None


def fallback_lines(fallbacks) -> list[str]:
    """Each distinct fallback once, with how often it occurred: ``"what: reason (x3)"``."""
    counts: dict[tuple, int] = {}
    for fb in fallbacks or ():
        key = (fb.what, fb.reason) if hasattr(fb, "what") else (fb.get("what"), fb.get("reason"))
        counts[key] = counts.get(key, 0) + 1
    return [f"{w}: {r}" + (f" (x{n})" if n > 1 else "") for (w, r), n in counts.items()]



def timed_match(f1, f2, mode, config=None, *, return_models=False, warm: bool = True):
    """``match`` with its Numba kernels warmed up first (untimed; ``warm=False``: the caller already did); returns
    ``(match's return value, matching_seconds, compile_seconds)`` -- ``match`` itself reports any compilation left
    in the timed run apart from ``stats.time_s`` (``stats.details["jit_compile_s"]``)."""
    from ..matcher import match  # (importing the matcher registers its warm-ups with ..jit)
    from ..jit import warm_up

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


def size_arg(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1600x1200, got {text!r}") from None
    if w < 64 or h < 64:
        raise argparse.ArgumentTypeError("size must be at least 64x64")
    return w, h


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def nonneg_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {v}")
    return v



#: ``guidedmatch.sfm.config.CAP_ABOVE_INLIERS``, written out: importing guidedmatch.sfm here would slow the start-up of
#: every command (tests/test_sfm.py checks the two agree)
CAP_ABOVE_DEFAULT = 100_000


def add_cap_above_option(p: argparse.ArgumentParser) -> None:
    """``--cap-above N`` of ``guidedmatch sfm`` and ``guidedmatch colmap``."""
    p.add_argument("--cap-above", type=nonneg_int, default=CAP_ABOVE_DEFAULT, metavar="N",
                   help="apply --max-inliers-per-pair only when the database holds more than N verified inliers in "
                        f"all (default {CAP_ABOVE_DEFAULT}: a few images map in seconds, and with all their inliers "
                        "more accurately; 0 = always; docs/sfm.md)")
