"""Ground truth of an image pair: a homography (:class:`HomographyGT`) or cameras (:class:`EpipolarGT`), and the
pair itself (:class:`Pair`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..alignment import apply_homography
from ..epipolar import skew, symmetric_epipolar_distance
from ..features import load_image
from .root import _image_size, _read_image

#: The paper's correctness threshold (Sec. IV-A): a match is correct if its GT error is below 3 px.
DEFAULT_THRESHOLD = 3.0


def _as_points(pts: Any) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 2))
    return p.reshape(-1, 2)


def _pixel_scale_matrix(s: float) -> np.ndarray:
    """3x3 map of pixel coords under image resizing by ``s`` (pixel-centre convention):
    ``x' = s (x + 0.5) - 0.5``."""
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])


def _inside(pts: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """Points inside an image of ``size = (w, h)``: ``x in [-0.5, w - 0.5]``, same for y."""
    if size is None:
        return np.isfinite(pts).all(axis=1)
    w, h = size
    with np.errstate(invalid="ignore"):
        return (pts[:, 0] >= -0.5) & (pts[:, 0] <= w - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] <= h - 0.5)


@dataclass(frozen=True, eq=False)
class HomographyGT:
    """Planar ground truth (Oxford, synthetic): image-1 pixel ``p1`` corresponds to ``proj(H p1)``.

    A match ``(p1, p2)`` is correct (paper Sec. IV-A) iff ``||proj(H p1) - p2|| < threshold`` (3 px),
    ``p1`` lies inside image 1 and ``proj(H p1)`` inside image 2 (the inside tests are skipped for an
    image whose size is ``None``).

    Attributes:
        H: ``(3, 3) float64`` homography, image-1 pixels -> image-2 pixels, column vectors.
        size1, size2: ``(w, h)`` of image 1 / image 2 in pixels, or ``None`` if unknown.
    """

    H: np.ndarray
    size1: tuple[int, int] | None = None
    size2: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        H = np.asarray(self.H, dtype=np.float64).reshape(3, 3)
        object.__setattr__(self, "H", H)

    def project(self, pts1: Any) -> np.ndarray:
        """Image-2 positions ``(N, 2)`` of image-1 points ``(N, 2)``: ``proj(H p1)``, NaN where undefined
        (mapped ``w <= 0``: :func:`~guidedmatch.alignment.apply_homography` with ``in_front=True``)."""
        return apply_homography(self.H, _as_points(pts1), in_front=True)

    def error(self, pts1: Any, pts2: Any) -> np.ndarray:
        """Transfer error ``||proj(H p1) - p2||`` in image-2 pixels, ``(M,) float64`` (inf where undefined)."""
        p1, p2 = _as_points(pts1), _as_points(pts2)
        e = np.linalg.norm(self.project(p1) - p2, axis=1)
        e[~np.isfinite(e)] = np.inf
        return e

    def correct(self, pts1: Any, pts2: Any, threshold: float = DEFAULT_THRESHOLD) -> np.ndarray:
        """``(M,) bool``: transfer error < ``threshold`` and both ends inside their images."""
        p1 = _as_points(pts1)
        proj = self.project(p1)
        e = self.error(p1, pts2)
        return (e < threshold) & _inside(p1, self.size1) & _inside(proj, self.size2)

    def rescaled(self, scale1: float, scale2: float) -> "HomographyGT":
        """Ground truth for image 1 resized by ``scale1`` and image 2 by ``scale2`` (pixel-centre convention)."""
        S1, S2 = _pixel_scale_matrix(scale1), _pixel_scale_matrix(scale2)
        sz = lambda s, k: None if s is None else (int(round(s[0] * k)), int(round(s[1] * k)))  # noqa: E731
        return HomographyGT(S2 @ self.H @ np.linalg.inv(S1), sz(self.size1, scale1), sz(self.size2, scale2))


@dataclass(frozen=True, eq=False)
class EpipolarGT:
    """Two-view ground truth from calibrated poses (Strecha pairs).

    Convention (SuperGlue ``pairs_with_gt``): ``X_cam2 = R X_cam1 + t``; essential matrix ``E = [t]_x R``
    with ``x2^T E x1 = 0`` for normalised coordinates; fundamental ``F = K2^-T [t]_x R K1^-1`` with
    ``[u2 v2 1] F [u1 v1 1]^T = 0`` for pixels. A match is correct iff the symmetric point-to-epipolar-line
    distance (:func:`guidedmatch.epipolar.symmetric_epipolar_distance`, the mean of the two point-to-line
    distances in pixels) is below ``threshold`` (3 px). Only the epipolar constraint is checked: a wrong match
    sliding along its epipolar line counts as correct.

    Attributes:
        F: ``(3, 3)`` fundamental matrix (image 1 -> image 2), scaled to unit Frobenius norm.
        K1, K2: ``(3, 3)`` intrinsics; R: ``(3, 3)``; t: ``(3,)`` (metres for Strecha).
        size1, size2: ``(w, h)`` or ``None``; when given, points outside their image are not correct.
    """

    F: np.ndarray
    K1: np.ndarray | None = None
    K2: np.ndarray | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    size1: tuple[int, int] | None = None
    size2: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        F = np.asarray(self.F, dtype=np.float64).reshape(3, 3)
        n = np.linalg.norm(F)
        object.__setattr__(self, "F", F / n if n > 0 else F)
        for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("R", (3, 3)), ("t", (3,))):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, np.asarray(v, dtype=np.float64).reshape(shape))

    @classmethod
    def from_pose(cls, K1: Any, K2: Any, R: Any, t: Any, size1=None, size2=None) -> "EpipolarGT":
        """Build from intrinsics and relative pose ``X_cam2 = R X_cam1 + t``: ``F = K2^-T [t]_x R K1^-1``."""
        K1 = np.asarray(K1, dtype=np.float64).reshape(3, 3)
        K2 = np.asarray(K2, dtype=np.float64).reshape(3, 3)
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        F = np.linalg.inv(K2).T @ skew(t) @ R @ np.linalg.inv(K1)
        return cls(F, K1, K2, R, t, size1, size2)

    def error(self, pts1: Any, pts2: Any) -> np.ndarray:
        """Symmetric point-to-epipolar-line distance in pixels, ``(M,) float64``; ``inf`` where a line is
        undefined (a point at an epipole, or non-finite input), where the epipolar module gives NaN: a GT error
        is "infinitely wrong", never missing (``error < threshold`` is False either way)."""
        d = symmetric_epipolar_distance(self.F, _as_points(pts1), _as_points(pts2))
        d[np.isnan(d)] = np.inf
        return d

    def correct(self, pts1: Any, pts2: Any, threshold: float = DEFAULT_THRESHOLD) -> np.ndarray:
        """``(M,) bool``: symmetric epipolar distance < ``threshold`` (and both points inside their images)."""
        p1, p2 = _as_points(pts1), _as_points(pts2)
        return (self.error(p1, p2) < threshold) & _inside(p1, self.size1) & _inside(p2, self.size2)

    def rescaled(self, scale1: float, scale2: float) -> "EpipolarGT":
        """Ground truth for images resized by ``scale1`` / ``scale2`` (pixel-centre convention).

        ``K`` is mapped by the same pixel-scaling matrix; ``R``, ``t`` are unchanged.
        """
        S1, S2 = _pixel_scale_matrix(scale1), _pixel_scale_matrix(scale2)
        F = np.linalg.inv(S2).T @ self.F @ np.linalg.inv(S1)
        sz = lambda s, k: None if s is None else (int(round(s[0] * k)), int(round(s[1] * k)))  # noqa: E731
        K1 = None if self.K1 is None else S1 @ self.K1
        K2 = None if self.K2 is None else S2 @ self.K2
        return EpipolarGT(F, K1, K2, self.R, self.t, sz(self.size1, scale1), sz(self.size2, scale2))


GroundTruth = HomographyGT | EpipolarGT


@dataclass(frozen=True, eq=False)
class Pair:
    """One image pair with ground truth.

    Attributes:
        name: unique id, e.g. ``"oxford/bikes/1-2"``, ``"strecha/Herz-Jesus-P8/0000-0001"``,
            ``"synthetic/set3/0007"``.
        image1, image2: a file path, or an in-memory ``uint8`` image (``(H, W)`` grey or ``(H, W, 3)`` BGR)
            for synthetic pairs.
        gt: :class:`HomographyGT` or :class:`EpipolarGT` (image 1 -> image 2).
        meta: dataset-specific extras (sequence, sizes, generation parameters, ...).
    """

    name: str
    image1: Path | np.ndarray
    image2: Path | np.ndarray
    gt: HomographyGT | EpipolarGT
    meta: dict[str, Any] = field(default_factory=dict)

    def load(self, grey: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Both images as ``uint8`` arrays (grey ``(H, W)`` if ``grey``, else BGR ``(H, W, 3)``)."""
        return self._load_one(self.image1, grey), self._load_one(self.image2, grey)

    @staticmethod
    def _load_one(src: Path | np.ndarray, grey: bool) -> np.ndarray:
        if isinstance(src, np.ndarray):
            return load_image(src, grey=grey)
        return _read_image(Path(src), grey)

    @property
    def sizes(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """``((w1, h1), (w2, h2))``."""
        out = []
        for src in (self.image1, self.image2):
            if isinstance(src, np.ndarray):
                out.append((int(src.shape[1]), int(src.shape[0])))
            else:
                out.append(_image_size(Path(src)))
        return out[0], out[1]
