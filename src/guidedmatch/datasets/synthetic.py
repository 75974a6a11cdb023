"""The synthetic set of Sec. IV-B (after Dosovitskiy et al. 2016, plus a perspective warp): pairs generated lazily
and deterministically from the photos of ``photos/unsplash/``; ground truth = the generated homography.
"""
from __future__ import annotations

import functools
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..alignment import apply_homography
from .ground_truth import HomographyGT, Pair
from .root import _image_size, _missing, list_photos

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
