"""``guidedmatch bench pairs``, its data: the scene and the unrelated photos, what runs on them, and the cached SIFT
features of every image (detected once, saved as ``.npz`` under ``<out>/features/``). The benchmark itself:
:mod:`guidedmatch.evaluation.bench_pairs`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SCENE = "Herz-Jesus-P8"
LONG_SIDE = 3072  # long side of the Herz-Jesus images; unrelated photos are resized to it
NUM_UNRELATED = 5
FEATURE_SETS = ("8192", "0.01")
OURS = ("so+epi+ia", "epi", "bf")
PEERS = ("faiss_flat", "faiss_ivf", "opencv_flann")
FLANN = dict(trees=4, checks=64)  # as benchmarks/bench_guided.py (the FLANN ratios of its table)
QUICK = dict(scale=0.5, pairs=("0000-0001", "0000-0005"), unrelated=1, cap={"8192": 2048, "0.01": 6000})
DENSE_PAIR = ("0002", "0003")
DENSE_CT = 0.002


def _cache_dir(out: Path) -> Path:
    d = out / "features"
    d.mkdir(parents=True, exist_ok=True)
    ign = d / ".gitignore"
    if not ign.exists():
        ign.write_text("*\n")
    return d


def _load_grey(path: Path, long_side: int | None, scale: float) -> np.ndarray:
    """Grey uint8 image; resized so its long side is ``long_side`` (if given), then by ``scale``."""
    import cv2

    from ..features import load_image

    img = load_image(path, grey=True)
    h, w = img.shape[:2]
    f = (long_side / max(h, w) if long_side else 1.0) * scale
    if f != 1.0:
        size = (max(1, round(w * f)), max(1, round(h * f)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
    return img


def cached_features(path: Path, cache: Path, ct: float, *, long_side: int | None = None, scale: float = 1.0):
    """SIFT (``contrastThreshold=ct``) of one image, from ``cache`` when there, else detected and saved."""
    from ..features import Features, detect

    tag = f"{path.parent.parent.name}_{path.stem}" if path.parent.name == "images" else path.stem
    f = cache / f"{tag}_ls{long_side or 0}_s{scale:g}_ct{ct:g}.npz"
    if f.exists():
        return Features.load(f)
    feats = detect(_load_grey(path, long_side, scale), "sift", contrastThreshold=ct)
    feats.save(f)
    return feats


def strongest(f, n: int | None):
    """The ``n`` strongest features by detector response (index order kept)."""
    if n is None or n >= len(f):
        return f
    idx = np.sort(np.argsort(-f.responses, kind="stable")[:n])
    return f.subset(idx)


def pair_list(root, quick: bool):
    """``(scene pairs, unrelated pairs)``; unrelated = ``(name, herz-jesus image path, photo path)``."""
    from ..datasets import list_photos, strecha_scene_pairs

    pairs = strecha_scene_pairs(root, SCENE)
    images = sorted({Path(p.image1) for p in pairs} | {Path(p.image2) for p in pairs})
    photos = list_photos(root)
    n_unrel = QUICK["unrelated"] if quick else NUM_UNRELATED
    if quick:
        pairs = [p for p in pairs if p.name.rsplit("/", 1)[1] in QUICK["pairs"]]
    unrelated = [(f"unrelated/{images[k].stem}-vs-{'-'.join(photos[k].stem.split('-')[:2])}", images[k], photos[k])
                 for k in range(n_unrel)]
    return pairs, unrelated


def _field(obj, name, default=None):
    """``obj[name]`` for dicts, ``getattr`` otherwise (stats and fallbacks are dataclasses or, before, dicts)."""
    if isinstance(obj, dict):
        return obj.get(name, default)
    return getattr(obj, name, default)
