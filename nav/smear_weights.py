"""The smear of a star in a tracked frame, and the attitude that weighs each star's centroid along and across it
(issue 22, point 6: availability and no false lock at rates up to 1 deg/s).

A star tracker at 0.9 deg/s with the reference's star camera (56 arcsec/px) and a 100 ms exposure sees each star as
a 6 px streak.  A detector that fits a round PSF to it states a Cramér-Rao sigma for a round star; measured on the
``realistic`` preset's frames (examples/star/track.toml, 100 sequences) the centroid error is 0.21 px RMS along the
streak and 0.08 px across it, against a stated 0.11 px: the fit's model error grows with the streak's length, and a
bright star whose stated sigma is 0.02 px can be 0.3 px off and pull a whole solution (a 7-sigma roll error).

* :func:`streak_length`, :func:`smear_axes`: each star's streak (direction and length, px) from the body rate: the
  image of ``dv/dt = -omega x v`` is ``d(px)/dt = G omega``, ``G`` the pixel Jacobian of
  ``nav.tracking.pixel_jacobian``.
* :func:`refine_anisotropic`: the attitude by Gauss-Newton on the reprojection error with a 2 x 2 covariance per
  star, its variance along and across the streak apart.
"""

from __future__ import annotations

import numpy as np

from dualsight.nav.tracking import pixel_jacobian
from dualsight.scene.rotation_vector import frame_rotation

__all__ = ["streak_length", "smear_axes", "refine_anisotropic"]


def streak_length(xy: np.ndarray, camera, omega: np.ndarray, exposure_s: float) -> np.ndarray:
    """(D,) px: the length of the streak of a star detected at ``xy`` (D, 2) px over ``exposure_s`` s at the body
    rate ``omega`` (3,) rad/s (camera frame): ``|G omega| t``, ``G`` the pixel Jacobian of a frame rotation at the
    star's direction (``nav.tracking.pixel_jacobian``; ``dv/dt = -omega x v``)."""
    G = pixel_jacobian(camera.backproject(np.asarray(xy, np.float64).reshape(-1, 2)), camera)
    vel = G @ np.asarray(omega, np.float64)
    return np.sqrt((vel * vel).sum(axis=1)) * float(exposure_s)


def smear_axes(G: np.ndarray, omega: np.ndarray, exposure_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Image motion of each star.  G : (M, 2, 3) px/rad pixel Jacobians (``nav.tracking.pixel_jacobian``).
    omega : (3,) rad/s body rate (camera frame).  exposure_s : s.  Returns u (M, 2) unit direction of the motion
    (px; (1, 0) where the star does not move) and length (M,) px of the streak over the exposure."""
    vel = G @ np.asarray(omega, np.float64)
    speed = np.sqrt((vel * vel).sum(axis=1))
    u = np.where(speed[:, None] > 0, vel / np.where(speed > 0, speed, 1.0)[:, None], np.array([1.0, 0.0]))
    return u, speed * float(exposure_s)


def refine_anisotropic(A: np.ndarray, det_xy: np.ndarray, r: np.ndarray, camera, var_along: np.ndarray,
                       var_cross: np.ndarray, u: np.ndarray, G: np.ndarray | None = None):
    """Weighted least-squares attitude with a 2 x 2 centroid covariance per star,
    ``C_i = var_along_i u u^T + var_cross_i n n^T`` (``n`` across the streak): one Gauss-Newton step on the
    reprojection error from ``A`` (Hartley & Zisserman, "Multiple View Geometry", 2nd ed., Sec. A6.1),
    ``delta = (sum G^T W G)^-1 sum G^T W (x_det - x_pred)``, ``A <- exp(-[delta x]) A``.  From the isotropic SVD
    answer (arcseconds off) the step leaves a linearisation error of order |delta|^2 (1e-9 rad), so the normal
    matrix and the residuals are not evaluated again: the covariance is ``(sum G^T W G)^-1`` at ``A``, the residuals
    ``y - G delta``.

    A : (3, 3) starting attitude (inertial -> camera).  det_xy : (M, 2) px.  r : (M, 3) catalog unit vectors of the
    same stars.  var_along, var_cross : (M,) px^2.  u : (M, 2) unit smear directions.  G : (M, 2, 3) the pixel
    Jacobians at ``r @ A.T`` when the caller has them (:func:`smear_axes`'s), else computed here.
    Returns A (3, 3), cov (3, 3) rad^2 and chi2 (the weighted residual sum of squares after the step).
    """
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    W = (u[:, :, None] * u[:, None, :] / var_along[:, None, None]
         + n[:, :, None] * n[:, None, :] / var_cross[:, None, None])
    v = r @ A.T
    px, _ = camera.project(v)
    y = det_xy - px
    G = pixel_jacobian(v, camera) if G is None else G
    GtW = np.einsum("mki,mkl->mil", G, W)
    cov = np.linalg.inv(np.einsum("mil,mlj->ij", GtW, G))
    delta = cov @ np.einsum("mil,ml->i", GtW, y)
    y = y - G @ delta
    return frame_rotation(delta) @ A, cov, float(np.einsum("mk,mkl,ml->", y, W, y))
