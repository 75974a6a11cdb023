"""Command-line interface: ``guidedmatch match | demo | experiment | bench | colmap | hloc | extract | map | sfm``.

Every error the user can cause is a :class:`~guidedmatch.errors.GuidedMatchError` (missing or unreadable image,
no features, bad option or config value, mismatched descriptors, an output path that cannot be written, ...): it
prints one line ``guidedmatch: error: ...`` on stderr and exits with status 2, checked before any work where
possible. The operating system refusing a write (a folder that cannot be created, a read-only file system, a full
disk) is also exit 2, naming the path and the reason. Any other exception is a bug: one line ``guidedmatch:
internal error: ...``, exit status 1. ``--debug`` (before or after the subcommand) shows the traceback of either.
Output files are written atomically.

The subcommands live in modules by group: :mod:`.pairs` (match, demo), :mod:`.collection` (colmap, hloc),
:mod:`.sfm` (extract, map, sfm), :mod:`.bench` (bench, experiment); :mod:`.common` holds the shared helpers.
"""
from __future__ import annotations

import argparse
import errno
import sys

from .. import __version__
from .._runtime import freeze_gc_at_exit, mark_own_process, plain_sigterm, reexec_with_hugepages
from ..errors import GuidedMatchError
from . import bench, collection, pairs, sfm
from .common import fallback_lines, jit_summary, matcher_config, parse_kv, timed_match, to_json
from .pairs import format_table, read_matches, write_matches

__all__ = ["main", "build_parser", "read_matches", "write_matches", "fallback_lines", "matcher_config", "to_json",
           "timed_match", "jit_summary", "format_table", "parse_kv"]

#: OSError numbers that mean the environment refused a file operation (not a bug): exit 2 naming the path.
_USER_OS_ERRORS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENOTDIR, errno.EISDIR,
                   errno.ENOENT, errno.EEXIST, errno.EFBIG, errno.ENAMETOOLONG, errno.ELOOP}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="guidedmatch", description="Guided image feature matching with feature spatial "
                                "order and epipolar geometry (Teng & Dong).")
    p.add_argument("--version", action="version", version=f"guidedmatch {__version__}")
    p.add_argument("--debug", action="store_true", help="show Python tracebacks on errors")
    # every subcommand takes --debug too (SUPPRESS: absent there, the value given before the subcommand stays)
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show Python tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for group in (pairs, bench, sfm, collection):
        group.add_commands(sub, [debug])
    return p


#: the commands that load pycolmap (and with it glog's SIGTERM handler, replaced by :func:`plain_sigterm`)
PYCOLMAP_COMMANDS = frozenset({"extract", "map", "sfm", "colmap", "bench"})
#: commands that only match features already extracted: they start once, without huge pages for malloc, which cost
#: matching time (Herz-Jesus-P8's `guidedmatch colmap` 2.17 -> 1.93 s, fox 71.9-82.2 -> 62.5-75.1 s, alternating runs;
#: docs/performance.md, "Huge pages for malloc")
NO_HUGEPAGE_COMMANDS = frozenset({"colmap", "hloc"})


def _os_error_line(exc: OSError) -> str:
    where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    return f"{exc.strerror or exc}" + (f": {where}" if where else "")


def main(argv: list[str] | None = None) -> int:
    own_process = argv is None   # the command line's own process, not main([...]) from Python
    freeze_gc_at_exit()  # a cheap interpreter shutdown (guidedmatch._runtime)
    mark_own_process()   # Numba's set-up may skip its SciPy BLAS probe (guidedmatch._runtime)
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = bench.delegated_bench(argv) or parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    if own_process and args.command not in NO_HUGEPAGE_COMMANDS:   # a command that extracts features will run: huge
        reexec_with_hugepages()   # pages for malloc -- after parsing, so that --help, --version and a mistyped option
        # do not pay a second start (returns when they do not apply)
    if args.command in PYCOLMAP_COMMANDS:
        plain_sigterm()   # SIGTERM (a job scheduler, timeout): end at once, no glog stack dump (guidedmatch._runtime)
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
    except OSError as exc:
        if args.debug:
            raise
        if exc.errno in _USER_OS_ERRORS:  # the system refused a file operation: a path and a reason, exit 2
            print(f"guidedmatch: error: {_os_error_line(exc)}", file=sys.stderr)
            return 2
        print(f"guidedmatch: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)",
              file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: one line, exit 1 (--debug: the traceback)
        if args.debug:
            raise
        print(f"guidedmatch: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)", file=sys.stderr)
        return 1
