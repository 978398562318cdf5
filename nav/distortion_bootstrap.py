"""Bootstrap of the distortion fit (:mod:`dualsight.nav.distortion_fit`): when the camera file has no
distortion, the frames are first solved from a central disc where a plausible lens moves stars little; this
module sizes that disc and the widened voting tolerance (pure functions of the camera's numbers)."""

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BootstrapPlan", "bootstrap_plan", "model_error_px"]

# ============================================================================================ bootstrap
PLAUSIBLE_CORNER_DISTORTION = 0.03
"""Radial displacement at the image corner of a strongly distorted wide lens, as a fraction of the
half-diagonal (3 %: e.g. 19 px of a 640 px half-diagonal)."""
PLAUSIBLE_FOCAL_ERROR = 0.01
"""Relative error of a nominal focal length (1 %: the ESA tetra3 frames' "35 mm" lens is 35.32 mm)."""
BOOTSTRAP_STARS = 10.0
"""Catalog stars expected, on average over the sky, in the first central disc (the robust voting verifies
an attitude with 4 stars; 10 leaves room for the sky's variations and for missed detections)."""


@dataclass(frozen=True)
class BootstrapPlan:
    """Central regions for solving frames with a camera model that lacks the distortion (and whose focal
    length is only nominal): radii_px (K,) px from the principal point, smallest first; tolerance_rad the
    voting tolerance of these passes (rad)."""

    radii_px: np.ndarray
    tolerance_rad: float


def model_error_px(r_px, half_diagonal_px: float, *, focal_error: float = PLAUSIBLE_FOCAL_ERROR,
                   corner_fraction: float = PLAUSIBLE_CORNER_DISTORTION):
    """How far (px) a star at radius ``r_px`` from the principal point can be from where an undistorted
    model with a nominal focal length puts it: ``focal_error * r + corner_fraction * R (r / R)^3``
    (the focal-length error scales the radius; the k1 term of a lens moving the corner, radius R =
    ``half_diagonal_px``, by ``corner_fraction * R``)."""
    r = np.asarray(r_px, np.float64)
    R = float(half_diagonal_px)
    return focal_error * r + corner_fraction * R * (r / R) ** 3


def bootstrap_plan(half_diagonal_px: float, focal_px: float, n_catalog: int, tolerance_rad: float, *,
                   stars: float = BOOTSTRAP_STARS, growth: float = 1.5, stop_fraction: float = 0.7,
                   max_tolerance_rad: float = math.pi / 180) -> BootstrapPlan:
    """The central regions of the bootstrap (``hil star --fit-distortion`` with a camera file without
    distortion), from the field size, the focal length (px), the catalog size and the voting tolerance.

    * First radius r0: the disc about the boresight that holds ``stars`` catalog stars on average
      (a cap of angular radius t holds n_catalog (1 - cos t) / 2 of them), r0 = f tan t, at most
      ``stop_fraction`` R (R = ``half_diagonal_px``).
    * Tolerance: the angle of an observed pair of stars in the disc is off by up to 2 e(r0) (two stars on
      opposite sides at r0; e = :func:`model_error_px`) and by about e(r0) for a typical pair (about r0
      apart); the passes vote with max(tolerance_rad, e(r0) / f), at most ``max_tolerance_rad`` (1 deg,
      VotingConfig's bound).  Twice that lets random coincidences through: on 12 frames of a 30 deg field
      with a 1 % focal error, 3 of 4 solutions at r0 were wrong at 2 e(r0) (444 arcsec), 0 of 3 at e(r0).
    * Then the radius grows by ``growth`` while it stays under ``stop_fraction`` R (a fit between passes
      removes most of the model error, so the same tolerance covers the wider disc); the whole field
      follows with the voting tolerance as given.
    """
    R, f = float(half_diagonal_px), float(focal_px)
    t = math.acos(max(-1.0, 1.0 - 2.0 * min(stars, n_catalog) / max(n_catalog, 1)))
    r0 = min(f * math.tan(min(t, 1.5)), stop_fraction * R)
    tol = min(max(tolerance_rad, float(model_error_px(r0, R)) / f), max_tolerance_rad)
    radii = [r0]
    while radii[-1] * growth < stop_fraction * R:
        radii.append(radii[-1] * growth)
    return BootstrapPlan(np.asarray(radii, np.float64), float(tol))
