"""Real image pairs with ground truth: the Oxford sequences (Sec. IV-A; homographies) and Strecha's Herz-Jesus-P8
(calibrated cameras: the pairs file, or every pair of a scene from its camera files).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .ground_truth import EpipolarGT, HomographyGT, Pair
from .root import _IMAGE_EXTS, _image_size, _missing, _require_root

OXFORD_SEQUENCES = ("bikes", "wall", "boat", "leuven", "ubc", "graf")  # the paper's six (Fig. 4)
OXFORD_ALL_SEQUENCES = OXFORD_SEQUENCES + ("bark",)  # bark: extra, large in-plane rotations
STRECHA_PAIRS_FILE = Path("pose_pairs") / "strecha" / "strecha_pairs_with_gt.txt"


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
