"""The figure (:func:`plot_reconstruction`) and the human-readable ``report.md`` (:func:`report_markdown`) of a run."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .config import mapper_label

__all__ = ["plot_reconstruction", "report_markdown"]


# --------------------------------------------------------------------------- figure and report
def plot_reconstruction(path: str | os.PathLike, rec: Any, title: str = "", max_points: int = 30000,
                        seed: int = 0) -> Path:
    """Cameras (centres + viewing directions) and sparse points, top view and side view.

    The axes follow the cameras: "up" = the mean of the cameras' image-up directions (``-y`` of each camera),
    "forward" = the mean viewing direction made orthogonal to it, "right" = forward x up. Points beyond the
    1st-99th percentile box are left out of the axis limits."""
    from ..plots import _plt, save_figure

    plt = _plt()
    centres, dirs, ups = [], [], []
    for i in rec.reg_image_ids():
        pose = rec.image(i).cam_from_world()
        R = pose.rotation.matrix()
        centres.append(-R.T @ np.asarray(pose.translation))
        dirs.append(R[2])
        ups.append(-R[1])
    centres = np.array(centres).reshape(-1, 3)
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    up = np.mean(ups, axis=0) if ups else np.array([0.0, -1.0, 0.0])
    up /= max(np.linalg.norm(up), 1e-12)
    fwd = np.mean(dirs, axis=0) if dirs else np.array([0.0, 0.0, 1.0])
    fwd = fwd - up * np.dot(fwd, up)
    if np.linalg.norm(fwd) < 1e-9:
        fwd = np.cross(up, [1.0, 0.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    B = np.stack([right, fwd, up])
    c, p = centres @ B.T, pts @ B.T
    d = np.array(dirs).reshape(-1, 3) @ B.T
    span = np.ptp(np.vstack([c, np.percentile(p, [1, 99], axis=0)]) if len(p) else c, axis=0).max() if len(c) else 1.0
    arrow = 0.08 * max(span, 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    size = 4.0 if len(p) < 5000 else 0.6
    for ax, (a, b, la, lb, name) in zip(axes, ((0, 1, "right", "forward", "top view"),
                                                 (1, 2, "forward", "up", "side view"))):
        if len(p):
            ax.scatter(p[:, a], p[:, b], s=size, c="0.35", alpha=0.5, linewidths=0)
        ax.scatter(c[:, a], c[:, b], s=25, c="tab:red", zorder=3, label="cameras")
        for ci, di in zip(c, d):
            ax.plot([ci[a], ci[a] + arrow * di[a]], [ci[b], ci[b] + arrow * di[b]], c="tab:red", lw=1.2)
        xy = np.vstack([np.percentile(p[:, [a, b]], [1, 99], axis=0), c[:, [a, b]]]) if len(p) else c[:, [a, b]]
        lo, hi = xy.min(0), xy.max(0)
        half = 0.55 * max(float((hi - lo).max()), 1e-9)          # square box: equal scales on both axes
        mid = (lo + hi) / 2
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.set_title(f"{name}: {len(c)} cameras, {rec.num_points3D()} points" + (f" (showing {len(p)})" if
                                                                                 len(p) < rec.num_points3D() else ""))
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def _fmt_s(v: float) -> str:
    return f"{v:.2f}"


def _mem(st: dict) -> str:
    m = st.get("peak_rss_mb") or {}
    return f"{m.get('self', 0):,.0f} / {m['children']:,.0f}" if m.get("children") else f"{m.get('self', 0):,.0f}"


def report_markdown(report: dict) -> str:
    """The human-readable ``report.md`` of a run."""
    st = report["stages"]
    lines = [f"# guidedmatch sfm: {report['image_dir']}", "",
             f"Command: `{report.get('command', '')}`  ", f"Finished: {report['meta'].get('timestamp_utc')}", "",
             "| stage | time (s) | peak memory (MB): this process / its largest worker process | details |", "|---|---|---|---|"]
    ex = st["extraction"]
    lines.append(f"| extraction ({ex['detector']}) | {_fmt_s(ex['time_s'])} | {_mem(ex)} | {ex['extracted']} extracted, "
                 f"{ex['reused']} reused, {len(ex.get('skipped', []))} skipped, keypoints median "
                 f"{ex['keypoints']['median']:.0f} (total {ex['keypoints']['total']:,}) |")
    ma = st["matching"]
    coll = ma["collection"]
    lines.append(f"| matching ({report['config']['mode']}, geometry {report['config']['geometry']}) | "
                 f"{_fmt_s(ma['time_s'])} | {_mem(ma)} | {ma['pairs']} pairs: {coll['done']} matched now, "
                 f"{coll['skipped']} reused, {len(coll['failed'])} failed; "
                 f"{ma['verified_pairs']} verified pairs, {ma['verified_inliers']:,} inlier matches"
                 + (f" (COLMAP verification {_fmt_s(ma['verify_time_s'])} s)" if report['config']['geometry'] == 'colmap' else "")
                 + (f"; second look at {lk['looked']} weak or rejected pairs: {lk['verified']} newly verified "
                    f"({_fmt_s(lk['time_s'])} s)" if (lk := ma.get("second_look")) else "")
                 + (f"; the mapper gets those within {ti['max_error_px']:g} px of their pair's F / H (at least "
                    f"{ti['min_inliers']}: {ti['inliers_before']:,} -> {ti['inliers_after']:,})"
                    if (ti := ma.get("inlier_px")) else "")
                 + ((f"; the mapper gets at most {ic['max_inliers']} per pair ({ic['pairs_capped']} pairs capped "
                     f"this run: {ic['inliers_before']:,} -> {ic['inliers_after']:,})" if ic.get("applied", True) else
                     f"; the mapper gets all of them (the cap of {ic['max_inliers']} per pair applies above "
                     f"{ic['above']:,} inliers in all)") if (ic := ma.get("inlier_cap")) else "")
                 + " |")
    mp = st["mapping"]
    lines.append(f"| mapping | {_fmt_s(mp['time_s'])} | {_mem(mp)} | {mapper_label(mp)}, "
                 f"{len(mp['models'])} model(s)" + (", reused (same database and settings)" if mp.get("reused") else "")
                 + " |")
    lines.append(f"| total | {_fmt_s(report['total_time_s'])} | {report.get('peak_rss_mb', '')} | |")
    pl = report.get("pipeline")
    if pl:
        if pl.get("overlapped"):
            lines += ["", f"Extraction and matching overlapped ({pl['why']}): "
                      f"{pl.get('pairs_matched_during_extraction', 0)} of {ma['pairs']} pairs matched during the "
                      f"extraction, the first {_fmt_s(pl['first_pair_s']) + ' s' if pl.get('first_pair_s') is not None else '(none)'} "
                      f"after the start; the matching row is the time after the extraction "
                      f"({_fmt_s(pl.get('tail_after_extraction_s', 0.0))} s of it overlapped pairs, then the staged "
                      "pass over the final pair list)."]
        else:
            lines += ["", f"Extraction, then matching: not overlapped ({pl['why']})."]
    models = mp["models"]
    lines += ["", "## Reconstruction", ""]
    if not models:
        lines.append("No model: the mapper could not initialise (too few verified pairs).")
    else:
        lines += ["| model | registered | 3D points | observations | mean track length | mean reprojection error (px) |",
                  "|---|---|---|---|---|---|"]
        for k, m in enumerate(models):
            lines.append(f"| sparse/{k} | {m['registered']}/{report['num_images']} | {m['points3D']:,} | "
                         f"{m['observations']:,} | {m['mean_track_length']:.2f} | "
                         f"{m['mean_reprojection_error_px']:.3f} |")
        if len(models) > 1:
            lines += [""] + [f"* sparse/{k}: {', '.join(m['registered_names'])}" for k, m in enumerate(models)]
        if report.get("figure"):
            lines += ["", f"![cameras and points of sparse/0]({Path(report['figure']).name})"]
        unreg = report.get("unregistered", [])
        if unreg:
            lines += ["", f"Not registered in any model: {', '.join(unreg)}"]
    if report.get("skipped_images"):
        lines += ["", "## Skipped images", ""] + [f"* {s['name']}: {s['reason']}" for s in report["skipped_images"]]
    if coll.get("failed"):
        lines += ["", "## Failed pairs", ""] + [f"* {' '.join(f['pair'])}: {f['reason']}" for f in coll["failed"]]
    rows = report["pairs"]
    lines += ["", f"## Pairs ({len(rows)} with matches; verdict = COLMAP two-view configuration)", "",
              "| image 1 | image 2 | matches | verdict | inliers |", "|---|---|---|---|---|"]
    cap = 300
    for r in rows[:cap]:
        lines.append(f"| {r['name1']} | {r['name2']} | {r['matches']} | {r['config'] or 'none'} | {r['inliers']} |")
    if len(rows) > cap:
        lines.append(f"| ... {len(rows) - cap} more in report.json | | | | |")
    return "\n".join(lines) + "\n"
