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
* the weights: ``nav.tracking.centroid_whitening`` turns the variances along and across each streak into a 2 x 2
  covariance per star, and ``nav.tracking.solve_reprojection`` fits the attitude with them (``nav/sequence.py``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["smear_axes"]


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
