"""Attitude math over arrays: elementary rotations, Euler 1-2-3, random attitudes, RA/Dec.

Attitude matrices ``A`` map inertial (ICRS) vectors into the camera frame: ``v_cam = A @ v_icrs``
(docs/architecture.md, Conventions).  All functions are vectorised over a leading batch axis; angles in radians.
The angle between two directions is :func:`dualsight.scene.units.angle_between`.
"""

from __future__ import annotations

import numpy as np


def rot_axis(axis: int, angle: np.ndarray) -> np.ndarray:
    """Frame (passive) rotation matrices about a coordinate axis.

    Parameters
    ----------
    axis : 1, 2 or 3 (x, y, z).
    angle : (B,) or scalar, radians.

    Returns
    -------
    (B, 3, 3) matrices R_axis(angle); e.g. R_3(a) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]
    (Markley & Crassidis 2014, Eq. 2.165).
    """
    a = np.atleast_1d(np.asarray(angle, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == 1:
        m = [[o, z, z], [z, c, s], [z, -s, c]]
    elif axis == 2:
        m = [[c, z, -s], [z, o, z], [s, z, c]]
    elif axis == 3:
        m = [[c, s, z], [-s, c, z], [z, z, o]]
    else:
        raise ValueError(f"axis must be 1, 2 or 3, got {axis}")
    return np.moveaxis(np.array(m), -1, 0)


def euler123_to_dcm(angles: np.ndarray) -> np.ndarray:
    """Direction-cosine matrices of a 1-2-3 rotation sequence.

    Parameters
    ----------
    angles : (B, 3) radians (theta1 about x, then theta2 about the new y, then theta3 about the new z).

    Returns
    -------
    (B, 3, 3) A = R_3(theta3) R_2(theta2) R_1(theta1), mapping inertial to body/camera.
    """
    a = np.asarray(angles, dtype=np.float64).reshape(-1, 3)
    return rot_axis(3, a[:, 2]) @ rot_axis(2, a[:, 1]) @ rot_axis(1, a[:, 0])


def random_euler123(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) angles uniform in [-pi, pi), as the reference's star Monte Carlo draws them."""
    return rng.uniform(-np.pi, np.pi, size=(n, 3))


def random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4) unit quaternions (x, y, z, w) uniform on SO(3) (Shoemake 1992, "Uniform random rotations")."""
    u1, u2, u3 = rng.random((3, n))
    return quaternions_from_uniforms(u1, u2, u3)


def quaternions_from_uniforms(u1: np.ndarray, u2: np.ndarray, u3: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (x, y, z, w) from three (n,) U[0, 1) draws (Shoemake 1992's map)."""
    a, b = np.sqrt(1 - u1), np.sqrt(u1)
    return np.stack([a * np.sin(2 * np.pi * u2), a * np.cos(2 * np.pi * u2),
                     b * np.sin(2 * np.pi * u3), b * np.cos(2 * np.pi * u3)], axis=-1)


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotation matrices of (B, 4) unit quaternions (x, y, z, w), active convention
    (R v rotates v); used for uniformly random rotations, where active/passive is immaterial."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)



def dcm_to_quat(R: np.ndarray) -> np.ndarray:
    """(B, 4) unit quaternions (x, y, z, w), w >= 0, with ``quat_to_dcm(q) == R`` for (B, 3, 3) rotation matrices
    (Shepperd 1978: from the largest of 1 + trace and the diagonal, no loss near 180 deg); NaN rows stay NaN."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    d0, d1, d2 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    cand = np.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2], axis=-1)
    k = np.argmax(np.nan_to_num(cand, nan=-1.0), axis=-1)
    s = 2 * np.sqrt(np.maximum(np.take_along_axis(cand, k[:, None], -1)[:, 0], 0))      # 4 |component k|
    xw, yw, zw = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]   # 4 xw, 4 yw, 4 zw
    xy, xz, yz = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]   # 4 xy, 4 xz, 4 yz
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.select([k[:, None] == 0, k[:, None] == 1, k[:, None] == 2],
                      [np.stack([xw, yw, zw, s * s / 4], -1), np.stack([s * s / 4, xy, xz, xw], -1),
                       np.stack([xy, s * s / 4, yz, yw], -1)],
                      np.stack([xz, yz, s * s / 4, zw], -1)) / s[:, None]
    return q * np.where(q[:, 3:] < 0, -1.0, 1.0)

def radec_to_unit(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """(..., 3) ICRS unit vectors from right ascension and declination (rad)."""
    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ra in [0, 2pi), dec in [-pi/2, pi/2]) in radians of (..., 3) vectors."""
    v = np.asarray(v, dtype=np.float64)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi), np.arcsin(np.clip(v[..., 2], -1, 1))


def boresight_radec(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RA/Dec (rad) of the camera +z axis for (B, 3, 3) inertial-to-camera matrices: the third row of A."""
    A = np.asarray(A, dtype=np.float64)
    return unit_to_radec(A[..., 2, :])
