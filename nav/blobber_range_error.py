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

The table ignores pixel sampling and the perspective of a near body (it is orthographic), and it is conditioned on
the silhouette's exact axis ratio where the blobber only sees a measured one: a blob of ~40 pixels measures its axis
ratio so poorly that q depends on the observed ratio far more than the table says (rendered 3U CubeSat at 50 m:
-5.8 % to +3.2 % between quintiles of the observed ratio, -1.7 % on average after ``m_q``; at 2-25 m within 0.4 %).
:class:`RangeRatioCalibration` is the measured answer: q over renders through the camera's own renderer and blobber
(``jobs/kinds/rendezvous_context.blobber_calibration``), its mean and standard deviation conditioned on what the
blobber sees, the blob's summed coverage ``n_blob`` and its observed axis ratio, by Gaussian-kernel regression
(Nadaraya-Watson; Hastie, Tibshirani & Friedman, *The Elements of Statistical Learning*, 2nd ed., 2009, Sec. 6.1)
in (log10 n_blob, axis ratio).  Orientations uniform on SO(3) in both.  Units: ratios (dimensionless); pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["range_ratio_statistics", "range_ratio_at", "RangeRatioCalibration", "kernel_means"]


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


@dataclass(frozen=True)
class RangeRatioCalibration:
    """Measured blobber range ratios ``q = range_est / true range`` (M,) with what the blobber saw: ``n_blob`` (M,)
    its summed coverage (pixels) and ``ratio`` (M,) its observed axis ratio; :meth:`at` gives q's conditional mean
    and standard deviation at new observations by a Gaussian kernel of widths ``bw_log_n`` (decades of n_blob) and
    ``bw_ratio`` (module docstring).  Non-finite samples are ignored."""

    n_blob: np.ndarray
    ratio: np.ndarray
    q: np.ndarray
    bw_log_n: float = 0.15
    bw_ratio: float = 0.03
    chunk: int = 256

    def at(self, n_blob, ratio) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean (B,), standard deviation (B,), effective sample count (sum w)^2 / sum w^2 (B,)) of q at
        observations n_blob (B,) px and axis ratio (B,); NaN where an input is not finite or n_blob <= 0."""
        ok_s = np.isfinite(self.n_blob) & (self.n_blob > 0) & np.isfinite(self.ratio) & np.isfinite(self.q)
        qs = self.q[ok_s]
        m, neff = kernel_means(n_blob, ratio, self.n_blob[ok_s], self.ratio[ok_s], np.stack([qs, qs ** 2], -1),
                               self.bw_log_n, self.bw_ratio, self.chunk)
        return m[:, 0], np.sqrt(np.clip(m[:, 1] - m[:, 0] ** 2, 0.0, None)), neff


def kernel_means(n_blob, ratio, n_s: np.ndarray, ratio_s: np.ndarray, values: np.ndarray, bw_log_n: float,
                 bw_ratio: float, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Nadaraya-Watson means of the samples' ``values`` (M, k) at new blobs of summed coverage ``n_blob`` (B,) px
    and axis ratio ``ratio`` (B,): Gaussian weights of widths ``bw_log_n`` decades of coverage and ``bw_ratio`` of
    axis ratio around each (samples at coverage ``n_s`` (M,) > 0 and ratio ``ratio_s`` (M,), all finite), in chunks
    of ``chunk`` queries.  Returns (means (B, k), effective sample count (sum w)^2 / sum w^2 (B,)), NaN where an
    input is not finite or n_blob <= 0."""
    n = np.asarray(n_blob, np.float64).ravel()
    r = np.asarray(ratio, np.float64).ravel()
    ls = np.log10(np.asarray(n_s, np.float64)) / bw_log_n
    rs = np.asarray(ratio_s, np.float64) / bw_ratio
    v = np.asarray(values, np.float64).reshape(ls.size, -1)
    ok = np.isfinite(n) & (n > 0) & np.isfinite(r)
    lq = np.log10(np.where(ok, n, 1.0)) / bw_log_n
    rq = np.where(ok, r, 1.0) / bw_ratio
    means, neff = np.full((n.size, v.shape[1]), np.nan), np.full(n.size, np.nan)
    for s in range(0, n.size, chunk):
        sl = slice(s, s + chunk)
        d2 = (lq[sl, None] - ls[None]) ** 2 + (rq[sl, None] - rs[None]) ** 2
        w = np.exp(-0.5 * (d2 - d2.min(axis=1, keepdims=True)))   # rescaled per query: the ratios are the same
        sw = w.sum(1)
        means[sl] = (w @ v) / sw[:, None]
        neff[sl] = sw ** 2 / (w ** 2).sum(1)
    return np.where(ok[:, None], means, np.nan), np.where(ok, neff, np.nan)
