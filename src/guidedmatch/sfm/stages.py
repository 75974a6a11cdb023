"""The three resumable stages of structure from motion, each a ``main(conf, paths)`` in the style of hloc:

1. :func:`extract_main` -- every image decoded once and completely, its features written into a COLMAP database
   (:func:`guidedmatch.collection.image_folder.extract_folder`; damaged images skipped and listed, or refused);
   images already there are not read again.
2. :func:`match_main` -- the collection engine over the pair list into the database (pairs already there are
   skipped), then at most ``max_inliers_per_pair`` inliers of each pair kept for the mapper.
3. :func:`map_main` -- ``pycolmap.incremental_mapping`` or ``pycolmap.global_mapping`` into ``sparse/<k>``
   (written to a temporary folder and moved into place when complete); a rerun on an unchanged database with the
   same mapper settings reuses the model.

Each stage's record carries its time and the peak resident memory of this process during the stage
(``VmHWM`` of ``/proc/self/status``, reset at the stage's start where Linux allows it) and of its child processes.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..collection.sink_base import open_pycolmap_database
from ..errors import DatabaseError, OutputError
from ..validation import config_from
from .config import COLMAP_MAX_IMAGE_SIZE, VERIFIED_CONFIGS, SfmConfig, SfmPaths, parse_camera, resolve_mapper, say

__all__ = ["check_output", "extract_main", "match_main", "match_into_database", "map_main", "run_mapping", "reconstruction_stats",
           "database_pair_stats", "verified_inliers", "extract_colmap_sift", "database_summary", "peak_memory", "make_folder"]


# --------------------------------------------------------------------------- memory
def _vm_hwm_mb() -> float | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


@contextlib.contextmanager
def peak_memory(record: dict):
    """Store in ``record["peak_rss_mb"]`` the peak resident memory (MB) of this process during the block
    (``self``; ``self_reset`` False: since the process started, where ``/proc/self/clear_refs`` cannot reset it) and
    of the child processes (``getrusage(RUSAGE_CHILDREN)``, the largest peak of any child that ended so far:
    ``children_so_far``; ``children``: that figure when a child of this block raised it, else None)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    reset = False
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        reset = True
    except OSError:
        pass
    try:
        yield
    finally:
        own = _vm_hwm_mb()
        if own is None:
            own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        record["peak_rss_mb"] = {"self": round(own, 1), "self_reset": reset,
                                 "children": round(kids / 1024.0, 1) if kids > before else None,
                                 "children_so_far": round(kids / 1024.0, 1)}


# --------------------------------------------------------------------------- project records and output checks
def make_folder(folder: Path, what: str) -> Path:
    """Create ``folder`` (and parents); OutputError naming it and the reason when that is impossible."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {what} {folder}: {exc.strerror or exc}") from None
    return folder


def project_file(database: Path) -> Path:
    """The record ``guidedmatch extract`` keeps next to a database it made (image folder, extraction settings)."""
    return database.with_name(database.name + ".guidedmatch.json")


def _read_project(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise OutputError(f"{path} is unreadable ({exc}); use a new output") from None


def write_project(path: Path, project: dict) -> None:
    from ..evaluation.meta import write_json

    write_json(path, project)


def _db_image_names(db_path: Path) -> dict[str, int]:
    """``{name: number of keypoints}`` of the images in a COLMAP database."""
    import pycolmap

    try:
        db = open_pycolmap_database(db_path)
    except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError subclasses for any SQLite problem
        raise DatabaseError(f"{db_path}: not a readable COLMAP database ({exc})") from None
    try:
        return {img.name: int(db.num_keypoints_for_image(img.image_id)) if db.exists_keypoints(img.image_id) else 0
                for img in db.read_all_images()}
    finally:
        db.close()


def _num_matched_pairs(db_path: Path) -> int:
    import pycolmap

    db = open_pycolmap_database(db_path)
    try:
        return int(db.num_matched_image_pairs())
    finally:
        db.close()


def check_output(conf: SfmConfig, paths: SfmPaths, project_path: Path, *, matching: bool = True) -> dict:
    """Refuse, before any work, an output that cannot be written, or a database that belongs to another project or
    was made with other settings. Returns the project record to write (image folder, extraction settings, and the
    matching settings when ``matching``).

    Raises:
        OutputError: the output folder cannot be created or written (the path and the reason), the database was not
            made by guidedmatch for this image folder (or names images that are not in it), or the settings differ
            from the recorded ones.
    """
    from ..features import writable_folder
    from ..collection.image_folder import list_images

    for folder, what in ((paths.out_dir, "output folder"), (paths.database.parent, "database folder")):
        writable_folder(folder, what)
    if paths.database.is_dir():
        raise OutputError(f"cannot write the database {paths.database}: it is a folder")
    project = {"format": "guidedmatch-sfm/1", "image_dir": str(paths.image_dir),
               "extraction": conf.extraction_settings()}
    if matching:
        project["matching"] = conf.matching_settings()
    # the record of this command, else that of the other route to the same database (sfm's or extract's)
    candidates = (project_path, paths.database.parent / "sfm_project.json", project_file(paths.database))
    old = next((r for r in map(_read_project, candidates) if r is not None), None)
    if paths.database.exists():
        if old is None:   # (the record is written before the database is created)
            raise OutputError(f"{paths.database} exists but was not made by guidedmatch (no {project_path.name}); "
                              "refusing to touch another project's database: use a new output path")
        in_db = _db_image_names(paths.database)
        if old.get("image_dir") != str(paths.image_dir):
            raise OutputError(f"{paths.database} belongs to the images in {old.get('image_dir')}, not {paths.image_dir}; "
                              "use a new output path")
        foreign = sorted(set(in_db) - set(list_images(paths.image_dir)))
        if foreign:
            raise OutputError(f"{paths.database} holds {len(foreign)} image(s) not in {paths.image_dir} "
                              f"(e.g. {foreign[0]!r}); it belongs to another project: use a new output path")
        if in_db and old.get("extraction") != project["extraction"]:
            raise OutputError(f"the features in {paths.database} were extracted with {old.get('extraction')}, not "
                              f"{project['extraction']}; rerun with the same options or use a new output path")
        if matching:
            # projects from before max_inliers_per_pair / inlier_px handed the mapper every inlier: they read as 0
            # (and before cap_above: they capped whatever the total, i.e. 0; before refit_below_deg: no refit, 0)
            old_matching = ({"max_inliers_per_pair": 0, "inlier_px": 0.0, "cap_above": 0, "refit_below_deg": 0.0,
                             **old["matching"]}
                            if isinstance(old.get("matching"), dict) else None)
            if _num_matched_pairs(paths.database) and old_matching is not None and old_matching != project["matching"]:
                raise OutputError(f"the pairs in {paths.database} were matched with {old.get('matching')}, not "
                                  f"{project['matching']}; rerun with the same options or use a new output path")
    return project


# --------------------------------------------------------------------------- stage 1: extraction
def extract_main(conf: SfmConfig, paths: SfmPaths, names: list[str]) -> dict:
    """Stage 1: features of every image in ``names`` not yet in the database. Returns the stage's record
    (``time_s``, ``extracted``, ``reused``, ``skipped`` = ``[{"name", "reason"}]`` of damaged or featureless
    images, ``failed`` = their names, keypoint stats, ``workers``, ``peak_rss_mb``)."""
    from ..collection.image_folder import ExtractorSpec, extract_folder

    record: dict = {}
    t0 = time.perf_counter()
    with peak_memory(record):
        before = _db_image_names(paths.database) if paths.database.exists() else {}
        todo = [n for n in names if before.get(n, 0) == 0]
        workers = (os.cpu_count() or 1) if conf.num_threads == -1 else conf.num_threads
        say(conf, f"[1/3] extraction ({conf.detector}): {len(todo)} image(s) to extract, {len(names) - len(todo)} "
                  "reused")
        if conf.detector == "sift":
            out = extract_opencv_sift(conf, paths, names, todo, workers)
        else:
            spec = ExtractorSpec(detector=conf.detector, max_features=conf.max_features,
                                 max_image_size=conf.max_image_size, peak_threshold=conf.peak_threshold)
            out = extract_folder(paths.image_dir, paths.database, names, spec, camera_model=conf.camera_model,
                                 camera=parse_camera(conf.camera), single_camera=conf.single_camera, workers=workers,
                                 bad_images=conf.bad_images, progress=conf.progress)
        after = _db_image_names(paths.database)
    skipped = out["skipped"] + [{"name": n, "reason": "no features detected (a blank or too small image?)"}
                                for n in names if n in after and after[n] == 0]
    counts = [after[n] for n in names if after.get(n, 0) > 0]
    record.update({"time_s": time.perf_counter() - t0, "detector": conf.detector, "extracted": out["extracted"],
                   "reused": out["reused"], "skipped": skipped, "failed": [s["name"] for s in skipped],
                   "workers": out["workers"],
                   "keypoints": {"total": int(sum(counts)), "min": int(min(counts, default=0)),
                                 "median": float(np.median(counts)) if counts else 0.0,
                                 "max": int(max(counts, default=0))}})
    for s in skipped:
        say(conf, f"      skipped {s['name']}: {s['reason']}")
    return record


def extract_opencv_sift(conf: SfmConfig, paths: SfmPaths, names: list[str], todo: list[str], workers: int) -> dict:
    """The default extractor: OpenCV SIFT written into the database as COLMAP writes its own SIFT
    (:func:`guidedmatch.extraction.extract_to_database`: COLMAP's image size, octaves, thresholds, whole-level
    feature selection, RootSIFT uint8 descriptors, pixel-centre keypoints, cameras from EXIF). ``bad_images="refuse"``
    decodes every image to extract first and raises before anything is written."""
    from ..collection.image_folder import decode_check
    from ..extraction import ExtractionConfig, extract_to_database

    if conf.bad_images == "refuse" and todo:
        decode_check(paths.image_dir, todo)
    cam = parse_camera(conf.camera)
    rep = extract_to_database(paths.image_dir, paths.database, ExtractionConfig(
        max_features=conf.max_features or 8192, max_image_size=conf.max_image_size or COLMAP_MAX_IMAGE_SIZE,
        peak_threshold=conf.peak_threshold or 0.02 / 3, camera_model=cam[0] if cam else conf.camera_model,
        single_camera=conf.single_camera or cam is not None, workers=max(1, workers), on_error="skip",
        progress=conf.progress), image_names=names)
    if cam is not None:
        _set_known_camera(paths.database, cam)
    return {"extracted": rep["extracted"], "reused": rep["reused"], "skipped": list(rep["failed"]),
            "workers": max(1, workers)}


def _set_known_camera(database: Path, cam: tuple[str, list[float]]) -> None:
    """Give every camera of ``database`` the known model and parameters (``--camera MODEL:params``), fixed prior."""
    import pycolmap

    model, params = cam
    db = open_pycolmap_database(database)
    try:
        for c in db.read_all_cameras():
            if c.model.name != model or list(c.params) != list(params):
                c.model = pycolmap.CameraModelId.__members__[model]
                c.params = np.asarray(params, float)
                c.has_prior_focal_length = True
                db.update_camera(c)
    finally:
        db.close()


def extract_colmap_sift(database: str | os.PathLike, image_dir: str | os.PathLike, image_names: list[str], *,
                        max_features: int | None = None, max_image_size: int | None = None,
                        peak_threshold: float | None = None, camera_model: str = "SIMPLE_RADIAL",
                        camera: str | None = None, single_camera: bool = False, num_threads: int = -1) -> None:
    """``pycolmap.extract_features`` (CPU SIFT, as ``colmap feature_extractor``, reading the files itself: the
    pycolmap pipeline the benchmarks compare with) for ``image_names`` of ``image_dir``.

    ``camera="MODEL:params"`` gives every image that camera (one shared camera); ``single_camera`` shares one
    estimated camera; otherwise COLMAP's AUTO mode (one camera per image size / EXIF focal length).
    """
    import pycolmap

    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = num_threads
    ext.use_gpu = False
    ext.max_image_size = int(max_image_size) if max_image_size else COLMAP_MAX_IMAGE_SIZE
    if max_features:
        ext.sift.max_num_features = int(max_features)
    if peak_threshold is not None:
        ext.sift.peak_threshold = float(peak_threshold)
    reader = pycolmap.ImageReaderOptions()
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
    reader.camera_model = camera_model
    cam = parse_camera(camera)
    if cam is not None:
        reader.camera_model = cam[0]
        reader.camera_params = ",".join(f"{v:.10g}" for v in cam[1])
        mode = pycolmap.CameraMode.SINGLE
    from ..collection.sink_base import check_database_space

    # COLMAP writes in its own threads, where a full disk aborts the process: room for every image is checked first
    check_database_space(Path(database), len(image_names) * ext.sift.max_num_features * 152)
    pycolmap.extract_features(str(database), str(image_dir), image_names=list(image_names), camera_mode=mode,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)


# --------------------------------------------------------------------------- stage 2: matching
def second_look_on(wanted: bool | None, geometry: str) -> bool:
    """Whether the second look runs: ``wanted`` True / False as asked; None (the default) -- with our two-view
    geometries (``geometry="ours"``), which it reads back; with COLMAP's verification it cannot run.

    >>> second_look_on(None, "ours"), second_look_on(None, "colmap"), second_look_on(False, "ours")
    (True, False, False)
    """
    return bool(wanted) if wanted is not None else geometry == "ours"


def match_into_database(source, pairs, database: str | os.PathLike, cconf, *, geometry: str = "ours",
                        max_inliers_per_pair: int = 0, expand: dict | None = None,
                        second_look: dict | None = None, inlier_px: float = 0.0, refit_below_deg: float = 0.0,
                        cap_above: int = 0) -> dict:
    """The matching stage's work, shared by ``guidedmatch colmap`` and :func:`match_main`: the collection engine over
    ``pairs`` into the COLMAP ``database`` (pairs already there skipped); with ``geometry="colmap"`` pycolmap's
    verification of the pairs without a geometry; then (``geometry="ours"``, ``inlier_px`` > 0) only the inliers
    within ``inlier_px`` of their pair's F / H (at least 15: :meth:`~guidedmatch.collection.ColmapSink.tighten_inliers`;
    the F of pairs whose median triangulation angle is below ``refit_below_deg`` fitted again first, 0: never),
    then at most ``max_inliers_per_pair`` inliers per pair for the mapper (0: all) when the database holds more
    than ``cap_above`` inliers in all (0: whatever the total). ``expand`` (ExpansionConfig
    fields): then the verified expansion -- the pairs closing a triangle of verified pairs, in rounds
    (:func:`guidedmatch.collection.expansion.match_collection_expanded`).
    ``second_look`` (SecondLookConfig fields; ``geometry="ours"`` only): then the rejected pairs that verified
    neighbours tie together by enough chained correspondences are matched again with a longer unguided start
    (:func:`guidedmatch.collection.second_look.second_look`).
    Returns ``{"report": CollectionReport, "match_time_s", "verified" (pairs verified by COLMAP
    now, or None), "verify_time_s", "second_look" (its record or None), "inlier_px" (the tightening's record or
    None), "inlier_cap" (the cap's record or None)}``."""
    from ..collection.engine import match_collection, shared_cluster
    from ..collection.sinks import ColmapSink

    t0 = time.perf_counter()
    verified, t_verify, cap, tight = None, 0.0, None, None
    memos = None
    if second_look is not None and geometry == "ours":
        from ..collection.memos import StartMemos
        from ..collection.second_look import SecondLookConfig

        lcfg = config_from(SecondLookConfig, second_look)
        if lcfg.start_memo_mb > 0 and lcfg.max_rounds > 0:  # the first pass's searches of the pairs looked at again
            memos = StartMemos(lcfg.weak_below, lcfg.start_memo_mb)
    with ColmapSink(database, geometry=geometry) as sink:
        # one local cluster (when the first pass needs one) for the first pass, the expansion and the second look
        with shared_cluster(source, pairs, sink, cconf) as client:
            if expand is not None:
                from ..collection.expansion import match_collection_expanded

                report = match_collection_expanded(source, pairs, sink, cconf, expand, client=client,
                                                   start_memos=memos)
            else:
                report = match_collection(source, pairs, sink, cconf, client=client, start_memos=memos)
            look = None
            if second_look is not None and geometry == "ours":
                from ..collection.second_look import second_look as run_second_look

                look = run_second_look(source, sink, cconf, second_look, looked=getattr(report, "prior_pairs", ()),
                                       client=client, start_memos=memos)
        t_match = time.perf_counter() - t0
        if geometry == "colmap":
            t1 = time.perf_counter()
            verified = sink.verify()   # COLMAP's default verification, of every pair still without a geometry
            t_verify = time.perf_counter() - t1
        # our verdict decides at 3 px; the mapper gets the inliers within inlier_px of the pair's model (at least
        # 15). Idempotent, like the cap: a resumed run leaves the rows already tightened as they are.
        if inlier_px and geometry == "ours":
            tight = sink.tighten_inliers(inlier_px, refit_below_deg=refit_below_deg)   # >= 15 per pair
        # the mapper's bundle adjustments cost what its observations cost: hand it at most K inliers per pair
        # (spread, best first; weaker pairs whole). Idempotent, so a resumed run caps only the new pairs.
        if max_inliers_per_pair:
            cap = sink.cap_inliers(max_inliers_per_pair, above=cap_above)
    return {"report": report, "match_time_s": t_match, "verified": verified, "verify_time_s": t_verify,
            "second_look": look, "inlier_px": tight, "inlier_cap": cap}


def describe_tightening(rec: dict) -> str:
    """One line for the record of :meth:`~guidedmatch.collection.ColmapSink.tighten_inliers`.

    >>> describe_tightening({"max_error_px": 1.5, "min_inliers": 15, "pairs": 10, "pairs_tightened": 9,
    ...                      "inliers_before": 30000, "inliers_after": 21000, "time_s": 0.5})
    "21,000 of 30,000 inliers within 1.5 px of their pair's F / H (at least 15 per pair; 9 of 10 pairs tightened, 0.50 s)"
    """
    refit = (f"; F fitted again for {rec['pairs_refit']} small-baseline pairs (< {rec['refit_below_deg']:g} deg)"
             if rec.get("refit_below_deg") else "")
    return (f"{rec['inliers_after']:,} of {rec['inliers_before']:,} inliers within {rec['max_error_px']:g} px of "
            f"their pair's F / H (at least {rec['min_inliers']} per pair; {rec['pairs_tightened']} of {rec['pairs']} "
            f"pairs tightened{refit}, {rec['time_s']:.2f} s)")


def describe_cap(rec: dict) -> str:
    """One line for the record of :meth:`~guidedmatch.collection.ColmapSink.cap_inliers`.

    >>> describe_cap({"max_inliers": 1000, "above": 100000, "applied": False, "pairs": 28, "pairs_capped": 0,
    ...               "inliers_before": 51000, "inliers_after": 51000, "time_s": 0.0})
    'all 51,000 inliers (28 pairs; the cap of 1000 per pair applies above 100,000 in all)'
    >>> describe_cap({"max_inliers": 1000, "above": 100000, "applied": True, "pairs": 300, "pairs_capped": 250,
    ...               "inliers_before": 400000, "inliers_after": 190000, "time_s": 1.25})
    '190,000 of 400,000 inliers (at most 1000 per pair, spread, best first; 250 of 300 pairs capped, 1.25 s)'
    """
    if not rec.get("applied", True):
        return (f"all {rec['inliers_after']:,} inliers ({rec['pairs']} pairs; the cap of {rec['max_inliers']} per "
                f"pair applies above {rec['above']:,} in all)")
    return (f"{rec['inliers_after']:,} of {rec['inliers_before']:,} inliers (at most {rec['max_inliers']} per pair, "
            f"spread, best first; {rec['pairs_capped']} of {rec['pairs']} pairs capped, {rec['time_s']:.2f} s)")


#: ``pairs="auto"``: every pair up to this many images, else retrieval pairs + the verified expansion
AUTO_EXHAUSTIVE_MAX_IMAGES = 60
AUTO_RETRIEVAL_K = 20


def auto_pairs(num_images: int) -> str:
    """The pair spec of ``pairs="auto"``: ``exhaustive`` up to :data:`AUTO_EXHAUSTIVE_MAX_IMAGES` images (at most
    1,770 pairs: minutes), ``retrieval:20`` above (n*20 shortlisted pairs, then the verified expansion).

    >>> auto_pairs(8), auto_pairs(220)
    ('exhaustive', 'retrieval:20')
    """
    return "exhaustive" if num_images <= AUTO_EXHAUSTIVE_MAX_IMAGES else f"retrieval:{AUTO_RETRIEVAL_K}"


def expansion_wanted(spec: str) -> dict | None:
    """The verified expansion follows a pair spec with a retrieval part (ExpansionConfig defaults), else None."""
    from ..collection.pairs import has_retrieval

    return {} if has_retrieval(spec) else None


def match_main(conf: SfmConfig, paths: SfmPaths, names: list[str], early: dict | None = None) -> dict:
    """Stage 2: match the pair list with the collection engine into the database (:func:`match_into_database`).

    ``early``: what :func:`guidedmatch.sfm.overlap.extract_and_match` matched while the extraction ran. The pair list
    is then made as in the staged path and every pair it already holds is skipped (pairs that failed there are not
    tried again); the record counts both parts (``collection``), its ``time_s`` is the matching after the extraction
    (the overlap's tail and this pass), and ``overlap`` says how much ran during the extraction."""
    from ..collection.engine import CollectionConfig
    from ..collection.pairs import pairs_from_spec
    from ..collection.sources import ColmapSource

    record: dict = {}
    t0 = time.perf_counter()
    with peak_memory(record):
        source = ColmapSource(paths.database)
        try:
            usable = [n for n in source.names() if n in set(names)]
            spec = auto_pairs(len(usable)) if conf.pairs == "auto" else conf.pairs
            pair_list = pairs_from_spec(spec, usable, source, retrieval=dict(progress=conf.progress),
                                        retrieval_cache=Path(str(paths.database) + ".retrieval.npz"))
            expand = expansion_wanted(spec)
            todo = pair_list.pairs
            if early is not None and early["report"] is not None:
                gave_up = {frozenset(p) for p, _ in early["report"].failed}
                todo = tuple(p for p in todo if frozenset(p) not in gave_up)
            say(conf, f"[2/3] matching ({conf.mode}, geometry {conf.geometry}): {len(pair_list.pairs)} pairs "
                      f"({spec}{', then the verified expansion' if expand is not None else ''})"
                      + (f"; {early['during_extraction']} matched during the extraction, "
                         f"{early['report'].done if early['report'] else 0} in all before this pass"
                         if early is not None else ""))
            # after an overlap, usually nothing is left for this pass: no empty progress bar then
            left = (todo if early is None else
                    [p for p in todo if frozenset(p) not in {frozenset(q) for q in early["oriented"]}])
            # every image its own k-means, as in the extraction's stream (sfm/overlap.py): which pairs the stream
            # matched depends on timing, so a shared quantizer here would make a pair's matches depend on it too
            cconf = CollectionConfig(mode=conf.mode, matcher=conf.matcher_for(len(usable)), workers=conf.workers,
                                     scheduler=conf.scheduler, progress=conf.progress and bool(left),
                                     log_path=str(paths.pair_log), shared_quantizer="off")
            done = match_into_database(source, todo, paths.database, cconf, geometry=conf.geometry,
                                       max_inliers_per_pair=conf.max_inliers_per_pair, expand=expand,
                                       second_look={} if second_look_on(conf.second_look, conf.geometry) else None,
                                       inlier_px=conf.inlier_px, refit_below_deg=conf.refit_below_deg,
                                       cap_above=conf.cap_above)
        finally:
            source.close()
        pairs = database_pair_stats(paths.database)
    look = done["second_look"]
    if conf.second_look is True and conf.geometry != "ours":
        say(conf, "      second look: not run (it reads our two-view geometries back: geometry ours)")
    if look is not None:
        from ..collection.second_look import describe

        say(conf, f"      second look: {describe(look)}")
    if (tight := done["inlier_px"]) is not None:
        say(conf, f"      mapper's inliers: {describe_tightening(tight)}")
    cap = done["inlier_cap"]
    if cap is not None:
        say(conf, f"      mapper's inliers: {describe_cap(cap)}")
    collection = done["report"].to_dict()
    elapsed = time.perf_counter() - t0
    if early is not None:
        collection, overlap = _merge_early(early, collection, pair_list.pairs)
        elapsed += early["end_s"] - early["extraction_end_s"]
        record["overlap"] = overlap
    record.update({"time_s": elapsed, "match_time_s": done["match_time_s"], "second_look": look,
                   "verify_time_s": done["verify_time_s"], "inlier_px": tight, "inlier_cap": cap,
                   "pairs": len(pair_list.pairs),
                   "pair_list_report": pair_list.report, "collection": collection,
                   "verified_pairs": sum(p["verified"] for p in pairs),
                   "verified_inliers": sum(p["inliers"] for p in pairs), "raw_matches": sum(p["matches"] for p in pairs)})
    return record


def _merge_early(early: dict, late: dict, final_pairs) -> tuple[dict, dict]:
    """The collection record of an overlapped run (the pairs matched during the extraction + the staged pass after
    it) and the overlap's own record. Pairs the overlap matched that the final list does not hold (as oriented) are
    counted in ``not_in_final_list``: it computes only pairs that are final, so anything there is a bug to report,
    not to hide."""
    rep = early["report"]
    final = set(final_pairs)
    stray = [list(p) for p in early["oriented"] if p not in final]
    overlap = {"pairs_matched_during_extraction": early["during_extraction"],
               "pairs_matched_overlapped": rep.done if rep is not None else 0,
               "first_pair_s": early["first_pair_s"], "extraction_end_s": early["extraction_end_s"],
               "overlap_end_s": early["end_s"], "tail_after_extraction_s": early["end_s"] - early["extraction_end_s"],
               "not_in_final_list": len(stray), "not_in_final_list_examples": stray[:5]}
    if rep is None:
        return late, overlap
    e = rep.to_dict()
    merged = dict(late)
    merged["done"] = e["done"] + late["done"]
    merged["skipped"] = late["skipped"] - e["done"]       # what an earlier run had stored
    merged["failed"] = e["failed"] + late["failed"]
    merged["per_pair"] = e["per_pair"] + late["per_pair"]
    merged["wall_s"] = e["wall_s"] + late["wall_s"]
    totals = dict(e["totals"])
    lt = late["totals"]
    for key in ("matches", "inliers", "verified_pairs", "load_s", "match_s", "image_loads", "cache_hits"):
        totals[key] = totals.get(key, 0) + (lt.get(key) or 0)
    totals["verdicts"] = {k: e["totals"]["verdicts"].get(k, 0) + lt.get("verdicts", {}).get(k, 0)
                          for k in {*e["totals"]["verdicts"], *lt.get("verdicts", {})}}
    totals["pairs"] = lt.get("pairs", totals["pairs"])
    totals["after_extraction"] = {k: lt.get(k) for k in ("backend", "backend_reason", "threads", "workers")}
    merged["totals"] = totals
    return merged, overlap


def database_pair_stats(database: str | os.PathLike) -> list[dict]:
    """Per image pair of a COLMAP database: ``name1, name2, matches`` (raw), ``config`` (two-view geometry
    configuration name or None), ``inliers`` (inlier matches of a verified geometry, else 0), ``verified``."""
    import pycolmap

    rows = []
    db = open_pycolmap_database(database)
    try:   # counts in bulk; each geometry read alone (its inlier matches), so memory stays one pair's worth
        names = {img.image_id: img.name for img in db.read_all_images()}
        raw = {int(pid): int(n) for pid, n in zip(*db.read_num_matches())}
        geo = {int(pid): int(n) for pid, n in zip(*db.read_two_view_geometry_num_inliers())}
        for pid in sorted(set(raw) | set(geo)):
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            config = None
            if pid in geo:
                config = pycolmap.TwoViewGeometryConfiguration(int(db.read_two_view_geometry(i1, i2).config)).name
            verified = config in VERIFIED_CONFIGS
            rows.append({"name1": names.get(i1, str(i1)), "name2": names.get(i2, str(i2)), "matches": raw.get(pid, 0),
                         "config": config, "inliers": geo[pid] if verified else 0, "verified": bool(verified)})
    finally:
        db.close()
    return rows


def verified_inliers(database: str | os.PathLike) -> tuple[int, int]:
    """``(verified pairs, total inlier matches of verified pairs)`` of a COLMAP database."""
    rows = database_pair_stats(database)
    return sum(r["verified"] for r in rows), sum(r["inliers"] for r in rows)


def database_summary(database: str | os.PathLike) -> dict:
    """What the mapper reads from a database, in a few numbers: images, keypoints, pairs with a two-view geometry
    and their inliers (a model made from a database with the same summary and settings is reused)."""
    import pycolmap

    db = open_pycolmap_database(database)
    try:
        ids, inl = db.read_two_view_geometry_num_inliers()
        return {"images": int(db.num_images()), "keypoints": int(db.num_keypoints()),
                "geometries": len(ids), "inliers": int(np.sum(inl)) if len(inl) else 0,
                "pair_ids_sum": int(np.sum(np.asarray(ids, np.int64))) if len(ids) else 0}
    finally:
        db.close()


# --------------------------------------------------------------------------- stage 3: mapping
def run_mapping(database: str | os.PathLike, image_dir: str | os.PathLike, sparse_dir: str | os.PathLike, *,
                mapper: str = "incremental", num_threads: int = -1, seed: int = 0, fixed_intrinsics: bool = False,
                record: dict | None = None) -> dict:
    """``pycolmap.incremental_mapping`` (or ``global_mapping``) into ``sparse_dir/<k>``, the largest model as
    ``0`` (a temporary sibling folder moved into place when complete, so an interrupted run leaves the previous
    model). ``record`` (JSON-able) is written into ``sparse_dir/mapping.json`` with the result. Returns ``{"mapper",
    "time_s", "models": [stats per model, largest first, with its image names], "best": 0 or None}``."""
    import pycolmap

    sparse_dir = Path(sparse_dir)
    tmp = sparse_dir.with_name(sparse_dir.name + ".tmp")
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
    except OSError as exc:
        raise OutputError(f"cannot create the model folder {tmp}: {exc.strerror or exc}") from None
    t0 = time.perf_counter()
    if mapper == "global":
        opts = pycolmap.GlobalPipelineOptions()
        opts.num_threads = num_threads
        opts.random_seed = seed
        opts.mapper.random_seed = seed
        opts.mapper.global_positioning.use_gpu = False   # CPU solvers (no warning about a missing CUDA build)
        opts.mapper.bundle_adjustment.ceres.use_gpu = False
        if fixed_intrinsics:
            ba = opts.mapper.bundle_adjustment
            ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False
        recs = pycolmap.global_mapping(str(database), str(image_dir), str(tmp), options=opts)
    else:
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = num_threads
        opts.random_seed = seed
        if fixed_intrinsics:
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
        recs = pycolmap.incremental_mapping(str(database), str(image_dir), str(tmp), options=opts)
    elapsed = time.perf_counter() - t0
    models = sorted(((int(k), r) for k, r in recs.items()), key=lambda kr: (-kr[1].num_reg_images(), kr[0]))
    # COLMAP numbers models in the order it found them; renumber so that sparse/0 is the largest
    final = sparse_dir.with_name(sparse_dir.name + ".new")
    if final.exists():
        shutil.rmtree(final)
    final.mkdir()
    stats = []
    for new_idx, (_, rec) in enumerate(models):
        d = final / str(new_idx)
        d.mkdir()
        rec.write(str(d))
        stats.append(dict(reconstruction_stats(rec), path=str(sparse_dir / str(new_idx))))
    result = {"mapper": mapper, "time_s": elapsed, "models": stats, "best": 0 if stats else None}
    from ..evaluation.meta import write_json

    write_json(final / "mapping.json", dict(record or {}, result=result))
    shutil.rmtree(tmp)
    if sparse_dir.exists():
        shutil.rmtree(sparse_dir)
    os.replace(final, sparse_dir)
    return result


def reconstruction_stats(rec: Any) -> dict:
    """Registered images, 3-D points, observations, mean track length, mean reprojection error (px) of a model."""
    return {"registered": int(rec.num_reg_images()), "images": int(rec.num_images()),
            "points3D": int(rec.num_points3D()), "observations": int(rec.compute_num_observations()),
            "mean_track_length": float(rec.compute_mean_track_length()),
            "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "registered_names": sorted(rec.image(i).name for i in rec.reg_image_ids())}


def map_main(conf: SfmConfig, paths: SfmPaths, fixed_intrinsics: bool | None = None) -> dict:
    """Stage 3: mapping from the database. A model in ``paths.sparse`` made from a database with the same
    :func:`database_summary` and the same mapping settings is reused (``reused: True``); otherwise the mapper runs
    and the previous model is replaced when it is done."""
    fixed = conf.camera is not None if fixed_intrinsics is None else bool(fixed_intrinsics)
    key = {"database": database_summary(paths.database), "settings": dict(conf.mapping_settings(), fixed=fixed)}
    mapper, rule = resolve_mapper(conf.mapper, key["database"]["images"])
    record: dict = {"mapper_rule": rule}
    with peak_memory(record):
        try:
            old = json.loads(paths.mapping_record.read_text()) if paths.mapping_record.is_file() else None
        except (OSError, json.JSONDecodeError):
            old = None
        if old and {k: old.get(k) for k in key} == key and "result" in old and all(
                Path(m["path"]).is_dir() for m in old["result"]["models"]):
            say(conf, f"[3/3] mapping ({mapper}): the model in {paths.sparse} is up to date (same database and "
                      "settings); reused")
            result = dict(old["result"], reused=True, time_s=0.0)
        else:
            say(conf, f"[3/3] mapping (pycolmap.{mapper}_mapping; {rule})")
            result = dict(run_mapping(paths.database, paths.image_dir, paths.sparse, mapper=mapper,
                                      num_threads=conf.num_threads, seed=conf.seed,
                                      fixed_intrinsics=fixed, record=key), reused=False)
    return dict(result, **record)


def models_summary(mapping: dict, num_images: int) -> str:
    """``"8/8 images registered, 4,321 points"`` or, for several models, ``"3 models: 25 + 8 + 2 of 40 images
    registered, ..."``."""
    models = mapping.get("models") or []
    if not models:
        return f"0/{num_images} images registered (no model)"
    pts = sum(m["points3D"] for m in models)
    if len(models) == 1:
        return f"{models[0]['registered']}/{num_images} images registered, {pts:,} points"
    return (f"{len(models)} models: {' + '.join(str(m['registered']) for m in models)} of {num_images} images "
            f"registered, {pts:,} points")
