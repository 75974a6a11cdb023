"""Figures: motion fields (as in the paper's real-image figure, Teng & Dong §IV-C), multi-panel
comparisons, and the search-region illustration (the paper's Fig. 1).

All functions write PNGs atomically (temp file + rename) with the non-interactive Agg backend.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """``fig.savefig`` to a temp file next to ``path`` then ``os.replace`` (no partial PNGs)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=path.suffix or ".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
        _plt().close(fig)
    return path


def draw_motion_field(ax, image1: np.ndarray, pts1: np.ndarray, pts2: np.ndarray,
                      correct: np.ndarray | None = None, title: str = "", max_lines: int = 6000,
                      rng: np.random.Generator | None = None) -> None:
    """Draw on ``ax``: image 1 (grey) and a line from each image-1 keypoint to its match's image-2 position.

    ``pts1, pts2``: ``(M, 2)`` pixel coordinates; ``correct``: ``(M,) bool`` (green = correct,
    red = wrong; yellow when unknown). At most ``max_lines`` lines are drawn (a seeded random subset).
    """
    from matplotlib.collections import LineCollection

    ax.imshow(image1, cmap="gray", vmin=0, vmax=255, alpha=0.7)
    m = len(pts1)
    idx = np.arange(m)
    if m > max_lines:
        idx = np.sort((rng or np.random.default_rng(0)).choice(m, max_lines, replace=False))
    segs = np.stack([pts1[idx], pts2[idx]], axis=1)
    if correct is None:
        colors = np.tile([1.0, 0.85, 0.0, 0.9], (len(idx), 1))
    else:
        c = np.asarray(correct, bool)[idx]
        colors = np.where(c[:, None], [[0.0, 0.8, 0.0, 0.8]], [[0.95, 0.05, 0.05, 0.9]])
        # draw wrong matches on top so they stay visible
        order = np.argsort(c, kind="stable")[::-1]
        segs, colors = segs[order], colors[order]
    ax.add_collection(LineCollection(segs, colors=colors, linewidths=0.6))
    ax.scatter(pts1[idx, 0], pts1[idx, 1], s=0.6, c="cyan", linewidths=0)
    h, w = image1.shape[:2]
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)


def motion_field(path, image1, pts1, pts2, correct=None, title: str = "") -> Path:
    """Single motion-field PNG (see :func:`draw_motion_field`)."""
    plt = _plt()
    h, w = image1.shape[:2]
    fig, ax = plt.subplots(figsize=(8, 8 * h / w))
    draw_motion_field(ax, image1, np.asarray(pts1), np.asarray(pts2), correct, title)
    return save_figure(fig, path)


def motion_field_panels(path, image1, panels: list[dict], ncols: int = 3, suptitle: str = "") -> Path:
    """Several motion fields side by side; each panel dict has ``pts1, pts2, correct, title``."""
    plt = _plt()
    n = len(panels)
    ncols = min(ncols, n)
    nrows = int(np.ceil(n / ncols))
    h, w = image1.shape[:2]
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 5.2 * nrows * h / w + 0.4), squeeze=False)
    for ax, p in zip(axes.ravel(), panels):
        draw_motion_field(ax, image1, np.asarray(p["pts1"]).reshape(-1, 2), np.asarray(p["pts2"]).reshape(-1, 2),
                          p.get("correct"), p.get("title", ""))
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)
