"""Local image features: detection (OpenCV), user-supplied arrays, save/load.

Conventions
-----------
* Keypoint coordinates are ``(N, 2) float64`` pixels in the OpenCV convention: ``(0, 0)`` is the
  centre of the top-left pixel, x grows to the right, y downwards.
* Float descriptors (SIFT, user float) are ``(N, D) float32`` and compared with L2.
  Binary descriptors (ORB, AKAZE/MLDB, BRISK) are ``(N, B) uint8`` packed bits compared with Hamming.
* Detection runs on an 8-bit grey image; colour input is converted with ``cv2.cvtColor`` (BGR order,
  as ``cv2.imread`` gives).

This is step 1 of the method (Teng & Dong §III-A, "Feature Detection": any detector may be used).
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, ImageReadError, InputError

DETECTORS = ("sift", "orb", "akaze", "brisk")
BINARY_KINDS = ("orb", "akaze", "brisk")


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints + descriptors of one image.

    Attributes:
        keypoints: ``(N, 2) float64`` pixel coordinates (OpenCV convention, see module doc).
        descriptors: ``(N, D) float32`` (L2) or ``(N, B) uint8`` packed binary (Hamming).
        image_size: ``(w, h)`` of the image the keypoints live in, pixels.
        kind: detector / descriptor name: ``"sift" | "orb" | "akaze" | "brisk" | "user"``.
        scales: optional ``(N,) float32`` keypoint diameter (``cv2.KeyPoint.size``), pixels.
        angles: optional ``(N,) float32`` orientation in degrees (OpenCV: clockwise from x, -1 = none).
        responses: optional ``(N,) float32`` detector response.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    image_size: tuple[int, int]
    kind: str = "user"
    scales: np.ndarray | None = None
    angles: np.ndarray | None = None
    responses: np.ndarray | None = None

    def __post_init__(self) -> None:
        kp = np.asarray(self.keypoints, dtype=np.float64)
        if kp.size == 0:
            kp = kp.reshape(0, 2)
        if kp.ndim != 2 or kp.shape[1] != 2:
            raise InputError(f"keypoints must be (N, 2), got shape {kp.shape}")
        if not np.all(np.isfinite(kp)):
            bad = int((~np.isfinite(kp).all(axis=1)).sum())
            raise InputError(f"keypoints contain {bad} non-finite (NaN/inf) coordinate rows")
        desc = np.asarray(self.descriptors)
        if desc.size == 0 and desc.ndim < 2:
            desc = desc.reshape(0, 128 if desc.dtype != np.uint8 else 32)
        if desc.ndim != 2:
            raise InputError(f"descriptors must be (N, D), got shape {desc.shape}")
        if len(desc) != len(kp):
            raise InputError(f"{len(kp)} keypoints but {len(desc)} descriptors")
        if self.kind in BINARY_KINDS and desc.dtype != np.uint8:
            raise InputError(f"binary descriptors ({self.kind}) must be uint8 packed bits, got {desc.dtype}")
        if desc.dtype != np.uint8 or self.kind == "sift":
            # float descriptors (L2); uint8 SIFT (e.g. COLMAP's) is cast to float32, not treated as bits
            if not np.issubdtype(desc.dtype, np.number):
                raise InputError(f"descriptors must be numeric, got {desc.dtype}")
            desc = desc.astype(np.float32, copy=False)
            if not np.all(np.isfinite(desc)):
                raise InputError("descriptors contain NaN/inf")
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0:
            raise InputError(f"image_size must be positive (w, h), got {self.image_size}")
        object.__setattr__(self, "keypoints", kp)
        object.__setattr__(self, "descriptors", np.ascontiguousarray(desc))
        object.__setattr__(self, "image_size", (w, h))
        for name in ("scales", "angles", "responses"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float32).reshape(-1)
                if len(v) != len(kp):
                    raise InputError(f"{name} has {len(v)} entries for {len(kp)} keypoints")
                object.__setattr__(self, name, v)

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def binary(self) -> bool:
        """True when descriptors are packed bits compared with Hamming distance."""
        return self.descriptors.dtype == np.uint8

    @property
    def dim(self) -> int:
        """Descriptor length (floats, or bytes for binary)."""
        return int(self.descriptors.shape[1])

    def subset(self, idx: np.ndarray) -> "Features":
        """Features at ``idx`` (an index or boolean array)."""
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return Features(self.keypoints[idx], self.descriptors[idx], self.image_size, self.kind,
                        pick(self.scales), pick(self.angles), pick(self.responses))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_arrays(cls, keypoints, descriptors, image_size, kind: str = "user", **extra) -> "Features":
        """From user arrays: ``keypoints (N,2)`` pixels, ``descriptors (N,D)``, ``image_size (w,h)``.

        ``uint8`` descriptors with ``kind="user"`` are treated as packed binary (Hamming); pass
        float descriptors for L2.
        """
        return cls(keypoints, descriptors, tuple(image_size), kind, **extra)

    @classmethod
    def from_cv(cls, keypoints: list, descriptors: np.ndarray | None, image_size, kind: str = "user") -> "Features":
        """From a list of ``cv2.KeyPoint`` and the descriptor array OpenCV returned (may be None)."""
        n = len(keypoints)
        if descriptors is None:
            descriptors = np.zeros((0, 32), np.uint8) if kind in BINARY_KINDS else np.zeros((0, 128), np.float32)
            if n:
                raise InputError("descriptors are None for a non-empty keypoint list")
        kp = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(n, 2)
        return cls(kp, descriptors, tuple(image_size), kind,
                   scales=np.array([k.size for k in keypoints], np.float32),
                   angles=np.array([k.angle for k in keypoints], np.float32),
                   responses=np.array([k.response for k in keypoints], np.float32))

    def to_cv_keypoints(self) -> list:
        """The keypoints as a list of ``cv2.KeyPoint``."""
        import cv2

        s = self.scales if self.scales is not None else np.ones(len(self), np.float32)
        a = self.angles if self.angles is not None else -np.ones(len(self), np.float32)
        r = self.responses if self.responses is not None else np.zeros(len(self), np.float32)
        return [cv2.KeyPoint(float(x), float(y), float(si), float(ai), float(ri))
                for (x, y), si, ai, ri in zip(self.keypoints, s, a, r)]

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike) -> None:
        """Save to ``.npz`` (written atomically: temp file + rename)."""
        arrays: dict[str, Any] = dict(keypoints=self.keypoints, descriptors=self.descriptors,
                                      image_size=np.array(self.image_size, np.int64), kind=np.array(self.kind))
        for name in ("scales", "angles", "responses"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        atomic_savez(path, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Features":
        """Load what :meth:`save` wrote."""
        path = Path(path)
        if not path.exists():
            raise InputError(f"features file not found: {path}")
        with np.load(path, allow_pickle=False) as z:
            extra = {k: z[k] for k in ("scales", "angles", "responses") if k in z}
            return cls(z["keypoints"], z["descriptors"], tuple(int(v) for v in z["image_size"]), str(z["kind"]), **extra)


def as_features(obj, name: str = "features") -> Features:
    """``obj`` as :class:`Features`: Features pass through; a tuple ``(keypoints (N,2) px, descriptors (N,D),
    image_size (w,h))`` or ``(keypoints, descriptors, image_size, kind)`` goes through :meth:`Features.from_arrays`
    (float descriptors: L2; uint8 with kind ``"user"``: packed bits, Hamming). InputError otherwise."""
    if isinstance(obj, Features):
        return obj
    if isinstance(obj, tuple) and len(obj) in (3, 4):
        return Features.from_arrays(*obj)
    raise InputError(f"{name} must be Features or a tuple (keypoints, descriptors, image_size[, kind]); "
                     f"got {type(obj).__name__}")


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give a finished temp file normal permissions (0666 minus the umask; mkstemp makes 0600) and rename it
    over ``path`` in one step (``os.replace``), so readers never see a partial file."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)


def atomic_savez(path: str | os.PathLike, **arrays: Any) -> None:
    """``np.savez_compressed`` to a temp file in the target folder, then ``os.replace`` (no partial files)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write text to a temp file in the target folder, then ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_image(image_or_path, grey: bool = True) -> np.ndarray:
    """Read an image as ``uint8``; grey ``(h, w)`` when ``grey`` else ``(h, w, 3)`` BGR. The one image reader
    of the package (CLI, :func:`detect`, the evaluation datasets).

    Accepts a path or an array (grey, BGR or BGRA; float arrays in [0, 1] are scaled to 0..255, uint16 to the
    high byte). A file is decoded by ``cv2.imread`` with ``IMREAD_GRAYSCALE`` when ``grey`` (the decoder's own
    grey conversion, as hloc and the benchmarks use; for JPEG it decodes the luminance directly) else
    ``IMREAD_COLOR``; an array is converted with ``cv2.cvtColor``. The two grey conversions may differ by one
    grey level in some pixels (libpng / libjpeg round differently from ``cvtColor``).
    Raises :class:`~guidedmatch.errors.ImageReadError` for a missing, unreadable or empty image.
    """
    import cv2

    if isinstance(image_or_path, (str, os.PathLike)):
        path = Path(image_or_path)
        if not path.exists():
            raise ImageReadError(f"image not found: {path}")
        if path.is_dir():
            raise ImageReadError(f"image path is a directory: {path}")
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
        if img is None:
            raise ImageReadError(f"cannot read image (unknown format or corrupt file): {path}")
    else:
        img = np.asarray(image_or_path)
    if img.size == 0 or img.ndim < 2 or min(img.shape[:2]) == 0:
        raise ImageReadError(f"empty image (shape {img.shape})")
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating):
            if not np.all(np.isfinite(img)):
                raise ImageReadError("image contains NaN/inf")
            scale = 255.0 if img.max() <= 1.0 else 1.0
            img = np.clip(img * scale, 0, 255).astype(np.uint8)
        elif img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        else:
            img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise ImageReadError(f"unsupported channel count {img.shape[2]}")
    if grey:
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    elif img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(img)


def _make_detector(method: str, max_features: int | None, options: dict):
    import cv2

    n = int(max_features) if max_features else 0
    if method == "sift":
        return cv2.SIFT_create(nfeatures=n, **options)
    if method == "orb":
        return cv2.ORB_create(nfeatures=n or 10000, **options)
    if method in ("akaze", "brisk"):
        # OpenCV 4.x has cv2.AKAZE_create / cv2.BRISK_create; OpenCV 5 moved them to cv2.xfeatures2d
        name = "AKAZE_create" if method == "akaze" else "BRISK_create"
        factory = getattr(cv2, name, None) or getattr(getattr(cv2, "xfeatures2d", None), name, None)
        if factory is None:
            raise ConfigError(f"{method} is not available in this OpenCV build ({cv2.__version__})")
        return factory(**options)
    raise ConfigError(f"unknown detector {method!r}; choose one of {', '.join(DETECTORS)}")


def detect(image_or_path, method: str = "sift", max_features: int | None = None, **detector_options) -> Features:
    """Detect keypoints and compute descriptors on the 8-bit grey image.

    Args:
        image_or_path: path or array (colour is converted to grey).
        method: ``"sift"`` (default, float 128-D, L2), ``"orb"``, ``"akaze"``, ``"brisk"`` (binary, Hamming).
        max_features: keep at most this many, strongest response first (None = detector default:
            unlimited for SIFT/AKAZE/BRISK, 10000 for ORB).
        **detector_options: passed to the OpenCV factory (e.g. ``contrastThreshold=0.01`` for SIFT).

    Returns:
        :class:`Features` (possibly empty: a textureless image gives ``len(f) == 0``; callers decide).

    Raises:
        ImageReadError: missing / unreadable image. ConfigError: unknown detector or detector option.

    >>> import numpy as np
    >>> from guidedmatch.testing.scenes import make_scene
    >>> f = detect(make_scene((320, 240), roll_deg=10.0, seed=1).image1, max_features=200)
    >>> len(f), f.keypoints.shape, f.descriptors.dtype, f.image_size
    (200, (200, 2), dtype('float32'), (320, 240))
    """
    import cv2

    method = method.lower()
    if method not in DETECTORS:
        raise ConfigError(f"unknown detector {method!r}; choose one of {', '.join(DETECTORS)}")
    img = load_image(image_or_path, grey=True)
    try:
        det = _make_detector(method, max_features, dict(detector_options))
    except (TypeError, cv2.error) as exc:
        raise ConfigError(f"invalid option for {method} detector: {exc}") from None
    kps, desc = det.detectAndCompute(img, None)
    kps = list(kps)
    if max_features and len(kps) > max_features:
        order = np.argsort([-k.response for k in kps], kind="stable")[: int(max_features)]
        order.sort()
        kps = [kps[i] for i in order]
        desc = desc[order]
    h, w = img.shape[:2]
    return Features.from_cv(kps, desc, (w, h), kind=method)
