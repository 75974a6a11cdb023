"""Epipolar geometry: robust fundamental matrix, epipolar distances and the band test.

Teng & Dong §III-D ("Feature filtering based on epipolar geometry"): once ``F`` is estimated from the
matches found so far, an image-2 feature ``x2`` is a candidate for the image-1 feature ``x1`` only when
its distance to the epipolar line ``l = F x1`` is at most a band half-width (default 5 px).

Conventions (see ``docs/CONVENTIONS.md``):

* Points are ``(N, 2) float64`` pixel coordinates, OpenCV convention (origin at the centre of the
  top-left pixel, x right, y down); homogeneous ``[x, y, 1]^T`` column vectors.
* ``F`` satisfies ``x2^T F x1 = 0`` (image 1 -> image 2, OpenCV's ``findFundamentalMat`` order).
  Every ``F`` returned here has rank 2, ``||F||_F = 1`` and a deterministic sign (the entry of largest
  magnitude is positive).
* Degenerate or invalid input never raises: :func:`estimate_fundamental` returns a falsy
  :class:`guidedmatch.results.Failure` with a reason. Distance functions return ``NaN`` for points
  whose epipolar line is undefined (``x1`` at the epipole) and :func:`in_band` treats ``NaN`` as
  outside the band.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .base import Failure

__all__ = [
    "FundamentalResult",
    "USAC_METHODS",
    "estimate_fundamental",
    "normalize_fundamental",
    "epipoles",
    "epipolar_lines",
    "point_line_distance",
    "sampson_distance",
    "symmetric_epipolar_distance",
    "in_band",
    "transform_fundamental",
    "check_points",
    "map_points",
    "skew",
    "median_triangulation_angle",
    "refit_fundamental",
]

#: Minimum number of correspondences accepted by :func:`estimate_fundamental` (8-point solver size).
MIN_POINTS = 8

#: Robust estimators selectable by name -> (sampler, score, local optimisation, LO sample size,
#: LO iterations). These mirror OpenCV's ``USAC_*`` presets (``calib3d/src/usac/ransac_solvers.cpp``
#: ``setParameters``) but are run through ``cv2.UsacParams`` so that the random generator state
#: (``seed``) can be set. ``"ransac"``/``"lmeds"`` are USAC with the plain RANSAC / LMedS score and
#: no local optimisation (seeded too, unlike the legacy ``cv2.FM_RANSAC``/``cv2.FM_LMEDS``). The names are
#: :data:`guidedmatch.base.USAC_METHOD_NAMES`, which the configs validate against without importing OpenCV.
USAC_METHODS: dict[str, tuple[int, int, int, int, int]] = {
    "magsac": (cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MAGSAC, cv2.LOCAL_OPTIM_SIGMA, 50, 10),
    "accurate": (cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MSAC, cv2.LOCAL_OPTIM_GC, 20, 25),
    "default": (cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MSAC, cv2.LOCAL_OPTIM_INNER_AND_ITER_LO, 12, 20),
    "prosac": (cv2.SAMPLING_PROSAC, cv2.SCORE_METHOD_MSAC, cv2.LOCAL_OPTIM_INNER_LO, 12, 20),
    "ransac": (cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_RANSAC, cv2.LOCAL_OPTIM_NULL, 12, 20),
    "lmeds": (cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_LMEDS, cv2.LOCAL_OPTIM_NULL, 12, 20),
}


@dataclass(frozen=True)
class FundamentalResult:
    """A robustly estimated fundamental matrix (truthy).

    Attributes:
        F: ``(3, 3) float64``, ``x2^T F x1 = 0``, rank 2, ``||F||_F = 1``, largest-magnitude entry > 0.
        inliers: ``(N,) bool`` inlier mask over the input correspondences (as returned by USAC).
        num_inliers: ``int(inliers.sum())``.
        method: the method name used (a key of :data:`USAC_METHODS`).
        threshold: the inlier threshold in pixels passed to USAC (for MAGSAC++ the maximum noise sigma).
        stats: ``num_points``, ``inlier_ratio``, ``sampson_median_px`` / ``sampson_max_px`` over the
            inliers, ``singular_values`` of the raw USAC matrix, ``seed``, ``time_s``.
    """

    F: np.ndarray
    inliers: np.ndarray
    num_inliers: int
    method: str
    threshold: float
    stats: dict = field(default_factory=dict)

    def __bool__(self) -> bool:  # noqa: D105 - truthy by design (Failure is falsy)
        return True


# ----------------------------------------------------------------------------------------- helpers
def skew(v) -> np.ndarray:
    """``[v]_x``, the ``(3, 3) float64`` cross-product matrix of a 3-vector: ``skew(v) @ w == cross(v, w)``
    (used in ``F = K2^-T [t]_x R K1^-1`` and ``E = [t]_x R``).

    >>> skew([1.0, 2.0, 3.0]) @ [4.0, 5.0, 6.0]  # = cross((1, 2, 3), (4, 5, 6))
    array([-3.,  6., -3.])
    """
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _h(pts: np.ndarray) -> np.ndarray:
    """``(N, 2)`` -> homogeneous ``(N, 3)``."""
    return np.hstack([pts, np.ones((len(pts), 1))])


def map_points(M: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``(N, 3)`` rows ``M @ (x, y, 1)`` of ``(N, 2)`` points ``pts`` for a ``(3, 3)`` matrix (F, H, ...).

    Written out element-wise on purpose: a ``(N, 3) @ (3, 3)`` product goes to a multi-threaded BLAS GEMM,
    whose threads then spin for tens of milliseconds and slow the Numba parallel kernel that follows (measured
    on 2 cores: the guided final pass 29 -> 46 ms).
    """
    M = np.asarray(M, np.float64)
    p = np.asarray(pts, np.float64).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    out = np.empty((len(p), 3))
    for k in range(3):
        out[:, k] = M[k, 0] * x + M[k, 1] * y + M[k, 2]
    return out


def check_points(x1, x2, min_points: int = MIN_POINTS) -> tuple[np.ndarray, np.ndarray] | Failure:
    """Validate a correspondence set: two ``(N, 2)`` finite arrays of equal length, ``N >= min_points``,
    neither image's points all (nearly) collinear or coincident.

    Collinearity test: the smaller singular value of the centred coordinates is below
    ``1e-9 * (1 + larger)`` (scale-aware), i.e. the points span no 2-D area.

    Returns:
        ``(x1, x2)`` as contiguous ``float64`` arrays, or a :class:`Failure` with the reason.
    """
    try:
        a = np.asarray(x1, dtype=np.float64)
        b = np.asarray(x2, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        return Failure(f"points are not numeric arrays ({exc})")
    if a.ndim != 2 or b.ndim != 2 or a.shape[1:] != (2,) or b.shape[1:] != (2,):
        return Failure(f"points must be (N, 2) arrays; got {a.shape} and {b.shape}")
    if len(a) != len(b):
        return Failure(f"x1 and x2 differ in length ({len(a)} vs {len(b)})")
    n = len(a)
    if n < min_points:
        return Failure(f"fewer than {min_points} correspondences ({n})", {"num_points": n})
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        bad = int((~np.isfinite(a).all(1) | ~np.isfinite(b).all(1)).sum())
        return Failure(f"non-finite coordinates (NaN/inf) in {bad} correspondences", {"num_bad": bad})
    for name, p in (("image 1", a), ("image 2", b)):
        s = np.linalg.svd(p - p.mean(0), compute_uv=False)
        if len(s) < 2 or s[1] <= 1e-9 * (1.0 + s[0]):
            return Failure(f"degenerate configuration: all points of {name} are collinear", {"image": name})
    return np.ascontiguousarray(a), np.ascontiguousarray(b)


def normalize_fundamental(F: np.ndarray) -> np.ndarray | Failure:
    """Project a ``3x3`` matrix to rank 2 (zero the smallest singular value), scale to ``||F||_F = 1``
    and fix the sign (largest-magnitude entry positive).

    Returns a :class:`Failure` when ``F`` is non-finite or its rank is below 2 (second singular value
    ``<= 1e-10`` times the first): such a matrix has no unique pair of epipoles.
    """
    F = np.asarray(F, dtype=np.float64)
    if F.shape != (3, 3) or not np.isfinite(F).all():
        return Failure("fundamental matrix is not a finite 3x3 matrix")
    U, s, Vt = np.linalg.svd(F)
    if s[0] <= 0 or s[1] <= 1e-10 * s[0]:
        return Failure(f"fundamental matrix has rank < 2 (singular values {s.tolist()})",
                       {"singular_values": s.tolist()})
    F2 = (U[:, :2] * s[:2]) @ Vt[:2]
    F2 /= np.linalg.norm(F2)
    k = np.argmax(np.abs(F2))
    if F2.flat[k] < 0:
        F2 = -F2
    return F2


# ------------------------------------------------------------------------------------- estimation
def estimate_fundamental(
    x1,
    x2,
    *,
    method: str = "magsac",
    threshold: float = 1.5,
    confidence: float = 0.999,
    max_iters: int = 10000,
    seed: int = 0,
) -> FundamentalResult | Failure:
    """Robust fundamental matrix from matched coordinates with OpenCV USAC (Teng & Dong §III-D).

    Args:
        x1, x2: ``(N, 2)`` matched pixel coordinates in image 1 / image 2 (row ``i`` of each is one
            correspondence). ``N >= 8``.
        method: a key of :data:`USAC_METHODS`; default ``"magsac"`` = MAGSAC++ (``cv2.USAC_MAGSAC``).
        threshold: inlier threshold in pixels (Sampson distance; for MAGSAC++ the maximum sigma).
        confidence: RANSAC confidence.
        max_iters: maximum number of USAC iterations.
        seed: USAC random generator state (``cv2.UsacParams.randomGeneratorState``); same input and
            seed -> same output. The global ``cv2`` RNG is not touched.

    Note: OpenCV's USAC converts the points to float32, so even noiseless correspondences leave
    residual epipolar distances of up to ~1e-3 px (for coordinates of a few hundred pixels).

    Returns:
        :class:`FundamentalResult` (truthy), or a falsy :class:`Failure` when there are fewer than 8
        correspondences, non-finite coordinates, collinear points, when USAC finds no model, the
        model has rank < 2, or fewer than 8 inliers support it.

    >>> import numpy as np
    >>> from guidedmatch.testing.twoview import general_pair
    >>> s = general_pair(rng=0, n_points=200, noise=0.3)          # known F, 0.3 px noise
    >>> x2 = s.x2n.copy(); x2[:40] = np.random.default_rng(1).uniform(0, 640, (40, 2))   # 20 % outliers
    >>> res = estimate_fundamental(s.x1n, x2)
    >>> bool(res), res.F.shape, bool(res.inliers[:40].sum() < 5), bool(res.inliers[40:].mean() > 0.95)
    (True, (3, 3), True, True)
    >>> estimate_fundamental(s.x1n[:5], x2[:5]).reason
    'fewer than 8 correspondences (5)'
    """
    t0 = time.perf_counter()
    if method not in USAC_METHODS:
        return Failure(f"unknown method {method!r}; choose one of {sorted(USAC_METHODS)}")
    checked = check_points(x1, x2)
    if not checked:
        return checked
    a, b = checked
    sampler, score, lo, lo_size, lo_iters = USAC_METHODS[method]
    params = cv2.UsacParams()
    params.threshold = float(threshold)
    params.confidence = float(confidence)
    params.maxIterations = int(max_iters)
    params.sampler = sampler
    params.score = score
    params.loMethod = lo
    params.loSampleSize = lo_size
    params.loIterations = lo_iters
    params.isParallel = False
    params.randomGeneratorState = int(seed) & 0x7FFFFFFF
    if score == cv2.SCORE_METHOD_MAGSAC:
        params.final_polisher = cv2.MAGSAC
    try:
        F, mask = cv2.findFundamentalMat(a, b, params)
    except cv2.error as exc:  # OpenCV rejects some degenerate samples with an exception
        return Failure(f"OpenCV USAC failed: {str(exc).strip().splitlines()[-1]}", {"method": method})
    if F is None or np.asarray(F).size == 0:
        return Failure("USAC found no fundamental matrix (degenerate configuration?)", {"method": method})
    F = np.asarray(F, dtype=np.float64)
    if F.shape != (3, 3):  # 7-point solver may stack several solutions; keep the first
        F = F[:3]
    raw_s = np.linalg.svd(F, compute_uv=False) if np.isfinite(F).all() else np.full(3, np.nan)
    Fn = normalize_fundamental(F)
    if isinstance(Fn, Failure):
        return Fn
    inliers = np.zeros(len(a), bool) if mask is None else (np.asarray(mask).reshape(-1) != 0)
    n_in = int(inliers.sum())
    if n_in < MIN_POINTS:
        return Failure(f"only {n_in} inliers support the fundamental matrix (< {MIN_POINTS})",
                       {"num_inliers": n_in, "method": method})
    d = sampson_distance(Fn, a[inliers], b[inliers])
    stats = {
        "num_points": len(a),
        "inlier_ratio": n_in / len(a),
        "sampson_median_px": float(np.median(d)),
        "sampson_max_px": float(np.max(d)),
        "singular_values": raw_s.tolist(),
        "seed": int(seed),
        "time_s": time.perf_counter() - t0,
    }
    return FundamentalResult(F=Fn, inliers=inliers, num_inliers=n_in, method=method,
                             threshold=float(threshold), stats=stats)


# -------------------------------------------------------------------------------------- distances
def epipoles(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epipoles of ``F`` as unit homogeneous 3-vectors ``(e1, e2)``: ``F e1 = 0`` (image 1, the image
    of camera 2's centre) and ``F^T e2 = 0`` (image 2). Sign: last coordinate >= 0."""
    U, _, Vt = np.linalg.svd(np.asarray(F, dtype=np.float64))
    e1, e2 = Vt[2].copy(), U[:, 2].copy()
    if e1[2] < 0:
        e1 = -e1
    if e2[2] < 0:
        e2 = -e2
    return e1, e2


def epipolar_lines(F: np.ndarray, x1) -> np.ndarray:
    """Epipolar lines in image 2 of image-1 points: ``l = F x1`` (Teng & Dong §III-D).

    Args:
        F: ``(3, 3)`` with ``x2^T F x1 = 0``.
        x1: ``(M, 2)`` image-1 pixel coordinates.

    Returns:
        ``(M, 3)`` lines ``(a, b, c)`` (``a x + b y + c = 0`` in image-2 pixels) scaled so that
        ``a^2 + b^2 = 1``; rows are ``NaN`` where the line is undefined (``x1`` at the epipole).
    """
    x1 = np.asarray(x1, dtype=np.float64).reshape(-1, 2)
    lines = map_points(F, x1)
    nrm = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        out = lines / nrm[:, None]
    out[~(nrm > 0)] = np.nan
    return out


def point_line_distance(F: np.ndarray, x1, x2) -> np.ndarray:
    """Distance in image-2 pixels from ``x2`` to the epipolar line ``F x1`` (``(M,)``; ``NaN`` where the
    line is undefined). ``x1``, ``x2``: ``(M, 2)`` corresponding rows."""
    lines = epipolar_lines(F, x1)
    x2 = np.asarray(x2, dtype=np.float64).reshape(-1, 2)
    return np.abs(lines[:, 0] * x2[:, 0] + lines[:, 1] * x2[:, 1] + lines[:, 2])


def sampson_distance(F: np.ndarray, x1, x2) -> np.ndarray:
    """Sampson distance in pixels (``(M,)``), the first-order approximation of the geometric
    (reprojection) error of a correspondence:

        ``sqrt( (x2^T F x1)^2 / ((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2) )``.

    Note: the square root is taken (OpenCV's ``computeSampsonDistance`` returns the square).
    ``NaN`` where the denominator is 0.
    """
    F = np.asarray(F, dtype=np.float64)
    h2 = _h(np.asarray(x2, dtype=np.float64).reshape(-1, 2))
    Fx1 = map_points(F, x1)
    Ftx2 = map_points(F.T, x2)
    num = np.einsum("ij,ij->i", h2, Fx1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(num) / np.sqrt(den)
    d[~(den > 0)] = np.nan
    return d


def symmetric_epipolar_distance(F: np.ndarray, x1, x2, reduce: str = "mean") -> np.ndarray:
    """Symmetric epipolar distance in pixels (``(M,)``): the point-line distances in both images,
    ``d2 = d(x2, F x1)`` and ``d1 = d(x1, F^T x2)``, combined by ``reduce``: ``"mean"`` (default,
    ``(d1 + d2) / 2``) or ``"max"``."""
    d2 = point_line_distance(F, x1, x2)
    d1 = point_line_distance(np.asarray(F).T, x2, x1)
    if reduce == "mean":
        return 0.5 * (d1 + d2)
    if reduce == "max":
        return np.maximum(d1, d2)
    raise ValueError(f"reduce must be 'mean' or 'max', got {reduce!r}")


def in_band(F: np.ndarray, x1, x2, band: float = 5.0) -> np.ndarray:
    """Band test of Teng & Dong §III-D: ``(M,) bool``, True where ``x2`` lies within ``band`` pixels
    (inclusive) of the epipolar line ``F x1`` in image 2. Undefined lines (``NaN``) are outside."""
    d = point_line_distance(F, x1, x2)
    with np.errstate(invalid="ignore"):
        return d <= band


def transform_fundamental(F: np.ndarray, H1: np.ndarray | None = None, H2: np.ndarray | None = None) -> np.ndarray:
    """Fundamental matrix for transformed coordinates ``x1' = H1 x1``, ``x2' = H2 x2``:
    ``F' = H2^-T F H1^-1`` (``None`` = identity), rank 2 and scaled to ``||F'||_F = 1``.

    Use it to run the band test in aligned coordinates (Teng & Dong §III-E): distances computed with
    ``F'`` on aligned points are in aligned-image pixels.
    """
    F = np.asarray(F, dtype=np.float64)
    A = F if H1 is None else F @ np.linalg.inv(np.asarray(H1, dtype=np.float64))
    if H2 is not None:
        A = np.linalg.inv(np.asarray(H2, dtype=np.float64)).T @ A
    n = np.linalg.norm(A)
    return A / n if n > 0 else A


def median_triangulation_angle(F: np.ndarray, x1, x2, K1: np.ndarray, K2: np.ndarray) -> float:
    """Median angle (degrees) between the two viewing rays of the correspondences ``x1 <-> x2`` (pixels of the
    cameras ``K1``, ``K2``) under the relative pose of ``E = K2^T F K1``: for a ray pair that meets in a point, the
    angle at that point between the two camera centres (the triangulation angle). Of the four poses of E
    (``cv2.decomposeEssentialMat``) the one with the most correspondences in front of both cameras is taken, the
    depths solved per ray pair in closed form (``cv2.recoverPose`` counts no point beyond 50 baselines, so below
    ~1 deg it cannot choose). NaN when fewer than 5 correspondences or ``E`` is zero or not finite.

    What it is for: telling a small-baseline pair (adjacent video frames: a few degrees) from a wide one before the
    mapper gets its inliers (:meth:`guidedmatch.collection.ColmapSink.tighten_inliers`, ``refit_below_deg``). With
    the database's camera guesses (focal 1.2 x the larger side when nothing is known) it is an estimate.

    >>> from guidedmatch.testing.twoview import general_pair
    >>> s = general_pair(rng=0, n_points=200, baseline=0.1)     # 0.1 units sideways, 4-8 units away: ~1 deg
    >>> round(median_triangulation_angle(s.F, s.x1, s.x2, s.K1, s.K2), 2)
    0.74
    """
    x1, x2 = (np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 2)) for x in (x1, x2))
    if len(x1) < 5 or len(x1) != len(x2):
        return float("nan")
    K1, K2 = np.asarray(K1, dtype=np.float64), np.asarray(K2, dtype=np.float64)
    E = K2.T @ np.asarray(F, dtype=np.float64) @ K1
    if not (np.isfinite(E).all() and np.any(E)):
        return float("nan")
    Ra, Rb, t = cv2.decomposeEssentialMat(E)
    from ._epipolar_kernels import median_ray_angle

    # the rays and the four poses' depths in one compiled pass per row (nogil: the collection's tightening runs its
    # rows in threads); tests/test_epipolar.py checks it against the NumPy formulation, vectorized over the rays
    return float(median_ray_angle(x1, x2, np.linalg.inv(K1), np.linalg.inv(K2), np.stack([Ra, Rb]), t.ravel()))


def refit_fundamental(F: np.ndarray, x1, x2, *, threshold: float = 1.0, seed: int = 0):
    """``F`` fitted again on the (verified) inliers ``x1 <-> x2`` (USAC MAGSAC++, ``threshold`` px, 10,000 iterations,
    ``seed``): ``(F_new, sampson_errors)`` when its median Sampson distance over *all* of them is at most ``F``'s,
    else ``(None, errors_to_F)`` -- a refit is kept only where it fits these inliers better.

    >>> from guidedmatch.testing.twoview import general_pair
    >>> s = general_pair(rng=0, n_points=200, noise=0.3)
    >>> F_new, err = refit_fundamental(s.F + 1e-7 * np.eye(3), s.x1n, s.x2n)   # a slightly wrong F
    >>> F_new is not None and bool(np.median(err) < 0.3)
    True
    """
    x1, x2 = (np.asarray(x, dtype=np.float64).reshape(-1, 2) for x in (x1, x2))
    err = sampson_distance(np.asarray(F, dtype=np.float64), x1, x2)
    fit = estimate_fundamental(x1, x2, threshold=threshold, confidence=0.9999, max_iters=10000, seed=seed)
    if not fit:
        return None, err
    e = sampson_distance(fit.F, x1, x2)
    return (fit.F, e) if np.median(e) <= np.median(err) else (None, err)
