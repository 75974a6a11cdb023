"""Evaluation data: image pairs with ground truth (Teng & Dong, Sec. IV).

Three sources, all read in place from the shared data folder (see ``../shared/data/SOURCES.md``):

* :func:`oxford_pairs` -- Oxford affine-covariant sequences (Sec. IV-A), ground truth = the
  dataset homography ``H1toN`` (:class:`HomographyGT`).
* :func:`strecha_pairs` -- real high-resolution pairs (Strecha Herz-Jesus-P8) with ground-truth
  intrinsics and relative pose (:class:`EpipolarGT`); stands in for the paper's real images (Sec. IV-C),
  for which the paper had no ground truth.
* :func:`synthetic_pairs` -- the simulated set of Sec. IV-B (after Dosovitskiy et al. 2016, plus a
  perspective warp), generated lazily and deterministically from ``photos/unsplash/``; ground truth = the
  generated homography.

Coordinates follow the package convention: pixels, origin at the *centre* of the top-left pixel,
x right, y down, arrays ``(N, 2) float64``. An image of width ``w`` covers ``x in [-0.5, w - 0.5]``.

The data root is the one configurable path (:func:`data_root`): an explicit override, else the
environment variable ``GUIDEDMATCH_DATA``, else ``../shared/data`` relative to the current directory or
to the repository root.
"""
from __future__ import annotations

import functools
import os
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataNotFoundError
from .alignment import apply_homography
from .epipolar import skew, symmetric_epipolar_distance
from .features import load_image

ENV_VAR = "GUIDEDMATCH_DATA"
#: The paper's correctness threshold (Sec. IV-A): a match is correct if its GT error is below 3 px.
DEFAULT_THRESHOLD = 3.0
OXFORD_SEQUENCES = ("bikes", "wall", "boat", "leuven", "ubc", "graf")  # the paper's six (Fig. 4)
OXFORD_ALL_SEQUENCES = OXFORD_SEQUENCES + ("bark",)  # bark: extra, large in-plane rotations
STRECHA_PAIRS_FILE = Path("pose_pairs") / "strecha" / "strecha_pairs_with_gt.txt"
PHOTOS_DIR = Path("photos") / "unsplash"
_IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")

# --------------------------------------------------------------------------------------------------
# data root
# --------------------------------------------------------------------------------------------------


def _repo_root() -> Path:
    """The repository root: the parent of ``src/`` (this file is ``src/guidedmatch/datasets.py``)."""
    return Path(__file__).resolve().parents[2]


def data_root(override: str | os.PathLike | None = None) -> Path | None:
    """The evaluation data folder, or ``None`` when it cannot be found.

    Resolution order:

    1. ``override`` if given (returned as is, even if missing, so a wrong explicit path fails loudly later);
    2. the environment variable ``GUIDEDMATCH_DATA`` if set and non-empty (same: returned as is);
    3. ``../shared/data`` relative to the current directory, then relative to the repository root
       (the parent of ``src/``); the first that is an existing directory wins;
    4. ``None``: tests needing data skip, benchmarks report how to set ``GUIDEDMATCH_DATA``.
    """
    if override is not None:
        return Path(override).expanduser()
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        return Path(env).expanduser()
    for base in (Path.cwd(), _repo_root()):
        cand = (base / ".." / "shared" / "data").resolve()
        if cand.is_dir():
            return cand
    return None


def _require_root(root: str | os.PathLike | None) -> Path:
    r = data_root(root)
    if r is None:
        raise DataNotFoundError(
            "evaluation data folder not found (looked for ../shared/data relative to the current directory "
            f"and to the repository root); set the environment variable {ENV_VAR} to the data folder "
            "or pass root=..."
        )
    return r


def _missing(path: Path, what: str) -> DataNotFoundError:
    return DataNotFoundError(
        f"{what} not found: {path} -- is the data root right? Set {ENV_VAR} to the folder holding "
        "oxford/, pose_pairs/ and photos/ (see ../shared/data/SOURCES.md), or pass root=..."
    )


# --------------------------------------------------------------------------------------------------
# ground truth
# --------------------------------------------------------------------------------------------------


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

# --------------------------------------------------------------------------------------------------
# pairs
# --------------------------------------------------------------------------------------------------


def _read_image(path: Path, grey: bool) -> np.ndarray:
    """:func:`guidedmatch.features.load_image` of a data file (FileNotFoundError with the data-root hint)."""
    if not Path(path).is_file():
        raise _missing(Path(path), "image")
    return load_image(Path(path), grey=grey)


def _image_size(path: Path) -> tuple[int, int]:
    """``(w, h)`` of an image file: read from the PNG header when possible, else by decoding."""
    path = Path(path)
    if not path.is_file():
        raise _missing(path, "image")
    with open(path, "rb") as fh:
        head = fh.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    img = _read_image(path, grey=True)
    return int(img.shape[1]), int(img.shape[0])


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


# --------------------------------------------------------------------------------------------------
# Oxford (Sec. IV-A)
# --------------------------------------------------------------------------------------------------


def oxford_pairs(
    root: str | os.PathLike | None = None,
    sequences: Sequence[str] = OXFORD_SEQUENCES,
    targets: Sequence[int] = (2, 3),
) -> list[Pair]:
    """Oxford pairs ``img1 -> imgN`` for every sequence and every ``N`` in ``targets`` (paper: N = 2, 3).

    ``root`` is the data root (see :func:`data_root`); the files are ``oxford/<seq>/img<k>.png`` and the
    plain-text ``oxford/<seq>/H1to<N>p`` (loaded with ``numpy.loadtxt``), which maps img1 pixels to imgN
    pixels. Sizes differ within a sequence for ``wall`` (img1 1000x700, img2-6 880x680); each
    :class:`HomographyGT` carries both sizes. Extended set: ``sequences=OXFORD_ALL_SEQUENCES``
    (adds ``bark``), ``targets=(2, 3, 4, 5, 6)``.

    Raises:
        FileNotFoundError: data root, image or homography file missing (message names the path).
        ValueError: a target outside 2..6.
    """
    base = _require_root(root) / "oxford"
    if not base.is_dir():
        raise _missing(base, "Oxford folder")
    pairs = []
    for seq in sequences:
        d = base / seq
        if not d.is_dir():
            raise _missing(d, f"Oxford sequence {seq!r}")
        img1 = d / "img1.png"
        size1 = _image_size(img1)
        for n in targets:
            n = int(n)
            if not 2 <= n <= 6:
                raise ValueError(f"Oxford target image index must be in 2..6, got {n}")
            img2 = d / f"img{n}.png"
            hfile = d / f"H1to{n}p"
            if not hfile.is_file():
                raise _missing(hfile, "Oxford homography")
            H = np.loadtxt(hfile, dtype=np.float64).reshape(3, 3)
            size2 = _image_size(img2)
            pairs.append(
                Pair(
                    name=f"oxford/{seq}/1-{n}",
                    image1=img1,
                    image2=img2,
                    gt=HomographyGT(H, size1, size2),
                    meta={"dataset": "oxford", "sequence": seq, "target": n, "size1": size1, "size2": size2},
                )
            )
    return pairs


# --------------------------------------------------------------------------------------------------
# Strecha (real, calibrated)
# --------------------------------------------------------------------------------------------------


def strecha_pairs(root: str | os.PathLike | None = None, with_sizes: bool = True) -> list[Pair]:
    """Pairs listed in ``pose_pairs/strecha/strecha_pairs_with_gt.txt`` (18 Herz-Jesus-P8 pairs, 3072x2048).

    Line format (SuperGlue ``pairs_with_gt``): ``path0 path1 rot0 rot1 K0[9] K1[9] T_0to1[16]``, paths
    relative to ``pose_pairs/strecha/``, ``T_0to1`` row-major with ``X_cam1 = R X_cam0 + t``. The GT is
    :meth:`EpipolarGT.from_pose` (``F = K1^-T [t]_x R K0^-1`` in the file's 0/1 naming). Non-zero
    EXIF rotation flags are rejected (all are 0 in this file). ``with_sizes`` reads the image sizes
    (decodes each JPEG once; pass ``False`` to skip and leave the inside test off).

    Raises:
        FileNotFoundError: data root, pairs file or an image missing.
        ValueError: a malformed line.
    """
    base = _require_root(root) / STRECHA_PAIRS_FILE.parent
    pfile = base / STRECHA_PAIRS_FILE.name
    if not pfile.is_file():
        raise _missing(pfile, "Strecha pairs file")
    pairs = []
    size_cache: dict[Path, tuple[int, int]] = {}
    for lineno, line in enumerate(pfile.read_text().splitlines(), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) != 38:
            raise ValueError(f"{pfile}:{lineno}: expected 38 fields, got {len(tok)}")
        p0, p1 = base / tok[0], base / tok[1]
        rot0, rot1 = int(tok[2]), int(tok[3])
        if rot0 or rot1:
            raise ValueError(f"{pfile}:{lineno}: EXIF rotation flags ({rot0}, {rot1}) are not supported")
        vals = np.array(tok[4:], dtype=np.float64)
        K0, K1, T = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:].reshape(4, 4)
        for p in (p0, p1):
            if not p.is_file():
                raise _missing(p, "Strecha image")
        s0 = s1 = None
        if with_sizes:
            for p in (p0, p1):
                if p not in size_cache:
                    size_cache[p] = _image_size(p)
            s0, s1 = size_cache[p0], size_cache[p1]
        gt = EpipolarGT.from_pose(K0, K1, T[:3, :3], T[:3, 3], s0, s1)
        scene = Path(tok[0]).parts[0]
        name = f"strecha/{scene}/{Path(tok[0]).stem}-{Path(tok[1]).stem}"
        rot_deg = float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))
        pairs.append(
            Pair(name, p0, p1, gt, {"dataset": "strecha", "scene": scene, "size1": s0, "size2": s1,
                                    "rotation_deg": rot_deg})
        )
    return pairs


STRECHA_SCENE_DIR = Path("pose_pairs") / "strecha"


@dataclass(frozen=True, eq=False)
class StrechaCamera:
    """One calibrated Strecha camera (``<image>.camera`` file).

    Attributes:
        K: ``(3, 3)`` intrinsics (pixels). R_wc: ``(3, 3)`` world -> camera rotation. t_wc: ``(3,)`` world -> camera
        translation (metres): ``X_cam = R_wc X_world + t_wc``. center: ``(3,)`` camera centre in world coordinates.
        size: ``(w, h)`` pixels. image: path of the image.
    """

    K: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    center: np.ndarray
    size: tuple[int, int]
    image: Path


def read_strecha_camera(path: str | os.PathLike, image: str | os.PathLike | None = None) -> StrechaCamera:
    """Parse a Strecha ``.camera`` file: K (3 lines), distortion (1 line, must be 0), R camera-to-world (3 lines),
    centre C (1 line), ``w h`` (see ``shared/data/SOURCES.md``); projection ``x ~ K [R^T | -R^T C] X``.

    Raises:
        FileNotFoundError: missing file. ValueError: not 9 lines of numbers, or non-zero distortion.
    """
    path = Path(path)
    if not path.is_file():
        raise _missing(path, "Strecha camera file")
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(rows) != 9:
        raise ValueError(f"{path}: expected 9 lines of numbers, got {len(rows)}")
    try:
        K = np.array(rows[0:3], dtype=np.float64)
        dist = np.array(rows[3], dtype=np.float64)
        R = np.array(rows[4:7], dtype=np.float64)
        C = np.array(rows[7], dtype=np.float64)
        w, h = (int(float(v)) for v in rows[8])
    except ValueError as exc:
        raise ValueError(f"{path}: malformed camera file ({exc})") from None
    if K.shape != (3, 3) or R.shape != (3, 3) or C.shape != (3,):
        raise ValueError(f"{path}: malformed camera file (K {K.shape}, R {R.shape}, C {C.shape})")
    if np.any(dist != 0):
        raise ValueError(f"{path}: non-zero radial distortion {dist.tolist()} is not supported")
    R_wc = R.T
    return StrechaCamera(K, R_wc, -R_wc @ C, C, (w, h), Path(image) if image is not None else path)


def relative_pose(cam1: StrechaCamera, cam2: StrechaCamera) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` with ``X_cam2 = R X_cam1 + t`` (the convention of :class:`EpipolarGT`)."""
    R = cam2.R_wc @ cam1.R_wc.T
    return R, cam2.t_wc - R @ cam1.t_wc


def camera_angles(cam1: StrechaCamera, cam2: StrechaCamera) -> dict[str, float]:
    """Angles between two cameras, degrees: ``rotation_deg`` (angle of the relative rotation) and
    ``axis_deg`` (angle between the optical axes)."""
    R, _ = relative_pose(cam1, cam2)
    rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    z1, z2 = cam1.R_wc[2], cam2.R_wc[2]  # optical axes in world coordinates (rows of R_wc)
    axis = float(np.degrees(np.arccos(np.clip(z1 @ z2, -1, 1))))
    return {"rotation_deg": rot, "axis_deg": axis}


def strecha_scene_pairs(root: str | os.PathLike | None = None, scene: str = "Herz-Jesus-P8") -> list[Pair]:
    """Every pair ``(i, j), i < j`` of a Strecha scene, GT from its ``gt_dense_cameras/*.camera`` files
    (Herz-Jesus-P8: 8 images, 28 pairs; :func:`strecha_pairs` lists only 18 of them).

    ``meta`` holds ``rotation_deg`` / ``axis_deg`` (:func:`camera_angles`) and the image sizes from the camera files.
    The GT is :meth:`EpipolarGT.from_pose` with :func:`relative_pose`, as in the pairs file.
    """
    base = _require_root(root) / STRECHA_SCENE_DIR / scene
    if not (base / "images").is_dir():
        raise _missing(base / "images", f"Strecha scene {scene!r}")
    images = sorted(p for p in (base / "images").iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    cams = [read_strecha_camera(base / "gt_dense_cameras" / (p.name + ".camera"), p) for p in images]
    pairs = []
    for a in range(len(cams)):
        for b in range(a + 1, len(cams)):
            c1, c2 = cams[a], cams[b]
            R, t = relative_pose(c1, c2)
            gt = EpipolarGT.from_pose(c1.K, c2.K, R, t, c1.size, c2.size)
            pairs.append(Pair(f"strecha/{scene}/{c1.image.stem}-{c2.image.stem}", c1.image, c2.image, gt,
                              {"dataset": "strecha", "scene": scene, "size1": c1.size, "size2": c2.size,
                               **camera_angles(c1, c2)}))
    return pairs


# --------------------------------------------------------------------------------------------------
# Synthetic set (Sec. IV-B, after Dosovitskiy et al. 2016)
# --------------------------------------------------------------------------------------------------

#: What each synthetic set applies (paper Tables 5-7): colour = PCA contrast + HSV + hue.
SYNTHETIC_SETS: dict[int, dict[str, bool]] = {
    1: {"translation": True, "scale": True, "rotation": False, "perspective": False},
    2: {"translation": False, "scale": True, "rotation": True, "perspective": False},
    3: {"translation": False, "scale": True, "rotation": True, "perspective": True},
}


@dataclass(frozen=True)
class SyntheticParams:
    """Ranges of the simulated transformations (paper Sec. IV-B). Defaults are the paper's."""

    max_rotation_deg: float = 90.0  # rotation uniform in [-90, 90] deg about the image centre
    max_translation: float = 0.1  # translation uniform in [-0.1, 0.1] x (w, h)
    scale_range: tuple[float, float] = (0.5, 2.0)  # scale log-uniform in [0.5, 2]
    pca_contrast_range: tuple[float, float] = (0.8, 1.2)  # factor on the principal-component projection
    sv_power_range: tuple[float, float] = (0.5, 2.0)  # exponent on HSV saturation / value, log-uniform
    sv_mult_range: tuple[float, float] = (0.8, 1.2)  # factor on saturation / value after the power
    sv_add_range: tuple[float, float] = (-0.05, 0.05)  # offset on saturation / value (range [0, 1])
    hue_add_range: tuple[float, float] = (-0.05, 0.05)  # offset on hue, as a fraction of the hue circle
    perspective_jitter: float = 0.05  # each corner moved uniformly in [-0.05, 0.05] x (w, h)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _corners(w: int, h: int) -> np.ndarray:
    """The four outer corners of a ``w x h`` image (pixel-centre convention: the image spans -0.5..w-0.5)."""
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])


def synthetic_homography(
    size: tuple[int, int], set_id: int, rng: np.random.Generator, params: SyntheticParams = SyntheticParams()
) -> tuple[np.ndarray, tuple[int, int], dict[str, Any]]:
    """Draw the geometric part of one simulated pair.

    Composition (image-1 pixels -> image-2 pixels): perspective ``P`` (set 3: the four image corners
    jittered by up to 0.05 of the size, ``P`` = the homography of that corner move) -> similarity about the
    image centre (scale ``s``, rotation ``theta``; set 1 has no rotation) -> a shift that puts the
    bounding box of the warped image at the canvas origin -> translation (set 1 only).

    Canvas (not cropped): image 2 is exactly large enough to hold the whole warped image 1, so no content
    is cut away. Because such a canvas would absorb any translation, the translation ``(tx, ty)`` (up to
    0.1 of the size) is realised as a black margin of ``|tx|`` (``|ty|``) pixels on the left (top) side for
    positive values and on the right (bottom) side for negative ones: the content moves by ``(tx, ty)``
    relative to the fitted position.

    Returns:
        ``(H, (w2, h2), info)`` with ``H`` ``(3, 3) float64``.
    """
    if set_id not in SYNTHETIC_SETS:
        raise ValueError(f"set_id must be one of {sorted(SYNTHETIC_SETS)}, got {set_id!r}")
    flags = SYNTHETIC_SETS[set_id]
    w, h = int(size[0]), int(size[1])
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    info: dict[str, Any] = {}

    P = np.eye(3)
    if flags["perspective"]:
        src = _corners(w, h)
        jit = rng.uniform(-params.perspective_jitter, params.perspective_jitter, size=(4, 2)) * [w, h]
        import cv2

        P = cv2.getPerspectiveTransform(src.astype(np.float32), (src + jit).astype(np.float32)).astype(np.float64)
        info["corner_jitter_px"] = jit.round(3).tolist()
    s = _log_uniform(rng, *params.scale_range) if flags["scale"] else 1.0
    theta = rng.uniform(-params.max_rotation_deg, params.max_rotation_deg) if flags["rotation"] else 0.0
    c, sn = np.cos(np.radians(theta)), np.sin(np.radians(theta))
    T_c = np.array([[1.0, 0, cx], [0, 1, cy], [0, 0, 1]])
    T_mc = np.array([[1.0, 0, -cx], [0, 1, -cy], [0, 0, 1]])
    A = T_c @ np.array([[s * c, -s * sn, 0], [s * sn, s * c, 0], [0, 0, 1]]) @ T_mc
    M = A @ P
    warped = apply_homography(M, _corners(w, h), in_front=True)
    lo = warped.min(axis=0)
    hi = warped.max(axis=0)
    tx = ty = 0.0
    if flags["translation"]:
        tx = float(rng.uniform(-params.max_translation, params.max_translation) * w)
        ty = float(rng.uniform(-params.max_translation, params.max_translation) * h)
    off = np.array([-0.5 - lo[0] + max(tx, 0.0), -0.5 - lo[1] + max(ty, 0.0)])
    H = np.array([[1.0, 0, off[0]], [0, 1, off[1]], [0, 0, 1]]) @ M
    w2 = int(np.ceil(hi[0] - lo[0] + abs(tx)))
    h2 = int(np.ceil(hi[1] - lo[1] + abs(ty)))
    H = H / H[2, 2]
    info.update({"rotation_deg": float(theta), "scale": float(s), "translation_px": [tx, ty]})
    return H, (w2, h2), info


def colour_transform(
    img: np.ndarray, rng: np.random.Generator, params: SyntheticParams = SyntheticParams()
) -> tuple[np.ndarray, dict[str, Any]]:
    """Photometric part of a simulated pair (paper Sec. IV-B, "contrast variation 1/2", "hue variation").

    On a BGR (or grey) ``uint8`` image: (1) PCA contrast -- the projection of every pixel (RGB in [0, 1],
    mean-centred) onto the first principal component of all pixels is multiplied by ``k in [0.8, 1.2]``;
    (2) HSV -- saturation and value (each in [0, 1]) are raised to a power (log-uniform in [0.5, 2]),
    multiplied by ``[0.8, 1.2]`` and shifted by ``[-0.05, 0.05]`` (independent draws for S and V),
    clipped to [0, 1]; (3) hue shifted by ``[-0.05, 0.05]`` of the full circle. Grey input is processed
    as R = G = B and converted back to grey. Returns ``(uint8 image of the same shape, parameters)``.
    """
    import cv2

    grey = img.ndim == 2
    x = img.astype(np.float32) / 255.0
    if grey:
        x = np.repeat(x[:, :, None], 3, axis=2)
    info: dict[str, Any] = {}
    # (1) PCA contrast (covariance from a strided subsample: the principal axis of a photo is stable).
    flat = x.reshape(-1, 3)
    sub = flat[:: max(1, len(flat) // 200_000)].astype(np.float64)
    mean = sub.mean(axis=0)
    cov = np.cov(sub, rowvar=False) if len(sub) > 1 else np.zeros((3, 3))
    evals, evecs = np.linalg.eigh(cov)
    v = evecs[:, -1].astype(np.float32)
    k = float(rng.uniform(*params.pca_contrast_range))
    proj = (flat - mean.astype(np.float32)) @ v
    flat = flat + np.float32(k - 1.0) * proj[:, None] * v[None, :]
    x = np.clip(flat.reshape(x.shape), 0.0, 1.0)
    info["pca_contrast"] = k
    # (2) + (3) HSV (OpenCV float HSV: H in [0, 360), S, V in [0, 1]).
    hsv = cv2.cvtColor(x, cv2.COLOR_BGR2HSV)
    for ch, key in ((1, "saturation"), (2, "value")):
        p = _log_uniform(rng, *params.sv_power_range)
        m = float(rng.uniform(*params.sv_mult_range))
        a = float(rng.uniform(*params.sv_add_range))
        hsv[:, :, ch] = np.clip(np.power(hsv[:, :, ch], p) * m + a, 0.0, 1.0)
        info[key] = {"power": p, "mult": m, "add": a}
    dh = float(rng.uniform(*params.hue_add_range))
    hsv[:, :, 0] = np.mod(hsv[:, :, 0] + dh * 360.0, 360.0)
    info["hue_add"] = dh
    out = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    out = np.clip(out * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if grey:
        out = cv2.cvtColor(out, cv2.COLOR_BGR2GRAY)
    return out, info


def synthesize_pair(
    image: np.ndarray,
    set_id: int,
    rng: np.random.Generator | int | None = 0,
    params: SyntheticParams = SyntheticParams(),
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Make image 2 of a simulated pair from image 1 (paper Sec. IV-B).

    Colour transform (:func:`colour_transform`) on image 1, then ``cv2.warpPerspective`` with the
    homography of :func:`synthetic_homography` (bilinear, black border; a Gaussian pre-blur with
    ``sigma = 0.5 sqrt(1/s^2 - 1)`` when shrinking by ``s < 1`` against aliasing; the blur is symmetric so
    positions are unchanged). OpenCV's warp uses the pixel-centre convention, so ``H`` maps image-1 pixel
    coordinates to image-2 pixel coordinates exactly.

    Returns:
        ``(image2 uint8, H (3, 3) float64, info)``.
    """
    import cv2

    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    h, w = image.shape[:2]
    H, (w2, h2), info = synthetic_homography((w, h), set_id, rng, params)
    col, cinfo = colour_transform(image, rng, params)
    info.update(cinfo)
    s = info["scale"]  # the similarity's scale (the perspective part changes it by a few % at most)
    if s < 1.0:
        sigma = 0.5 * np.sqrt(1.0 / s**2 - 1.0)
        col = cv2.GaussianBlur(col, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    img2 = cv2.warpPerspective(col, H, (w2, h2), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    info["size1"] = (w, h)
    info["size2"] = (w2, h2)
    return img2, H, info


def list_photos(root: str | os.PathLike | None = None) -> list[Path]:
    """The photos of the synthetic set, ``photos/unsplash/*`` sorted by file name."""
    d = _require_root(root) / PHOTOS_DIR
    if not d.is_dir():
        raise _missing(d, "photo folder")
    photos = sorted(p for p in d.iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    if not photos:
        raise _missing(d / "*.jpg", "photos")
    return photos


@functools.lru_cache(maxsize=2)
def _load_photo(path: str, max_side: int) -> np.ndarray:
    """A photo (BGR uint8), downscaled (INTER_AREA, aspect kept) so its long side is ``<= max_side``."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise _missing(p, "photo")
    full = _image_size(p) if p.suffix.lower() == ".png" else None
    img = None
    if full is None:
        # Decode at 1/2, 1/4 or 1/8 size when that still leaves >= max_side pixels (fast JPEG decoding).
        probe = cv2.imread(str(p), cv2.IMREAD_REDUCED_COLOR_8)
        if probe is not None:
            long8 = max(probe.shape[:2])
            for f, flag in ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
                            (2, cv2.IMREAD_REDUCED_COLOR_2)):
                if long8 * 8 // f >= max_side:
                    img = probe if f == 8 else cv2.imread(str(p), flag)
                    break
    if img is None:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f"could not decode photo {p}")
    h, w = img.shape[:2]
    long_side = max(h, w)
    if long_side > max_side:
        f = max_side / long_side
        img = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    img.setflags(write=False)
    return img


def synthetic_pair(
    root: str | os.PathLike | None,
    set_id: int,
    index: int,
    seed: int = 0,
    max_side: int = 2400,
    params: SyntheticParams = SyntheticParams(),
    photos: Sequence[Path] | None = None,
) -> Pair:
    """Pair ``index`` of simulated set ``set_id`` (1: colour + translation + scaling; 2: colour + scaling +
    rotation; 3: set 2 + perspective). Deterministic in ``(set_id, index, seed, max_side)``.

    Image 1 = photo ``index mod n_photos`` (sorted by name) downscaled so its long side is ``<= max_side``
    (paper: ImageNet photos of about 2000-3000 px; default 2400; use ~1000 for quick runs); image 2 =
    :func:`synthesize_pair` of it with ``rng = default_rng([seed, set_id, index])``, so reused photos get
    different transformations. Both images are BGR ``uint8`` in memory.
    """
    photos = list(photos) if photos is not None else list_photos(root)
    photo = photos[index % len(photos)]
    img1 = _load_photo(str(photo), int(max_side))
    rng = np.random.default_rng([int(seed), int(set_id), int(index)])
    img2, H, info = synthesize_pair(img1, set_id, rng, params)
    gt = HomographyGT(H, info["size1"], info["size2"])
    meta = {"dataset": "synthetic", "set": int(set_id), "index": int(index), "seed": int(seed),
            "max_side": int(max_side), "photo": photo.name, **info}
    return Pair(f"synthetic/set{set_id}/{index:04d}", img1, img2, gt, meta)


def synthetic_pairs(
    root: str | os.PathLike | None = None,
    set_id: int = 1,
    n_pairs: int = 100,
    seed: int = 0,
    max_side: int = 2400,
    params: SyntheticParams = SyntheticParams(),
) -> Iterator[Pair]:
    """Lazily yield the ``n_pairs`` pairs of simulated set ``set_id`` (paper Sec. IV-B: 100 pairs per set).

    Each pair is generated only when the iterator reaches it (:func:`synthetic_pair`); with 24 photos,
    every photo is used ``ceil(n_pairs / 24)`` times, each time with a different transformation.
    The arguments and the photo folder are checked at call time (``FileNotFoundError``/``ValueError``).
    """
    if set_id not in SYNTHETIC_SETS:
        raise ValueError(f"set_id must be one of {sorted(SYNTHETIC_SETS)}, got {set_id!r}")
    photos = list_photos(root)  # raises here (not at the first next()) when the folder is missing

    def _gen() -> Iterator[Pair]:
        for i in range(int(n_pairs)):
            yield synthetic_pair(root, set_id, i, seed, max_side, params, photos)

    return _gen()
