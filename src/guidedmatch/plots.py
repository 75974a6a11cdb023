"""Figures: motion fields (as in the paper's real-image figure, Teng & Dong §IV-C), multi-panel
comparisons, the search-region illustration (the paper's Fig. 1), and the timeline of a collection run.

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
    from ._runtime import require_zlib
    from .errors import OutputError

    path = Path(path)
    try:
        require_zlib(path)  # an OutputError now rather than an abort inside the PNG encoder
    except OutputError:
        _plt().close(fig)
        raise
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=path.suffix or ".png", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        _plt().close(fig)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        # PNG at zlib level 3 instead of 6: identical pixels, files ~1 % larger, encoding ~2x faster (demo figure:
        # 0.59 -> 0.34 s of its ~1.5 s)
        extra = {"pil_kwargs": {"compress_level": 3}} if Path(tmp).suffix.lower() == ".png" else {}
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", **extra)
        from .features import publish

        publish(tmp, path)
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
    """Several motion fields side by side; each panel dict has ``pts1, pts2, correct, title``.

    Laid out with Matplotlib's constrained layout (titles wrapped to the panel width), so titles of one row never
    overlap the panels above and the figure title stays clear of the first row.
    """
    import textwrap

    plt = _plt()
    n = len(panels)
    ncols = min(ncols, n)
    nrows = int(np.ceil(n / ncols))
    h, w = image1.shape[:2]
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 5.2 * nrows * h / w + 0.8 * nrows + 0.6),
                             squeeze=False, layout="constrained")
    for ax, p in zip(axes.ravel(), panels):
        draw_motion_field(ax, image1, np.asarray(p["pts1"]).reshape(-1, 2), np.asarray(p["pts2"]).reshape(-1, 2),
                          p.get("correct"), textwrap.fill(p.get("title", ""), 60))
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if suptitle:
        fig.suptitle(textwrap.fill(suptitle, 30 * ncols), fontsize=11)
    return save_figure(fig, path)


def match_pair(path, image1, image2, pts1, pts2, inliers=None, title: str = "", max_lines: int = 250,
               rng: np.random.Generator | None = None) -> Path:
    """Both images side by side with their matches, readable at any match count.

    Every match is a dot in both images (green = inlier of the two-view verdict, red = outlier; small and
    translucent, so thousands of matches show as a density); lines join a seeded random subsample of at most
    ``max_lines`` inliers and ``max_lines`` outliers. The legend gives the counts and how many lines are drawn.

    Args:
        image1, image2: grey or BGR images; pts1, pts2: ``(M, 2)`` matched pixel coordinates.
        inliers: ``(M,) bool`` (the verdict's inlier mask); None = all unverified (drawn as outliers).
    """
    import textwrap

    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    plt = _plt()
    rng = rng or np.random.default_rng(0)
    pts1 = np.asarray(pts1, np.float64).reshape(-1, 2)
    pts2 = np.asarray(pts2, np.float64).reshape(-1, 2)
    m = len(pts1)
    inl = np.zeros(m, bool) if inliers is None else np.asarray(inliers, bool).reshape(-1)

    def rgb(img):
        img = np.asarray(img)
        return img if img.ndim == 2 else img[:, :, ::-1]

    h1, w1 = image1.shape[:2]
    h2, w2 = image2.shape[:2]
    H = max(h1, h2)
    canvas_w = w1 + w2 + max(10, (w1 + w2) // 100)
    off = canvas_w - w2
    fig, ax = plt.subplots(figsize=(14, 14 * H / canvas_w + 0.9), layout="constrained")
    grey = image1.ndim == 2 and image2.ndim == 2
    kw = dict(cmap="gray", vmin=0, vmax=255) if grey else {}
    ax.imshow(rgb(image1), extent=(-0.5, w1 - 0.5, h1 - 0.5, -0.5), **kw)
    ax.imshow(rgb(image2), extent=(off - 0.5, off + w2 - 0.5, h2 - 0.5, -0.5), **kw)
    dot = max(0.5, min(6.0, 4000.0 / max(m, 1)))
    handles = []
    for mask, colour, label in ((~inl, (0.95, 0.1, 0.1), "outlier"), (inl, (0.1, 0.85, 0.1), "inlier")):
        idx = np.flatnonzero(mask)
        if len(idx) == 0:
            continue
        lines = np.sort(rng.choice(idx, max_lines, replace=False)) if len(idx) > max_lines else idx
        segs = np.stack([pts1[lines], pts2[lines] + [off, 0]], axis=1)
        ax.add_collection(LineCollection(segs, colors=[(*colour, 0.55)], linewidths=0.6))
        for p, dx in ((pts1[idx], 0), (pts2[idx], off)):
            ax.scatter(p[:, 0] + dx, p[:, 1], s=dot, color=colour, alpha=0.6, linewidths=0)
        shown = f", {len(lines)} lines drawn" if len(lines) < len(idx) else ""
        handles.append(Line2D([], [], color=colour, marker="o", lw=1, label=f"{label}s: {len(idx)}{shown}"))
    ax.set_xlim(-0.5, canvas_w - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    if handles:
        ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=len(handles), fontsize=9,
                  frameon=False)
    full = f"{title} (image 1 left, image 2 right)" if title else "image 1 left, image 2 right"
    fig.suptitle(textwrap.fill(full, 140), fontsize=11)
    return save_figure(fig, path)


def search_regions(path, image1, image2, f1, f2, result, models=None, num_samples: int = 4) -> Path:
    """The paper's Fig. 1 for a few sample features: on image 2, the epipolar band (green), the
    spatial-order x-range (red) and their intersection (yellow, the final search region), with the
    candidates (cyan dots) and the accepted match (white cross). Left column: the feature in image 1.

    ``models`` is the :class:`~guidedmatch.matcher.GuidanceModels` of the run (``match(..., return_models=True)``).
    Regions are evaluated per pixel of image 2 through the alignment homography, so they are drawn in
    original image-2 coordinates.
    """
    plt = _plt()
    if models is None:
        raise ValueError("search regions need the guidance models of a guided run (not available for mode 'bf')")
    fin = np.asarray(models.final_queries)
    matched = dict(zip(result.pairs[:, 0].tolist(), result.pairs[:, 1].tolist()))
    pool = np.array([q for q in fin if q in matched]) if len(fin) else np.zeros(0, int)
    if len(pool) == 0:
        raise ValueError("no feature was matched in the guided final pass; nothing to illustrate")
    xs = f1.keypoints[pool, 0]
    # spread the samples over the image width
    picks = [pool[np.argmin(np.abs(xs - q))] for q in np.quantile(xs, np.linspace(0.15, 0.85, num_samples))]
    picks = list(dict.fromkeys(int(p) for p in picks))
    h2, w2 = image2.shape[:2]
    step = max(1, int(max(h2, w2) // 700))
    gy, gx = np.mgrid[0:h2:step, 0:w2:step]
    P = np.c_[gx.ravel(), gy.ravel(), np.ones(gx.size)] @ models.H2.T
    Pa = P[:, :2] / P[:, 2:3]
    keep, lo, hi, lines, _ = models.regions(np.array(picks))
    fig, axes = plt.subplots(len(picks), 2, figsize=(10, 3.6 * len(picks)), squeeze=False)
    for r, q in enumerate(picks):
        a0, a1 = axes[r]
        a0.imshow(image1, cmap="gray", vmin=0, vmax=255)
        a0.plot(*f1.keypoints[q], "o", ms=9, mfc="none", mec="yellow", mew=2)
        a0.set_title(f"image 1: feature {q}", fontsize=9)
        in_so = (Pa[:, 0] >= lo[r]) & (Pa[:, 0] <= hi[r]) if keep[r] else np.zeros(len(Pa), bool)
        in_band = (np.abs(Pa @ lines[r, :2] + lines[r, 2]) <= models.band_px * max(1, step / 2)) if lines is not None \
            else np.ones(len(Pa), bool)
        overlay = np.zeros((*gx.shape, 4))
        overlay[in_band.reshape(gx.shape)] = [0.0, 0.8, 0.0, 0.45]
        overlay[in_so.reshape(gx.shape)] = [0.9, 0.0, 0.0, 0.25]
        overlay[(in_so & in_band).reshape(gx.shape)] = [1.0, 0.9, 0.0, 0.9]
        a1.imshow(image2, cmap="gray", vmin=0, vmax=255)
        a1.imshow(overlay, extent=(0, w2, h2, 0), interpolation="nearest")
        cand = models.candidates(q)
        a1.scatter(f2.keypoints[cand, 0], f2.keypoints[cand, 1], s=6, c="cyan", linewidths=0)
        j = matched[q]
        a1.plot(*f2.keypoints[j], "x", ms=10, mec="white", mew=2)
        a1.set_title(f"image 2: band (green), SO range (red), search region (yellow): {len(cand)} candidates", fontsize=9)
        for ax in (a0, a1):
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    return save_figure(fig, path)


# --------------------------------------------------------------------------- collection timeline
def timeline_lanes(spans: list) -> list[int]:
    """A row per span of a collection run's timeline: one row per worker process; the spans of in-process threads
    (all "in-process") go on the first row free at their start (greedy interval partitioning), which gives as many
    rows as pairs ran at once.

    ``spans``: ``[worker, start, end]`` per pair.

    >>> timeline_lanes([["w1", 0, 2], ["w2", 0, 1], ["w1", 2, 3]])
    [0, 1, 0]
    >>> timeline_lanes([["in-process", 0, 2], ["in-process", 0, 1], ["in-process", 1.5, 3]])
    [0, 1, 1]
    """
    workers = sorted({w for w, _, _ in spans})
    if len(workers) > 1 or (workers and workers[0] != "in-process"):
        return [workers.index(w) for w, _, _ in spans]
    free_at: list[float] = []
    lanes = [0] * len(spans)
    for i in sorted(range(len(spans)), key=lambda k: spans[k][1]):
        start, end = spans[i][1], spans[i][2]
        lane = next((j for j, t in enumerate(free_at) if t <= start + 1e-9), len(free_at))
        if lane == len(free_at):
            free_at.append(end)
        else:
            free_at[lane] = end
        lanes[i] = lane
    return lanes


def draw_timeline(ax, spans: list, end: float | None = None, row_name: str = "worker") -> tuple[float, float]:
    """One bar per pair on its worker's (or thread's) row, times in seconds on the x axis; grey before the first pair
    (from 0) and after the last one (up to ``end``). Returns ``(first start, last end)``."""
    colors = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
    lanes = timeline_lanes(spans)
    first = min(s[1] for s in spans)
    last = max(s[2] for s in spans)
    for i, ((_, t0, t1), lane) in enumerate(zip(spans, lanes)):
        ax.broken_barh([(t0, t1 - t0)], (lane - 0.4, 0.8), facecolors=colors[i % len(colors)], edgecolor="white",
                       linewidth=0.5)
    n = max(lanes) + 1
    end = last if end is None else max(end, last)
    ax.axvspan(min(0.0, first), first, color="0.85", zorder=0)
    ax.axvspan(last, end, color="0.85", zorder=0)
    ax.set_xlim(min(0.0, first), end * 1.01 if end > 0 else 1.0)
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_yticks(range(n), [f"{row_name} {k + 1}" for k in range(n)], fontsize=7)
    ax.tick_params(axis="x", labelsize=7)
    return first, last


def collection_timeline(path: str | os.PathLike, records: list[dict], title: str = "") -> Path | None:
    """The timeline of a collection run (``guidedmatch colmap|hloc --timeline PNG``): when each pair was loaded and
    matched, on which worker or thread, from the per-pair records of :class:`~guidedmatch.collection.engine.
    CollectionReport` (``worker``, ``t_start``, ``t_end``: Unix time of each worker's own clock, so workers on
    several machines need synchronized clocks). Time 0 is the start of the first pair. None when no record has
    times (nothing was matched)."""
    recs = [r for r in records if r.get("status") == "done" and "t_start" in r]
    if not recs:
        return None
    t0 = min(r["t_start"] for r in recs)
    spans = [[r.get("worker", "?"), r["t_start"] - t0, r["t_end"] - t0] for r in recs]
    threads = all(s[0] == "in-process" for s in spans)
    n_rows = max(timeline_lanes(spans)) + 1
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 1.2 + 0.35 * n_rows))
    first, last = draw_timeline(ax, spans, row_name="thread" if threads else "worker")
    busy = sum(s[2] - s[1] for s in spans)
    ax.set_xlabel("seconds since the first pair started", fontsize=8)
    kind = ("thread" if threads else "worker") + ("s" if n_rows != 1 else "")
    use = busy / max(last - first, 1e-9) / n_rows
    ax.set_title((title + ": " if title else "") + f"{len(spans)} pairs in {last - first:.2f} s on {n_rows} {kind}; "
                 f"rows busy {use:.0%} of that time", fontsize=9, loc="left")
    return save_figure(fig, path)
