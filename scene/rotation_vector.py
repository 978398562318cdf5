"""Rotation vectors and frame rotations: the exponential and logarithm maps of SO(3), batched.

The project's attitude ``A`` maps inertial (ICRS) vectors into the camera frame (docs/architecture.md).  A camera
turning at the body rate ``omega`` (rad/s, camera frame) obeys ``dA/dt = -[omega x] A`` (Markley & Crassidis 2014,
"Fundamentals of Spacecraft Attitude Determination and Control", Eq. 3.21), so over ``dt`` at a constant rate
``A(t + dt) = exp(-[phi x]) A(t)`` with the rotation vector ``phi = omega dt``.  :func:`frame_rotation` is that
matrix (the *passive* rotation of the frame by ``|phi|`` about ``phi / |phi|``, Rodrigues' formula), so that
``frame_rotation([0, 0, a])`` equals ``scene.attitude.rot_axis(3, a)``; :func:`frame_rotation_vector` is its
inverse (the logarithm map).  Radians throughout; pure numpy.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["cross_matrix", "frame_rotation", "frame_rotation_vector"]


def cross_matrix(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) skew matrices ``[v x]`` of (..., 3) vectors (``[v x] u = v x u``)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def frame_rotation(phi: np.ndarray) -> np.ndarray:
    """``exp(-[phi x])``: (..., 3, 3) passive rotation matrices of (..., 3) rotation vectors (rad).

    Rodrigues: ``I - (sin t / t) [phi x] + ((1 - cos t) / t^2) [phi x]^2`` with ``t = |phi|``; the two
    coefficients by their Taylor series below t = 1e-4 rad (relative error < 1e-17), exact at t = 0.
    """
    phi = np.asarray(phi, dtype=np.float64)
    if phi.shape == (3,):                      # one rotation (a tracker's frame step): the same formula in scalars
        x, y, z = (float(c) for c in phi)
        t2 = x * x + y * y + z * z
        t = math.sqrt(t2)
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0 if t < 1e-4 else math.sin(t) / t
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0 if t < 1e-4 else (1.0 - math.cos(t)) / t2
        return np.array([[1.0 - b * (y * y + z * z), a * z + b * x * y, -a * y + b * x * z],
                         [-a * z + b * x * y, 1.0 - b * (x * x + z * z), a * x + b * y * z],
                         [a * y + b * x * z, -a * x + b * y * z, 1.0 - b * (x * x + y * y)]])
    t2 = np.sum(phi * phi, axis=-1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(ts)) / (ts * ts))
    K = cross_matrix(phi)
    return np.eye(3) - a[..., None, None] * K + b[..., None, None] * (K @ K)


def frame_rotation_vector(R: np.ndarray) -> np.ndarray:
    """The logarithm map: (..., 3) rotation vectors ``phi`` (rad, ``|phi|`` in [0, pi]) with
    ``frame_rotation(phi) == R`` for (..., 3, 3) rotation matrices ``R``.

    ``t = atan2(|s|, (trace R - 1) / 2)`` with ``s`` the axial vector of ``(R^T - R) / 2`` (= ``sin t`` times
    the axis); ``phi = t s / |s|``, by the series ``s (1 + |s|^2 / 6)`` below ``|s|`` = 1e-6.  Within 1e-3 rad
    of pi the axis ``u`` comes from the symmetric part ``(R + R^T) / 2 = cos t I + (1 - cos t) u u^T`` (its
    largest column), signed by ``s`` (at exactly pi both signs are the same rotation).
    """
    R = np.asarray(R, dtype=np.float64)
    s = 0.5 * np.stack([R[..., 1, 2] - R[..., 2, 1], R[..., 2, 0] - R[..., 0, 2], R[..., 0, 1] - R[..., 1, 0]], -1)
    sn = np.linalg.norm(s, axis=-1)
    c = np.clip(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    t = np.arctan2(sn, c)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.where((sn < 1e-6)[..., None] & (c > 0)[..., None], s * (1.0 + sn * sn / 6.0)[..., None],
                       s * (t / np.where(sn > 0, sn, 1.0))[..., None])
    near_pi = (np.pi - t) < 1e-3
    if np.any(near_pi):
        S = 0.5 * (R[near_pi] + np.swapaxes(R[near_pi], -1, -2))
        cp = c[near_pi]
        M = (S - cp[:, None, None] * np.eye(3)) / (1.0 - cp)[:, None, None]        # u u^T
        col = np.argmax(np.diagonal(M, axis1=-2, axis2=-1), axis=-1)
        u = np.take_along_axis(M, col[:, None, None], axis=-1)[..., 0]
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        sgn = np.where(np.sum(u * s[near_pi], axis=-1) < 0, -1.0, 1.0)
        phi[near_pi] = u * (sgn * t[near_pi])[:, None]
    return phi
