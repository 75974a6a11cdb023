"""Synthetic two-view scenes with exact ground truth (the built-in demo and the test fixture).

A few textured planes (procedural multi-scale texture rich in corners and blobs) are rendered by two
pinhole cameras with known ``K``, ``R``, ``t`` -- including a roll of camera 2 about its optical axis --
with a z-buffer, so occlusions are exact.

Conventions
-----------
* World frame = camera-1 frame. Camera 2 maps a point as ``X2 = R @ X1 + t``; pixels ``x ~ K X``.
* Pixel coordinates follow OpenCV (origin at the centre of the top-left pixel).
* ``F = K2^-T [t]_x R K1^-1`` so that ``x2^T F x1 = 0`` for homogeneous pixels.
* Ground truth for a match ``(p1, p2)``: the plane visible at ``p1`` in image 1 (z-buffer label) maps
  ``p1`` to ``p2* = H_plane p1``; the match is correct when ``p2*`` is visible on the same plane in
  image 2 and ``||p2* - p2|| < threshold`` (3 px, the paper's criterion, Teng & Dong §IV-A).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..alignment import apply_homography
from ..epipolar import skew


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation about a unit ``axis`` by ``angle`` radians."""
    axis = np.asarray(axis, float)
    k = skew(axis / np.linalg.norm(axis))
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def fundamental_from_pose(K1, K2, R, t) -> np.ndarray:
    """``F = K2^-T [t]_x R K1^-1`` (``X2 = R X1 + t``), scaled to unit Frobenius norm; all zeros when ``t = 0``
    (a pure rotation: no epipolar geometry, as in :mod:`guidedmatch.testing.twoview`).

    >>> bool(fundamental_from_pose(np.eye(3), np.eye(3), np.eye(3), np.zeros(3)).any())
    False
    """
    F = np.linalg.inv(K2).T @ skew(np.asarray(t, float).ravel()) @ R @ np.linalg.inv(K1)
    norm = np.linalg.norm(F)
    return F / norm if norm > 0 else np.zeros((3, 3))


def procedural_texture(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A ``(height, width) uint8`` texture: multi-octave value noise plus random shapes (corners, blobs)."""
    import cv2

    img = np.zeros((height, width), np.float32)
    for cells, amp in ((4, 0.3), (12, 0.25), (40, 0.2), (120, 0.15), (360, 0.1)):
        g = rng.random((max(2, height * cells // width), cells)).astype(np.float32)
        img += amp * cv2.resize(g, (width, height), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / max(float(img.max() - img.min()), 1e-6) * 150 + 50
    canvas = img.astype(np.uint8)
    n_shapes = int(width * height / 250)
    scale = max(width, height)
    for _ in range(n_shapes):
        c = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        r = int(max(2, rng.lognormal(np.log(scale / 300), 0.7)))
        kind = rng.integers(0, 4)
        if kind == 0:
            cv2.circle(canvas, (x, y), r, c, -1, lineType=cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(canvas, (x, y), (x + r, y + int(r * rng.uniform(0.5, 2))), c, -1)
        elif kind == 2:
            pts = (np.array([x, y]) + rng.normal(0, r, (int(rng.integers(3, 6)), 2))).astype(np.int32)
            cv2.fillPoly(canvas, [pts], c, lineType=cv2.LINE_AA)
        else:
            cv2.line(canvas, (x, y), (x + int(rng.normal(0, 2 * r)), y + int(rng.normal(0, 2 * r))), c,
                     int(rng.integers(1, 4)), lineType=cv2.LINE_AA)
    return cv2.GaussianBlur(canvas, (0, 0), 0.7)


@dataclass(frozen=True)
class Plane:
    """A textured rectangle: centre ``C`` (world, metres), in-plane unit axes ``e1, e2``, half sizes."""

    center: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    half_w: float
    half_h: float
    texture: np.ndarray  # (th, tw) uint8

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.e1, self.e2)
        return n / np.linalg.norm(n)

    def texture_to_world(self) -> np.ndarray:
        """3x3 ``A`` with ``X = A @ [u, v, 1]`` for texture pixel ``(u, v)`` (X as a world point)."""
        th, tw = self.texture.shape
        su, sv = 2 * self.half_w / (tw - 1), 2 * self.half_h / (th - 1)
        origin = self.center - self.half_w * self.e1 - self.half_h * self.e2
        return np.column_stack([self.e1 * su, self.e2 * sv, origin])


@dataclass(frozen=True, eq=False)
class TwoViewScene:
    """Two rendered views with exact geometry. Images are ``(h, w) uint8`` grey."""

    image1: np.ndarray
    image2: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray               # X2 = R X1 + t
    t: np.ndarray
    F: np.ndarray               # x2^T F x1 = 0
    labels1: np.ndarray         # (h, w) int16 plane id visible at each pixel, -1 = background
    labels2: np.ndarray
    homographies: tuple         # per plane: 3x3 H mapping image-1 pixels to image-2 pixels
    roll_deg: float

    @property
    def size(self) -> tuple[int, int]:
        return (self.image1.shape[1], self.image1.shape[0])

    def project(self, pts1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth image-2 position of image-1 pixels ``pts1 (M,2)``.

        Returns ``(pts2 (M,2), visible (M,) bool)``; ``visible`` is False on background, outside image 2,
        or when another plane occludes the point in image 2 (``pts2`` is NaN where no plane is hit).
        """
        pts1 = np.asarray(pts1, float).reshape(-1, 2)
        h, w = self.labels1.shape
        out = np.full_like(pts1, np.nan)
        vis = np.zeros(len(pts1), bool)
        if len(pts1) == 0:
            return out, vis
        ix = np.clip(np.rint(pts1[:, 0]).astype(int), 0, w - 1)
        iy = np.clip(np.rint(pts1[:, 1]).astype(int), 0, h - 1)
        lab = self.labels1[iy, ix]
        for k, H in enumerate(self.homographies):
            sel = lab == k
            if not sel.any():
                continue
            out[sel] = apply_homography(H, pts1[sel])
        ok = np.isfinite(out).all(axis=1)
        h2, w2 = self.labels2.shape
        qx = np.rint(np.where(ok, out[:, 0], -1)).astype(int)
        qy = np.rint(np.where(ok, out[:, 1], -1)).astype(int)
        inside = ok & (qx >= 0) & (qx < w2) & (qy >= 0) & (qy < h2)
        vis[inside] = self.labels2[qy[inside], qx[inside]] == lab[inside]
        return out, vis

    def correct(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float = 3.0) -> np.ndarray:
        """``(M,) bool``: match ``(pts1[m], pts2[m])`` is a true correspondence (within ``threshold`` px)."""
        proj, vis = self.project(pts1)
        err = np.linalg.norm(proj - np.asarray(pts2, float).reshape(-1, 2), axis=1)
        return vis & (np.nan_to_num(err, nan=np.inf) < threshold)


def _render(planes, K, R, t, size):
    import cv2

    w, h = size
    img = np.zeros((h, w), np.uint8)
    zbuf = np.full((h, w), np.inf)
    labels = np.full((h, w), -1, np.int16)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    Kinv = np.linalg.inv(K)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ Kinv.T  # z component is 1 -> lambda is depth
    Hs = []
    for k, pl in enumerate(planes):
        P = K @ np.column_stack([R, t])
        A = np.vstack([pl.texture_to_world(), [0, 0, 1]])
        H = P @ A  # texture pixel -> image pixel
        Hs.append(H)
        warped = cv2.warpPerspective(pl.texture, H, (w, h), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.ones_like(pl.texture), H, (w, h), flags=cv2.INTER_NEAREST) > 0
        n_c = R @ pl.normal
        d_c = n_c @ (R @ pl.center + t)
        denom = rays @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = d_c / denom
        sel = mask & (depth > 0) & (depth < zbuf)
        img[sel] = warped[sel]
        zbuf[sel] = depth[sel]
        labels[sel] = k
    return img, labels, Hs


def make_scene(size: tuple[int, int] = (1600, 1200), roll_deg: float = 30.0, seed: int = 0, *,
               focal: float | None = None, baseline: float = 1.0, noise_sigma: float = 2.0,
               texture_px_per_m: float | None = None) -> TwoViewScene:
    """Render a two-view scene of three textured planes (a back wall and two slanted panels).

    Args:
        size: ``(w, h)`` of both images, pixels (default 1600x1200).
        roll_deg: rotation of camera 2 about its optical axis, degrees (the demo uses 20-40).
        seed: seeds the textures, the camera-2 position and the image noise.
        focal: focal length in pixels (default ``0.9 * w``).
        baseline: distance between camera centres, metres (scene depth is 5-9 m).
        noise_sigma: std of additive Gaussian image noise (grey levels) so the views differ photometrically.
        texture_px_per_m: texture resolution (default: about 1.3 texture pixels per image pixel).
    """
    import cv2

    rng = np.random.default_rng(seed)
    w, h = int(size[0]), int(size[1])
    f = float(focal) if focal else 0.9 * w
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    ppm = texture_px_per_m or 1.3 * f / 8.0
    ex, ey = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])

    def plane(center, e1, e2, hw, hh):
        tw, th = int(2 * hw * ppm * 0.5 + 2), int(2 * hh * ppm * 0.5 + 2)  # half-res texture, upsampled below
        tex = procedural_texture(tw, th, rng)
        tex = cv2.resize(tex, (2 * tw, 2 * th), interpolation=cv2.INTER_CUBIC)
        return Plane(np.asarray(center, float), e1, e2, hw, hh, tex)

    Ry1 = _rot(ey, np.deg2rad(35))
    Ry2 = _rot(ey, np.deg2rad(-30))
    planes = [
        plane([0, 0, 9.0], ex, ey, 9.0, 7.0),                                  # back wall
        plane([-1.6, -0.3, 6.0], Ry1 @ ex, ey, 1.5, 1.8),                      # left panel, slanted
        plane([1.8, 0.6, 5.0], Ry2 @ ex, Ry2 @ _rot(ex, 0.3) @ ey, 1.3, 1.2),  # right panel
    ]
    # camera 2: offset by `baseline` in a random mostly-lateral direction, looking at the scene centre,
    # then rolled about its optical axis by roll_deg
    direction = np.array([rng.uniform(0.6, 1.0) * rng.choice([-1, 1]), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
    c2 = baseline * direction / np.linalg.norm(direction)
    # look at a point off camera 1's optical axis: intersecting optical axes make Bougnoux's focal
    # estimate degenerate (Bougnoux 1998), which real camera pairs rarely are exactly
    target = np.array([rng.uniform(0.4, 0.9) * rng.choice([-1, 1]), rng.uniform(0.3, 0.7) * rng.choice([-1, 1]), 7.5])
    z = (target - c2) / np.linalg.norm(target - c2)
    x = np.cross(ey, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_look = np.vstack([x, y, z])  # world -> camera-2 (before roll)
    R = _rot([0, 0, 1], np.deg2rad(roll_deg)) @ R_look
    t = -R @ c2
    img1, lab1, H1 = _render(planes, K, np.eye(3), np.zeros(3), (w, h))
    img2, lab2, H2 = _render(planes, K, R, t, (w, h))
    if noise_sigma > 0:
        img1 = np.clip(img1 + rng.normal(0, noise_sigma, img1.shape), 0, 255).astype(np.uint8)
        img2 = np.clip(img2 * 0.95 + 8 + rng.normal(0, noise_sigma, img2.shape), 0, 255).astype(np.uint8)
    homos = tuple(Hb @ np.linalg.inv(Ha) for Ha, Hb in zip(H1, H2))
    return TwoViewScene(img1, img2, K, K.copy(), R, t, fundamental_from_pose(K, K, R, t), lab1, lab2, homos,
                        float(roll_deg))
