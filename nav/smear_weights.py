"""The smear of a star in a tracked frame, from which tracking weighs each star's centroid along and across its streak
(issue 22, point 6: availability and no false lock at rates up to 1 deg/s).

A star tracker at 0.9 deg/s with the reference's star camera (56 arcsec/px) and a 100 ms exposure sees each star as
a 6 px streak.  A detector that fits a round PSF to it states a Cramér-Rao sigma for a round star; measured on the
``realistic`` preset's frames (examples/star/track.toml, 100 sequences) the centroid error is 0.21 px RMS along the
streak and 0.08 px across it, against a stated 0.11 px: the fit's model error grows with the streak's length, and a
bright star whose stated sigma is 0.02 px can be 0.3 px off and pull a whole solution (a 7-sigma roll error).

* :func:`smear_axes`: each star's streak (direction and length, px) from the body rate: the
  image of ``dv/dt = -omega x v`` is ``d(px)/dt = G omega``, ``G`` the pixel Jacobian of
  ``nav.tracking.pixel_jacobian``.
* :func:`along_gain`: how much the detector's stated variance grows along a streak (its profile is wider there).
* :func:`streak_inside`: whether each predicted streak lies whole inside the image (a streak cut by the edge has
  its centroid pulled inwards along it, an error no weight describes; tracking leaves such stars out).
* the weights: ``nav.tracking.centroid_whitening`` turns the variances along and across each streak into a 2 x 2
  covariance per star, and ``nav.tracking.solve_reprojection`` fits the attitude with them (``nav/sequence.py``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["smear_axes", "along_gain", "streak_inside"]


def smear_axes(G: np.ndarray, omega: np.ndarray, exposure_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Image motion of each star.  G : (M, 2, 3) px/rad pixel Jacobians (``nav.tracking.pixel_jacobian``).
    omega : (3,) rad/s body rate (camera frame).  exposure_s : s.  Returns u (M, 2) unit direction of the motion
    (px; (1, 0) where the star does not move) and length (M,) px of the streak over the exposure."""
    vel = G @ np.asarray(omega, np.float64)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    if len(speed) and speed.min() > 0:
        return vel / speed[:, None], speed * float(exposure_s)
    u = np.where(speed[:, None] > 0, vel / np.where(speed > 0, speed, 1.0)[:, None], np.array([1.0, 0.0]))
    return u, speed * float(exposure_s)


def streak_inside(xy: np.ndarray, u: np.ndarray | None, length: np.ndarray | None, margin_px: float, width: int,
                  height: int) -> np.ndarray:
    """Whether each streak lies whole inside a ``width`` x ``height`` image with ``margin_px`` to spare.

    xy : (M, 2) px predicted centroids (col, row; the image spans [0, width) x [0, height)).  u : (M, 2) unit
    directions of the image motion, length : (M,) px streak lengths (:func:`smear_axes`; zeros for a still star;
    both None: still stars, the margin alone).
    The streak runs from ``xy - u length / 2`` to ``xy + u length / 2``; its bounding box grown by ``margin_px``
    must fit in ``[0, width] x [0, height]``.  Returns (M,) bool.  A streak cut by the edge loses the part outside,
    so a round-PSF fit's centroid moves inwards along the streak by up to ``length / 2``.
    """
    # inside [ext, size - ext] on both axes  <=>  |xy - size / 2| + ext <= size / 2, ext = |u| L / 2 + margin
    half = np.array([0.5 * width, 0.5 * height])
    if u is None:
        return (np.abs(xy - half) <= half - float(margin_px)).all(axis=1)
    return (np.abs(xy - half) + np.abs(u) * (0.5 * length)[:, None] <= half - float(margin_px)).all(axis=1)


def along_gain(length: np.ndarray, psf_sigma_px: float) -> np.ndarray:
    """Relative growth of a centroid's variance along its streak: ``L^2 / (12 s^2)`` (M,), so that the variance
    along the streak is ``sigma_det^2 (1 + L^2 / (12 s^2))``.

    length : (M,) px streak lengths L (:func:`smear_axes`).  psf_sigma_px : s, the 1-sigma width (px) of the star's
    profile across the streak (the PSF with the pixel).  A streak's profile along it is the PSF convolved with a
    uniform segment of length L: variance ``s^2 + L^2 / 12``; a centroid's error scales with its profile's width at
    a given flux and background (the Cramer-Rao bound of a Gaussian profile's position: width / sqrt(N), Winick
    1986, JOSA A 3(11)), and a detector that fits a round PSF states the round star's.  Measured on the
    ``realistic`` preset's frames (examples/star/track.toml, seed 2202, sequences 0-39, 59,928 tracked stars): the
    along-streak error over the stated sigma grows as ``sqrt(1 + L^2 / (12 s^2))`` with s = 1.28 px (maximum
    likelihood; its RMS z-score 0.94-1.12 in every bin of L 0-9 px and sigma 0.05-0.5 px), while the error across
    the streak stays at 0.7-1.0 of the stated sigma.
    """
    s = float(psf_sigma_px)
    L = np.asarray(length, np.float64)
    return L * L / (12.0 * s * s) if s > 0 else np.zeros_like(L)
