"""Where a collection's matches go: a COLMAP database (matches + two-view geometries) or an hloc ``matches.h5``.

Every sink is a context manager holding an exclusive write lock (``fcntl.flock`` on ``<file>.lock`` beside it):
a second writer of the same file gets :class:`~guidedmatch.errors.DatabaseBusyError` at once. A file that cannot
be written raises :class:`~guidedmatch.errors.OutputError` in the constructor, before any matching. Each
:meth:`MatchSink.write` stores one pair completely or not at all, and :meth:`MatchSink.done_pairs` lists the pairs
already stored, so an interrupted run resumes where it stopped.

COLMAP conventions handled here
-------------------------------
* COLMAP stores a pair once, under ``image_id1 < image_id2``; a pair given the other way round is stored with its
  match columns swapped, ``F -> F^T`` and ``H -> H^-1`` (and read back the same way by ``pycolmap``).
* Our ``F``/``H`` act on OpenCV pixels (origin at the centre of the top-left pixel); COLMAP's on COLMAP pixels
  (``x_colmap = x_cv + 0.5``). With ``T = [[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]]`` (``x_cv = T x_colmap``):
  ``F_colmap = T^T F T`` and ``H_colmap = T^-1 H T``.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..base import COLMAP_MIN_INLIERS, DEFAULT_INLIER_PX, DEFAULT_REFIT_DEG
from ..errors import ConfigError, DatabaseError, InputError, OutputError
from .hloc_sink import H5MatchesSink, names_to_pair
from .sink_base import MatchSink, WriteLock, _check_pairs, _check_writable, check_database_space
from .sink_base import SPACE_MARGIN  # noqa: F401 - found here by the fault bench and the tests

__all__ = ["MatchSink", "ColmapSink", "H5MatchesSink", "names_to_pair", "WriteLock", "colmap_pixel_geometry",
           "cap_two_view_inliers", "tighten_two_view_inliers", "CAP_ORDERS"]

_T = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])  # x_cv = T x_colmap
_T_INV = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])


#: how :meth:`ColmapSink.cap_inliers` ranks a pair's inliers (its docstring; "track" is the default)
CAP_ORDERS = ("track", "residual", "distance")


def _model_error(g, x1: np.ndarray, x2: np.ndarray) -> np.ndarray | None:
    """The error of matches ``x1 <-> x2`` (COLMAP pixels) to a two-view geometry row's own model, or None (no model):
    the Sampson distance to its F; a planar / panoramic row (configuration 4-6, which carries the larger of its H
    and F inlier sets) the smaller of its H transfer error and that."""
    from ..epipolar import sampson_distance
    from ..geometry import transfer_error

    F = None if g.F is None or not np.any(g.F) else np.asarray(g.F, dtype=np.float64)
    H = None if g.H is None or not np.any(g.H) else np.asarray(g.H, dtype=np.float64)
    if int(g.config) not in (4, 5, 6):
        H = None   # only a planar / panoramic row is judged by its H
    if F is None and H is None:
        return None
    x1, x2 = np.asarray(x1, dtype=np.float64), np.asarray(x2, dtype=np.float64)
    err = None if H is None else transfer_error(H, x1, x2)
    if F is not None:
        e = sampson_distance(F, x1, x2)
        err = e if err is None else np.minimum(err, e)
    return err


def colmap_pixel_geometry(F: np.ndarray | None, H: np.ndarray | None, swap: bool = False):
    """``(F, H)`` from OpenCV pixels to COLMAP pixels, transposed / inverted when the pair is stored swapped.

    >>> F = np.arange(9.0).reshape(3, 3); x1 = np.array([3.0, 4.0, 1.0]); x2 = np.array([7.0, 1.0, 1.0])
    >>> Fc, _ = colmap_pixel_geometry(F, None)
    >>> bool(np.isclose(x2 @ F @ x1, (x2 + [.5, .5, 0]) @ Fc @ (x1 + [.5, .5, 0])))
    True
    """
    Fc = Hc = None
    if F is not None:
        Fc = _T.T @ np.asarray(F, np.float64) @ _T
        if swap:
            Fc = Fc.T
    if H is not None:
        Hc = _T_INV @ np.asarray(H, np.float64) @ _T
        if swap:
            Hc = np.linalg.inv(Hc)
        Hc = Hc / Hc[2, 2] if abs(Hc[2, 2]) > 1e-12 else Hc
    return Fc, Hc


# ====================================================================== COLMAP
#: done_pairs_in() checks every image pair exactly up to this many pairs (50,000 ~ 0.6 s), else bulk reads
EXACT_PAIRS = 50_000


def _pair_names(names: dict[int, str], pair_id: int) -> frozenset[str] | None:
    import pycolmap

    i1, i2 = pycolmap.pair_id_to_image_pair(int(pair_id))
    a, b = names.get(int(i1)), names.get(int(i2))
    return frozenset((a, b)) if a is not None and b is not None else None


def done_pairs_in(db, ids: dict[str, int], geometry: str = "ours", candidates=None, *,
                  exact_pairs: int = EXACT_PAIRS) -> set[frozenset[str]]:
    """Pairs of the open ``pycolmap.Database`` ``db`` (images ``ids``: name -> image id) with a two-view geometry row
    (``geometry="ours"``) or a matches row (otherwise).

    With ``candidates`` (pairs of names) each one is checked exactly (~12 us per pair). Without, databases of up to
    ``exact_pairs`` image pairs (~320 images) are checked pair by pair too; larger ones are read with pycolmap's
    bulk readers, which skip rows with zero matches and no geometry matrix: such a pair (an image without features)
    is matched again on resume and its rows are replaced (same result).
    """
    import pycolmap

    exists = db.exists_two_view_geometry if geometry == "ours" else db.exists_matches
    if candidates is None and len(ids) * (len(ids) - 1) // 2 <= exact_pairs:
        names = sorted(ids)
        candidates = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    if candidates is not None:
        return {frozenset((a, b)) for a, b in candidates if a in ids and b in ids and exists(ids[a], ids[b])}
    pids = set(db.read_num_matches()[0])
    if geometry == "ours":
        geo_ids = set(db.read_two_view_geometry_num_inliers()[0])
        geo_ids |= set(db.read_two_view_geometries()[0])
        pids = geo_ids | {p for p in pids - geo_ids if exists(*pycolmap.pair_id_to_image_pair(int(p)))}
    by_id = {v: k for k, v in ids.items()}
    return {s for s in (_pair_names(by_id, p) for p in pids) if s is not None}


def verified_pairs_in(db, ids: dict[str, int], min_inliers: int = 1) -> set[frozenset[str]]:
    """Pairs of the open ``pycolmap.Database`` ``db`` (images ``ids``: name -> image id) whose two-view geometry has
    at least ``min_inliers`` inlier matches."""
    by_id = {v: k for k, v in ids.items()}
    pids, nums = db.read_two_view_geometry_num_inliers()
    return {s for pid, num in zip(pids, nums) if int(num) >= min_inliers and (s := _pair_names(by_id, pid)) is not None}


class ColmapSink(MatchSink):
    """Write matches (and two-view geometries) into an existing COLMAP database through ``pycolmap.Database``.

    Args:
        database_path: a COLMAP database with the images (and their keypoints) the matches refer to.
        geometry: ``"ours"`` -- write the matches and our two-view geometry: ``config`` =
            ``geometry.colmap_config`` (3 UNCALIBRATED / 6 PLANAR_OR_PANORAMIC when verified, 1 DEGENERATE
            otherwise), ``F`` and/or ``H`` (COLMAP pixels) and the inlier matches, so ``colmap mapper`` /
            ``pycolmap.incremental_mapping`` runs without a verification step (unverified pairs get a geometry
            row with no inliers: the mapper ignores them, and the pair counts as done);
            ``"colmap"`` -- write raw matches only, then :meth:`verify` runs COLMAP's geometric verification over
            them; ``"none"`` -- raw matches only.
        overwrite: rematch pairs already in the database (``done_pairs()`` is empty; writes replace rows).

    Raises (in the constructor, before any work): DatabaseError (missing / not a COLMAP database),
    OutputError (read-only), DatabaseBusyError (another process holds the lock), ConfigError (bad ``geometry``).
    """

    kind = "colmap"
    EXACT_PAIRS = EXACT_PAIRS  # done_pairs(): exact up to this many image pairs (module constant)

    def __init__(self, database_path: str | os.PathLike, geometry: str = "ours", *, overwrite: bool = False) -> None:
        from ..validation import check_bool, check_choice
        from .colmap_source import _open_colmap

        check_choice("ColmapSink", "geometry", geometry, ("ours", "colmap", "none"))
        check_bool("ColmapSink", "overwrite", overwrite)
        self.path = Path(database_path)
        self.geometry = geometry
        self.overwrite = overwrite
        self._db = None
        if not self.path.exists():
            raise DatabaseError(f"COLMAP database not found: {self.path}")
        _check_writable(self.path, "COLMAP database")
        self._lock = WriteLock(self.path).acquire()
        try:
            self._db = _open_colmap(self.path)
            images = self._db.read_all_images()
            self._ids = {im.name: int(im.image_id) for im in images}
            self._names = {v: k for k, v in self._ids.items()}
            self._nkp = {im.name: (self._db.num_keypoints_for_image(im.image_id)
                                   if self._db.exists_keypoints(im.image_id) else 0) for im in images}
        except BaseException:
            self.close()
            raise
        self.written = 0

    def add_image(self, name: str, image_id: int, num_keypoints: int) -> None:
        """Make an image written into the database after this sink was opened known to it (its writer, in this
        process, gives the facts: ``guidedmatch sfm`` writes pairs while the extraction still writes images)."""
        self._ids[name] = int(image_id)
        self._names[int(image_id)] = name
        self._nkp[name] = int(num_keypoints)

    def _id(self, name: str) -> int:
        try:
            return self._ids[name]
        except KeyError:
            raise InputError(f"image {name!r} is not in COLMAP database {self.path}") from None

    def done_pairs(self, candidates=None) -> set[frozenset[str]]:
        """Pairs already complete: with a two-view geometry row (``geometry="ours"``) or a matches row
        (:func:`done_pairs_in`; empty with ``overwrite``)."""
        if self.overwrite:
            return set()
        return done_pairs_in(self._db, self._ids, self.geometry, candidates, exact_pairs=self.EXACT_PAIRS)

    def _two_view(self, p: np.ndarray, geometry, swap: bool):
        import pycolmap

        tvg = pycolmap.TwoViewGeometry()
        if geometry is None:
            tvg.config = 0  # UNDEFINED: the matcher gave no verdict
            return tvg
        inl = np.asarray(geometry.inliers, bool).reshape(-1)
        if len(inl) != len(p):
            raise InputError(f"geometry.inliers has {len(inl)} entries for {len(p)} matches")
        tvg.config = int(geometry.colmap_config)
        if geometry:
            Fc, Hc = colmap_pixel_geometry(geometry.F, geometry.H, swap)
            if Fc is not None:
                tvg.F = Fc
            if Hc is not None:
                tvg.H = Hc
            tvg.inlier_matches = np.ascontiguousarray(p[inl], dtype=np.uint32).reshape(-1, 2)
        return tvg

    def write(self, name1: str, name2: str, pairs: np.ndarray, scores: np.ndarray | None = None,
              geometry=None) -> None:
        """Store one pair's matches (+ two-view geometry with ``geometry="ours"``) in one transaction.

        ``pairs (M, 2)`` index name1's and name2's keypoints; the pair is stored under COLMAP's order (smaller
        image id first: columns swapped, F transposed, H inverted when needed). Scores are not stored (COLMAP has
        no column for them). A pair already in the database is replaced.
        """
        import pycolmap

        if self._db is None:
            raise OutputError(f"ColmapSink({self.path}) is closed")
        i1, i2 = self._id(name1), self._id(name2)
        p, _ = _check_pairs(name1, name2, pairs, scores, self._nkp[name1], self._nkp[name2])
        swap = i1 > i2
        if swap:
            i1, i2, p = i2, i1, p[:, ::-1]
        m = np.ascontiguousarray(p, dtype=np.uint32).reshape(-1, 2)
        tvg = self._two_view(p, geometry, swap) if self.geometry == "ours" else None
        db = self._db
        self.check_space(2 * m.nbytes)
        with pycolmap.DatabaseTransaction(db):
            # pycolmap's transaction commits on exit even after an exception: undo by hand so a pair is stored
            # completely or not at all (a crash / kill -9 leaves the open transaction to SQLite's rollback)
            try:
                self._write_rows(db, i1, i2, m, tvg)
            except BaseException:
                for fn in (db.delete_matches, db.delete_two_view_geometry):
                    try:
                        fn(i1, i2)
                    except Exception:
                        pass
                raise
        self.written += 1

    def check_space(self, nbytes: int = 0) -> None:
        """OutputError naming the database when a transaction of ``nbytes`` might not fit on its disk (or under
        the process's file size limit): :func:`~guidedmatch.collection.sink_base.check_database_space`, checked
        before each transaction."""
        check_database_space(self.path, nbytes, kept="finished pairs are kept")

    @staticmethod
    def _write_rows(db, i1: int, i2: int, m: np.ndarray, tvg) -> None:
        """Replace the pair's rows (called inside the transaction of :meth:`write`)."""
        if db.exists_matches(i1, i2):
            db.delete_matches(i1, i2)
        if db.exists_two_view_geometry(i1, i2):
            db.delete_two_view_geometry(i1, i2)
        db.write_matches(i1, i2, m)
        if tvg is not None:
            db.write_two_view_geometry(i1, i2, tvg)

    def verify(self, options=None, pairs=None) -> int:
        """Run COLMAP's geometric verification (``pycolmap.verify_matches``) over the pairs with matches and no
        two-view geometry (or the given ``pairs``); returns the number of pairs verified.

        ``options``: ``pycolmap.TwoViewGeometryOptions`` or a dict of its fields (COLMAP defaults otherwise).
        Only for ``geometry="colmap"``.
        """
        import pycolmap

        if self.geometry != "colmap":
            raise ConfigError(f"ColmapSink.verify needs geometry='colmap' (this sink has geometry={self.geometry!r})")
        if isinstance(options, dict):
            opts = pycolmap.TwoViewGeometryOptions()
            opts.mergedict(options)
            options = opts
        options = options or pycolmap.TwoViewGeometryOptions()
        self.check_space()
        db = self._db
        if pairs is None:
            todo = []
            for pid in db.read_num_matches()[0]:
                i1, i2 = pycolmap.pair_id_to_image_pair(int(pid))
                if not db.exists_two_view_geometry(i1, i2):
                    todo.append((self._names[int(i1)], self._names[int(i2)]))
        else:
            todo = [(a, b) for a, b in pairs if db.exists_matches(self._id(a), self._id(b))]
        if not todo:
            return 0
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".pairs.txt", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.writelines(f"{a} {b}\n" for a, b in todo)
            self._db.close()  # COLMAP opens its own connection; ours holds no transaction but keep it simple
            self._db = None
            pycolmap.verify_matches(str(self.path), tmp, options)
        finally:
            os.unlink(tmp)
            from .colmap_source import _open_colmap

            if self._db is None and self._lock.held:
                self._db = _open_colmap(self.path)
        return len(todo)

    def cap_inliers(self, max_inliers: int, *, grid: int = 16, order: str = "track",
                    track_px: float = DEFAULT_INLIER_PX, above: int = 0) -> dict:
        """Keep at most ``max_inliers`` inlier matches in every two-view geometry of the database, spread over
        image 1 and best first (:func:`guidedmatch.geometry.spread_matches`: a ``grid x grid`` lattice, the
        best-ranked match of each cell first, round after round) -- only when the database holds more than
        ``above`` inliers in all (0: always; else nothing changes and the record says ``applied: False``).

        ``above`` -- the cap is a time measure (below), and a small mapper input maps in seconds: ``guidedmatch
        sfm`` caps only above 100,000 inliers (:data:`guidedmatch.sfm.config.CAP_ABOVE_INLIERS`, where the reasons
        are). Decided on the inliers the geometry rows hold when the cap runs (after an earlier cap: the capped
        counts).

        ``order`` -- which inliers of a cell are the best (:data:`CAP_ORDERS`):

        * ``"track"`` (default): those whose two keypoints take part in the most verified pairs of the database
          (the multi-view evidence a pair cannot see: such a match is a piece of a long track, which the mapper
          keeps whole instead of getting a different thousand of every pair), then the smallest error to the row's
          own model. A keypoint counts in a pair when one of the pair's raw matches uses it within ``track_px`` of
          that row's F / H -- the raw ``matches`` rows and the models are what the cap never changes, so an
          interrupted pass and its rerun rank as an uninterrupted pass does.
        * ``"residual"``: the smallest error to the row's own model (Sampson distance to F; a planar row: the
          smaller of its H transfer error and F's Sampson distance).
        * ``"distance"``: the smallest descriptor distance (before 2026-12-05).

        Measured (COLMAP's mapper, 3 seeds, cap 1000; accuracy history, "twelfth round"): median error /
        AUC@1 with "distance" -> "track": Herz-Jesus-P8 0.215 / 0.783 -> 0.208 / 0.788, P25 0.376 / 0.614 -> 0.352 /
        0.633, buddha 0.211 / 0.737 -> 0.210 / 0.739. A row without a model ranks by descriptor distance.

        Only the geometry rows change (their configuration, F / E / H and pose are kept); the raw ``matches`` rows
        keep every match. Pairs with at most ``max_inliers`` inliers are not touched, so weak links of the view
        graph stay whole and a rerun with the same value changes nothing (each pair is rewritten in its own
        transaction: an interrupted pass leaves every pair either capped or as it was, and the rerun completes it).
        Works on any COLMAP database: our geometries or COLMAP's own verification.

        Why: the mapper's bundle adjustments cost what its observations cost (docs/collections.md, "How many inliers
        the mapper needs"). Returns ``{"max_inliers", "grid", "order", "above", "applied", "pairs", "pairs_capped",
        "inliers_before", "inliers_after", "time_s"}`` (``pairs`` = geometries with inliers; ``time_s`` includes the
        track count).
        """
        from ..geometry import spread_matches
        from ..validation import check_choice, check_number
        from .colmap_source import _descriptor_rows, _is_binary

        check_number("cap_inliers", "max_inliers", max_inliers, lo=1, integer=True)
        check_number("cap_inliers", "grid", grid, lo=1, integer=True)
        check_choice("cap_inliers", "order", order, CAP_ORDERS)
        check_number("cap_inliers", "track_px", track_px, lo=0, lo_open=True)
        check_number("cap_inliers", "above", above, lo=0, integer=True)
        t0 = time.perf_counter()
        rec = {"max_inliers": int(max_inliers), "grid": int(grid), "order": order, "above": int(above)}
        if above:
            if self._db is None:
                raise OutputError(f"ColmapSink({self.path}) is closed")
            counts = np.asarray(self._db.read_two_view_geometry_num_inliers()[1], dtype=np.int64)
            total = int(counts.sum())
            if total <= above:
                return dict(rec, applied=False, pairs=int(np.count_nonzero(counts)), pairs_capped=0,
                            inliers_before=total, inliers_after=total, time_s=time.perf_counter() - t0)
        degree = self._keypoint_degrees(float(track_px)) if order == "track" else None

        def rows(db, iid):
            """(keypoints x, y, raw descriptor rows, binary?, image size): no float copy of the descriptors -- only
            the inlier rows are compared. Raw rows are ~150 B per SIFT feature: 256 MB hold ~200 images of 8192."""
            desc = db.read_descriptors(iid)
            shape = np.shape(desc.data)
            kind, raw = _descriptor_rows(desc, int(shape[1]) if len(shape) == 2 else 0)
            cam = db.read_camera(db.read_image(iid).camera_id)
            return (np.asarray(db.read_keypoints(iid))[:, :2], raw, _is_binary(kind), (int(cam.width), int(cam.height)))

        def keep(g, m, load, i1, i2):
            if len(m) <= max_inliers:
                return None
            (kp1, d1, binary, size1), (kp2, d2, _, _) = load(i1), load(i2)
            err = None if order == "distance" else _model_error(g, kp1[m[:, 0]], kp2[m[:, 1]])
            if err is None:
                a, b = d1[m[:, 0]], d2[m[:, 1]]
                if binary:   # packed bits: Hamming
                    dist = np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(axis=1).astype(np.float64)
                else:
                    dist = np.linalg.norm(a.astype(np.float32) - b.astype(np.float32), axis=1)
                # no model: rank by descriptor distance (in [0, 1) for the track order's tie-break)
                err = dist if order == "distance" else np.argsort(np.argsort(dist, kind="stable")) / len(dist)
            if order == "track":
                # lexicographic: more verified pairs first, then the smaller model error (capped below 1 track)
                score = -(degree[i1][m[:, 0]] + degree[i2][m[:, 1]]).astype(np.float64) + np.minimum(err, 9.99) / 10
            else:
                score = err
            return np.sort(spread_matches(kp1[m[:, 0]], size1, score, max_inliers, grid))

        report = self._rewrite_inliers(lambda counts: counts > max_inliers, rows, keep)
        return dict(rec, applied=True, pairs=report["pairs"], pairs_capped=report["pairs_rewritten"],
                    inliers_before=report["inliers_before"], inliers_after=report["inliers_after"],
                    time_s=time.perf_counter() - t0)

    def _keypoint_degrees(self, px: float) -> dict[int, np.ndarray]:
        """Per image id, for every keypoint, the number of verified pairs (geometry rows with inliers) whose raw
        matches use it within ``px`` of the row's F / H (a row without a model: its inlier matches). Read from what
        :meth:`cap_inliers` and :meth:`tighten_inliers` never change, so it is the same before, during and after them."""
        import pycolmap

        if self._db is None:
            raise OutputError(f"ColmapSink({self.path}) is closed")
        db = self._db
        kps = {int(img.image_id): np.asarray(db.read_keypoints(img.image_id))[:, :2].astype(np.float64)
               for img in db.read_all_images()}
        degree = {iid: np.zeros(len(k), np.int32) for iid, k in kps.items()}
        pids, counts = (np.asarray(a, dtype=np.int64) for a in db.read_two_view_geometry_num_inliers())
        for pid in np.sort(pids[counts > 0]):
            i1, i2 = (int(i) for i in pycolmap.pair_id_to_image_pair(int(pid)))
            g = db.read_two_view_geometry(i1, i2)
            m = np.asarray(db.read_matches(i1, i2), dtype=np.int64).reshape(-1, 2)
            err = _model_error(g, kps[i1][m[:, 0]], kps[i2][m[:, 1]]) if len(m) else None
            if err is None:
                m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            else:
                m = m[err <= px]
            degree[i1][np.unique(m[:, 0])] += 1
            degree[i2][np.unique(m[:, 1])] += 1
        return degree

    def tighten_inliers(self, max_error_px: float = DEFAULT_INLIER_PX, *,
                        min_inliers: int = COLMAP_MIN_INLIERS, refit_below_deg: float = DEFAULT_REFIT_DEG,
                        threads: int | None = None) -> dict:
        """Keep, in every two-view geometry of the database, the inlier matches within ``max_error_px`` of the row's
        own model: the Sampson distance to its F (COLMAP pixels, as the keypoints), or for a planar / panoramic row
        (configuration 4-6) the transfer error of its H or, when smaller, the Sampson distance to its F (such a row
        carries the larger of the two inlier sets, ``planar_inliers="larger"``); at least the ``min_inliers`` closest (COLMAP's mapper uses
        no pair with fewer: ``min_num_matches`` 15), and rows with at most ``min_inliers`` inliers untouched
        (:func:`guidedmatch.geometry.closest_inliers`). Rows without a model (UNDEFINED, DEGENERATE, or no F / H)
        are not touched.

        Why: our verdict decides at 3 px, where random correspondences are rare enough to tell a pair from chance;
        the mapper then triangulates what it is given, and the inliers between 1.5 and 3 px (5-6 % of ours on
        Herz-Jesus and buddha, 22 % on fox) carry more localization error than information (docs/collections.md,
        "The inliers the mapper gets"). Like :meth:`cap_inliers`: only the geometry rows change, each pair in its own transaction, and
        a rerun with the same value changes nothing.

        **Small baselines** (``refit_below_deg`` > 0): the F of a row (configuration other than 4-6, more than 15
        inliers, some beyond ``max_error_px``) whose inliers' median triangulation angle is below ``refit_below_deg``
        degrees (:func:`~guidedmatch.epipolar.median_triangulation_angle`, with the database's camera guesses) is first
        fitted again on those inliers (:func:`~guidedmatch.epipolar.refit_fundamental`; kept, and written to the
        row, only when its median Sampson distance is smaller) and the inliers are selected around the new F. The
        verdict's F is an early fit (one model update), least determined where the baseline is small: on fox
        (video frames, 215 of 2,001 rows refit) the median pose error went from 0.487 to 0.478 deg against COLMAP's
        0.481 (docs/collections.md; refitting every row instead made Herz-Jesus-P8's worse). A refit row's inliers all lie within ``max_error_px`` of its new F
        (or it keeps exactly ``min_inliers``), so a rerun does not refit it again.

        ``threads`` (default: the usable cores): the rows' selections and refits run in that many threads (OpenCV's
        fit and the angle's kernel release the GIL; the database is read and written in this thread, row by row in
        pair-id order): the same rows as in one thread. On fox (2,001 rows, 215 refit), with the compiled angle, 2 threads
        took the pass from 2.7-3.4 s (one thread, NumPy angles) to 1.9-2.6 s (collection history, nineteenth round).

        Returns ``{"max_error_px", "min_inliers", "refit_below_deg", "pairs", "pairs_tightened", "pairs_refit",
        "inliers_before", "inliers_after", "time_s"}`` (``pairs_refit``: rows whose F was replaced).
        """
        from ..epipolar import median_triangulation_angle, refit_fundamental
        from ..geometry import closest_inliers
        from ..validation import check_number

        check_number("tighten_inliers", "max_error_px", max_error_px, lo=0, lo_open=True)
        check_number("tighten_inliers", "min_inliers", min_inliers, lo=0, integer=True)
        check_number("tighten_inliers", "refit_below_deg", refit_below_deg, lo=0, hi=180)
        if threads is None:
            from .planning import _usable_cores

            threads = _usable_cores()
        check_number("tighten_inliers", "threads", threads, lo=1, integer=True)
        px, floor, refit_deg = float(max_error_px), int(min_inliers), float(refit_below_deg)
        K = self._calibration_matrices() if refit_deg > 0 else {}
        refit = []   # list.append is atomic: keep() runs in threads

        def rows(db, iid):
            return (np.asarray(db.read_keypoints(iid))[:, :2].astype(np.float64),)

        def keep(g, m, load, i1, i2):
            (kp1,), (kp2,) = load(i1), load(i2)
            x1, x2 = kp1[m[:, 0]], kp2[m[:, 1]]
            err = _model_error(g, x1, x2)
            if err is None:
                return None
            new_F = None
            if (refit_deg > 0 and int(g.config) not in (4, 5, 6) and g.F is not None and np.any(g.F)
                    and len(m) >= 16 and np.any(err > px)
                    and median_triangulation_angle(np.asarray(g.F), x1, x2, K[i1], K[i2]) < refit_deg):
                new_F, e = refit_fundamental(np.asarray(g.F), x1, x2)
                if new_F is not None:
                    g.F, err = new_F, e
                    refit.append(True)
            idx = closest_inliers(err, px, floor)
            return None if len(idx) == len(m) and new_F is None else idx

        report = self._rewrite_inliers(lambda counts: counts > min_inliers, rows, keep, threads=int(threads))
        return {"max_error_px": px, "min_inliers": floor, "refit_below_deg": refit_deg, "pairs": report["pairs"],
                "pairs_tightened": report["pairs_rewritten"], "pairs_refit": len(refit),
                "inliers_before": report["inliers_before"], "inliers_after": report["inliers_after"],
                "time_s": report["time_s"]}

    def _calibration_matrices(self) -> dict[int, np.ndarray]:
        """Per image id, the calibration matrix of its database camera (COLMAP pixels, as the keypoints)."""
        if self._db is None:
            raise OutputError(f"ColmapSink({self.path}) is closed")
        cams = {int(c.camera_id): np.asarray(c.calibration_matrix(), dtype=np.float64)
                for c in self._db.read_all_cameras()}
        return {int(img.image_id): cams[int(img.camera_id)] for img in self._db.read_all_images()}

    def _rewrite_inliers(self, candidates, rows, keep, cache_bytes: int = 256 << 20, threads: int = 1,
                         chunk: int = 64) -> dict:
        """The pass :meth:`cap_inliers` and :meth:`tighten_inliers` share: for every two-view geometry whose inlier
        count ``candidates(counts)`` selects (in pair-id order), ``keep(g, m, load, i1, i2)`` gives the indices into
        its ``(K, 2)`` inlier matches ``m`` to keep (or None: unchanged), and the row is rewritten with those in its
        own transaction. ``load(image_id)`` returns ``rows(db, image_id)``, kept in a cache of ``cache_bytes`` (oldest
        out first). ``threads`` > 1: the rows are read, then ``keep`` runs on ``chunk`` of them at a time in that many
        threads (it must be a pure function of its row: the result is the same as in one thread), then they are
        written in pair-id order -- all database access stays in this thread. Returns ``{"pairs",
        "pairs_rewritten", "inliers_before", "inliers_after", "time_s"}``."""
        import pycolmap

        if self._db is None:
            raise OutputError(f"ColmapSink({self.path}) is closed")
        t0 = time.perf_counter()
        db = self._db
        pids, counts = (np.asarray(a, dtype=np.int64) for a in db.read_two_view_geometry_num_inliers())
        report = {"pairs": int(np.count_nonzero(counts)), "pairs_rewritten": 0,
                  "inliers_before": int(counts.sum()), "inliers_after": int(counts.sum())}
        cache: dict[int, tuple] = {}

        def load(iid: int):
            if iid not in cache:
                while cache and sum(a.nbytes for c in cache.values() for a in c if isinstance(a, np.ndarray)) \
                        > cache_bytes:
                    cache.pop(next(iter(cache)))   # oldest first
                cache[iid] = rows(db, iid)
            return cache[iid]

        def read(pid: int):
            i1, i2 = (int(i) for i in pycolmap.pair_id_to_image_pair(pid))
            g = db.read_two_view_geometry(i1, i2)
            m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            return g, m, i1, i2, {i1: load(i1), i2: load(i2)}

        def decide(row):
            g, m, i1, i2, loaded = row
            return keep(g, m, loaded.__getitem__, i1, i2)

        todo = np.sort(pids[candidates(counts)])
        step = chunk if threads > 1 else 1
        with ThreadPoolExecutor(threads) if threads > 1 else contextlib.nullcontext() as pool:
            for s0 in range(0, len(todo), step):
                batch = [read(int(pid)) for pid in todo[s0:s0 + step]]
                for row, idx in zip(batch, pool.map(decide, batch) if pool else map(decide, batch)):
                    self._write_kept(db, row, idx, report)   # in order, while the pool decides the next rows
        report["time_s"] = time.perf_counter() - t0
        return report

    def _write_kept(self, db, row, idx, report: dict) -> None:
        """Rewrite one row of :meth:`_rewrite_inliers` with the inliers ``idx`` it keeps (None: unchanged)."""
        import pycolmap

        g, m, i1, i2, _ = row
        if idx is None:
            return
        g.inlier_matches = np.ascontiguousarray(m[idx], dtype=np.uint32).reshape(-1, 2)
        self.check_space(g.inlier_matches.nbytes)
        with pycolmap.DatabaseTransaction(db):
            db.update_two_view_geometry(i1, i2, g)
        report["pairs_rewritten"] += 1
        report["inliers_after"] -= len(m) - len(idx)

    def close(self) -> None:
        db, self._db = self._db, None
        if db is not None:
            db.close()
        lock = getattr(self, "_lock", None)
        if lock is not None:
            lock.release()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def cap_two_view_inliers(database_path: str | os.PathLike, max_inliers: int, *, grid: int = 16,
                         order: str = "track", above: int = 0) -> dict:
    """:meth:`ColmapSink.cap_inliers` on a COLMAP database (under the sink's write lock), e.g. after
    ``colmap exhaustive_matcher``: every two-view geometry keeps at most ``max_inliers`` spread, best-first inliers
    (``order``: :data:`CAP_ORDERS`) -- when the database holds more than ``above`` inliers in all (0: always).

    >>> cap_two_view_inliers("missing.db", 1000)
    Traceback (most recent call last):
    ...
    guidedmatch.errors.DatabaseError: COLMAP database not found: missing.db
    """
    with ColmapSink(database_path, geometry="none") as sink:
        return sink.cap_inliers(max_inliers, grid=grid, order=order, above=above)


def tighten_two_view_inliers(database_path: str | os.PathLike, max_error_px: float = DEFAULT_INLIER_PX, *,
                             min_inliers: int = COLMAP_MIN_INLIERS, refit_below_deg: float = DEFAULT_REFIT_DEG,
                             threads: int | None = None) -> dict:
    """:meth:`ColmapSink.tighten_inliers` on a COLMAP database (under the sink's write lock): every two-view
    geometry keeps its inliers within ``max_error_px`` of its own F / H (at least the ``min_inliers`` closest), the F
    of small-baseline rows (median triangulation angle < ``refit_below_deg``; 0 = never) fitted again first, in
    ``threads`` threads (default: the usable cores).

    >>> tighten_two_view_inliers("missing.db", 1.5)
    Traceback (most recent call last):
    ...
    guidedmatch.errors.DatabaseError: COLMAP database not found: missing.db
    """
    with ColmapSink(database_path, geometry="none") as sink:
        return sink.tighten_inliers(max_error_px, min_inliers=min_inliers, refit_below_deg=refit_below_deg,
                                    threads=threads)
