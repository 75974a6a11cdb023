"""Synthetic two-view scenes with known ``K1, K2, R, t`` (tests of epipolar geometry / alignment and the
alignment simulation of Teng & Dong §III-E).

Camera convention (the paper's, §III-E Eq. for ``m1``/``m2``): the world frame is camera 1's frame,

    ``m1 ~ K1 [I | 0] M``,   ``m2 ~ K2 [R | -R t] M``,

so ``R`` maps camera-1 (world) coordinates to camera-2 coordinates (``X2 = R (X1 - t)``) and ``t`` is
the centre of camera 2 in camera-1 coordinates. (OpenCV's ``recoverPose`` uses ``X2 = R X1 + t_cv``,
i.e. the same ``R`` and ``t_cv = -R t``.) The viewing direction of camera 2 in camera-1 coordinates
is therefore the third ROW of ``R`` (``R^T e3``); the third COLUMN ``R e3`` is camera 1's viewing
direction seen from camera 2.

Pixels follow the OpenCV convention (origin at the centre of the top-left pixel); the principal
point of :func:`intrinsics_matrix` is the image centre ``((w - 1)/2, (h - 1)/2)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "TwoViewScene",
    "intrinsics_matrix",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_about",
    "look_at_rotation",
    "project",
    "fundamental_from_pose",
    "make_scene",
    "sphere_pair",
    "general_pair",
    "roll_pair",
    "forward_pair",
]


def intrinsics_matrix(f: float, size: tuple[int, int]) -> np.ndarray:
    """``K`` with focal ``f`` (pixels), zero skew, unit aspect, principal point ``((w-1)/2, (h-1)/2)``."""
    w, h = size
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about the x axis (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about the y axis (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about the z axis (right-handed)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rotation_about(axis, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` radians about ``axis`` (any non-zero 3-vector)."""
    u = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(u)
    if n == 0:
        return np.eye(3)
    u = u / n
    Kx = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * (Kx @ Kx)


def look_at_rotation(center, target, roll: float = 0.0, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera rotation of a camera at ``center`` whose optical axis (+z) points at ``target``,
    image x to the right and y down relative to ``up`` (world -y by default), then rolled by ``roll``
    radians about its optical axis (the image content rotates by ``-roll``)."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    upv = np.asarray(up, float)
    if abs(np.dot(upv, z)) > 0.999:  # looking along the up vector: pick another
        upv = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(-upv, z)  # image x = right
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y = down
    Rwc = np.stack([x, y, z])  # rows: camera axes in world coords
    return rot_z(roll).T @ Rwc


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of world points ``X (N, 3)`` in the camera ``K [R | -R t]`` (``t`` = centre)."""
    Xc = (X - t) @ R.T
    uvw = Xc @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[:, :2] / uvw[:, 2:3], Xc[:, 2]


def fundamental_from_pose(K1, K2, R, t) -> np.ndarray:
    """True ``F`` (``x2^T F x1 = 0``, ``||F||_F = 1``) for ``m1 ~ K1[I|0]M``, ``m2 ~ K2[R|-Rt]M``:
    ``E = R [t]_x`` (up to sign), ``F = K2^-T E K1^-1``."""
    t = np.asarray(t, float)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = R @ tx
    F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)


@dataclass(frozen=True)
class TwoViewScene:
    """Two views of ``N`` points, all in front of both cameras.

    Attributes:
        X: ``(N, 3)`` points in camera-1 (= world) coordinates.
        K1, K2: ``(3, 3)`` intrinsics. R: ``(3, 3)`` camera-1 -> camera-2 rotation. t: ``(3,)`` centre of
            camera 2 in camera-1 coordinates (``m2 ~ K2 [R | -R t] M``).
        size1, size2: ``(w, h)`` image sizes.
        x1, x2: ``(N, 2)`` noiseless projections. x1n, x2n: the same plus Gaussian noise.
        noise: noise sigma in pixels. F: true fundamental matrix.
    """

    X: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size1: tuple[int, int]
    size2: tuple[int, int]
    x1: np.ndarray
    x2: np.ndarray
    x1n: np.ndarray
    x2n: np.ndarray
    noise: float
    F: np.ndarray

    @property
    def viewing_angle_deg(self) -> float:
        """Angle between the two optical axes in degrees (``acos(R[2, 2])``)."""
        return float(np.degrees(np.arccos(np.clip(self.R[2, 2], -1, 1))))


def make_scene(X, K1, K2, R, t, size1, size2, noise: float = 0.0, rng=None, keep_in_image: bool = True) -> TwoViewScene:
    """Project ``X`` (camera-1 coordinates) into both views, drop points behind either camera (and,
    with ``keep_in_image``, outside either image), add ``N(0, noise^2)`` pixel noise to both images."""
    rng = np.random.default_rng(rng)
    X = np.asarray(X, float)
    x1, z1 = project(K1, np.eye(3), np.zeros(3), X)
    x2, z2 = project(K2, R, np.asarray(t, float), X)
    keep = (z1 > 1e-6) & (z2 > 1e-6)
    if keep_in_image:
        for x, (w, h) in ((x1, size1), (x2, size2)):
            keep &= (x[:, 0] >= -0.5) & (x[:, 0] <= w - 0.5) & (x[:, 1] >= -0.5) & (x[:, 1] <= h - 0.5)
    X, x1, x2 = X[keep], x1[keep], x2[keep]
    x1n = x1 + rng.normal(0.0, noise, x1.shape) if noise > 0 else x1.copy()
    x2n = x2 + rng.normal(0.0, noise, x2.shape) if noise > 0 else x2.copy()
    t = np.asarray(t, float)
    F = fundamental_from_pose(K1, K2, R, t) if np.linalg.norm(t) > 0 else np.zeros((3, 3))
    return TwoViewScene(X, np.asarray(K1, float), np.asarray(K2, float), np.asarray(R, float), t,
                        tuple(size1), tuple(size2), x1, x2, x1n, x2n, float(noise), F)


def _frustum_points(rng, n_points: int, size, f: float, depth=(4.0, 8.0)) -> tuple[np.ndarray, np.ndarray]:
    """``(K, X)``: camera 1's intrinsics (focal ``f``, centred principal point) and ``n_points`` 3-D points in its
    frustum at a depth uniform in ``depth``, each projecting uniformly into the image (drawn as depth, u, v)."""
    w, h = size
    z = rng.uniform(*depth, n_points)
    u = rng.uniform(0, w - 1, n_points)
    v = rng.uniform(0, h - 1, n_points)
    K = intrinsics_matrix(f, size)
    return K, np.stack([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z], 1)


def _random_unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def sphere_pair(
    rng=None,
    n_points: int = 200,
    size: tuple[int, int] = (640, 480),
    f: float = 800.0,
    distance: tuple[float, float] = (2.5, 5.0),
    radius: float = 1.0,
    noise: float = 1.0,
    max_roll_deg: float = 180.0,
) -> TwoViewScene:
    """The simulation of Teng & Dong §III-E: ``n_points`` uniform in a ball of ``radius`` about the
    origin; two cameras at uniformly random directions on a sphere about the origin, each at a random
    distance in ``distance``, looking at the origin, with a random roll uniform in
    ``[-max_roll_deg, max_roll_deg]``; same ``K`` (focal ``f``, centred principal point) for both.
    Expressed in camera-1 coordinates. Note that both optical axes pass through the origin, so they
    intersect: this is exactly the configuration in which Bougnoux's focal formula is degenerate."""
    rng = np.random.default_rng(rng)
    P = rng.normal(size=(n_points, 3))
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    P *= radius * rng.random((n_points, 1)) ** (1 / 3)
    rolls = np.radians(rng.uniform(-max_roll_deg, max_roll_deg, 2))
    C = [_random_unit(rng) * rng.uniform(*distance) for _ in range(2)]
    Rw = [look_at_rotation(C[i], np.zeros(3), rolls[i]) for i in range(2)]
    X1 = (P - C[0]) @ Rw[0].T  # points in camera-1 coordinates
    R = Rw[1] @ Rw[0].T
    t = Rw[0] @ (C[1] - C[0])
    K = intrinsics_matrix(f, size)
    return make_scene(X1, K, K, R, t, size, size, noise, rng)


def general_pair(
    rng=None,
    n_points: int = 200,
    size: tuple[int, int] = (640, 480),
    f1: float = 800.0,
    f2: float = 800.0,
    max_angle_deg: float = 30.0,
    baseline: float = 1.0,
    depth: tuple[float, float] = (4.0, 8.0),
    noise: float = 0.0,
    roll_deg: float | None = None,
) -> TwoViewScene:
    """A generic (non-degenerate for Bougnoux) pair: points in a frustum slab ``depth`` in front of
    camera 1; camera 2 at a random offset of length ``baseline`` (mostly sideways), rotated by a random
    rotation of at most ``max_angle_deg`` about a random axis (optical axes do not intersect in
    general); optional extra roll ``roll_deg`` of camera 2 about its optical axis."""
    rng = np.random.default_rng(rng)
    K1, X = _frustum_points(rng, n_points, size, f1, depth)
    d = rng.normal(size=3) * np.array([1.0, 0.5, 0.3])
    t = baseline * d / np.linalg.norm(d)
    R = rotation_about(_random_unit(rng), np.radians(rng.uniform(0, max_angle_deg)))
    if roll_deg is not None:
        R = rot_z(np.radians(roll_deg)) @ R
    return make_scene(X, K1, intrinsics_matrix(f2, size), R, t, size, size, noise, rng, keep_in_image=False)


def roll_pair(rng=None, roll_deg: float = 30.0, n_points: int = 200, size=(640, 480), f: float = 800.0,
              baseline=(0.0, 0.0, 0.0), noise: float = 0.0) -> TwoViewScene:
    """Camera 2 = camera 1 rolled by ``roll_deg`` about the optical axis, centre at ``baseline``
    (``(0, 0, 0)`` = pure roll, no epipolar geometry; a sideways baseline gives a valid ``F``)."""
    rng = np.random.default_rng(rng)
    K, X = _frustum_points(rng, n_points, size, f)
    return make_scene(X, K, K, rot_z(np.radians(roll_deg)), np.asarray(baseline, float), size, size,
                      noise, rng, keep_in_image=False)


def forward_pair(rng=None, n_points: int = 200, size=(640, 480), f: float = 800.0, step: float = 1.0,
                 noise: float = 0.0) -> TwoViewScene:
    """Pure translation along the optical axis (camera 2 = camera 1 moved forward by ``step``): the
    epipoles are at the principal points, the degenerate case of Bougnoux's formula."""
    rng = np.random.default_rng(rng)
    K, X = _frustum_points(rng, n_points, size, f)
    return make_scene(X, K, K, np.eye(3), np.array([0.0, 0.0, step]), size, size, noise, rng,
                      keep_in_image=False)
