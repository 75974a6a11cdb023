"""The pipeline: ``guidedmatch sfm`` (:func:`main`, :func:`run_sfm`) and the staged commands ``guidedmatch extract``
(:func:`run_extract`) and ``guidedmatch map`` (:func:`run_map`), all made of the stages of :mod:`.stages`."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from pathlib import Path

from ..collection.sinks import WriteLock
from ..errors import InputError
from ..validation import config_from
from .config import IMAGE_EXTENSIONS, SfmConfig, SfmPaths, say
from .overlap import extract_and_match, overlap_plan
from .report import plot_reconstruction, report_markdown
from .stages import (check_output, database_pair_stats, extract_main, make_folder, map_main, match_main,
                     models_summary, project_file, write_project)

__all__ = ["main", "run_sfm", "run_extract", "run_map", "list_images", "image_names", "colmap_log_level"]


def list_images(image_dir: str | os.PathLike) -> list[str]:
    """Image files under ``image_dir`` (recursive, by suffix), as sorted POSIX paths relative to it -- the names
    COLMAP gives them. Other files (e.g. a ``K.txt``) are ignored."""
    from ..collection.image_folder import list_images as _list

    return _list(image_dir)


def image_names(image_dir: Path) -> list[str]:
    """:func:`list_images`; InputError when the folder is missing or holds no image files."""
    if not image_dir.is_dir():
        raise InputError(f"image folder not found: {image_dir}")
    names = list_images(image_dir)
    if not names:
        raise InputError(f"no images in {image_dir} (looked for {', '.join(IMAGE_EXTENSIONS)})")
    return names


def _enough(names: list[str], skipped: list[dict], image_dir: Path) -> list[str]:
    bad = {s["name"] for s in skipped}
    good = [n for n in names if n not in bad]
    if len(good) < 2:
        extra = f" ({len(bad)} skipped: {'; '.join(s['name'] + ': ' + s['reason'] for s in skipped[:3])})" if bad else ""
        raise InputError(f"structure from motion needs at least 2 usable images; {image_dir} has {len(good)}{extra}")
    return good


def main(conf: SfmConfig, paths: SfmPaths, command: str = "") -> dict:
    """Run (or resume) the three stages; write ``report.json``, ``report.md`` and the figure. Returns the report.

    Raises before any work: InputError (no images), OutputError (an output folder that cannot be created or
    written; OUT_DIR of another project or made with other settings; a process where zlib cannot be used,
    :func:`guidedmatch._runtime.zlib_shadowed`), ConfigError (bad settings). After the extraction: InputError when
    fewer than 2 images are usable; ImageReadError with ``bad_images="refuse"`` and a damaged image."""
    from .._runtime import require_zlib
    from ..collection.pairs import check_pairs_spec

    conf = config_from(SfmConfig, conf)
    require_zlib(paths.figure)  # a process where the figure's PNG encoder would abort: say so before any work
    t_start = time.perf_counter()
    names = image_names(paths.image_dir)
    project = check_output(conf, paths, paths.project)
    if conf.pairs != "auto":
        check_pairs_spec(conf.pairs, names)   # a bad spec, a missing pairs file or unknown names fail here, before any work
    overlap_plan(conf, names)                 # pipeline="on" where the stages cannot overlap: refused here
    make_folder(paths.out_dir, "OUT_DIR")
    make_folder(paths.database.parent, "database folder")
    with WriteLock(paths.database, reentrant=True):   # a second sfm on the same project refuses here (exit 2), before any write
        return _main_locked(conf, paths, command, names, project, t_start)


def _main_locked(conf: SfmConfig, paths: SfmPaths, command: str, names: list[str], project: dict,
                 t_start: float) -> dict:
    """:func:`main` once the database's write lock is held."""
    from ..evaluation.meta import run_metadata, write_json
    from ..features import atomic_write_text

    write_project(paths.project, project)

    overlap, why, spec = overlap_plan(conf, names)
    if overlap:   # pairs matched as soon as both images are written (sfm/overlap.py)
        extraction, early = extract_and_match(conf, paths, names, spec)
    else:
        # No matching set-up in a thread during the extraction: the extraction keeps both cores busy, and on
        # Herz-Jesus-P8 the thread's imports and kernel loads cost the extraction more than they saved in matching.
        say(conf, f"      extraction, then matching ({why})")
        extraction, early = extract_main(conf, paths, names), None
    skipped = list(extraction["skipped"])
    names = _enough(names, skipped, paths.image_dir)
    matching = match_main(conf, paths, names, early=early)
    # the report's bookkeeping (run metadata, per-pair table, the plotting library's import: ~0.5 s) runs in a thread
    # while the mapper works -- pycolmap releases the GIL and its mapping does not keep both cores busy
    side: dict = {}

    def bookkeeping() -> None:
        try:
            side["meta"] = run_metadata(conf.seed)
            side["pairs"] = database_pair_stats(paths.database)
            from ..plots import _plt

            _plt()
        except Exception as exc:  # noqa: BLE001 - redone (and raised) in the main thread below
            side["error"] = exc

    helper = threading.Thread(target=bookkeeping, name="guidedmatch-sfm-report", daemon=True)
    helper.start()
    try:
        mapping = map_main(conf, paths)
    finally:
        helper.join()
    models = mapping["models"]
    best = models[0] if models else None
    in_models = {n for m in models for n in m["registered_names"]}
    stages = {"extraction": extraction, "matching": matching, "mapping": mapping}
    report = {"image_dir": str(paths.image_dir), "out_dir": str(paths.out_dir), "command": command,
              "config": dataclasses.asdict(conf), "num_images": len(names), "skipped_images": skipped,
              "pipeline": {"setting": conf.pipeline, "overlapped": overlap, "why": why,
                           **(matching.get("overlap") or {})},
              "stages": stages, "total_time_s": time.perf_counter() - t_start,
              "peak_rss_mb": max(max(s["peak_rss_mb"]["self"], s["peak_rss_mb"]["children"] or 0)
                                 for s in stages.values()),
              "mapper": mapping["mapper"], "mapper_rule": mapping.get("mapper_rule"),
              "models": [{k: m[k] for k in ("path", "registered", "points3D", "registered_names")} for m in models],
              "registered": best["registered"] if best else 0, "points3D": best["points3D"] if best else 0,
              "unregistered": sorted(set(names) - in_models),
              "pairs": side["pairs"] if "pairs" in side else database_pair_stats(paths.database),
              "database": str(paths.database), "sparse": str(paths.sparse / "0") if best else None, "figure": None,
              "meta": side["meta"] if "meta" in side else run_metadata(conf.seed)}
    if best:
        import pycolmap

        rec = pycolmap.Reconstruction(str(paths.sparse / "0"))
        report["figure"] = str(plot_reconstruction(paths.figure, rec, title=f"{paths.image_dir.name}: "
                                                   f"{best['registered']}/{len(names)} images, {best['points3D']:,} points"))
    report["summary"] = summary_line(report)
    write_json(paths.report_json, report)
    atomic_write_text(paths.report_md, report_markdown(report))
    say(conf, report["summary"] + f"; report {paths.report_md}")
    return report


def summary_line(report: dict) -> str:
    """The one line ``guidedmatch sfm`` ends with: time and peak memory per stage, the models."""
    st = report["stages"]
    parts = ", ".join(f"{k} {s['time_s']:.1f} s" for k, s in st.items())
    ov = st["matching"].get("overlap")
    if ov:   # the matching's time_s is what ran after the extraction
        parts = parts.replace(f"matching {st['matching']['time_s']:.1f} s", f"matching {st['matching']['time_s']:.1f} s "
                              f"after it ({ov['pairs_matched_during_extraction']}/{st['matching']['pairs']} pairs "
                              "during the extraction)")
    skipped = f", {len(report['skipped_images'])} image(s) skipped" if report["skipped_images"] else ""
    return (f"done in {report['total_time_s']:.1f} s ({parts}; peak memory {report['peak_rss_mb']:,.0f} MB): "
            f"{models_summary(st['mapping'], report['num_images'])} ({st['mapping']['mapper']} mapper){skipped} -> "
            f"{Path(report['sparse']) if report['sparse'] else 'no model'}")


def run_sfm(image_dir: str | os.PathLike, out_dir: str | os.PathLike, config: SfmConfig | dict | None = None,
            command: str = "", colmap_log: bool = False) -> dict:
    """``guidedmatch sfm IMAGE_DIR OUT_DIR`` as a function: :func:`main` with :class:`SfmPaths`.

    The extraction may start worker processes (``spawn``): in a script, call it under ``if __name__ == "__main__":``.

    COLMAP's own INFO log lines (thousands for a mapping run) are silenced unless ``colmap_log``; its warnings and
    errors still show."""
    with colmap_log_level(0 if colmap_log else 1):
        return main(config_from(SfmConfig, config), SfmPaths(image_dir, out_dir), command=command)


def _no_images(database: Path) -> bool:
    """True when ``database`` is missing or holds no image (what a refused extraction leaves)."""
    import sqlite3

    if not database.exists():
        return True
    try:
        con = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
        try:
            return con.execute("SELECT COUNT(*) FROM images").fetchone()[0] == 0
        finally:
            con.close()
    except sqlite3.Error:
        return False


def run_extract(image_dir: str | os.PathLike, database: str | os.PathLike, config: SfmConfig | dict | None = None,
                colmap_log: bool = False) -> dict:
    """``guidedmatch extract IMAGE_DIR DATABASE``: stage 1 of :func:`main` alone, into ``database`` (created when
    missing; its settings recorded next to it, ``DATABASE.guidedmatch.json``). Resumable. Returns the stage
    record (``skipped`` lists the damaged images by name and reason)."""
    conf = config_from(SfmConfig, config)
    database = Path(database)
    paths = SfmPaths(image_dir, database.parent if str(database.parent) else Path("."), database_path=database)
    names = image_names(paths.image_dir)
    project = check_output(conf, paths, project_file(paths.database), matching=False)
    make_folder(paths.database.parent, "database folder")
    record, had_database = project_file(paths.database), paths.database.exists()
    lock = WriteLock(paths.database, reentrant=True).acquire()   # another writer of this database: refused here, before any write
    try:
        write_project(record, project)
        with colmap_log_level(0 if colmap_log else 1):
            rec = extract_main(conf, paths, names)
    except BaseException:
        if not had_database and _no_images(paths.database):  # refused before any image was written: leave nothing
            for side in ("", "-wal", "-shm", "-journal"):
                paths.database.with_name(paths.database.name + side).unlink(missing_ok=True)
            record.unlink(missing_ok=True)
        raise
    finally:
        lock.release()
    rec["images"] = len(names)
    return rec


def run_map(database: str | os.PathLike, image_dir: str | os.PathLike, out: str | os.PathLike,
            config: SfmConfig | dict | None = None, colmap_log: bool = False,
            fixed_intrinsics: bool | None = None) -> dict:
    """``guidedmatch map DATABASE IMAGE_DIR OUT``: stage 3 of :func:`main` alone -- the models into ``OUT/<k>``
    (largest first) and ``OUT/mapping.json``. A rerun on an unchanged database with the same settings reuses the
    model. ``fixed_intrinsics`` (default: whether ``config.camera`` is given) holds the cameras' intrinsics fixed in
    bundle adjustment. Returns the stage record."""
    from ..errors import DatabaseError
    from ..features import writable_folder

    conf = config_from(SfmConfig, config)
    out = Path(out)
    paths = SfmPaths(image_dir, out.parent if str(out.parent) else Path("."), database_path=database,
                     sparse_path=out)
    if not paths.database.is_file():
        raise DatabaseError(f"database not found: {paths.database}")
    if not paths.image_dir.is_dir():
        raise InputError(f"image folder not found: {paths.image_dir}")
    if out.exists() and not out.is_dir():
        from ..errors import OutputError

        raise OutputError(f"cannot write the models into {out}: it exists and is not a folder")
    writable_folder(out, "OUT")
    from .stages import database_summary

    try:
        summary = database_summary(paths.database)
    except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError subclasses for any SQLite problem
        raise DatabaseError(f"{paths.database}: not a readable COLMAP database ({exc})") from None
    if not summary["geometries"]:
        raise InputError(f"{paths.database} has no image pairs with a two-view geometry: nothing to map; match it "
                         f"first (guidedmatch colmap {paths.database})")
    with colmap_log_level(0 if colmap_log else 1):
        rec = map_main(conf, paths, fixed_intrinsics=fixed_intrinsics)
    return rec


@contextlib.contextmanager
def colmap_log_level(level: int = 1):
    """COLMAP's (glog) minimum log level inside the block: 0 INFO, 1 WARNING, 2 ERROR; restored afterwards."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
