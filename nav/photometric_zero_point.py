"""Photometric zero point of a frame from its identified stars, and magnitudes of anything else it detects.

The instrumental magnitude of a detection is ``m_inst = -2.5 log10(F)`` (F its total flux, ADU: the detector's
PSF-fit flux); for an identified star of catalog magnitude V, ``V - m_inst`` is the frame's zero point plus the
star's colour term in the camera's band and the flux error.  The zero point is the median of those offsets over
the frame's identified, unsaturated stars, and its scatter the robust standard deviation (1.4826 x the median
absolute deviation: one red star or a blend does not move either).  A detection's magnitude on the catalog's
scale is then ``zp - 2.5 log10(F)``.

Source: the standard differential photometry of an image against catalog stars (e.g. Howell, *Handbook of CCD
Astronomy*, 2nd ed., Sec. 5.2); the colour terms are not fitted (one band, Johnson V of the catalog), so the
scatter states how far a magnitude may be off for a star of unknown colour.

Units: ADU in, magnitudes out.  Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MAD_TO_SIGMA", "ZeroPoint", "zero_point", "magnitude"]

MAD_TO_SIGMA = 1.4826
"""Median absolute deviation -> standard deviation of a normal distribution (1 / Phi^-1(3/4))."""


@dataclass(frozen=True)
class ZeroPoint:
    """zp_mag : V = zp_mag - 2.5 log10(flux_adu) (NaN with no star); scatter_mag : robust 1-sigma of the stars'
    offsets (NaN with fewer than 2); n : stars used."""

    zp_mag: float
    scatter_mag: float
    n: int


def zero_point(flux_adu, vmag, use=None) -> ZeroPoint:
    """The zero point of one frame from its identified stars.

    flux_adu : (S,) total fluxes (ADU); vmag : (S,) their catalog magnitudes; use : optional (S,) bool, the stars
    to fit (e.g. not saturated: a saturated star's flux is low).  Stars with a non-positive or non-finite flux
    are left out."""
    f = np.asarray(flux_adu, np.float64)
    v = np.asarray(vmag, np.float64)
    ok = np.isfinite(f) & (f > 0) & np.isfinite(v)
    if use is not None:
        ok &= np.asarray(use, bool)
    if not ok.any():
        return ZeroPoint(float("nan"), float("nan"), 0)
    off = v[ok] + 2.5 * np.log10(f[ok])
    zp = float(np.median(off))
    n = int(ok.sum())
    scatter = float(MAD_TO_SIGMA * np.median(np.abs(off - zp))) if n >= 2 else float("nan")
    return ZeroPoint(zp, scatter, n)


def magnitude(flux_adu, zp_mag: float) -> np.ndarray:
    """(K,) magnitudes ``zp_mag - 2.5 log10(flux_adu)`` on the catalog's scale; NaN where the flux is not
    positive."""
    f = np.asarray(flux_adu, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(f > 0, zp_mag - 2.5 * np.log10(np.where(f > 0, f, 1.0)), np.nan)
