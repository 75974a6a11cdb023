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

import contextlib
import os
import re
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, ImageReadError, InputError, MemoryLimitError, OutputError
from .validation import check_number

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
        float descriptors for L2. ``**extra``: optional ``scales``, ``angles``, ``responses`` (each ``(N,)``).

        **Responses drive the draw order.** The guided matcher draws image-1 features group by group, strongest
        detector response first (Teng & Dong §III-A), and fits its first models on the earliest correspondences.
        Without ``responses`` (the default here, unlike :meth:`from_cv` and :func:`detect`, which keep
        ``cv2.KeyPoint.response``) -- or when all responses are equal -- the order inside each group is a seeded
        random permutation (``MatcherConfig.seed``), so the models, and hence the matches, differ slightly from a
        run on the same arrays with responses: Oxford graf 1-2, SIFT, ``so+epi+ia``: 1,189 matches with
        responses, 1,185 / 1,197 / 1,193 without (seeds 0 / 1 / 2); another pair gave 1,467 vs 1,426. Results are deterministic for a given seed either way; pass ``responses=`` to reproduce a
        ``detect`` / ``from_cv`` run exactly.

        >>> import numpy as np
        >>> f = Features.from_arrays(np.zeros((3, 2)), np.ones((3, 8), np.float32), (10, 10))
        >>> f.responses is None, f.binary
        (True, False)
        """
        return cls(keypoints, descriptors, tuple(image_size), kind, **extra)

    @classmethod
    def from_cv(cls, keypoints: list, descriptors: np.ndarray | None, image_size, kind: str = "user") -> "Features":
        """From a list of ``cv2.KeyPoint`` and the descriptor array OpenCV returned (may be None).

        Keeps ``pt`` (keypoints), ``size`` (scales), ``angle`` and ``response``: the responses set the matcher's
        draw order (strongest first within each x-group), so ``from_cv`` reproduces :func:`detect` exactly, while
        :meth:`from_arrays` on the same arrays without ``responses=`` draws in a seeded random order and can give
        slightly different matches (see :meth:`from_arrays`).
        """
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


def check_output_path(path: str | os.PathLike, what: str = "output") -> Path:
    """Check before any work that ``path`` can be written; raise :class:`~guidedmatch.errors.OutputError` naming it.

    The nearest existing ancestor folder must accept a new file: a probe file is created there and removed
    (the only reliable test: as root, ``os.access`` says yes to ``/proc`` and read-only mounts). Missing folders
    below it are created later by the writers. ``path`` itself must not be a folder.

    >>> check_output_path("/proc/m.csv", "-o")
    Traceback (most recent call last):
    ...
    guidedmatch.errors.OutputError: cannot write -o /proc/m.csv: folder /proc does not accept new files (No such file or directory)
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise OutputError(f"cannot write {what} {path}: it is a folder")
        parent = path.parent if str(path.parent) else Path(".")
        _folder_accepts_files(parent, f"{what} {path}")
        if path.exists() and not os.access(path, os.W_OK) and not os.access(parent, os.W_OK):
            raise OutputError(f"cannot write {what} {path}: the file is read-only")
    except OSError as exc:  # e.g. a folder on the way that cannot be searched
        raise OutputError(f"cannot write {what} {path}: {exc.strerror or exc}") from None
    return path


def _folder_accepts_files(folder: Path, shown: str) -> None:
    """The nearest existing ancestor of ``folder`` (itself included) is a folder in which a probe file can be
    created (and is removed again); OutputError "cannot write {shown}: ..." otherwise."""
    anc = folder
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise OutputError(f"cannot write {shown}: {anc} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".guidedmatch-probe-", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"cannot write {shown}: folder {anc} does not accept new files ({exc.strerror or exc})") \
            from None


def writable_folder(folder: str | os.PathLike, what: str = "--out") -> Path:
    """Check before any work that ``folder`` is, or can be created as, a folder that accepts new files (a probe
    file in its nearest existing ancestor); nothing is created. :class:`~guidedmatch.errors.OutputError` naming
    ``folder`` otherwise.

    >>> writable_folder("/proc/out")
    Traceback (most recent call last):
    ...
    guidedmatch.errors.OutputError: cannot write --out /proc/out: folder /proc does not accept new files (No such file or directory)
    """
    folder = Path(folder)
    try:
        if folder.exists() and not folder.is_dir():
            raise OutputError(f"cannot write {what} {folder}: it exists and is not a folder")
        _folder_accepts_files(folder, f"{what} {folder}")
    except OSError as exc:
        raise OutputError(f"cannot write {what} {folder}: {exc.strerror or exc}") from None
    return folder


@contextlib.contextmanager
def _output_errors(path: Path):
    """OSError while writing ``path`` (through a temp file) -> OutputError naming ``path``, not the temp file."""
    try:
        yield
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None


def atomic_savez(path: str | os.PathLike, **arrays: Any) -> None:
    """``np.savez_compressed`` to a temp file in the target folder, then ``os.replace`` (no partial files).

    Raises :class:`~guidedmatch.errors.OutputError` naming ``path`` when it cannot be written (also when zlib
    cannot be used in this process: :func:`guidedmatch._runtime.zlib_shadowed`)."""
    from ._runtime import require_zlib

    path = Path(path)
    require_zlib(path)
    with _output_errors(path):
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
    """Write text to a temp file in the target folder, then ``os.replace``.

    Raises :class:`~guidedmatch.errors.OutputError` naming ``path`` when it cannot be written."""
    path = Path(path)
    with _output_errors(path):
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


class ImageNotFoundError(ImageReadError, FileNotFoundError):
    """An image path that does not exist (an :class:`~guidedmatch.errors.ImageReadError` and a FileNotFoundError)."""


#: decoder messages (libjpeg, libpng, libtiff, libwebp through OpenCV) that mean the pixels are incomplete or wrong
_CORRUPT_MESSAGE = re.compile(r"premature end|corrupt|truncat|read error|crc error|invalid|bogus|not a jpeg|"
                              r"unsupported marker|bad huffman|incorrect|incomplete|error", re.IGNORECASE)
_BENIGN_MESSAGE = re.compile(r"iCCP|sRGB|known incorrect|unknown field|TIFFReadDirectory: Warning", re.IGNORECASE)


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _capture_native_stderr():
    """Collect what native code (libjpeg, libpng: ``fprintf(stderr, ...)``) writes to file descriptor 2 meanwhile.

    Yields a list that receives the captured text on exit. Falls back to no capture when fd 2 is unavailable.
    Serialized by a lock: fd 2 is process-wide, and two threads redirecting it at once could leave it pointing at
    a temp file.
    """
    out: list[str] = []
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):
            yield out
            return
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                out.append(tmp.read().decode("utf-8", "replace"))


def read_image_strict(path: str | os.PathLike, flags: int | None = None) -> np.ndarray:
    """Decode an image file completely or raise :class:`~guidedmatch.errors.ImageReadError` -- never a partial decode.

    OpenCV's JPEG reader returns the decoded part of a truncated file (libjpeg only warns "Premature end of JPEG
    file" on stderr and fills the rest with grey) and lets corrupt entropy-coded data through with "Corrupt JPEG
    data: ..." warnings. Here the decoder's messages are captured during ``cv2.imread``: a message about missing or
    corrupt data (premature end, corrupt, truncated, CRC or read error) is an error naming the file; benign ones
    (e.g. libpng's "iCCP: known incorrect sRGB profile") are passed on to stderr unchanged. A PNG must also end with
    its ``IEND`` chunk and a JPEG must contain an end-of-image marker.

    Args:
        path: image file.
        flags: ``cv2.imread`` flags (default ``cv2.IMREAD_UNCHANGED``).

    Returns:
        the decoded array as ``cv2.imread`` gives it.

    >>> import tempfile, cv2, numpy as np, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (64, 64), np.uint8))
    >>> _ = (d / "cut.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    >>> read_image_strict(d / "cut.jpg")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    guidedmatch.errors.ImageReadError: image file is truncated or corrupt: .../cut.jpg (decoder: ...)
    """
    import cv2

    path = Path(path)
    if not path.exists():
        raise ImageNotFoundError(f"image not found: {path}")
    if path.is_dir():
        raise ImageReadError(f"image path is a directory: {path}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageReadError(f"cannot read image file {path}: {exc.strerror or exc}") from None
    if len(data) == 0:
        raise ImageReadError(f"image file is empty: {path}")
    problem = None
    if data[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND\xaeB`\x82" not in data[-4096:]:  # IEND + its fixed CRC
        problem = "PNG without its IEND chunk"
    elif data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[2:]:
        problem = "JPEG without an end-of-image marker"
    buf = np.frombuffer(data, np.uint8)
    with _capture_native_stderr() as captured:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED if flags is None else flags)
    text = "".join(captured).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    bad = [ln for ln in lines if _CORRUPT_MESSAGE.search(ln) and not _BENIGN_MESSAGE.search(ln)]
    if bad:
        problem = "; ".join(dict.fromkeys(re.sub(r"^\[ ?WARN:[^\]]*\]\s*", "", ln) for ln in bad))
    if problem is not None:
        raise ImageReadError(f"image file is truncated or corrupt: {path} (decoder: {problem})")
    if img is None:
        raise ImageReadError(f"cannot read image (unknown format or corrupt file): {path}")
    for ln in lines:  # benign decoder warnings of a complete image are passed on
        print(ln, file=sys.stderr)
    return img


def load_image(image_or_path, grey: bool = True) -> np.ndarray:
    """Read an image as ``uint8``; grey ``(h, w)`` when ``grey`` else ``(h, w, 3)`` BGR. The one image reader
    of the package (CLI, :func:`detect`, the evaluation datasets).

    Accepts a path or an array (grey, BGR or BGRA; float arrays in [0, 1] are scaled to 0..255, uint16 to the
    high byte). A file is decoded by ``cv2.imread`` with ``IMREAD_GRAYSCALE`` when ``grey`` (the decoder's own
    grey conversion, as hloc and the benchmarks use; for JPEG it decodes the luminance directly) else
    ``IMREAD_COLOR``; an array is converted with ``cv2.cvtColor``. The two grey conversions may differ by one
    grey level in some pixels (libpng / libjpeg round differently from ``cvtColor``).
    Files are decoded completely or not at all (:func:`read_image_strict`): a truncated or corrupt file raises
    :class:`~guidedmatch.errors.ImageReadError` (a ``ValueError``); a missing path raises :class:`ImageNotFoundError`
    (also a ``FileNotFoundError``); an empty image raises :class:`~guidedmatch.errors.ImageReadError`.
    """
    import cv2

    if isinstance(image_or_path, (str, os.PathLike)):
        img = read_image_strict(image_or_path, cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
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


#: Keyword options of each detector's OpenCV factory and their types (``nfeatures`` is ``max_features``). The names
#: actually offered are those the installed OpenCV's factory signature also lists (:func:`detector_options`).
DETECTOR_PARAMS: dict[str, dict[str, type]] = {
    "sift": dict(nOctaveLayers=int, contrastThreshold=float, edgeThreshold=float, sigma=float,
                 enable_precise_upscale=bool),
    "orb": dict(scaleFactor=float, nlevels=int, edgeThreshold=int, firstLevel=int, WTA_K=int, scoreType=int,
                patchSize=int, fastThreshold=int),
    "akaze": dict(descriptor_type=int, descriptor_size=int, descriptor_channels=int, threshold=float, nOctaves=int,
                  nOctaveLayers=int, diffusivity=int, max_points=int),
    "brisk": dict(thresh=int, octaves=int, patternScale=float),
}


def _factory(method: str):
    import cv2

    name = {"sift": "SIFT_create", "orb": "ORB_create", "akaze": "AKAZE_create", "brisk": "BRISK_create"}[method]
    # OpenCV 4.x has cv2.AKAZE_create / cv2.BRISK_create; OpenCV 5 moved them to cv2.xfeatures2d
    factory = getattr(cv2, name, None) or getattr(getattr(cv2, "xfeatures2d", None), name, None)
    if factory is None:
        raise ConfigError(f"{method} is not available in this OpenCV build ({cv2.__version__})")
    return factory


def detector_options(method: str) -> dict[str, type]:
    """The options :func:`detect` accepts for ``method`` (name -> type): :data:`DETECTOR_PARAMS` restricted to the
    names in the installed OpenCV factory's signature (``SIFT_create([, nfeatures[, nOctaveLayers[, ...``).

    >>> sorted(detector_options("brisk"))
    ['octaves', 'patternScale', 'thresh']
    """
    method = _check_method(method)
    known = DETECTOR_PARAMS[method]
    try:
        head = (_factory(method).__doc__ or "").split("->")[0]
        offered = set(re.findall(r"\[, (\w+)", head))
    except ConfigError:
        offered = set()
    return {k: t for k, t in known.items() if k in offered} if offered else dict(known)


def _check_method(method) -> str:
    m = str(method).lower()
    if m not in DETECTORS:
        raise ConfigError(f"unknown detector {method!r}; choose one of {', '.join(DETECTORS)}")
    return m


def check_detector_options(method: str, options: dict) -> dict:
    """Check ``options`` against the detector's known parameter names and types; returns them (ints given for
    float parameters are converted). Raises :class:`~guidedmatch.errors.ConfigError` listing the valid options.

    >>> check_detector_options("sift", {"contrastThreshold": 0.01})
    {'contrastThreshold': 0.01}
    >>> check_detector_options("sift", {"contrastThreshold": "abc"})
    Traceback (most recent call last):
    ...
    guidedmatch.errors.ConfigError: sift option contrastThreshold must be a float; got 'abc' (sift options: nOctaveLayers (int), contrastThreshold (float), edgeThreshold (float), sigma (float), enable_precise_upscale (bool))
    """
    method = _check_method(method)
    valid = detector_options(method)
    listing = f"{method} options: " + ", ".join(f"{k} ({t.__name__})" for k, t in valid.items())
    out = {}
    for k, v in dict(options).items():
        if k == "nfeatures":
            raise ConfigError(f"use max_features (--max-features) instead of the detector option nfeatures ({listing})")
        if k not in valid:
            raise ConfigError(f"unknown {method} option {k!r} ({listing})")
        t = valid[k]
        ok = (isinstance(v, bool) if t is bool else
              isinstance(v, (int, np.integer)) and not isinstance(v, bool) if t is int else
              isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and np.isfinite(v))
        if not ok:
            raise ConfigError(f"{method} option {k} must be {'an' if t is int else 'a'} {t.__name__}; got {v!r} ({listing})")
        out[k] = float(v) if t is float else (int(v) if t is int else v)
    return out


def _make_detector(method: str, max_features: int | None, options: dict):
    import cv2

    method = _check_method(method)
    options = check_detector_options(method, options)
    n = int(max_features) if max_features else 0
    kw = {"nfeatures": n} if method == "sift" else {"nfeatures": n or 10000} if method == "orb" else {}
    try:
        return _factory(method)(**kw, **options)
    except (TypeError, cv2.error) as exc:
        raise ConfigError(f"invalid option for {method} detector: {exc}") from None


# ------------------------------------------------------------------ memory guard
#: Peak extra memory of ``detectAndCompute`` in bytes per image pixel (grey 8-bit input): the largest of the
#: measured per-pixel peaks (VmHWM, 1000x750 .. 3200x2400 photo, OpenCV 5.0; benchmarks/detect_memory.py, results in
#: benchmarks/results/detect_memory.json) plus a few percent. SIFT's is its pyramid on the 2x upsampled image
#: (6 Gaussian + 5 DoG float32 levels per octave: 16 B * 4/3 * 11 = 235 B/px; measured 235-242); ORB's is bounded by
#: its 10000-feature default (6-12 B/px measured).
DETECT_BYTES_PER_PIXEL = {"sift": 245.0, "orb": 16.0, "akaze": 125.0, "brisk": 30.0}
DETECT_BYTES_BASE = 64 << 20  # fixed overhead (OpenCV buffers, keypoints, descriptors), bytes


def estimate_detect_memory(width: int, height: int, method: str = "sift") -> int:
    """Estimated peak extra memory (bytes) of detecting ``method`` features on a ``width x height`` image.

    >>> round(estimate_detect_memory(6000, 4500, "sift") / 1e9, 1)   # measured: 6.3 GB
    6.7
    """
    return int(DETECT_BYTES_BASE + DETECT_BYTES_PER_PIXEL[_check_method(method)] * int(width) * int(height))


def available_memory() -> int | None:
    """Bytes this process can still allocate: ``MemAvailable`` of /proc/meminfo, capped by a cgroup (v2 or v1)
    limit minus its usage; None when unknown (then no memory check is made)."""
    vals = []
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    vals.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError):
        pass
    for lim, cur in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                     ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(lim).read_text().strip()
            if limit != "max" and int(limit) < 1 << 60:
                vals.append(int(limit) - int(Path(cur).read_text().strip()))
        except (OSError, ValueError):
            continue
    return max(0, min(vals)) if vals else None


def suggest_max_image_size(width: int, height: int, method: str, budget: int) -> int:
    """Largest long side (a multiple of 64 px, at least 64) whose detection estimate fits in ``budget`` bytes."""
    px = max(0.0, (budget - DETECT_BYTES_BASE) / DETECT_BYTES_PER_PIXEL[_check_method(method)])
    scale = min(1.0, float(np.sqrt(px / max(1, width * height))))
    return max(64, int(max(width, height) * scale) // 64 * 64)


def check_detect_memory(width: int, height: int, method: str, what: str = "image", *, fraction: float = 0.8) -> None:
    """Raise :class:`~guidedmatch.errors.MemoryLimitError` (with a suggested ``max_image_size``) when the estimated
    peak of detecting on ``width x height`` exceeds ``fraction`` of :func:`available_memory`."""
    avail = available_memory()
    if avail is None:
        return
    need = estimate_detect_memory(width, height, method)
    budget = int(avail * fraction)
    if need > budget:
        size = suggest_max_image_size(width, height, method, budget)
        raise MemoryLimitError(
            f"{method} detection on {what} ({width}x{height}) needs about {need / 1e9:.1f} GB, more than the "
            f"{budget / 1e9:.1f} GB available (80 % of {avail / 1e9:.1f} GB free); downscale for detection with max_image_size={size} "
            f"(CLI: --max-image-size {size})")


def downscale_for_detection(img: np.ndarray, max_image_size: int | None) -> tuple[np.ndarray, float, float]:
    """``img`` resized (``cv2.INTER_AREA``) so that its long side is at most ``max_image_size``; returns
    ``(image, sx, sy)`` with the per-axis scale factors (1.0 when not resized)."""
    import cv2

    h, w = img.shape[:2]
    if not max_image_size or max(w, h) <= max_image_size:
        return img, 1.0, 1.0
    s = float(max_image_size) / max(w, h)
    nw, nh = max(1, int(round(w * s))), max(1, int(round(h * s)))
    return cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA), nw / w, nh / h


def detect(image_or_path, method: str = "sift", max_features: int | None = None, *,
           max_image_size: int | None = None, **detector_options) -> Features:
    """Detect keypoints and compute descriptors on the 8-bit grey image.

    Args:
        image_or_path: path or array (colour is converted to grey). Files are read strictly (:func:`load_image`).
        method: ``"sift"`` (default, float 128-D, L2), ``"orb"``, ``"akaze"``, ``"brisk"`` (binary, Hamming).
        max_features: keep at most this many, strongest response first (None = detector default:
            unlimited for SIFT/AKAZE/BRISK, 10000 for ORB).
        max_image_size: when the image's long side is larger, detect on a copy downscaled to this long side
            (``cv2.INTER_AREA``); keypoints and scales are reported in **original-image pixels**
            (``x = (x_small + 0.5) / s - 0.5``, OpenCV pixel-centre convention) and ``image_size`` is the original.
        **detector_options: passed to the OpenCV factory (e.g. ``contrastThreshold=0.01`` for SIFT); checked
            against :func:`detector_options` (names and types) before any work.

    Raises:
        ConfigError: unknown detector, unknown option or wrong type (the message lists the valid options).
        ImageReadError: unreadable, truncated or corrupt image file.
        MemoryLimitError: the estimated peak of detection (:func:`estimate_detect_memory`) exceeds 80 % of the
            available memory; the message suggests a ``max_image_size`` that fits.

    Returns:
        :class:`Features` (possibly empty: a textureless image gives ``len(f) == 0``; callers decide).

    >>> import numpy as np
    >>> from guidedmatch.testing.scenes import make_scene
    >>> f = detect(make_scene((320, 240), roll_deg=10.0, seed=1).image1, max_features=200)
    >>> len(f), f.keypoints.shape, f.descriptors.dtype, f.image_size
    (200, (200, 2), dtype('float32'), (320, 240))
    >>> img = np.random.default_rng(0).integers(0, 255, (400, 600)).astype(np.uint8)
    >>> f = detect(img, max_image_size=300)
    >>> f.image_size, bool(f.keypoints[:, 0].max() > 300)
    ((600, 400), True)
    """
    method = _check_method(method)
    if max_image_size is not None:
        max_image_size = int(check_number("detect", "max_image_size", max_image_size, lo=16, integer=True))
    det = _make_detector(method, max_features, dict(detector_options))
    img = load_image(image_or_path, grey=True)
    h, w = img.shape[:2]
    small, sx, sy = downscale_for_detection(img, max_image_size)
    what = str(image_or_path) if isinstance(image_or_path, (str, os.PathLike)) else "the image"
    check_detect_memory(small.shape[1], small.shape[0], method, what)
    kps, desc = det.detectAndCompute(small, None)
    kps = list(kps)
    if max_features and len(kps) > max_features:
        order = np.argsort([-k.response for k in kps], kind="stable")[: int(max_features)]
        order.sort()
        kps = [kps[i] for i in order]
        desc = desc[order]
    f = Features.from_cv(kps, desc, (w, h), kind=method)
    if (sx, sy) == (1.0, 1.0):
        return f
    kp = (f.keypoints + 0.5) / np.array([sx, sy]) - 0.5
    scales = None if f.scales is None else f.scales / np.float32(np.sqrt(sx * sy))
    return Features(kp, f.descriptors, (w, h), f.kind, scales, f.angles, f.responses)
