"""Angular rate of the camera from a star sequence, with its covariance (issue 22, point 3).

Two estimates of the body rate ``omega`` (rad/s, camera frame, ``dA/dt = -[omega x] A`` as in
``scene/rotation_vector.py``), both exact for a constant rate over the interval ``dt`` (the mean rate otherwise):

* :func:`rate_from_attitudes`: two successive attitudes (openstartracker's approach):
  ``omega = log(A_k A_{k-1}^T) / dt`` (the logarithm map, ``scene.rotation_vector.frame_rotation_vector``), with
  ``cov = (P_k + Phi P_{k-1} Phi^T) / dt^2`` from the two attitudes' error covariances (independent centroid noise
  in the two frames; first order).
* :func:`rate_from_stars`: directly from the same stars seen in both frames, without the catalog's positions
  (Crassidis, "Angular Velocity Determination Directly from Star Tracker Measurements", JGCD 25(6), 2002): the
  camera-frame directions obey ``b_k = Phi b_{k-1}`` with ``Phi = exp(-[omega dt x])``, so ``Phi`` minimises
  ``sum_j w_j |b_k,j - Phi b_{k-1},j|^2``, Wahba's problem with the earlier frame as the reference, solved exactly by
  SVD (``nav.attitude.svd_attitude``, Markley 1988) rather than by Crassidis' first-order form
  ``b_k - b_{k-1} = [b_{k-1} x] phi``, whose least squares has the same covariance
  ``(sum_j w_j (I - b_j b_j^T))^-1`` to first order but a bias of order ``|phi|^2``.  Each star's weight is
  ``1 / (sigma_{k-1}^2 + sigma_k^2)`` (rad^-2): both directions are noisy.  Then ``omega = log(Phi) / dt`` and
  ``cov = P_Phi / dt^2``.

Vectorised over a leading batch axis; padded stars carry weight 0.  A tracker's frame step (one pair of attitudes,
one frame's stars) has its one-case forms, :func:`rate_between` and :func:`rate_from_star_pairs`: the same formulas
in scalars and 3 x 3 products (the batched forms' array set-up costs more than the arithmetic on one case).
"""

from __future__ import annotations

import math

import numpy as np

from dualsight.nav.attitude import svd_attitude
from dualsight.nav.tracking import solve_pairs
from dualsight.scene.rotation_vector import frame_rotation_vector

__all__ = ["rate_from_attitudes", "rate_from_stars", "pair_by_identity", "log_rotation", "rate_between",
           "rate_from_star_pairs"]


def rate_from_attitudes(A_prev: np.ndarray, A_next: np.ndarray, dt, cov_prev: np.ndarray | None = None,
                        cov_next: np.ndarray | None = None):
    """Mean body rate between two attitudes.

    A_prev, A_next : (B, 3, 3) inertial -> camera at t and t + dt.  dt : (B,) or scalar s (> 0).
    cov_prev, cov_next : optional (B, 3, 3) rad^2 attitude error covariances (camera frame, as
        ``svd_attitude`` states them).
    Returns omega (B, 3) rad/s in the camera frame of ``A_next`` and, with both covariances, cov (B, 3, 3)
    (rad/s)^2 (else None).  Exact for |omega dt| < pi.
    """
    A0 = np.asarray(A_prev, np.float64).reshape(-1, 3, 3)
    A1 = np.asarray(A_next, np.float64).reshape(-1, 3, 3)
    Phi = A1 @ np.swapaxes(A0, -1, -2)
    dt = np.broadcast_to(np.asarray(dt, np.float64), (A0.shape[0],))
    omega = frame_rotation_vector(Phi) / dt[:, None]
    if cov_prev is None or cov_next is None:
        return omega, None
    P0 = np.asarray(cov_prev, np.float64).reshape(-1, 3, 3)
    P1 = np.asarray(cov_next, np.float64).reshape(-1, 3, 3)
    cov = (P1 + Phi @ P0 @ np.swapaxes(Phi, -1, -2)) / (dt * dt)[:, None, None]
    return omega, cov


def rate_from_stars(b_prev: np.ndarray, b_next: np.ndarray, var_prev: np.ndarray, var_next: np.ndarray, dt):
    """Mean body rate from the displacements of the same stars between two frames (module docstring).

    b_prev, b_next : (B, S, 3) camera-frame unit vectors of the same star (row by row) at t and t + dt
        (NaN allowed in padding).
    var_prev, var_next : (B, S) rad^2 per-axis variance of each direction (e.g. ``(sigma_px / fx)^2``); a
        non-finite or non-positive entry in either marks padding.
    dt : (B,) or scalar s (> 0).
    Returns omega (B, 3) rad/s (camera frame of the later frame), cov (B, 3, 3) (rad/s)^2, ok (B,) bool
    (at least two non-parallel stars; NaN elsewhere).
    """
    v = np.asarray(var_prev, np.float64) + np.asarray(var_next, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(np.isfinite(v) & (v > 0), 1.0 / np.where(v > 0, v, 1.0), 0.0)
    Phi, ok, P = svd_attitude(b_next, b_prev, w, return_cov=True)
    dt = np.broadcast_to(np.asarray(dt, np.float64), (Phi.shape[0],))
    omega = frame_rotation_vector(np.where(ok[:, None, None], Phi, np.eye(3))) / dt[:, None]
    omega[~ok] = np.nan
    return omega, P / (dt * dt)[:, None, None], ok


def pair_by_identity(rows_prev: np.ndarray, rows_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_prev, i_next) of the detections of two frames that carry the same catalog row (>= 0), in
    ascending row order: the star pairs of :func:`rate_from_stars` (a catalog row appears once per frame after
    tracking's unique matching)."""
    rp = np.asarray(rows_prev)
    rn = np.asarray(rows_next)
    gp, gn = np.flatnonzero(rp >= 0), np.flatnonzero(rn >= 0)
    _, ip, jn = np.intersect1d(rp[gp], rn[gn], assume_unique=False, return_indices=True)
    return gp[ip], gn[jn]


def log_rotation(R: np.ndarray) -> np.ndarray:
    """(3,) rotation vector ``phi`` with ``exp(-[phi x]) = R`` of one (3, 3) rotation matrix: the logarithm map of
    ``scene.rotation_vector.frame_rotation_vector`` in scalars (``t = atan2(|s|, (trace R - 1) / 2)``, ``s`` the
    axial vector of ``(R^T - R) / 2``, ``phi = t s / |s|``; the series ``s (1 + |s|^2 / 6)`` below |s| = 1e-6),
    handing angles within 1e-3 rad of pi (the axis from the symmetric part) to that function."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    sx, sy, sz = 0.5 * (r12 - r21), 0.5 * (r20 - r02), 0.5 * (r01 - r10)
    sn = math.sqrt(sx * sx + sy * sy + sz * sz)
    c = min(1.0, max(-1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
    t = math.atan2(sn, c)
    if math.pi - t < 1e-3:
        return frame_rotation_vector(R)
    k = 1.0 + sn * sn / 6.0 if (sn < 1e-6 and c > 0) else t / sn
    return np.array([sx * k, sy * k, sz * k])


def rate_between(A_prev: np.ndarray, A_next: np.ndarray, dt: float, cov_prev: np.ndarray, cov_next: np.ndarray):
    """:func:`rate_from_attitudes` of one pair: A_prev, A_next (3, 3), dt s, cov_prev, cov_next (3, 3) rad^2.
    Returns omega (3,) rad/s and cov (3, 3) (rad/s)^2 (``(P_k + Phi P_{k-1} Phi^T) / dt^2``)."""
    Phi = A_next @ A_prev.T
    inv = 1.0 / (float(dt) * float(dt))
    return log_rotation(Phi) / float(dt), (cov_next + Phi @ cov_prev @ Phi.T) * inv


def rate_from_star_pairs(b_prev: np.ndarray, b_next: np.ndarray, var_prev: np.ndarray, var_next: np.ndarray,
                         dt: float):
    """:func:`rate_from_stars` of one frame pair: b_prev, b_next (S, 3) unit vectors of the same stars row by row,
    var_prev, var_next (S,) rad^2 (finite, > 0).  Returns (omega (3,) rad/s, cov (3, 3) (rad/s)^2, ok); the
    SVD by ``nav.tracking.solve_pairs`` (Markley 1988, one case)."""
    Phi, ok, P = solve_pairs(b_next, b_prev, 1.0 / (var_prev + var_next))
    if not ok:
        return np.full(3, np.nan), np.full((3, 3), np.nan), False
    inv = 1.0 / (float(dt) * float(dt))
    return log_rotation(Phi) / float(dt), P * inv, True
