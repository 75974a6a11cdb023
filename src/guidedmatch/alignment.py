"""Image alignment from the fundamental matrix (Teng & Dong §III-E).

The spatial-order model compares x-ranks, so an in-plane rotation between the two images destroys it.
Alignment removes that rotation with a homography of image 2 (and of image 1 for approach "d"):

1. focal lengths from ``F`` by Bougnoux's formula (principal point at the image centre
   ``((w-1)/2, (h-1)/2)`` -- the centre of the pixel grid in the OpenCV pixel-centre convention --,
   zero skew, unit aspect), with Fusiello's range ``[(w+h)/3, 3(w+h)]`` and the fallback ``f = w+h``;
2. ``E = K2^T F K1``, the two ``R`` and two ``t`` from its SVD (Hartley & Zisserman §9.6), chosen by
   cheirality (most triangulated points in front of both cameras);
3. one of the alignment homographies below.

Camera convention (the paper's): ``m1 ~ K1 [I | 0] M``, ``m2 ~ K2 [R | -R t] M``. ``R`` maps camera-1
(world) coordinates to camera-2 coordinates, ``X2 = R (X1 - t)``; ``t`` is the centre of camera 2 in
camera-1 coordinates (OpenCV's ``recoverPose`` returns the same ``R`` and ``t_cv = -R t``). Camera 2's
viewing direction in camera-1 coordinates is the third ROW of ``R``; the third COLUMN ``r3 = R e3`` is
camera 1's viewing direction expressed in camera-2 coordinates.

Approaches (``approach=``):

* ``"a"``: ``H_a = K2 R_Z^T K2^-1`` with ``R = R_Z R_Y R_X`` (Euler ZYX): removes the Euler Z angle.
* ``"b"``: ``H_b = K2 R^T K2^-1``: camera 2 rotated to camera 1's orientation (``H_b m2 ~ K2[I|-t]M``).
* ``"c"`` (default, the paper's formula taken literally): ``H_c = K2 R_u R^T K2^-1``, ``R_u`` the
  rotation about ``u = r3 x e3`` by ``theta = angle(r3, e3)``. ``R_u`` maps ``r3`` to ``e3``, so the
  aligned camera has orientation ``R_u`` and looks along ``R_u^T e3 = r3 = R e3`` (camera-1 coordinates).
  The paper intends "turn the viewing direction back" to camera 2's original one, ``R^T e3``; the
  literal formula instead turns it to ``R e3``, the mirror image of ``R^T e3`` about camera 1's axis
  (the same tilt ``theta`` from ``e3``, on the other side). The aligned view is thus tilted by up to
  ``2 theta`` from the original camera 2 (perspective distortion grows with the viewing angle); for a
  pure roll (``r3 = e3``) ``R_u = I`` and ``H_c = K2 R^T K2^-1`` removes the roll exactly.
* ``"c_inplane"`` (what the text of approach 3 describes): the same construction with the third ROW of
  ``R`` (camera 2's true viewing direction): ``R_u'`` about ``d2 x e3`` with ``d2 = R^T e3``. Then
  ``R_u' R^T`` fixes camera 2's optical axis, i.e. it is a pure rotation about the optical axis,
  ``H = K2 R_Z(phi) K2^-1``: the image is only rotated about the principal point by the twist angle of
  the swing-twist decomposition of ``R`` (no perspective distortion at all).
* ``"d"``: the SVD rectification of Wu et al. 2018 as written in the paper, two-sided:
  ``H_L = K R_X^T R_L K^-1`` (image 1), ``H_R = K R_X^T R_R K^-1`` (image 2), ``K = (K1 + K2)/2``,
  ``E = U diag(1, sigma, 0) V^T``, ``R_L = R_G U^T R``, ``R_R = R_G U'^T R^T``,
  ``U' = R^T U diag(1, sigma, 1)``, ``R_L = R_X R_Y R_Z`` (Euler XYZ). Note that
  ``R_R = R_G diag(1, sigma, 1) U^T`` (a rotation only when ``sigma = 1``, i.e. for an exact essential
  matrix). ``u3`` (the epipole direction) is signed so that camera 2 lies at +x of the rectified
  frame, and ``det U = +1``.

All functions return a falsy :class:`guidedmatch.results.Failure` instead of raising on degenerate
input.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from .epipolar import check_points, epipoles, map_points, normalize_fundamental, skew
from .base import APPROACHES, Failure

__all__ = [
    "APPROACHES",
    "FocalResult",
    "PoseResult",
    "AlignmentResult",
    "bougnoux_focals",
    "bougnoux_focal_squared",
    "intrinsics",
    "relative_pose",
    "euler_zyx",
    "euler_xyz",
    "twist_angle",
    "alignment_homographies",
    "align_from_fundamental",
    "apply_homography",
    "warp_to_canvas",
    "AlignmentCheck",
    "check_alignment",
    "SafeAlignment",
    "safe_alignment",
]


_E3 = np.array([0.0, 0.0, 1.0])
_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_RG = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


# ------------------------------------------------------------------------------------------ focal
@dataclass(frozen=True)
class FocalResult:
    """Focal lengths (pixels) of both views from ``F``.

    Attributes:
        f1, f2: the focal lengths to use (Bougnoux's value, or ``w + h`` after a fallback).
        raw_f1, raw_f2: Bougnoux's value (``NaN`` when ``f^2 <= 0`` or undefined).
        fallback1, fallback2: whether ``w + h`` was used.
        reason1, reason2: ``"ok"``, ``"given"`` (intrinsics supplied by the caller),
            ``"epipole at principal point"``, ``"degenerate (zero denominator)"``, ``"f^2 <= 0"``,
            ``"outside [(w+h)/3, 3(w+h)]"`` or ``"non-finite"``.
    """

    f1: float
    f2: float
    raw_f1: float
    raw_f2: float
    fallback1: bool
    fallback2: bool
    reason1: str
    reason2: str


def intrinsics(f: float, size: tuple[int, int]) -> np.ndarray:
    """``K = [[f, 0, (w-1)/2], [0, f, (h-1)/2], [0, 0, 1]]`` for an image of ``size = (w, h)``: principal
    point at the image centre in the OpenCV pixel-centre convention, zero skew, unit aspect (§III-E)."""
    w, h = size
    return np.array([[float(f), 0.0, (w - 1) / 2.0], [0.0, float(f), (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def bougnoux_focal_squared(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[float, float, float]:
    """Bougnoux's ``f1^2`` (Teng & Dong §III-E, Eq. for ``f1``):

        ``f1^2 = - (p2^T [e2]_x I~ F p1)(p1^T F^T p2) / (p2^T [e2]_x I~ F I~ F^T p2)``,

    ``I~ = diag(1, 1, 0)``, ``e2`` the image-2 epipole (``F^T e2 = 0``), ``p1``, ``p2`` homogeneous
    principal points. (For ``f2^2`` call with ``F^T`` and ``p1``, ``p2`` swapped.)

    Returns:
        ``(f1^2, numerator, denominator)`` (``f1^2 = -num/den``; ``NaN`` when ``den == 0``).
    """
    _, e2 = epipoles(F)
    It = np.diag([1.0, 1.0, 0.0])
    A = p2 @ skew(e2) @ It
    num = float((A @ F @ p1) * (p1 @ F.T @ p2))
    den = float(A @ F @ It @ F.T @ p2)
    f2 = -num / den if den != 0 else float("nan")
    return f2, num, den


def _one_focal(F: np.ndarray, size_a, size_b) -> tuple[float, float, bool, str]:
    """Focal of the view whose image-size is ``size_a`` for ``F`` mapping that view -> the other.

    Works in normalised coordinates (principal point at the origin, scale ``1/(w+h)``) so that the
    degeneracy tolerances are scale-free."""
    wa, ha = size_a
    wb, hb = size_b
    sa, sb = float(wa + ha), float(wb + hb)
    Ta = np.array([[1 / sa, 0, -(wa - 1) / 2 / sa], [0, 1 / sa, -(ha - 1) / 2 / sa], [0, 0, 1.0]])
    Tb = np.array([[1 / sb, 0, -(wb - 1) / 2 / sb], [0, 1 / sb, -(hb - 1) / 2 / sb], [0, 0, 1.0]])
    Fn = np.linalg.inv(Tb).T @ F @ np.linalg.inv(Ta)
    Fn /= np.linalg.norm(Fn)
    fallback = sa  # w + h
    lo, hi = sa / 3.0, 3.0 * sa
    if not np.isfinite(Fn).all():
        return fallback, float("nan"), True, "non-finite"
    _, e_b = epipoles(Fn)  # epipole in the other image, normalised coordinates
    if np.hypot(e_b[0], e_b[1]) <= 1e-4 * abs(e_b[2]):  # within ~0.1 px of the principal point
        return fallback, float("nan"), True, "epipole at principal point"
    p = _E3
    f2n, num, den = bougnoux_focal_squared(Fn, p, p)
    if not np.isfinite(den) or abs(den) <= 1e-12:
        return fallback, float("nan"), True, "degenerate (zero denominator)"
    if not np.isfinite(f2n):
        return fallback, float("nan"), True, "non-finite"
    if f2n <= 0:
        return fallback, float("nan"), True, "f^2 <= 0"
    f = float(np.sqrt(f2n) * sa)
    if not (lo <= f <= hi):
        return fallback, f, True, "outside [(w+h)/3, 3(w+h)]"
    return f, f, False, "ok"


def bougnoux_focals(F: np.ndarray, size1: tuple[int, int], size2: tuple[int, int]) -> FocalResult:
    """Focal lengths of both views from ``F`` (Bougnoux 1998; Teng & Dong §III-E).

    Assumes principal points at the image centres ``((w-1)/2, (h-1)/2)``, zero skew and unit aspect.
    ``f1`` uses ``F``; ``f2`` uses ``F^T`` with the roles of the images swapped. When ``f^2 <= 0``, the
    formula is degenerate (epipole at the principal point, zero denominator -- e.g. the optical axes
    intersect, as for two cameras looking at the same point, or translation along the optical axis)
    or ``f`` lies outside Fusiello's range ``[(w+h)/3, 3(w+h)]``, ``f = w + h`` is used and the
    reason is reported.

    Args:
        F: ``(3, 3)``, ``x2^T F x1 = 0``. size1, size2: ``(w, h)`` of image 1 / image 2.
    """
    F = np.asarray(F, dtype=np.float64)
    f1, r1, fb1, why1 = _one_focal(F, size1, size2)
    f2, r2, fb2, why2 = _one_focal(F.T, size2, size1)
    return FocalResult(f1, f2, r1, r2, fb1, fb2, why1, why2)


# ------------------------------------------------------------------------------------------- pose
@dataclass(frozen=True)
class PoseResult:
    """Relative pose from ``E`` (paper convention ``m2 ~ K2 [R | -R t] M``).

    Attributes:
        R: ``(3, 3)`` rotation camera 1 -> camera 2 (``X2 = R (X1 - t)``).
        t: ``(3,)`` unit vector, centre of camera 2 in camera-1 coordinates (``t_opencv = -R t``).
        E: ``(3, 3)`` ``K2^T F K1`` scaled to largest singular value 1 (``E = U diag(1, sigma, 0) V^T``).
        num_in_front: points triangulated in front of both cameras for the chosen ``(R, t)``.
        num_points: points used.
    """

    R: np.ndarray
    t: np.ndarray
    E: np.ndarray
    num_in_front: int
    num_points: int


def _depths(R: np.ndarray, tcv: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths ``(z1, z2)`` of the least-squares (midpoint) triangulation of rays ``a`` (camera 1) and
    ``b`` (camera 2), ``z2 b = z1 R a + t_cv``. Vectorised closed-form 2x2 normal equations; ``NaN`` for
    (near-)parallel rays."""
    Ra = a @ R.T
    # minimise |z1 Ra - z2 b + tcv|^2
    A11 = np.einsum("ij,ij->i", Ra, Ra)
    A22 = np.einsum("ij,ij->i", b, b)
    A12 = -np.einsum("ij,ij->i", Ra, b)
    r1 = -Ra @ tcv
    r2 = b @ tcv
    det = A11 * A22 - A12 * A12
    ok = det > 1e-12 * A11 * A22
    with np.errstate(divide="ignore", invalid="ignore"):
        z1 = np.where(ok, (A22 * r1 - A12 * r2) / det, np.nan)
        z2 = np.where(ok, (A11 * r2 - A12 * r1) / det, np.nan)
    return z1, z2


def relative_pose(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1, x2) -> PoseResult | Failure:
    """Relative pose from ``F`` and intrinsics (Hartley & Zisserman §9.6; Teng & Dong §III-E).

    ``E = K2^T F K1 = U diag(1, sigma, 0) V^T`` (``det U = det V = +1``); candidates
    ``R in {U W V^T, U W^T V^T}``, ``t_cv = +-u3``; the one with the most points triangulated in front
    of both cameras wins. Pass the F-inliers as ``x1``, ``x2`` (``(N, 2)``, N >= 1); the majority vote
    tolerates a minority of outliers.

    Returns:
        :class:`PoseResult` with ``R`` (camera 1 -> camera 2) and ``t`` (camera-2 centre in camera-1
        coordinates, unit length), or :class:`Failure` (non-finite input, rank-deficient ``E``, no
        point in front of both cameras).
    """
    chk = check_points(x1, x2, min_points=1)
    if not chk and "collinear" not in chk.reason:
        return chk
    a_pix = np.asarray(x1, np.float64).reshape(-1, 2)
    b_pix = np.asarray(x2, np.float64).reshape(-1, 2)
    F = np.asarray(F, np.float64)
    K1 = np.asarray(K1, np.float64)
    K2 = np.asarray(K2, np.float64)
    if not (np.isfinite(F).all() and np.isfinite(K1).all() and np.isfinite(K2).all()):
        return Failure("non-finite F or K")
    E = K2.T @ F @ K1
    U, s, Vt = np.linalg.svd(E)
    if not (s[0] > 0) or s[1] <= 1e-10 * s[0]:
        return Failure(f"essential matrix has rank < 2 (singular values {s.tolist()})")
    E = E / s[0]
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    a = np.hstack([a_pix, np.ones((len(a_pix), 1))]) @ np.linalg.inv(K1).T
    b = np.hstack([b_pix, np.ones((len(b_pix), 1))]) @ np.linalg.inv(K2).T
    best = None
    for R in (U @ _W @ Vt, U @ _W.T @ Vt):
        for tcv in (U[:, 2], -U[:, 2]):
            z1, z2 = _depths(R, tcv, a, b)
            n = int(np.sum((z1 > 0) & (z2 > 0)))
            if best is None or n > best[0]:
                best = (n, R, tcv)
    n, R, tcv = best
    if n == 0:
        return Failure("no (R, t) candidate puts any point in front of both cameras", {"num_points": len(a)})
    t = -R.T @ tcv
    return PoseResult(R=R, t=t / np.linalg.norm(t), E=E, num_in_front=n, num_points=len(a))


# ----------------------------------------------------------------------------------- homographies
def euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    """Angles ``(z, y, x)`` in radians with ``R = R_Z(z) R_Y(y) R_X(x)`` (approach "a")."""
    z = float(np.arctan2(R[1, 0], R[0, 0]))
    y = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    x = float(np.arctan2(R[2, 1], R[2, 2]))
    return z, y, x


def euler_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Angles ``(x, y, z)`` in radians with ``R = R_X(x) R_Y(y) R_Z(z)`` (approach "d")."""
    x = float(np.arctan2(-R[1, 2], R[2, 2]))
    y = float(np.arcsin(np.clip(R[0, 2], -1.0, 1.0)))
    z = float(np.arctan2(-R[0, 1], R[0, 0]))
    return x, y, z


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    n = np.linalg.norm(axis)
    if n == 0:
        return np.eye(3)
    Kx = skew(axis / n)
    return np.eye(3) + np.sin(angle) * Kx + (1.0 - np.cos(angle)) * (Kx @ Kx)


def _turn_to_e3(v: np.ndarray) -> np.ndarray:
    """The rotation about ``u = v x e3`` by ``angle(v, e3)`` (maps unit ``v`` to ``e3``). For
    ``v = -e3`` the axis is undefined; the x axis is used."""
    v = v / np.linalg.norm(v)
    theta = float(np.arccos(np.clip(v @ _E3, -1.0, 1.0)))
    u = np.cross(v, _E3)
    if np.linalg.norm(u) < 1e-12:
        return np.eye(3) if theta < np.pi / 2 else _rot("x", np.pi)
    return _rodrigues(u, theta)


def twist_angle(Q: np.ndarray) -> float:
    """Twist angle (radians) about z of a rotation ``Q`` in its swing-twist decomposition:
    ``atan2(Q10 - Q01, Q00 + Q11)`` (= ``2 atan2(q_z, q_w)`` for the quaternion of ``Q``)."""
    return float(np.arctan2(Q[1, 0] - Q[0, 1], Q[0, 0] + Q[1, 1]))


def alignment_homographies(R: np.ndarray, K1: np.ndarray, K2: np.ndarray, approach: str = "c",
                           E: np.ndarray | None = None, t: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, float]:
    """Alignment homographies for a known relative pose (see the module docstring for the approaches).

    Args:
        R: camera 1 -> camera 2 rotation (paper convention ``m2 ~ K2 [R | -R t] M``).
        K1, K2: intrinsics. approach: one of :data:`APPROACHES`.
        E: essential matrix (needed by ``"d"``; built from ``R``, ``t`` when omitted).
        t: centre of camera 2 in camera-1 coordinates (``"d"``: sign of the rectified x axis / to build E).

    Returns:
        ``(H1, H2, roll_deg)``: homographies for image-1 / image-2 pixel coordinates (``H1 = I`` except
        for ``"d"``), and the in-plane rotation removed from image 2 in degrees (minus the twist angle
        about the optical axis of the rotation ``Q`` in ``H2 = K Q K^-1``).
    """
    R = np.asarray(R, np.float64)
    K1 = np.asarray(K1, np.float64)
    K2 = np.asarray(K2, np.float64)
    K2i = np.linalg.inv(K2)
    H1 = np.eye(3)
    if approach == "a":
        z, _, _ = euler_zyx(R)
        Q = _rot("z", z).T
    elif approach == "b":
        Q = R.T
    elif approach == "c":
        Q = _turn_to_e3(R[:, 2]) @ R.T  # literal: r3 = third COLUMN of R
    elif approach == "c_inplane":
        Q = _turn_to_e3(R[2, :]) @ R.T  # third ROW = camera 2's viewing direction: pure twist
    elif approach == "d":
        if E is None:
            if t is None:
                raise ValueError("approach 'd' needs E or t")
            E = skew(-R @ np.asarray(t, np.float64)) @ R
        U, s, _ = np.linalg.svd(np.asarray(E, np.float64))
        sigma = s[1] / s[0]
        if t is not None and U[:, 2] @ (R @ np.asarray(t, np.float64)) < 0:
            U[:, 2] = -U[:, 2]  # camera 2 at +x of the rectified frame
        if np.linalg.det(U) < 0:
            U[:, 1] = -U[:, 1]
        Up = R.T @ U @ np.diag([1.0, sigma, 1.0])
        RL = _RG @ U.T @ R
        RR = _RG @ Up.T @ R.T
        ax, _, _ = euler_xyz(RL)
        RXt = _rot("x", ax).T
        K = (K1 + K2) / 2.0
        Ki = np.linalg.inv(K)
        H1 = K @ RXt @ RL @ Ki
        H2 = K @ RXt @ RR @ Ki
        Q2 = RXt @ RR
        return H1, H2, float(-np.degrees(twist_angle(Q2)))
    else:
        raise ValueError(f"unknown approach {approach!r}; choose one of {APPROACHES}")
    H2 = K2 @ Q @ K2i
    return H1, H2, float(-np.degrees(twist_angle(Q)))


@dataclass(frozen=True)
class AlignmentResult:
    """Alignment of image 2 to image 1 (truthy).

    Attributes:
        H2: ``(3, 3)`` homography applied to image-2 pixel coordinates (``x2' ~ H2 x2``).
        H1: ``(3, 3)`` homography for image-1 coordinates; identity except approach ``"d"``.
        approach: one of :data:`APPROACHES`.
        R, t: relative pose (``m2 ~ K2 [R | -R t] M``; ``t`` = camera-2 centre in camera-1 coordinates).
        K1, K2: intrinsics used. focal: how the focal lengths were obtained.
        roll_deg: in-plane rotation removed from image 2, degrees (for reports).
        stats: ``viewing_angle_deg`` (``acos R33``), ``num_in_front``, ``num_points``, ``sigma``
            (second singular value of the unit-scaled ``E``).
    """

    H2: np.ndarray
    H1: np.ndarray
    approach: str
    R: np.ndarray
    t: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    focal: FocalResult
    roll_deg: float
    stats: dict = field(default_factory=dict)

    def __bool__(self) -> bool:  # noqa: D105 - truthy by design
        return True


def _valid_h(H: np.ndarray, size) -> bool:
    """Finite and non-singular, judged in coordinates normalised to ``[-1, 1]`` over the image."""
    if not np.isfinite(H).all():
        return False
    w, h = size
    T = np.array([[2.0 / w, 0.0, -1.0], [0.0, 2.0 / h, -1.0], [0.0, 0.0, 1.0]])
    Hn = T @ H @ np.linalg.inv(T)
    return bool(abs(np.linalg.det(Hn / np.linalg.norm(Hn))) > 1e-12)


def align_from_fundamental(F, x1, x2, size1, size2, approach: str = "c", *, K1=None, K2=None
                           ) -> AlignmentResult | Failure:
    """Alignment homographies from ``F`` (Teng & Dong §III-E): Bougnoux focal lengths (or the given
    ``K1``, ``K2``), relative pose by SVD + cheirality, then the homography of ``approach``.

    Args:
        F: ``(3, 3)`` with ``x2^T F x1 = 0``.
        x1, x2: ``(N, 2)`` F-inlier correspondences (pixels), ``N >= 8``, used for cheirality.
        size1, size2: ``(w, h)`` of the images.
        approach: one of :data:`APPROACHES` (default ``"c"``, the paper's choice).
        K1, K2: optional known intrinsics; when both are given Bougnoux is skipped (reason ``"given"``).

    Returns:
        :class:`AlignmentResult`, or :class:`Failure` (bad points, ``F`` of rank < 2 or non-finite,
        pose failure, singular/non-finite homography).
    """
    if approach not in APPROACHES:
        return Failure(f"unknown approach {approach!r}; choose one of {APPROACHES}")
    Fn = normalize_fundamental(F)
    if isinstance(Fn, Failure):
        return Fn
    chk = check_points(x1, x2)
    if not chk:
        return chk
    a, b = chk
    if K1 is not None and K2 is not None:
        K1 = np.asarray(K1, np.float64)
        K2 = np.asarray(K2, np.float64)
        focal = FocalResult(float(K1[0, 0]), float(K2[0, 0]), float(K1[0, 0]), float(K2[0, 0]),
                            False, False, "given", "given")
    else:
        focal = bougnoux_focals(Fn, size1, size2)
        K1 = intrinsics(focal.f1, size1)
        K2 = intrinsics(focal.f2, size2)
    pose = relative_pose(Fn, K1, K2, a, b)
    if not pose:
        return pose
    H1, H2, roll = alignment_homographies(pose.R, K1, K2, approach, E=pose.E, t=pose.t)
    if not (_valid_h(H1, size1) and _valid_h(H2, size2)):
        return Failure(f"alignment homography of approach {approach!r} is singular or non-finite")
    sigma = float(np.linalg.svd(pose.E, compute_uv=False)[1])
    stats = {"viewing_angle_deg": float(np.degrees(np.arccos(np.clip(pose.R[2, 2], -1, 1)))),
             "num_in_front": pose.num_in_front, "num_points": pose.num_points, "sigma": sigma}
    return AlignmentResult(H2=H2, H1=H1, approach=approach, R=pose.R, t=pose.t, K1=K1, K2=K2,
                           focal=focal, roll_deg=roll, stats=stats)


# -------------------------------------------------------------------------------------- applying
def apply_homography(H: np.ndarray, pts, *, in_front: bool = False) -> np.ndarray:
    """Map ``(N, 2)`` pixel coordinates by ``H`` (homogeneous column vectors): ``(N, 2) float64``,
    ``proj(H [x, y, 1]^T)``, computed element-wise (:func:`~guidedmatch.epipolar.map_points`).

    Rows are ``NaN`` where the mapped ``w == 0`` (points on the line sent to infinity). With
    ``in_front=False`` (alignment: the rectifying homographies of §III-E) points with ``w < 0`` (behind the
    rotated camera) are mapped normally. ``in_front=True`` is the ground-truth projection of a planar scene
    (:class:`guidedmatch.datasets.HomographyGT`): rows with ``w <= 0`` or a non-finite result are ``NaN`` (no
    image point).

    >>> H = np.array([[2.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    >>> apply_homography(H, [[1.0, 2.0]])
    array([[3., 4.]])
    >>> apply_homography(-H, [[1.0, 2.0]]), apply_homography(-H, [[1.0, 2.0]], in_front=True)
    (array([[3., 4.]]), array([[nan, nan]]))
    """
    q = map_points(H, pts)
    w = q[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = q[:, :2] / w
    if in_front:
        out[(w[:, 0] <= 0) | ~np.isfinite(out).all(axis=1)] = np.nan
    else:
        out[(w[:, 0] == 0)] = np.nan
    return out


def warp_to_canvas(image: np.ndarray, H: np.ndarray, max_scale: float = 4.0,
                   interpolation: int = cv2.INTER_LINEAR) -> tuple[np.ndarray, np.ndarray]:
    """Render ``image`` warped by ``H`` onto a canvas holding the whole warped image (for figures).

    The canvas is the bounding box of the warped image border (sampled densely; border points with
    ``w <= 0`` are skipped), clipped to ``max_scale`` times the image size around the warped image
    centre so that near-horizon homographies cannot allocate huge canvases.

    Returns:
        ``(warped, H_canvas)`` with ``H_canvas = T @ H`` (``T`` the canvas-offset translation): a pixel
        ``x`` of ``image`` lands at ``H_canvas x`` in ``warped``.
    """
    h, w = image.shape[:2]
    H = np.asarray(H, np.float64)
    s = np.linspace(0.0, 1.0, 65)
    border = np.concatenate([
        np.stack([s * (w - 1), np.zeros_like(s)], 1), np.stack([s * (w - 1), np.full_like(s, h - 1)], 1),
        np.stack([np.zeros_like(s), s * (h - 1)], 1), np.stack([np.full_like(s, w - 1), s * (h - 1)], 1)])
    q = np.hstack([border, np.ones((len(border), 1))]) @ H.T
    q = q[q[:, 2] > 1e-12]
    if len(q) == 0:  # the whole image maps behind the camera
        return np.zeros_like(image), H
    pts = q[:, :2] / q[:, 2:3]
    lo, hi = pts.min(0), pts.max(0)
    c = apply_homography(H, np.array([[(w - 1) / 2.0, (h - 1) / 2.0]]))[0]
    if not np.isfinite(c).all():
        c = (lo + hi) / 2
    lim = max_scale * np.array([w, h], float)
    lo = np.maximum(lo, c - lim)
    hi = np.minimum(hi, c + lim)
    x0, y0 = np.floor(lo)
    W = int(np.ceil(hi[0] - x0)) + 1
    Hh = int(np.ceil(hi[1] - y0)) + 1
    T = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    Hc = T @ H
    warped = cv2.warpPerspective(image, Hc, (max(W, 1), max(Hh, 1)), flags=interpolation,
                                 borderMode=cv2.BORDER_CONSTANT)
    return warped, Hc


# ------------------------------------------------------------------------------------- validation
@dataclass(frozen=True)
class AlignmentCheck:
    """Whether an alignment homography is safe to match in (truthy when it is), :func:`check_alignment`.

    Attributes:
        ok: the homography passed every test.
        reason: ``"ok"`` or one sentence naming the failed test and its numbers.
        scale_range: ``(min, max)`` local scale ``sqrt|det J|`` over the keypoints (how the homography stretches
            distances there; the epipolar band of ``band_px`` aligned pixels is ``band_px / scale`` original pixels).
        horizon_px: distance (pixels) from the nearest keypoint to the line the homography sends to infinity
            (``inf`` for an affine map).
    """

    ok: bool
    reason: str
    scale_range: tuple[float, float]
    horizon_px: float

    def __bool__(self) -> bool:  # noqa: D105
        return bool(self.ok)


#: Default bounds of :func:`check_alignment`: local scale in ``[1/4, 4]`` (a band of 5 aligned px then spans
#: 1.25..20 original px) and every keypoint at least half the image diagonal away from the line sent to infinity.
SCALE_BOUNDS = (0.25, 4.0)
HORIZON_DIAGONALS = 0.5


def check_alignment(H, pts, size, *, scale_bounds: tuple[float, float] = SCALE_BOUNDS,
                    horizon_diagonals: float = HORIZON_DIAGONALS) -> AlignmentCheck:
    """Validate an alignment homography over the keypoints it will move (Teng & Dong §III-E).

    The matcher compares aligned x-ranks and measures the epipolar band in aligned pixels, so a homography is
    only safe when, over the keypoints ``pts (N, 2)`` (pixels) of the image it maps (size ``(w, h)``):

    1. it is finite and non-singular;
    2. it keeps the orientation everywhere: ``det J(x) = det(H) / w(x)^3 > 0`` at every keypoint, with
       ``w(x) = h_3 . (x, y, 1)`` (a mirrored or folded frame reverses x-order) -- this also means all ``w``
       have one sign, i.e. the line sent to infinity (``w = 0``) does not pass between keypoints;
    3. the local scale ``sqrt|det J|`` lies within ``scale_bounds`` at every keypoint (a band of ``b``
       aligned pixels is ``b / scale`` original pixels wide; an exploding scale makes the aligned frame
       span millions of pixels);
    4. no keypoint lies within ``horizon_diagonals`` image diagonals of the line sent to infinity.

    Returns:
        :class:`AlignmentCheck` (truthy when safe); never raises on degenerate input.

    >>> import numpy as np
    >>> pts = np.array([[0.0, 0.0], [639.0, 479.0], [320.0, 240.0]])
    >>> bool(check_alignment(np.eye(3), pts, (640, 480)))
    True
    >>> tilt = np.array([[1.0, 0, 0], [0, 1.0, 0], [0.003, 0, 1.0]])  # sends the line x = -333 to infinity
    >>> check_alignment(tilt, pts, (640, 480)).reason.split(":")[0]
    'local scale out of range'
    """
    H = np.asarray(H, np.float64)
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    nan2 = (float("nan"), float("nan"))
    if H.shape != (3, 3) or not np.isfinite(H).all() or not np.linalg.norm(H) > 0:
        return AlignmentCheck(False, "homography is not a finite non-zero 3x3 matrix", nan2, float("nan"))
    Hn = H / np.linalg.norm(H)
    w_img, h_img = (float(v) for v in size)
    diag = math.hypot(w_img, h_img)
    T = np.array([[1.0 / diag, 0.0, 0.0], [0.0, 1.0 / diag, 0.0], [0.0, 0.0, 1.0]])
    if abs(np.linalg.det(T @ Hn @ np.linalg.inv(T) / np.linalg.norm(T @ Hn @ np.linalg.inv(T)))) <= 1e-12:
        return AlignmentCheck(False, "homography is singular", nan2, float("nan"))
    if len(pts) == 0:
        return AlignmentCheck(True, "ok", (1.0, 1.0), float("inf"))
    w = pts @ Hn[2, :2] + Hn[2, 2]
    detH = float(np.linalg.det(Hn))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        detj = detH / w**3
        scale = np.sqrt(np.abs(detj))
    sr = (float(np.min(scale)), float(np.max(scale)))
    a = float(np.hypot(Hn[2, 0], Hn[2, 1]))
    horizon = float(np.min(np.abs(w)) / a) if a > 0 else float("inf")
    flipped = int(np.sum(~(detj > 0)))
    if flipped:
        return AlignmentCheck(False, f"orientation not kept: det J <= 0 at {flipped} of {len(pts)} keypoints "
                              "(the frame is mirrored or the line sent to infinity crosses the keypoints)",
                              sr, horizon)
    lo, hi = scale_bounds
    if not (sr[0] >= lo and sr[1] <= hi):
        return AlignmentCheck(False, f"local scale out of range: sqrt|det J| spans {sr[0]:.3g}..{sr[1]:.3g} over "
                              f"the keypoints (allowed {lo:g}..{hi:g})", sr, horizon)
    if horizon < horizon_diagonals * diag:
        return AlignmentCheck(False, f"keypoint near the line at infinity: {horizon:.0f} px away (at least "
                              f"{horizon_diagonals:g} image diagonals = {horizon_diagonals * diag:.0f} px required)",
                              sr, horizon)
    return AlignmentCheck(True, "ok", sr, horizon)


@dataclass(frozen=True)
class SafeAlignment:
    """The alignment the matcher uses after validation (:func:`safe_alignment`).

    Attributes:
        H1, H2: ``(3, 3)`` homographies of image-1 / image-2 keypoints (identity when none is used).
        approach: the approach actually used: one of :data:`APPROACHES` or ``"none"``.
        requested: the approach asked for.
        fallbacks: ``[(approach, reason), ...]`` every approach tried and rejected, in order.
        result: the :class:`AlignmentResult` of the approach used (None for ``"none"``).
        check: the :class:`AlignmentCheck` of the used ``H2`` (over image-2 keypoints).
    """

    H1: np.ndarray
    H2: np.ndarray
    approach: str
    requested: str
    fallbacks: tuple
    result: AlignmentResult | None
    check: AlignmentCheck

    @property
    def fell_back(self) -> bool:
        return self.approach != self.requested


def safe_alignment(F, x1, x2, size1, size2, approach: str, pts2, pts1=None, *, K1=None, K2=None,
                   scale_bounds: tuple[float, float] = SCALE_BOUNDS,
                   horizon_diagonals: float = HORIZON_DIAGONALS) -> SafeAlignment:
    """Alignment from ``F`` with validation and a reported fallback chain: ``approach`` -> ``"c_inplane"``
    (in-plane rotation of image 2 about its principal point only: scale 1, nothing at infinity) -> ``"none"``.

    Every candidate's ``H2`` is checked with :func:`check_alignment` over the image-2 keypoints ``pts2`` (and
    ``H1`` over ``pts1`` for approach ``"d"``); a failed estimation or a failed check moves to the next link and
    is recorded in ``fallbacks``. Args as :func:`align_from_fundamental`.

    >>> import numpy as np
    >>> from guidedmatch.testing.twoview import general_pair
    >>> s = general_pair(0)
    >>> al = safe_alignment(s.F, s.x1, s.x2, (640, 480), (640, 480), "c_inplane", s.x2)
    >>> al.approach, al.fallbacks
    ('c_inplane', ())
    """
    pts2 = np.asarray(pts2, np.float64).reshape(-1, 2)
    chain = [approach] + [a for a in ("c_inplane",) if a != approach]
    fallbacks = []
    for ap in chain:
        res = align_from_fundamental(F, x1, x2, size1, size2, ap, K1=K1, K2=K2)
        if not res:
            fallbacks.append((ap, f"alignment failed: {res.reason}"))
            continue
        chk = check_alignment(res.H2, pts2, size2, scale_bounds=scale_bounds, horizon_diagonals=horizon_diagonals)
        if chk and ap == "d" and pts1 is not None:
            c1 = check_alignment(res.H1, pts1, size1, scale_bounds=scale_bounds, horizon_diagonals=horizon_diagonals)
            if not c1:
                chk = AlignmentCheck(False, "image-1 homography: " + c1.reason, c1.scale_range, c1.horizon_px)
        if chk:
            return SafeAlignment(np.asarray(res.H1, float), np.asarray(res.H2, float), ap, approach,
                                 tuple(fallbacks), res, chk)
        fallbacks.append((ap, chk.reason))
    return SafeAlignment(np.eye(3), np.eye(3), "none", approach, tuple(fallbacks), None,
                         AlignmentCheck(True, "ok", (1.0, 1.0), float("inf")))
