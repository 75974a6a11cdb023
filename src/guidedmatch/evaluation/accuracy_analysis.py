"""Candidate causes of a pose-accuracy gap between two match sets, each tested by removing or restoring it.

Every variant is a copy of a matched database (``ours`` or ``colmap`` of :mod:`.bench_accuracy`, same keypoints)
whose two-view geometries are rewritten, then mapped and scored like the base methods:

* ``ours-added``: our inliers that COLMAP's matcher also verified (same keypoint pair), nothing else -- removes the
  correspondences (and the pairs) we add;
* ``colmap+added``: COLMAP's inliers plus ours on keypoints COLMAP left unmatched (and our pairs COLMAP did not
  verify) -- restores them on COLMAP's side;
* ``ours-epi``: our inliers within 4 px of the reference epipolar lines (an oracle: wrong matches removed);
* ``ours-epi1``: within 1 px (an oracle of localisation precision: the least precise third removed, about);
* ``ours-judged``: our inliers not labelled wrong or uncertain (> 3 px) by the model mapped from COLMAP's own matches
  (a multi-view oracle);
* ``ours+rejected``: ours plus COLMAP's geometries of the pairs COLMAP verified and we did not (our verdict
  overruled);
* ``colmap-epi``: COLMAP's inliers within 4 px of the reference epipolar lines (the oracle on the peer's side).

:func:`rejected_pairs_table` counts the pairs COLMAP verifies and we do not, by inlier count and camera angle, and
says how many of their inliers agree with the reference; :func:`track_stats` describes a model's tracks;
:func:`added_stats` compares the inliers we add with those both verify (scale ratio, descriptor distance, reference
epipolar distance).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

#: variant -> (base method, what it does)
VARIANTS = {
    "ours-added": ("ours", "our inliers that COLMAP also verified, only"),
    "colmap+added": ("colmap", "COLMAP's inliers plus ours on keypoints COLMAP left free"),
    "ours-epi": ("ours", "our inliers within 4 px of the reference epipolar lines (oracle)"),
    "ours-epi1": ("ours", "our inliers within 1 px of the reference epipolar lines (oracle)"),
    "ours-judged": ("ours", "our inliers consistent (<= 3 px) with COLMAP's seed-0 model (oracle)"),
    "ours+rejected": ("ours", "plus COLMAP's geometry of every pair COLMAP verified and we did not"),
    "colmap-epi": ("colmap", "COLMAP's inliers within 4 px of the reference epipolar lines (oracle)"),
}


def read_geometries(db_path: Path) -> dict[tuple[int, int], np.ndarray]:
    """``{(image_id1, image_id2): (M, 2) int64 inlier matches}`` of every two-view geometry with inliers."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        out = {}
        pids, counts = db.read_two_view_geometry_num_inliers()
        for pid, n in zip(pids, counts):
            if int(n):
                i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
                out[(int(i1), int(i2))] = np.asarray(db.read_two_view_geometry(i1, i2).inlier_matches,
                                                     np.int64).reshape(-1, 2)
        return out
    finally:
        db.close()


def rewrite_geometries(db_path: Path, inliers: dict[tuple[int, int], np.ndarray], donor: Path | None = None) -> dict:
    """Set the inlier matches of each pair of ``inliers`` in ``db_path`` (an empty array: the mapper ignores the
    pair); a pair without a geometry in ``db_path`` takes the donor database's geometry (F / E / H, configuration).
    Returns ``{"pairs_changed", "inliers"}``."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    dd = pycolmap.Database.open(str(donor)) if donor is not None else None
    changed = total = 0
    try:
        with pycolmap.DatabaseTransaction(db):
            for (i1, i2), m in inliers.items():
                m = np.ascontiguousarray(np.asarray(m, np.int64).reshape(-1, 2), dtype=np.uint32)
                total += len(m)
                if db.exists_two_view_geometry(i1, i2):
                    g = db.read_two_view_geometry(i1, i2)
                    old = np.asarray(g.inlier_matches).reshape(-1, 2)
                    if old.shape == m.shape and np.array_equal(old, m):
                        continue
                    g.inlier_matches = m
                    db.update_two_view_geometry(i1, i2, g)
                else:
                    if dd is None or not dd.exists_two_view_geometry(i1, i2):
                        raise ValueError(f"pair {i1} {i2}: no geometry to take")
                    g = dd.read_two_view_geometry(i1, i2)
                    g.inlier_matches = m
                    db.write_two_view_geometry(i1, i2, g)
                changed += 1
    finally:
        db.close()
        if dd is not None:
            dd.close()
    return {"pairs_changed": changed, "inliers": total}


def _keys(m: np.ndarray) -> np.ndarray:
    return m[:, 0] * (1 << 32) + m[:, 1]


def intersect_inliers(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of ``a`` that are also rows of ``b`` (``(M, 2)`` keypoint index pairs).

    >>> intersect_inliers(np.array([[1, 2], [3, 4], [5, 6]]), np.array([[3, 4], [1, 9]])).tolist()
    [[3, 4]]
    """
    return a[np.isin(_keys(a), _keys(b))]


def union_free(base: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """``base`` plus the rows of ``extra`` whose keypoints are unmatched in ``base`` on both sides (no keypoint
    gets two partners).

    >>> union_free(np.array([[1, 2]]), np.array([[1, 3], [4, 2], [5, 6]])).tolist()
    [[1, 2], [5, 6]]
    """
    free = ~np.isin(extra[:, 0], base[:, 0]) & ~np.isin(extra[:, 1], base[:, 1])
    return np.concatenate([base, extra[free]])


def _epi_filter(db_path: Path, cache: Path, px: float) -> dict:
    from .bench_accuracy import distortion, epipolar_distances, reference_cameras, undistort
    import pycolmap

    root, scene = _scene_of(cache)
    ref, dist = reference_cameras(root, scene), distortion(root, scene)
    geoms = read_geometries(db_path)
    db = pycolmap.Database.open(str(db_path))
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        kps = {i: undistort(np.asarray(db.read_keypoints(i), np.float64), ref[n].K, dist) for i, n in names.items()}
    finally:
        db.close()
    out = {}
    for (i1, i2), m in geoms.items():
        d = epipolar_distances(kps[i1][m[:, 0]], kps[i2][m[:, 1]], ref[names[i1]], ref[names[i2]])
        out[(i1, i2)] = m[d <= px]
    return out


def _scene_of(cache: Path) -> tuple[Path, str]:
    """(data root, scene) of a scene's cache folder, from the ``scene.json`` the driver leaves there."""
    import json

    info = json.loads((cache / "scene.json").read_text())
    return Path(info["root"]), info["scene"]


def make_variant(method: str, cache: Path, db: Path, threads: int) -> dict:
    """Build variant ``method``'s database at ``db`` (a copy of its base's, rewritten); the record of
    :func:`guidedmatch.evaluation.bench_accuracy.match` (``match_s``: the base's matching time; the rewrite is an
    analysis, not a method)."""
    import time

    from .bench_accuracy import match

    if method not in VARIANTS:
        raise KeyError(method)
    base = VARIANTS[method][0]
    brec = match(base, cache, threads)
    shutil.copyfile(cache / base / "database.db", db)
    t0 = time.perf_counter()
    geoms = read_geometries(db)
    if method in ("ours-added", "colmap+added", "ours+rejected"):
        other = read_geometries(cache / ("colmap" if base == "ours" else "ours") / "database.db")
    if method == "ours-added":
        new = {p: intersect_inliers(m, other.get(p, np.zeros((0, 2), np.int64))) for p, m in geoms.items()}
        donor = None
    elif method == "colmap+added":
        new = {p: union_free(geoms.get(p, np.zeros((0, 2), np.int64)), m) for p, m in other.items()}
        donor = cache / "ours" / "database.db"
    elif method == "ours+rejected":
        new = {p: m for p, m in other.items() if p not in geoms}
        donor = cache / "colmap" / "database.db"
    elif method in ("ours-epi", "colmap-epi", "ours-epi1"):
        new = _epi_filter(db, cache, 1.0 if method == "ours-epi1" else 4.0)
        donor = None
    elif method == "ours-judged":
        new, donor = _judged(db, cache / "colmap" / "seed0" / "sparse" / "0"), None
    info = rewrite_geometries(db, new, donor)
    return {"method": method, "match_s": brec["match_s"], "variant_of": base, "what": VARIANTS[method][1],
            "rewrite": dict(info, time_s=time.perf_counter() - t0)}


def _judged(db_path: Path, model: Path, ok_px: float = 3.0) -> dict:
    import pycolmap

    from .consistency import ModelJudge

    judge = ModelJudge(model)
    geoms = read_geometries(db_path)
    db = pycolmap.Database.open(str(db_path))
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        kps = {i: np.asarray(db.read_keypoints(i)) for i, n in names.items() if judge.has(n)}
    finally:
        db.close()
    out = {}
    for (i1, i2), m in geoms.items():
        if i1 in kps and i2 in kps:
            e = judge.errors(names[i1], names[i2], m, kps[i1], kps[i2])
            out[(i1, i2)] = m[~(e > ok_px)]   # unlabelled (NaN) kept: the judge cannot see them
    return out
