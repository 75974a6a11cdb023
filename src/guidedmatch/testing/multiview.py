"""A small rendered multi-view collection with known poses (the collection / SfM test fixture).

Extends :mod:`guidedmatch.testing.scenes` (textured planes, z-buffered rendering, exact ground truth) from two
views to a sequence: ``n_views`` cameras translate along a long textured wall with slanted panels in front of it
(so every view sees 3-D structure, not a single plane), each with its own small yaw / pitch / roll. Neighbouring
views overlap strongly; the first and the last see disjoint parts of the scene (a known non-overlapping pair
inside the connected sequence). With ``isolated=True`` one more view looks the other way, at a different textured
plane behind the cameras, and overlaps no other view.

Conventions
-----------
* World-to-camera poses: ``X_cam = R_i X_world + t_i``; pixels ``x ~ K X_cam`` (one shared ``K``).
* Pixel coordinates follow OpenCV (origin at the centre of the top-left pixel).
* ``fundamental(i, j)`` satisfies ``x_j^T F x_i = 0``; ``two_view(i, j)`` is a
  :class:`~guidedmatch.testing.scenes.TwoViewScene` of views ``i`` -> ``j`` with exact per-plane homographies.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .scenes import Plane, TwoViewScene, _render, _rot, fundamental_from_pose, procedural_texture

__all__ = ["MultiViewScene", "make_multiview", "write_views"]


@dataclass(frozen=True, eq=False)
class MultiViewScene:
    """Rendered views with exact geometry.

    Attributes:
        images: per view ``(h, w) uint8`` grey image.
        names: per view file name (``view_00.png``, ...).
        K: ``(3, 3)`` intrinsics shared by all views (focal ``0.9 w``, principal point at the image centre).
        R, t: per view world-to-camera rotation ``(3, 3)`` and translation ``(3,)`` (metres).
        labels: per view ``(h, w) int16`` plane id visible at each pixel (-1 = background).
        plane_maps: per view, per plane ``(3, 3)`` homography texture pixel -> image pixel.
        isolated: indices of the views that overlap no other view.
        overlap: ``(n, n)`` fraction of view i's plane pixels (8 px grid) visible in view j (diagonal 1).
    """

    images: tuple
    names: tuple
    K: np.ndarray
    R: tuple
    t: tuple
    labels: tuple
    plane_maps: tuple
    isolated: tuple
    overlap: np.ndarray

    def __len__(self) -> int:
        return len(self.images)

    @property
    def size(self) -> tuple[int, int]:
        """``(w, h)`` of every view, pixels."""
        return (self.images[0].shape[1], self.images[0].shape[0])

    def center(self, i: int) -> np.ndarray:
        """Camera centre of view ``i`` in world coordinates (``-R^T t``)."""
        return -self.R[i].T @ self.t[i]

    def relative_pose(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R_ij, t_ij)`` with ``X_j = R_ij X_i + t_ij`` (camera-i to camera-j coordinates)."""
        R = self.R[j] @ self.R[i].T
        return R, self.t[j] - R @ self.t[i]

    def fundamental(self, i: int, j: int) -> np.ndarray:
        """``F_ij`` (unit Frobenius norm) with ``x_j^T F x_i = 0`` for pixels of views i and j."""
        R, t = self.relative_pose(i, j)
        return fundamental_from_pose(self.K, self.K, R, t)

    def homographies(self, i: int, j: int) -> tuple:
        """Per plane ``H`` mapping view-i pixels on that plane to view-j pixels."""
        return tuple(Hj @ np.linalg.inv(Hi) for Hi, Hj in zip(self.plane_maps[i], self.plane_maps[j]))

    def two_view(self, i: int, j: int) -> TwoViewScene:
        """Views ``i`` -> ``j`` as a :class:`TwoViewScene` (ground-truth ``project`` / ``correct`` of matches)."""
        R, t = self.relative_pose(i, j)
        return TwoViewScene(self.images[i], self.images[j], self.K, self.K.copy(), R, t, self.fundamental(i, j),
                            self.labels[i], self.labels[j], self.homographies(i, j), 0.0)

    def overlapping(self, i: int, j: int, min_fraction: float = 0.0) -> bool:
        """True when more than ``min_fraction`` of either view's plane pixels is visible in the other."""
        return max(self.overlap[i, j], self.overlap[j, i]) > min_fraction

    def non_overlapping_pairs(self) -> list[tuple[int, int]]:
        """``(i, j)``, ``i < j``, sharing no visible scene point (exactly zero overlap both ways)."""
        n = len(self)
        return [(i, j) for i in range(n) for j in range(i + 1, n) if not self.overlapping(i, j)]


def _look_at(center: np.ndarray, target: np.ndarray, roll_deg: float, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera rotation of a camera at ``center`` looking at ``target`` (y down), rolled about its axis."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return _rot([0, 0, 1], np.deg2rad(roll_deg)) @ np.vstack([x, y, z])


def _overlap(labels_i, labels_j, Hs_ij, step: int = 8) -> float:
    h, w = labels_i.shape
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    pts = np.c_[u.ravel(), v.ravel()].astype(float)
    lab = labels_i[v.ravel(), u.ravel()]
    on = lab >= 0
    if not on.any():
        return 0.0
    vis = 0
    for k, H in enumerate(Hs_ij):
        sel = lab == k
        if not sel.any():
            continue
        q = np.c_[pts[sel], np.ones(sel.sum())] @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            q = q[:, :2] / q[:, 2:3]
        ok = np.isfinite(q).all(axis=1)
        qx = np.rint(np.where(ok, q[:, 0], -1)).astype(int)
        qy = np.rint(np.where(ok, q[:, 1], -1)).astype(int)
        inside = ok & (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
        vis += int((labels_j[qy[inside], qx[inside]] == k).sum())
    return vis / int(on.sum())


def make_multiview(n_views: int = 6, size: tuple[int, int] = (640, 480), seed: int = 0, *, isolated: bool = True,
                   spacing: float = 2.4, max_roll_deg: float = 15.0, noise_sigma: float = 2.0) -> MultiViewScene:
    """Render ``n_views`` (>= 2) views along a textured wall, plus an isolated view when ``isolated``.

    Args:
        n_views: views of the connected sequence (cameras ``spacing`` metres apart along x, 9 m from the wall,
            panels at 5-6.5 m; with the default 2.4 m and 6 views the first and last views share nothing).
        size: ``(w, h)`` of every view, pixels.
        seed: seeds textures, camera jitter (+-0.3 m, a few degrees of yaw/pitch, up to ``max_roll_deg`` roll)
            and image noise.
        isolated: append one view (the last) looking backwards at a different plane behind the cameras.
        noise_sigma: std of additive Gaussian image noise (grey levels); each view also gets its own gain/offset.

    >>> mv = make_multiview(3, (160, 120), seed=1, spacing=0.5)
    >>> len(mv), mv.isolated, mv.non_overlapping_pairs()
    (4, (3,), [(0, 3), (1, 3), (2, 3)])
    """
    import cv2

    if n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {n_views}")
    rng = np.random.default_rng(seed)
    w, h = int(size[0]), int(size[1])
    f = 0.9 * w
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    ppm = 1.3 * f / 9.0  # texture pixels per metre: ~1.3 per image pixel on the wall
    ex, ey = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])

    def plane(center, e1, e2, hw, hh):
        tw, th = int(hw * ppm + 2), int(hh * ppm + 2)  # half-resolution texture, upsampled x2
        tex = procedural_texture(tw, th, rng)
        tex = cv2.resize(tex, (2 * tw, 2 * th), interpolation=cv2.INTER_CUBIC)
        return Plane(np.asarray(center, float), np.asarray(e1, float), np.asarray(e2, float), hw, hh, tex)

    x_end = spacing * (n_views - 1) / 2
    wall_half = x_end + 6.0
    planes = [plane([0, 0, 9.0], ex, ey, wall_half, 6.0)]
    for k, x in enumerate(np.arange(-x_end, x_end + 1e-9, 4.0)):
        a = np.deg2rad(rng.uniform(25, 40) * (-1) ** k)
        planes.append(plane([x + rng.uniform(-0.5, 0.5), rng.uniform(-0.6, 0.3), rng.uniform(5.0, 6.5)],
                            _rot(ey, a) @ ex, _rot(ex, rng.uniform(-0.3, 0.3)) @ ey, 1.3, 1.2))
    planes.append(plane([0, 1.8, 5.5], ex, np.array([0, 0, 1.0]), wall_half, 3.5))  # floor, 1.8 m below
    centers, targets, rolls = [], [], []
    for x in np.linspace(-x_end, x_end, n_views):
        c = np.array([x, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        centers.append(c)
        targets.append(np.array([x + rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), 8.0]))
        rolls.append(rng.uniform(-max_roll_deg, max_roll_deg))
    if isolated:
        planes.append(plane([0, 0, -12.0], -ex, ey, 5.0, 4.0))  # behind the sequence's cameras
        centers.append(np.array([0.3, 0.1, -4.0]))
        targets.append(np.array([0.0, 0.0, -12.0]))
        rolls.append(rng.uniform(-max_roll_deg, max_roll_deg))
    images, labels, maps, Rs, ts = [], [], [], [], []
    for i, (c, tg, roll) in enumerate(zip(centers, targets, rolls)):
        R = _look_at(c, tg, roll)
        t = -R @ c
        img, lab, Hs = _render(planes, K, R, t, (w, h))
        if noise_sigma > 0:
            gain, offset = rng.uniform(0.9, 1.05), rng.uniform(-8, 8)
            img = np.clip(img * gain + offset + rng.normal(0, noise_sigma, img.shape), 0, 255).astype(np.uint8)
        images.append(img)
        labels.append(lab)
        maps.append(tuple(Hs))
        Rs.append(R)
        ts.append(t)
    n = len(images)
    ov = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i != j:
                Hij = tuple(Hj @ np.linalg.inv(Hi) for Hi, Hj in zip(maps[i], maps[j]))
                ov[i, j] = _overlap(labels[i], labels[j], Hij)
    iso = tuple(i for i in range(n) if all(max(ov[i, j], ov[j, i]) == 0 for j in range(n) if j != i))
    return MultiViewScene(tuple(images), tuple(f"view_{i:02d}.png" for i in range(n)), K, tuple(Rs), tuple(ts),
                          tuple(labels), tuple(maps), iso, ov)


def write_views(scene: MultiViewScene, folder, ext: str = ".png") -> list[Path]:
    """Write every view as an image file ``folder/view_XX<ext>`` (created); returns the paths.

    The file names are ``scene.names`` with the suffix replaced by ``ext`` (``.png`` lossless, ``.jpg`` at
    quality 95).
    """
    import cv2

    from .._runtime import require_zlib

    folder = Path(folder)
    if ext.lower() == ".png":
        require_zlib(folder)  # OpenCV's PNG codec uses the system zlib
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, img in zip(scene.names, scene.images):
        p = folder / (Path(name).stem + ext)
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if ext.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(p), img, params):
            raise OSError(f"cannot write {p}")
        paths.append(p)
    return paths
