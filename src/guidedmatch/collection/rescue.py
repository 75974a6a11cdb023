"""Second look at the pairs our verdict called no-overlap, confirmed by a third view.

Our two-view verdict rejects a pair early when its guided search finds too little; on wide baselines (40-95 deg
between the cameras) that also rejects true pairs with a few dozen correct matches -- the loop closures that tie the
ends of a capture sequence together, whose loss shows as pose error growing with the distance along the sequence.
COLMAP's exhaustive matcher verifies them, and with them, on repeated structure, pairs that are wrong (a repeated
window matched to its neighbour satisfies some fundamental matrix).

:func:`rescue_pairs` runs on a COLMAP database after ``guidedmatch colmap``:

1. candidates: pairs with a geometry row but no inliers (tried, rejected) whose two images have a verified common
   neighbour (they close a triangle of verified pairs; unrelated images never do);
2. the candidates are matched again by COLMAP's own matcher and verification (``pycolmap.match_image_pairs``:
   ratio test, cross-check, RANSAC, COLMAP's defaults);
3. a candidate COLMAP verifies is kept only if enough of its inliers are *confirmed by a third view*: inlier
   ``(i in a, j in b)`` is confirmed when, for some verified common neighbour ``c``, the verified pairs ``a-c`` and
   ``b-c`` match ``i`` and ``j`` to the same keypoint of ``c``. A wrong match on a repeated structure is not
   confirmed: its keypoints' correct partners in ``c`` differ. Kept when confirmed >= ``min_confirmed`` and
   >= ``min_share`` of the inliers; otherwise its geometry is written back with no inliers (the mapper ignores it).

Nothing in it is specific to a scene; the two thresholds are the only settings.
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .sink_base import open_pycolmap_database

__all__ = ["RescueConfig", "rescue_pairs", "confirmed_by_third_view", "contradicted_by_third_view"]


@dataclass(frozen=True)
class RescueConfig:
    """Settings of :func:`rescue_pairs`."""

    min_confirmed: int = 8        # inliers confirmed by a third view for a rescued pair to be kept
    min_share: float = 0.2        # and at least this share of its inliers
    num_threads: int = -1         # COLMAP matcher threads (-1: all cores)
    matcher: str = "bf"           # "bf": our brute-force mode (ratio test), "colmap": COLMAP's matcher; both verified by COLMAP

    def __post_init__(self) -> None:
        from ..validation import check_number

        check_number("RescueConfig", "min_confirmed", self.min_confirmed, lo=1, integer=True)
        check_number("RescueConfig", "min_share", self.min_share, lo=0.0, hi=1.0)
        check_number("RescueConfig", "num_threads", self.num_threads, lo=-1, integer=True)
        if self.matcher not in ("bf", "colmap"):
            from ..errors import ConfigError

            raise ConfigError(f"RescueConfig.matcher must be 'bf' or 'colmap', got {self.matcher!r}")


def _partner(m: np.ndarray, n: int, col_from: int) -> np.ndarray:
    """``(n,)`` keypoint of the other image matched to each keypoint of one side (-1: none)."""
    out = np.full(n, -1, np.int64)
    out[m[:, col_from]] = m[:, 1 - col_from]
    return out


def confirmed_by_third_view(a: int, b: int, inliers: np.ndarray, verified: dict, num_keypoints: dict) -> np.ndarray:
    """``(M,) bool``: inlier ``(i, j)`` of pair ``(a, b)`` (``a < b``, ``i`` in ``a``, ``j`` in ``b``) is matched to
    the same keypoint of some third image ``c`` by the verified pairs ``a-c`` and ``b-c``. ``verified``:
    ``{(id1, id2): (K, 2) inlier matches}`` with ``id1 < id2``, columns in that order.

    >>> v = {(1, 3): np.array([[0, 5], [1, 6]]), (2, 3): np.array([[4, 5], [7, 9]])}
    >>> confirmed_by_third_view(1, 2, np.array([[0, 4], [1, 7]]), v, {1: 2, 2: 8, 3: 10}).tolist()
    [True, False]
    """
    m = np.asarray(inliers, np.int64).reshape(-1, 2)
    ok = np.zeros(len(m), bool)
    neighbours = {k for p in verified for k in p if a in p} & {k for p in verified for k in p if b in p}
    for c in neighbours - {a, b}:
        ac = verified[(min(a, c), max(a, c))]
        bc = verified[(min(b, c), max(b, c))]
        pa = _partner(ac, num_keypoints[a], 0 if a < c else 1)   # a's keypoint -> c's
        pb = _partner(bc, num_keypoints[b], 0 if b < c else 1)
        ka, kb = pa[m[:, 0]], pb[m[:, 1]]
        ok |= (ka >= 0) & (ka == kb)
    return ok


def contradicted_by_third_view(a: int, b: int, inliers: np.ndarray, verified: dict, num_keypoints: dict
                               ) -> np.ndarray:
    """``(M,) bool``: inlier ``(i, j)`` of pair ``(a, b)`` is *contradicted*: for some third image ``c`` the verified
    pairs ``a-c`` and ``b-c`` match ``i`` and ``j`` to two *different* keypoints of ``c`` (arguments as
    :func:`confirmed_by_third_view`).

    >>> v = {(1, 3): np.array([[0, 5], [1, 6]]), (2, 3): np.array([[4, 5], [7, 9]])}
    >>> contradicted_by_third_view(1, 2, np.array([[0, 4], [1, 7], [0, 3]]), v, {1: 2, 2: 8, 3: 10}).tolist()
    [False, True, False]
    """
    m = np.asarray(inliers, np.int64).reshape(-1, 2)
    bad = np.zeros(len(m), bool)
    neighbours = {k for p in verified for k in p if a in p} & {k for p in verified for k in p if b in p}
    for c in neighbours - {a, b}:
        pa = _partner(verified[(min(a, c), max(a, c))], num_keypoints[a], 0 if a < c else 1)
        pb = _partner(verified[(min(b, c), max(b, c))], num_keypoints[b], 0 if b < c else 1)
        ka, kb = pa[m[:, 0]], pb[m[:, 1]]
        bad |= (ka >= 0) & (kb >= 0) & (ka != kb)
    return bad


def rescue_pairs(database: str | os.PathLike, config: RescueConfig | None = None) -> dict:
    """Re-examine the rejected pairs of a COLMAP database (see the module docstring). Returns a report:
    ``candidates``, ``colmap_verified``, ``kept`` (with their inlier counts), ``refused`` (verified by COLMAP, not
    confirmed by a third view), ``time_s``, and per candidate ``name1, name2, inliers, confirmed, kept``."""
    import pycolmap

    conf = config or RescueConfig()
    t0 = time.perf_counter()
    db = open_pycolmap_database(database)
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        nkp = {i: int(db.read_keypoints(i).shape[0]) for i in names}
        pids, counts = (np.asarray(x, np.int64) for x in db.read_two_view_geometry_num_inliers())
        verified_ids = {tuple(int(v) for v in pycolmap.pair_id_to_image_pair(int(p))) for p, n in zip(pids, counts)
                        if n > 0}
        ids = sorted(names)   # geometry rows without inliers are not in the counts above: look each pair up
        rejected = [(a, b) for k, a in enumerate(ids) for b in ids[k + 1:]
                    if (a, b) not in verified_ids and db.exists_two_view_geometry(a, b)]
        adj: dict[int, set] = {}
        for a, b in verified_ids:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
        candidates = sorted(p for p in rejected if adj.get(p[0], set()) & adj.get(p[1], set()))
        verified = {p: np.asarray(db.read_two_view_geometry(*p).inlier_matches, np.int64).reshape(-1, 2)
                    for p in verified_ids}
        with pycolmap.DatabaseTransaction(db):
            for a, b in candidates:
                db.delete_matches(a, b)
                db.delete_two_view_geometry(a, b)
    finally:
        db.close()
    report = {"candidates": len(candidates), "colmap_verified": 0, "kept": 0, "refused": 0, "kept_inliers": 0,
              "per_pair": [], "min_confirmed": conf.min_confirmed, "min_share": conf.min_share}
    if candidates:
        if conf.matcher == "colmap":
            _match_colmap(database, [(names[a], names[b]) for a, b in candidates], conf.num_threads)
        else:
            _match_bf(database, [(names[a], names[b]) for a, b in candidates])
        db = open_pycolmap_database(database)
        try:
            with pycolmap.DatabaseTransaction(db):
                for a, b in candidates:
                    if not db.exists_two_view_geometry(a, b):
                        continue
                    g = db.read_two_view_geometry(a, b)
                    m = np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
                    if not len(m):
                        continue
                    report["colmap_verified"] += 1
                    conf_mask = confirmed_by_third_view(a, b, m, verified, nkp)
                    n_ok = int(conf_mask.sum())
                    keep = n_ok >= conf.min_confirmed and n_ok >= conf.min_share * len(m)
                    report["per_pair"].append({"name1": names[a], "name2": names[b], "inliers": len(m),
                                               "confirmed": n_ok, "kept": bool(keep)})
                    if keep:
                        report["kept"] += 1
                        report["kept_inliers"] += len(m)
                    else:
                        report["refused"] += 1
                        g.inlier_matches = np.zeros((0, 2), np.uint32)
                        g.config = 1   # DEGENERATE: no inliers, the mapper ignores the pair
                        db.update_two_view_geometry(a, b, g)
        finally:
            db.close()
    report["time_s"] = time.perf_counter() - t0
    return report



def _match_colmap(database, pairs: list[tuple[str, str]], num_threads: int) -> None:
    """COLMAP's matcher and verification on ``pairs`` (``pycolmap.match_image_pairs``)."""
    import pycolmap

    with tempfile.TemporaryDirectory() as tmp:
        pairs_file = Path(tmp) / "pairs.txt"
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        mo = pycolmap.FeatureMatchingOptions()
        mo.num_threads = num_threads
        mo.use_gpu = False
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(str(database), matching_options=mo, pairing_options=po, device=pycolmap.Device.cpu)


def _match_bf(database, pairs: list[tuple[str, str]]) -> None:
    """Our brute-force mode (every feature against every feature, ratio test) on ``pairs``, raw matches written,
    then COLMAP's verification of them."""
    from .engine import CollectionConfig, match_collection
    from .sinks import ColmapSink
    from .sources import ColmapSource

    with ColmapSource(database) as source, ColmapSink(database, geometry="colmap") as sink:
        match_collection(source, pairs, sink, CollectionConfig(mode="bf", progress=False))
        sink.verify(pairs=pairs)
