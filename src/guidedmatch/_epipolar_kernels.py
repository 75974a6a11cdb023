"""Compiled kernel of :func:`guidedmatch.epipolar.median_triangulation_angle` (Numba, ``nogil``): the rays of every
correspondence, the depths of each of the four poses of ``E`` solved per ray pair in closed form, and the median angle
between the two rays under the pose with the most points in front of both cameras. Its own module so that
:mod:`guidedmatch.epipolar` loads without Numba."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")   # x / 0 -> inf / nan as in NumPy, not an exception
def median_ray_angle(x1, x2, K1inv, K2inv, Rs, t):
    """Median triangulation angle (degrees) of ``x1 <-> x2 (n, 2)`` pixels under the poses ``Rs (2, 3, 3)`` x
    ``(-t, +t)`` of ``E`` (``cv2.decomposeEssentialMat``), the one with the most correspondences in front of both
    cameras (the first of equals, in the order Ra -t, Ra +t, Rb -t, Rb +t). ``K1inv``, ``K2inv``: inverse
    calibration matrices; ``t (3,)``."""
    n = x1.shape[0]
    d1 = np.empty((n, 3))
    d2 = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            d1[i, k] = x1[i, 0] * K1inv[k, 0] + x1[i, 1] * K1inv[k, 1] + K1inv[k, 2]
            d2[i, k] = x2[i, 0] * K2inv[k, 0] + x2[i, 1] * K2inv[k, 1] + K2inv[k, 2]
        n1 = np.sqrt(d1[i, 0] * d1[i, 0] + d1[i, 1] * d1[i, 1] + d1[i, 2] * d1[i, 2])
        n2 = np.sqrt(d2[i, 0] * d2[i, 0] + d2[i, 1] * d2[i, 1] + d2[i, 2] * d2[i, 2])
        for k in range(3):
            d1[i, k] /= n1
            d2[i, k] /= n2
    best_front = -1
    best = np.empty(n)
    b = np.empty(n)
    r2 = np.empty(3)
    for r in range(2):
        R = Rs[r]
        c = np.empty(3)   # camera 2's centre in camera 1's frame for +t: R^T t
        for k in range(3):
            c[k] = R[0, k] * t[0] + R[1, k] * t[1] + R[2, k] * t[2]
        front_m = 0
        front_p = 0
        for i in range(n):
            for k in range(3):   # camera 2's ray in camera 1's frame: R^T d2
                r2[k] = d2[i, 0] * R[0, k] + d2[i, 1] * R[1, k] + d2[i, 2] * R[2, k]
            bi = d1[i, 0] * r2[0] + d1[i, 1] * r2[1] + d1[i, 2] * r2[2]
            b[i] = bi
            det = bi * bi - 1.0   # of lambda1 d1 - lambda2 r2 = c, least squares
            p = d1[i, 0] * c[0] + d1[i, 1] * c[1] + d1[i, 2] * c[2]
            q = r2[0] * c[0] + r2[1] * c[1] + r2[2] * c[2]
            # centre -c (-t): p, q change sign
            l1 = (bi * -q + p) / det
            l2 = (-q + bi * p) / det
            if l1 > 0 and l2 > 0:
                front_m += 1
            l1 = (bi * q - p) / det
            l2 = (q - bi * p) / det
            if l1 > 0 and l2 > 0:
                front_p += 1
        if front_m > best_front:
            best_front = front_m
            best[:] = b
        if front_p > best_front:
            best_front = front_p
            best[:] = b
    ang = np.empty(n)
    for i in range(n):
        ang[i] = np.arccos(min(max(best[i], -1.0), 1.0))
    return np.degrees(np.median(ang))
