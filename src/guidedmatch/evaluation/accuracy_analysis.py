"""Candidate causes of a pose-accuracy gap between two match sets, each tested by removing or restoring it.

Every variant is a copy of a matched database (``ours`` or ``colmap`` of :mod:`.bench_accuracy`, same keypoints)
whose two-view geometries are rewritten, then mapped and scored like the base methods:

* ``ours-added``: our inliers that COLMAP's matcher also verified (same keypoint pair), nothing else -- removes the
  correspondences (and the pairs) we add;
* ``colmap+added``: COLMAP's inliers plus ours on keypoints COLMAP left unmatched (and our pairs COLMAP did not
  verify) -- restores them on COLMAP's side;
* ``ours+lacked``: ours plus COLMAP's inliers on keypoints we left unmatched (and COLMAP's pairs we did not verify)
  -- restores what we lack on our side (an oracle);
* ``ours-epi``: our inliers within 4 px of the reference epipolar lines (an oracle: wrong matches removed);
* ``ours-epi1``: within 1 px (an oracle of localisation precision: the least precise third removed, about);
* ``ours-judged``: our inliers not labelled wrong or uncertain (> 3 px) by the model mapped from COLMAP's own matches
  (a multi-view oracle);
* ``ours+rejected``: ours plus COLMAP's geometries of the pairs COLMAP verified and we did not (our verdict
  overruled);
* ``colmap-epi``: COLMAP's inliers within 4 px of the reference epipolar lines (the oracle on the peer's side);
* ``ours-f1``: our inliers within 1 px of the epipolar lines of the pair's own fundamental matrix (no oracle: a
  tighter two-view threshold);
* ``ours-scale``: our inliers whose keypoint scale ratio is within a factor 2^0.5 of the pair's median ratio (no
  oracle); ``ours+rejected-scale``: the same on ``ours+rejected``;
* ``ours-distinct``: our inliers that pass the exact ratio test against all of image 2 (the partner is the nearest
  neighbour, at < 0.8 of the second's distance: COLMAP's matcher's test; a pair left with < 15 keeps all -- no
  oracle); ``ours-nn``: our inliers whose partner is the nearest neighbour in all of image 2 (no ratio test);
* ``ours-3view``: our inliers a third view confirms; ``ours-contra``: our inliers minus those a third view
  contradicts (:mod:`guidedmatch.collection.rescue`; no oracle).

:func:`rejected_pairs_table` counts the pairs COLMAP verifies and we do not, by inlier count and camera angle, and
says how many of their inliers agree with the reference; :func:`track_stats` describes a model's tracks;
:func:`added_stats` compares the inliers we add with those both verify (scale ratio, descriptor distance, reference
epipolar distance).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from .meta import default_cache

#: variant -> (base method, what it does)
VARIANTS = {
    "ours-added": ("ours", "our inliers that COLMAP also verified, only"),
    "colmap+added": ("colmap", "COLMAP's inliers plus ours on keypoints COLMAP left free"),
    "ours+lacked": ("ours", "ours plus COLMAP's inliers on keypoints we left free (oracle)"),
    "ours-epi": ("ours", "our inliers within 4 px of the reference epipolar lines (oracle)"),
    "ours-epi1": ("ours", "our inliers within 1 px of the reference epipolar lines (oracle)"),
    "ours-judged": ("ours", "our inliers consistent (<= 3 px) with COLMAP's seed-0 model (oracle)"),
    "ours+rejected": ("ours", "plus COLMAP's geometry of every pair COLMAP verified and we did not"),
    "colmap-epi": ("colmap", "COLMAP's inliers within 4 px of the reference epipolar lines (oracle)"),
    "ours-f1": ("ours", "our inliers within 1 px of the epipolar lines of our own two-view F"),
    "ours-scale": ("ours", "our inliers whose scale ratio is within 2^0.5 of the pair's median ratio"),
    "ours+rejected-scale": ("ours+rejected", "ours+rejected, then the ours-scale filter"),
    "ours-distinct": ("ours", "our inliers that pass the ratio test (0.8) against all of image 2, no oracle"),
    "ours-nn": ("ours", "our inliers whose partner is the nearest neighbour in all of image 2, no oracle"),
    "ours-contra": ("ours", "our inliers minus those a third view contradicts (collection.rescue."
                    "contradicted_by_third_view), no oracle"),
    "ours-3view": ("ours", "our inliers confirmed by a third view (collection.rescue.confirmed_by_third_view), no oracle"),
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
                here = db.exists_two_view_geometry(i1, i2)
                g = db.read_two_view_geometry(i1, i2) if here else None
                if here and len(g.inlier_matches) == 0 and dd is not None and dd.exists_two_view_geometry(i1, i2):
                    here = False   # a rejected pair (no inliers): take the donor's whole geometry, configuration too
                    db.delete_two_view_geometry(i1, i2)
                if here:
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
    from .accuracy_scenes import distortion, reference_cameras
    from .consistency import epipolar_distances, undistort
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


def make_variant(method: str, cache: Path, db: Path, threads: int, *, match) -> dict:
    """Build variant ``method``'s database at ``db`` (a copy of its base's, rewritten); the record of
    :func:`guidedmatch.evaluation.bench_accuracy.match` (``match_s``: the base's matching time; the rewrite is an
    analysis, not a method). ``match``: the benchmark's ``match(method, cache, threads)``, which builds the base."""
    import time

    from .accuracy_scenes import copy_database

    if method not in VARIANTS:
        raise KeyError(method)
    base = VARIANTS[method][0]
    brec = match(base, cache, threads)
    copy_database(cache / base.replace("+", "_") / "database.db", db)
    t0 = time.perf_counter()
    geoms = read_geometries(db)
    if method in ("ours-added", "colmap+added", "ours+rejected", "ours+lacked"):
        other = read_geometries(cache / ("colmap" if base == "ours" else "ours") / "database.db")
    if method == "ours-added":
        new = {p: intersect_inliers(m, other.get(p, np.zeros((0, 2), np.int64))) for p, m in geoms.items()}
        donor = None
    elif method in ("colmap+added", "ours+lacked"):
        new = {p: union_free(geoms.get(p, np.zeros((0, 2), np.int64)), m) for p, m in other.items()}
        donor = cache / ("ours" if base == "colmap" else "colmap") / "database.db"
    elif method == "ours+rejected":
        new = {p: m for p, m in other.items() if p not in geoms}
        donor = cache / "colmap" / "database.db"
    elif method in ("ours-epi", "colmap-epi", "ours-epi1"):
        new = _epi_filter(db, cache, 1.0 if method == "ours-epi1" else 4.0)
        donor = None
    elif method in ("ours-3view", "ours-contra"):
        new, donor = _three_view(db, contra=method == "ours-contra"), None
    elif method in ("ours-f1", "ours-scale", "ours+rejected-scale"):
        new, donor = _self_filter(db, "ours-scale" if method.endswith("-scale") else method), None
    elif method in ("ours-distinct", "ours-nn"):
        new, donor = _global_filter(db, ratio=0.8 if method == "ours-distinct" else None), None
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


# --------------------------------------------------------------------------- measurements
INLIER_BINS = (15, 30, 100, 300)
ANGLE_BINS = (0, 30, 60, 90, 180)


def _bin(v, edges):
    for lo, hi in zip(edges[:-1], list(edges[1:])):
        if lo <= v < hi:
            return f"{lo}-{hi}"
    return f">={edges[-1]}" if v >= edges[-1] else f"<{edges[0]}"


def rejected_pairs_table(colmap_pairs: list[dict], our_pairs: list[dict], true_share: float = 0.5) -> dict:
    """The pairs COLMAP verifies (``pairs.json`` rows of :func:`.bench_accuracy.pair_table`) that we do not, by
    COLMAP's inlier count and by the reference cameras' relative rotation; a pair is *true* when at least
    ``true_share`` of COLMAP's inliers (and >= 15) lie within 4 px of the reference epipolar lines.

    >>> c = [dict(name1="a", name2="b", inliers=40, epi_ok=0, angle_deg=10.0),
    ...      dict(name1="a", name2="c", inliers=120, epi_ok=110, angle_deg=95.0), dict(name1="b", name2="c",
    ...      inliers=50, epi_ok=50, angle_deg=5.0)]
    >>> t = rejected_pairs_table(c, [dict(name1="b", name2="c", inliers=80, epi_ok=80, angle_deg=5.0)])
    >>> t["rejected"], t["rejected_true"], t["by_inliers"]["30-100"], t["by_angle"]["90-180"]
    (2, 1, {'pairs': 1, 'true': 0}, {'pairs': 1, 'true': 1})
    """
    ours = {(p["name1"], p["name2"]) for p in our_pairs}
    rej = [p for p in colmap_pairs if (p["name1"], p["name2"]) not in ours]
    is_true = [p["epi_ok"] >= max(15, true_share * p["inliers"]) for p in rej]
    out = {"colmap_verified": len(colmap_pairs), "ours_verified": len(our_pairs), "rejected": len(rej),
           "rejected_true": int(sum(is_true)), "by_inliers": {}, "by_angle": {},
           "pairs": [dict(p, true=bool(t)) for p, t in zip(rej, is_true)],
           "ours_only": len(ours - {(p["name1"], p["name2"]) for p in colmap_pairs})}
    for key, edges, field in (("by_inliers", INLIER_BINS, "inliers"), ("by_angle", ANGLE_BINS, "angle_deg")):
        for p, t in zip(rej, is_true):
            b = out[key].setdefault(_bin(p[field], edges), {"pairs": 0, "true": 0})
            b["pairs"] += 1
            b["true"] += int(t)
    return out


def track_stats(model: Path, long_range: int | None = None) -> dict:
    """Tracks of a model: points, mean / median track length, median reprojection error, and how the image pairs
    ``long_range`` or more apart in name order (default a quarter of the registered images) are tied: share of
    points seen by such a pair, median co-visible points over those pairs."""
    import pycolmap
    from scipy import sparse

    rec = pycolmap.Reconstruction(str(model))
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.image(i).name)
    pos = {i: k for k, i in enumerate(ids)}
    n = len(ids)
    L = long_range or max(2, n // 4)
    rows, cols, lens, errs, spans = [], [], [], [], []
    for k, (pid, p) in enumerate(rec.points3D.items()):
        imgs = sorted({pos[e.image_id] for e in p.track.elements if e.image_id in pos})
        rows += [k] * len(imgs)
        cols += imgs
        lens.append(p.track.length())
        errs.append(p.error)
        spans.append(imgs[-1] - imgs[0] if imgs else 0)
    B = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(lens), n))
    C = (B.T @ B).toarray()
    iu = np.triu_indices(n, L)
    far = C[iu]
    return {"images": n, "points": len(lens), "mean_track_length": float(np.mean(lens)) if lens else 0.0,
            "median_track_length": float(np.median(lens)) if lens else 0.0,
            "median_reprojection_px": float(np.median(errs)) if errs else float("nan"),
            "long_range": L, "points_spanning_long_range": float(np.mean(np.array(spans) >= L)) if spans else 0.0,
            "long_range_pairs": int(len(far)), "long_range_pairs_tied": int((far > 0).sum()),
            "median_covisible_long_range": float(np.median(far)) if len(far) else 0.0}


def added_stats(cache: Path, px: float = 4.0) -> dict:
    """Our inliers that COLMAP's matcher did not verify, against those both verified, on the pairs both verified:
    reference epipolar distance (px; share within ``px`` and within 1 px), descriptor distance (L2 of the uint8
    SIFT rows), scale disagreement (``|log2(s1 / s2) - pair median|``) and distance from the image centre."""
    import pycolmap

    from .accuracy_scenes import distortion, reference_cameras
    from .consistency import epipolar_distances, undistort

    root, scene = _scene_of(cache)
    ref, dist = reference_cameras(root, scene), distortion(root, scene)
    ours, theirs = read_geometries(cache / "ours" / "database.db"), read_geometries(cache / "colmap" / "database.db")
    db = pycolmap.Database.open(str(cache / "ours" / "database.db"))
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        raw = {i: np.asarray(db.read_keypoints(i), np.float64) for i in names}
        desc = {i: np.asarray(db.read_descriptors(i).data, np.float32) for i in names}
    finally:
        db.close()
    und = {i: undistort(k, ref[names[i]].K, dist) for i, k in raw.items()}
    scale = {i: np.sqrt(np.abs(k[:, 2] * k[:, 5] - k[:, 3] * k[:, 4])) if k.shape[1] >= 6 else np.ones(len(k))
             for i, k in raw.items()}
    acc = {"shared": [], "added": [], "colmap_only": []}
    for p in set(ours) & set(theirs):
        i1, i2 = p
        sets = {"shared": intersect_inliers(ours[p], theirs[p]),
                "added": ours[p][~np.isin(_keys(ours[p]), _keys(theirs[p]))],
                "colmap_only": theirs[p][~np.isin(_keys(theirs[p]), _keys(ours[p]))]}
        lr_all = np.log2(scale[i1][ours[p][:, 0]] / scale[i2][ours[p][:, 1]])
        med = float(np.median(lr_all)) if len(lr_all) else 0.0
        for k, m in sets.items():
            if not len(m):
                continue
            e = epipolar_distances(und[i1][m[:, 0]], und[i2][m[:, 1]], ref[names[i1]], ref[names[i2]])
            d = np.linalg.norm(desc[i1][m[:, 0]] - desc[i2][m[:, 1]], axis=1)
            s = np.abs(np.log2(scale[i1][m[:, 0]] / scale[i2][m[:, 1]]) - med)
            acc[k].append(np.c_[e, d, s])
    out = {}
    for k, parts in acc.items():
        a = np.concatenate(parts) if parts else np.zeros((0, 3))
        out[k] = {"inliers": int(len(a)), "epi_within_px": float(np.mean(a[:, 0] <= px)) if len(a) else None,
                  "epi_within_1px": float(np.mean(a[:, 0] <= 1.0)) if len(a) else None,
                  "epi_median_px": float(np.median(a[:, 0])) if len(a) else None,
                  "descriptor_median": float(np.median(a[:, 1])) if len(a) else None,
                  "scale_off_median": float(np.median(a[:, 2])) if len(a) else None,
                  "scale_off_gt_1": float(np.mean(a[:, 2] > 1.0)) if len(a) else None}
    return out


def analyse(cache_scene: Path, methods=("colmap", "ours", "ours+cap", "ours+rescue", "ours+rejected", "ours-added")
            ) -> dict:
    """Every measurement of one scene's cache: rejected pairs, inlier statistics, tracks of each method's models."""
    import json

    pairs = {m: json.loads((cache_scene / m.replace("+", "_") / "pairs.json").read_text())
             for m in ("colmap", "ours")}
    out = {"rejected": rejected_pairs_table(pairs["colmap"], pairs["ours"]), "added": added_stats(cache_scene),
           "tracks": {}}
    rescue = cache_scene / "ours_rescue" / "match.json"
    if rescue.is_file():
        rep = json.loads(rescue.read_text()).get("rescue", {})
        truth = {(p["name1"], p["name2"]): p for p in pairs["colmap"]}
        rows = []
        for q in rep.get("per_pair", []):
            t = truth.get((min(q["name1"], q["name2"]), max(q["name1"], q["name2"])))
            rows.append(dict(q, true=None if t is None else bool(t["epi_ok"] >= max(15, 0.5 * t["inliers"])),
                             angle_deg=None if t is None else t["angle_deg"]))
        out["rescue"] = {k: v for k, v in rep.items() if k != "per_pair"} | {"per_pair": rows}
    for m in methods:
        for seed_dir in sorted((cache_scene / m.replace("+", "_")).glob("seed*")):
            model = seed_dir / "sparse" / "0"
            if model.is_dir():
                out["tracks"].setdefault(m, {})[seed_dir.name] = track_stats(model)
    return out


def analysis_markdown(scene: str, a: dict) -> str:
    """The measurements of :func:`analyse` as markdown tables."""
    r = a["rejected"]
    out = [f"## {scene}", "",
           f"Pairs COLMAP verifies: {r['colmap_verified']}; we verify: {r['ours_verified']}; COLMAP verifies and we do "
           f"not: **{r['rejected']}**, of them true by the reference cameras (>= half of COLMAP's inliers, and >= 15, "
           f"within 4 px of the reference epipolar lines): **{r['rejected_true']}**; we verify and COLMAP does not: "
           f"{r['ours_only']}.", "", "| COLMAP's inliers | pairs | true | | camera angle (deg) | pairs | true |",
           "|---|---|---|---|---|---|---|"]
    bi, ba_ = list(r["by_inliers"].items()), list(r["by_angle"].items())
    for k in range(max(len(bi), len(ba_))):
        left = f"{bi[k][0]} | {bi[k][1]['pairs']} | {bi[k][1]['true']}" if k < len(bi) else " | | "
        right = f"{ba_[k][0]} | {ba_[k][1]['pairs']} | {ba_[k][1]['true']}" if k < len(ba_) else " | | "
        out.append(f"| {left} | | {right} |")
    out += ["", "Inliers on the pairs both verify (reference epipolar distance, undistorted; descriptor L2; scale "
            "disagreement |log2(s1/s2) - pair median|):", "",
            "| inliers | count | within 4 px | within 1 px | median epipolar px | median descriptor distance | "
            "median scale disagreement | scale off > 2x |", "|---|---|---|---|---|---|---|---|"]
    for k, v in a["added"].items():
        if not v["inliers"]:
            continue
        out.append(f"| {k} | {v['inliers']:,} | {100 * v['epi_within_px']:.1f} % | {100 * v['epi_within_1px']:.1f} % | "
                   f"{v['epi_median_px']:.2f} | {v['descriptor_median']:.0f} | {v['scale_off_median']:.2f} | "
                   f"{100 * v['scale_off_gt_1']:.1f} % |")
    if a.get("rescue"):
        rs = a["rescue"]
        rows = rs["per_pair"]

        def n(kept, true):
            return sum(1 for q in rows if q["kept"] == kept and q["true"] == true)
        out += ["", f"Rescue (collection.rescue.rescue_pairs, COLMAP's matcher on the {rs['candidates']} rejected pairs "
                f"that close a triangle; {rs['time_s']:.0f} s): COLMAP verifies {rs['colmap_verified']}; a third view "
                f"confirms (>= {rs['min_confirmed']} and >= {100 * rs['min_share']:.0f} % of the inliers) and keeps "
                f"{rs['kept']}. Against the reference cameras (true: >= half of COLMAP's inliers within 4 px): kept "
                f"true {n(True, True)}, kept false {n(True, False)}, refused true {n(False, True)}, refused false "
                f"{n(False, False)} (pairs COLMAP's exhaustive run did not verify count as unknown: "
                f"{sum(1 for q in rows if q['true'] is None)})."]
    out += ["", "Tracks of the models (median over seeds):", "",
            "| method | points | mean track length | median reprojection px | points spanning >= L images | "
            "pairs >= L apart tied / all | median co-visible points of those pairs |", "|---|---|---|---|---|---|---|"]
    for m, seeds in a["tracks"].items():
        v = list(seeds.values())

        def md(k):
            return float(np.median([x[k] for x in v]))
        out.append(f"| {m} | {md('points'):,.0f} | {md('mean_track_length'):.2f} | {md('median_reprojection_px'):.3f} "
                   f"| {100 * md('points_spanning_long_range'):.1f} % (L={v[0]['long_range']}) | "
                   f"{md('long_range_pairs_tied'):.0f} / {v[0]['long_range_pairs']} | {md('median_covisible_long_range'):.0f} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    import argparse
    import json

    from .meta import write_json

    p = argparse.ArgumentParser(prog="python -m guidedmatch.evaluation.accuracy_analysis",
                                description="measurements of the accuracy benchmark's cached scenes")
    p.add_argument("--scenes", default="Herz-Jesus-P8,Herz-Jesus-P25,buddha,fox")
    p.add_argument("--cache", default=default_cache("accuracy"))
    p.add_argument("--out", default="benchmarks/results/accuracy")
    args = p.parse_args(argv)
    res, md = {}, ["# What our match sets give the mapper, per scene", ""]
    for scene in args.scenes.split(","):
        c = Path(args.cache) / scene
        if not (c / "ours" / "pairs.json").is_file() or not (c / "colmap" / "pairs.json").is_file():
            print(f"{scene}: not benchmarked yet, skipped")
            continue
        res[scene] = analyse(c)
        md.append(analysis_markdown(scene, res[scene]))
    out = Path(args.out)
    write_json(out / "analysis.json", {s: {k: v for k, v in a.items()} for s, a in res.items()})
    (out / "analysis.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def _self_filter(db_path: Path, method: str, f_px: float = 1.0, log2_scale: float = 0.5) -> dict:
    """``ours-f1`` / ``ours-scale`` (see the module docstring): filters that need no reference."""
    import pycolmap

    from .consistency import epipolar_distances
    from .poses import CameraPose

    db = pycolmap.Database.open(str(db_path))
    out = {}
    try:
        kps: dict[int, np.ndarray] = {}

        def kp(i):
            if i not in kps:
                kps[i] = np.asarray(db.read_keypoints(i), np.float64)
            return kps[i]

        eye = CameraPose(np.eye(3), np.zeros(3), np.eye(3))
        for (i1, i2), m in read_geometries(db_path).items():
            a, b = kp(i1)[m[:, 0]], kp(i2)[m[:, 1]]
            if method == "ours-f1":
                F = np.asarray(db.read_two_view_geometry(i1, i2).F, np.float64)
                if not np.isfinite(F).all() or np.abs(F).max() == 0:
                    out[(i1, i2)] = m   # no F (e.g. a homography only): kept as it is
                    continue
                d = _f_distances(a, b, F)
                out[(i1, i2)] = m[d <= f_px]
            else:
                s1 = np.sqrt(np.abs(a[:, 2] * a[:, 5] - a[:, 3] * a[:, 4]))
                s2 = np.sqrt(np.abs(b[:, 2] * b[:, 5] - b[:, 3] * b[:, 4]))
                lr = np.log2(s1 / s2)
                out[(i1, i2)] = m[np.abs(lr - np.median(lr)) <= log2_scale]
    finally:
        db.close()
    return out


def global_distances(q: np.ndarray, t: np.ndarray, partner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared L2 distances of the matches ``q[k] -> t[partner[k]]`` and of each ``q[k]`` to the best other row of
    ``t``: ``(mine, other)``, float32 ``(Q,)``. Exact for byte-valued descriptors of up to 128 dimensions (SIFT:
    every float32 sum is an integer < 2^24, in any order)."""
    q = np.asarray(q, np.float32)
    t = np.asarray(t, np.float32)
    partner = np.asarray(partner, np.int64)
    if len(q) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    d2 = np.maximum((q * q).sum(1)[:, None] + (t * t).sum(1)[None, :] - 2 * (q @ t.T), 0)
    rows = np.arange(len(q))
    mine = d2[rows, partner]
    d2[rows, partner] = np.inf
    return mine, d2.min(1)


def ratio_test(mine: np.ndarray, other: np.ndarray, ratio: float | None = 0.8) -> np.ndarray:
    """The matches of :func:`global_distances` whose partner is a nearest neighbour (ties count) and, with
    ``ratio``, at < ``ratio`` x the best other's distance (L2)."""
    ok = mine <= other
    if ratio is not None:
        ok &= np.sqrt(mine) < ratio * np.sqrt(other)
    return ok


def global_test(q: np.ndarray, t: np.ndarray, partner: np.ndarray, ratio: float | None = 0.8) -> np.ndarray:
    """Which matches ``q[k] -> t[partner[k]]`` pass a ratio test against all of ``t`` (bool per row): the partner is
    a nearest neighbour (ties count) and, with ``ratio``, its distance is < ``ratio`` x the distance of the best other
    row of ``t`` (L2; :func:`global_distances`, :func:`ratio_test`).

    >>> t = np.array([[0, 0], [10, 0], [0, 10], [11, 0]], np.float32)
    >>> global_test(np.array([[1, 0], [10.5, 0], [4, 4]], np.float32), t, np.array([0, 1, 2])).tolist()
    [True, False, False]
    >>> global_test(np.array([[1, 0], [10.5, 0], [4, 4]], np.float32), t, np.array([0, 1, 2]), None).tolist()
    [True, True, False]
    """
    return ratio_test(*global_distances(q, t, partner), ratio)


def _global_filter(db_path: Path, ratio: float | None, keep_below: int = 15) -> dict:
    """``ours-distinct`` / ``ours-nn``: each row's inliers that pass :func:`global_test` (a row left with fewer than
    ``keep_below`` keeps all of them)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    out, desc = {}, {}
    try:
        def d(i):
            if i not in desc:
                desc[i] = np.asarray(db.read_descriptors(i).data, np.float32)
            return desc[i]

        for (i1, i2), m in read_geometries(db_path).items():
            ok = global_test(d(i1)[m[:, 0]], d(i2), m[:, 1], ratio)
            out[(i1, i2)] = m[ok] if ok.sum() >= keep_below else m
    finally:
        db.close()
    return out


def _f_distances(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Max of the two point-to-epipolar-line distances (px) under ``F`` (``x2^T F x1 = 0``).

    >>> F = np.array([[0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])   # a pure x translation: lines are image rows
    >>> _f_distances(np.array([[5.0, 7.0]]), np.array([[9.0, 9.5]]), F).tolist()
    [2.5]
    """
    h1 = np.c_[x1[:, :2], np.ones(len(x1))]
    h2 = np.c_[x2[:, :2], np.ones(len(x2))]
    l2, l1 = h1 @ F.T, h2 @ F
    num = np.abs(np.sum(h2 * l2, axis=1))
    return np.maximum(num / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-12),
                      num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12))


def _three_view(db_path: Path, contra: bool = False) -> dict:
    """``ours-3view``: every verified pair keeps the inliers a third view confirms (the same keypoint of some image
    ``c`` matched to both through verified pairs)."""
    import pycolmap

    from ..collection.rescue import confirmed_by_third_view, contradicted_by_third_view

    geoms = read_geometries(db_path)
    db = pycolmap.Database.open(str(db_path))
    try:
        nkp = {img.image_id: int(db.read_keypoints(img.image_id).shape[0]) for img in db.read_all_images()}
    finally:
        db.close()
    if contra:
        return {(a, b): m[~contradicted_by_third_view(a, b, m, geoms, nkp)] for (a, b), m in geoms.items()}
    return {(a, b): m[confirmed_by_third_view(a, b, m, geoms, nkp)] for (a, b), m in geoms.items()}
