"""The blobber's single-frame range error as a measurement model: its mean (a bias of the estimator) and its
standard deviation, per observed axis ratio, from the projected-area table itself (issue 23, point 6 c).

The blobber (``nav/blobber.py``) turns a blob of N pixels into a range by Eq. 1, ``rho_est = sqrt(f^2 A_c / N)``,
with A_c the table's area at the blob's axis ratio (``catalogs/areas.py``: the ``relopt`` curve for the
``subpixel`` estimator).  The target's true projected area A is unknown (its attitude is), and
``N = f^2 A / rho^2`` (up to pixel sampling), so ``q = rho_est / rho = sqrt(A_c / A)``.  Over the orientations
that give the observed axis ratio (the table's bin: the same samples it was built from), q has

    mean   m_q = sqrt(A_c) E[A^-1/2]          (the relopt curve's A_c = (E[A^-1/2] / E[A^-1])^2 gives
                                               m_q = E[A^-1/2]^2 / E[A^-1] <= 1 by Cauchy-Schwarz: the estimator
                                               that minimises the mean squared relative error is biased short)
    s.d.   s_q = sqrt(A_c E[A^-1] - m_q^2)

so a blobber range is ``rho m_q`` plus a zero-mean error of ``rho s_q``: a known bias, not the [min, max]
interval as a uniform white error.  A target that turns between frames (the rendezvous targets spin at ~1 deg/s,
frames ~100 s apart) draws a fresh orientation per frame: the errors are independent from frame to frame, and
the filter takes ``rho_meas / m_q`` with 1-sigma ``rho_meas s_q / m_q^2`` (first order in s_q).

Ignored (stated): pixel sampling and the perspective of a near body (the table is orthographic); orientations
weighted uniformly on SO(3), as the table's.  Units: ratios (dimensionless); pure numpy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["range_ratio_statistics", "range_ratio_at"]


def range_ratio_statistics(samples_ratio, samples_area, ratio_lo, ratio_hi, area_curve):
    """Per bin of an area table: (mean m_q (K,), standard deviation s_q (K,)) of ``q = sqrt(A_c / A)`` over the
    bin's samples (module docstring); samples_ratio, samples_area (N,) the table's raw samples (axis ratio, A/A0);
    ratio_lo, ratio_hi (K,) bin edges (a sample at the last edge joins the last bin); area_curve (K,) A_c / A0 of
    the curve the blobber uses.  NaN in empty bins or bins without a finite curve value."""
    r = np.asarray(samples_ratio, np.float64)
    a = np.asarray(samples_area, np.float64)
    lo, hi = np.asarray(ratio_lo, np.float64), np.asarray(ratio_hi, np.float64)
    ac = np.asarray(area_curve, np.float64)
    K = lo.size
    ok = np.isfinite(r) & np.isfinite(a) & (a > 0)
    r, a = r[ok], a[ok]
    k = np.clip(np.searchsorted(np.r_[lo, hi[-1:]], r, side="right") - 1, 0, K - 1)   # as catalogs/areas.bin_table
    count = np.bincount(k, minlength=K).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        e_isqrt = np.bincount(k, a ** -0.5, minlength=K) / count
        e_inv = np.bincount(k, 1.0 / a, minlength=K) / count
        mean = np.sqrt(ac) * e_isqrt
        sd = np.sqrt(np.clip(ac * e_inv - mean ** 2, 0.0, None))
    bad = (count == 0) | ~np.isfinite(ac)
    return np.where(bad, np.nan, mean), np.where(bad, np.nan, sd)


def range_ratio_at(ratio, centres, mean, sd):
    """(m_q, s_q) at observed axis ratios (B,): linear interpolation between the centres (K,) of bins with finite
    statistics, held beyond the ends (as ``AreaTable.lookup``); NaN ratios give NaN."""
    ok = np.isfinite(mean) & np.isfinite(sd)
    x = np.asarray(ratio, np.float64)
    nan = np.where(np.isfinite(x), 0.0, np.nan)
    return np.interp(x, centres[ok], mean[ok]) + nan, np.interp(x, centres[ok], sd[ok]) + nan
