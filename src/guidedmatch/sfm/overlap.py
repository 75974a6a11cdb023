"""Extraction and matching overlapped (``SfmConfig.pipeline``): a pair is matched as soon as both its images'
features are in the database, while the other images are still being extracted.

:func:`overlap_plan` says whether a run can overlap the two stages and why (not): the pair list must be computable
from the images written so far -- ``exhaustive``, ``sequential[:K]``, pairs files and their ``+`` unions are;
``retrieval`` is not (its visual words are learnt from every image's descriptors, and its shortlist ranks each image
against all others), nor is ``pairs="auto"`` above :data:`~guidedmatch.sfm.stages.AUTO_EXHAUSTIVE_MAX_IMAGES`
images (retrieval there). The default extractor only (OpenCV SIFT, :mod:`guidedmatch.extraction`), and matching in
this process (the in-process collection engine: ``workers`` None or 0, no ``scheduler``).

:func:`extract_and_match` is the overlapped stage 1 + most of stage 2, in one thread pool of this process:

* **one reader of each image**: every image is read and decoded once, by its extraction task
  (:func:`guidedmatch.extraction.extract_image`); matching reads the features back from the database (the same
  bytes the staged path reads), never the image;
* **one writer** (this thread): images are written in name order (:class:`~guidedmatch.extraction.OrderedImageWriter`,
  so image ids are those of the staged run), pairs in completion order (:class:`~guidedmatch.collection.streaming.
  PairStream`), each in its own transaction -- a kill -9 leaves complete images and complete pairs, and a rerun
  skips both;
* **when a pair is ready**: images are resolved in name order (written, damaged, or already in the database); once
  the first ``k`` names are all resolved, the pairs of the spec among the usable ones of them are final -- for
  ``sequential`` because every image between two of them in name order is among them, for ``exhaustive`` and pairs
  files trivially -- and oriented as the staged run orients them (images in image id order);
* **CPU**: one pool of ``max(extraction workers, matching threads)`` threads, the extraction first: up to 2 images
  per worker are queued (as :func:`~guidedmatch.extraction.extract_to_database` keeps them, so a thread never waits
  for this thread to write an image), and a pair is submitted only to a thread no image is queued for -- in practice
  the extraction's tail, when fewer images than threads remain, then every thread. Memory as in the staged
  extraction: at most ``2 x workers`` images decoded or being detected, at most ``2 x workers`` finished images'
  features waiting for an earlier image to be written, at most one pair per thread, and the loaded images of the
  matching bounded by ``CollectionConfig.cache_mb``. Measured and not kept: pairs in a pool of their own (2
  threads) beside the extraction's, matched as soon as both images are written -- on Herz-Jesus-P8 15-21 of the 28
  pairs were matched during the extraction, but the run was no faster than the staged one (median 36.2 s vs 31.9 s,
  3 alternating runs each, load 4-6 on 2 cores: the pairs take CPU from the extraction) and peaked at 3.4 GB
  instead of 3.0 (``tools/ab_pipeline.py``; docs/sfm.md);
* the stage's remainder (:func:`~guidedmatch.sfm.stages.match_main`) then runs as in the staged path over the final
  pair list: it finds every pair done (or matches what is not, e.g. after a resume with other images) and keeps at
  most ``max_inliers_per_pair`` inliers per pair.
"""
from __future__ import annotations

import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path

import numpy as np

from ..errors import ConfigError, ImageReadError
from .config import COLMAP_MAX_IMAGE_SIZE, SfmConfig, SfmPaths, parse_camera, say

__all__ = ["PIPELINE_SETTINGS", "overlap_plan", "extract_and_match", "prefix_pairs"]

#: ``SfmConfig.pipeline`` values: overlap when the run allows it (``auto``), always (``on``: refused when it cannot),
#: never (``off``: the stages one after the other)
PIPELINE_SETTINGS = ("auto", "on", "off")


def overlap_plan(conf: SfmConfig, names: list[str]) -> tuple[bool, str, str | None]:
    """``(overlap, why, pair spec)`` for a run over ``names`` (the pair spec that will be matched, ``"auto"``
    resolved, when it overlaps). ``pipeline="on"`` where the stages cannot overlap: ConfigError naming the reason.

    >>> overlap_plan(SfmConfig(pipeline="auto"), ["a.jpg", "b.jpg"])[:2]
    (True, 'pipeline=auto: pairs exhaustive are known as images are written')
    >>> ok, why, _ = overlap_plan(SfmConfig(pipeline="auto", pairs="retrieval:5"), ["a.jpg", "b.jpg"])
    >>> ok, why[:40]
    (False, "pairs 'retrieval:5' has a retrieval part")
    """
    from ..collection.pairs import has_retrieval
    from .stages import AUTO_EXHAUSTIVE_MAX_IMAGES

    if conf.pipeline == "off":
        return False, "pipeline=off", None
    spec, why_not = conf.pairs, None
    if conf.detector != "sift":
        why_not = (f"detector {conf.detector!r} extracts in worker processes that write the database themselves; "
                   "the overlap is implemented for the default detector 'sift'")
    elif conf.workers not in (None, 0) or conf.scheduler is not None:
        why_not = ("matching on worker processes or a Dask cluster (workers >= 1 or scheduler); the overlap matches "
                   "in this process")
    elif spec == "auto":
        if len(names) > AUTO_EXHAUSTIVE_MAX_IMAGES:
            why_not = (f"pairs auto with {len(names)} images > {AUTO_EXHAUSTIVE_MAX_IMAGES}: retrieval pairs, whose "
                       "visual words and shortlist need every image's features first")
        spec = "exhaustive"
    elif has_retrieval(spec):
        why_not = (f"pairs {spec!r} has a retrieval part: its visual words and shortlist need every image's features "
                   "first")
    if why_not is not None:
        if conf.pipeline == "on":
            raise ConfigError(f"pipeline='on' but extraction and matching cannot overlap: {why_not}; use "
                              "pipeline='auto' or 'off'")
        return False, why_not, None
    return True, f"pipeline={conf.pipeline}: pairs {spec} are known as images are written", spec


def _spec_parts(spec: str) -> list:
    """The parts of a spec, a pairs file read once: ``[("spec", part) | ("file", PairList)]``."""
    from ..collection.pairs import read_pairs_file

    if Path(spec).exists() or "+" not in spec:
        parts = [spec]
    else:
        parts = [p.strip() for p in spec.split("+")]
    return [("file", read_pairs_file(p, None)) if Path(p).exists() else ("spec", p) for p in parts]


def prefix_pairs(parts: list, usable: list[str]) -> list[tuple[str, str]]:
    """The pairs of the spec ``parts`` (:func:`_spec_parts`) among ``usable`` (images in image id order), as
    :func:`guidedmatch.collection.pairs.pairs_from_spec` gives them over the final image list: the same parts in
    the same order, each pair kept in its first orientation.

    >>> prefix_pairs([("spec", "sequential:1"), ("spec", "exhaustive")], ["b", "a", "c"])
    [('a', 'b'), ('b', 'c'), ('b', 'a'), ('b', 'c'), ('a', 'c')]
    """
    from ..collection.pairs import pairs_from_spec

    have = set(usable)
    out: list[tuple[str, str]] = []
    for kind, part in parts:
        if kind == "file":
            out += [p for p in part.pairs if p[0] in have and p[1] in have]
        else:
            out += list(pairs_from_spec(part, usable).pairs)
    return out


def _read_images(db) -> dict[str, tuple[int, int]]:
    """``{name: (image id, keypoints)}`` of an open pycolmap database."""
    return {im.name: (int(im.image_id), int(db.num_keypoints_for_image(im.image_id))
                      if db.exists_keypoints(im.image_id) and db.exists_descriptors(im.image_id) else 0)
            for im in db.read_all_images()}


def extract_and_match(conf: SfmConfig, paths: SfmPaths, names: list[str], spec: str) -> tuple[dict, dict]:
    """Stage 1 with the pairs of ``spec`` matched as their images are written (module docstring). Returns
    ``(extraction record, early)``: the record as :func:`~guidedmatch.sfm.stages.extract_main`'s (``time_s`` up to
    the last image written) and ``early`` = ``{"report": CollectionReport of the pairs matched here, "pairs",
    "during_extraction" (pairs finished before the last image was written), "extraction_end_s", "end_s"
    (seconds from the start), "first_pair_s"}``."""
    import cv2

    from ..collection.config import CollectionConfig
    from ..collection.image_folder import decode_check
    from ..collection.sink_base import check_database_space, open_pycolmap_database
    from ..collection.sinks import ColmapSink
    from ..collection.sources import ColmapSource
    from ..collection.streaming import PairStream
    from ..extraction import ExtractionConfig, OrderedImageWriter, extract_image
    from .stages import _db_image_names, _set_known_camera, peak_memory

    record: dict = {}
    early: dict = {}
    t0 = time.perf_counter()
    with peak_memory(record):
        before_counts = _db_image_names(paths.database) if paths.database.exists() else {}
        todo = [n for n in names if before_counts.get(n, 0) == 0]
        workers = max(1, (os.cpu_count() or 1) if conf.num_threads == -1 else conf.num_threads)
        cconf = CollectionConfig(mode=conf.mode, matcher=conf.matcher_for(len(names)), workers=0, progress=False,
                                 log_path=str(paths.pair_log), shared_quantizer="off")  # images still arriving
        from ..collection.planning import _usable_cores

        threads = cconf.threads or _usable_cores()
        say(conf, f"[1/3] extraction ({conf.detector}) overlapped with [2/3] matching ({conf.mode}, geometry "
                  f"{conf.geometry}, pairs {spec}): {len(todo)} image(s) to extract, {len(names) - len(todo)} reused")
        if conf.bad_images == "refuse" and todo:
            decode_check(paths.image_dir, todo)
        cam = parse_camera(conf.camera)
        econf = ExtractionConfig(
            max_features=conf.max_features or 8192, max_image_size=conf.max_image_size or COLMAP_MAX_IMAGE_SIZE,
            peak_threshold=conf.peak_threshold or 0.02 / 3, camera_model=cam[0] if cam else conf.camera_model,
            single_camera=conf.single_camera or cam is not None, workers=workers, on_error="skip",
            progress=conf.progress)
        parts = _spec_parts(spec)
        check_database_space(paths.database, 0)  # opening a new database writes its schema
        db = open_pycolmap_database(paths.database)
        stream = source = sink = None
        slots = max(workers, threads)
        pool = ThreadPoolExecutor(slots, thread_name_prefix="guidedmatch-sfm")
        old_cv = cv2.getNumThreads()
        cv2.setNumThreads(1)  # the images (and pairs) give the parallelism
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="SIFT", unit="img", disable=not conf.progress, file=sys.stderr,
                   dynamic_ncols=True)
        limits = None
        t_ext_end = None
        during = 0
        try:
            writer = OrderedImageWriter(db, econf, paths.database, todo, bar=bar)
            known = _read_images(db)                       # name -> (image id, keypoints): written and usable
            status = {n: known[n] for n in names if known.get(n, (0, 0))[1] > 0 and n not in todo}
            k = 0                                          # names[:k] are resolved
            usable: list[tuple[int, str]] = []             # (image id, name) of the usable images of names[:k]
            pending = iter(todo)
            ext: dict = {}                                 # future -> name

            def advance() -> None:
                nonlocal k, stream, source, sink
                grew = False
                while k < len(names) and (names[k] in status or names[k] in bad):
                    if names[k] in status:
                        usable.append((status[names[k]][0], names[k]))
                        grew = True
                    k += 1
                if not grew or len(usable) < 2:
                    return
                order = [n for _, n in sorted(usable)]
                if stream is None:
                    source = ColmapSource(paths.database)
                    sink = ColmapSink(paths.database, geometry=conf.geometry)
                    stream = PairStream(source, sink, cconf)
                else:
                    for n in order:
                        if n not in source:
                            iid, nkp = status[n]
                            source.add_image(n, iid, sizes[n], nkp)
                            sink.add_image(n, iid, nkp)
                stream.add(prefix_pairs(parts, order))

            bad: set[str] = set()
            sizes: dict[str, tuple[int, int]] = {}

            def fill() -> None:
                nonlocal limits
                # images: as many queued as extract_to_database keeps (2 per worker: a thread never waits for this
                # thread to write the previous image), and at most as many finished ones waiting for an earlier one
                while len(ext) < 2 * workers and writer.waiting < 2 * workers:
                    name = next(pending, None)
                    if name is None:
                        break
                    ext[pool.submit(extract_image, paths.image_dir, name, econf)] = name
                # pairs: only the threads no image is queued for (the pool runs its queue in order)
                while stream is not None and stream.waiting and len(ext) + len(stream.inflight) < slots:
                    if limits is None:
                        # the matcher's libraries (faiss, Numba) load here, in this thread, when a thread is free
                        limits = PairStream.thread_limits()
                    stream.submit(pool)

            advance()
            if not todo:
                t_ext_end = time.perf_counter()
            fill()
            while ext or (stream is not None and stream.inflight):
                futs = list(ext) + (list(stream.inflight) if stream is not None else [])
                finished, _ = wait(futs, return_when=FIRST_COMPLETED)
                for fut in finished:
                    if fut in ext:
                        name = ext.pop(fut)
                        try:
                            item = fut.result()
                        except ImageReadError as exc:
                            item = (name, exc)
                        bar.update(1)
                        for n, iid, f in writer.add(item):
                            if iid is None or len(f.keypoints) == 0:
                                bad.add(n)
                            else:
                                status[n] = (iid, len(f.keypoints))
                                sizes[n] = (f.width, f.height)
                        if writer.next == len(todo) and t_ext_end is None:
                            t_ext_end = time.perf_counter()
                            during = stream.writer.done if stream is not None else 0
                    else:
                        stream.finish(fut)
                        bar.set_postfix_str(f"{stream.writer.done} pairs matched", refresh=False)
                advance()
                fill()
        except BaseException:
            for fut in list(ext) + (list(stream.inflight) if stream is not None else []):
                fut.cancel()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            if limits is not None:
                limits.close()
            cv2.setNumThreads(old_cv)
            bar.close()
            db.close()
            if stream is not None:
                stream.close()
            for h in (sink, source):
                if h is not None:
                    h.close()
        t_end = time.perf_counter()
        if cam is not None:
            _set_known_camera(paths.database, cam)
        after = _db_image_names(paths.database)
    skipped = list(writer.failed) + [{"name": n, "reason": "no features detected (a blank or too small image?)"}
                                     for n in names if n in after and after[n] == 0]
    counts = [after[n] for n in names if after.get(n, 0) > 0]
    t_ext_end = t_ext_end or t_end
    record.update({"time_s": t_ext_end - t0, "detector": conf.detector,
                   "extracted": sum(1 for n in todo if after.get(n, 0) > 0), "reused": len(names) - len(todo),
                   "skipped": skipped, "failed": [s["name"] for s in skipped], "workers": workers,
                   "overlapped_with_matching": True,
                   "keypoints": {"total": int(sum(counts)), "min": int(min(counts, default=0)),
                                 "median": float(np.median(counts)) if counts else 0.0,
                                 "max": int(max(counts, default=0))}})
    for s in skipped:
        say(conf, f"      skipped {s['name']}: {s['reason']}")
    if stream is not None:
        rep = stream.report(slots, f"overlapped with the extraction: {slots} threads shared with it, the extraction "
                                   "first")
        early = {"report": rep, "pairs": len(stream.added), "oriented": list(stream.pairs), "during_extraction": during,
                 "first_pair_s": (stream.t_first - t0) if stream.t_first else None,
                 "extraction_end_s": t_ext_end - t0, "end_s": t_end - t0}
    else:
        early = {"report": None, "pairs": 0, "oriented": [], "during_extraction": 0, "first_pair_s": None,
                 "extraction_end_s": t_ext_end - t0, "end_s": t_end - t0}
    return record, early
