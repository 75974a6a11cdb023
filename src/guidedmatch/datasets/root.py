"""The evaluation data folder (:func:`data_root`) and reading its files: images with a hint when one is missing,
the photo folder (:func:`list_photos`).
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from ..errors import DataNotFoundError
from ..features import load_image

ENV_VAR = "GUIDEDMATCH_DATA"
PHOTOS_DIR = Path("photos") / "unsplash"
_IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def _repo_root() -> Path:
    """The repository root: the parent of ``src/`` (this file is ``src/guidedmatch/datasets/root.py``)."""
    return Path(__file__).resolve().parents[3]


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


def list_photos(root: str | os.PathLike | None = None) -> list[Path]:
    """The photos of the synthetic set, ``photos/unsplash/*`` sorted by file name."""
    d = _require_root(root) / PHOTOS_DIR
    if not d.is_dir():
        raise _missing(d, "photo folder")
    photos = sorted(p for p in d.iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    if not photos:
        raise _missing(d / "*.jpg", "photos")
    return photos
