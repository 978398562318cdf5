"""A simultaneous band for a filter's mean NEES over a run of frames (issue 23, point 6 c).

The two-sided 95 % chi-square bounds of a mean of M approaches (:func:`dualsight.nav.relative_filter.chi2_mean_bounds`)
hold at one frame.  Held at every one of F frames, a consistent filter fails them far more often than 5 %: how
often depends on how persistent the errors are from frame to frame (``benchmarks/bench_rendezvous_nees.py
--bootstrap``: with the rendezvous presets' persistence, a consistent Gaussian filter stays inside at every one of 51-54
frames in only ~52 % of campaigns).  :func:`simultaneous_mean_bounds` widens the per-frame level until a consistent
filter with the run's own persistence stays inside at every frame with the stated probability.

Model (a Gaussian copula): each approach's normalised errors are first-order autoregressions with correlation rho per
frame, so its NEES, a chi-square(dof) at every frame, has the lag-l correlation rho^(2l) (for x ~ N(0, 1) pairs of
correlation c, corr(x^2, y^2) = c^2); the mean over the approaches keeps it.  That mean's normal score at each frame
is then a stationary Gaussian AR(1) with lag-1 correlation ``lag1`` = rho^2, and the band is the chi-square quantile
of the per-frame level a at which the largest |score| over the F frames stays below Phi^-1(1 - a / 2) with
probability ``prob``.  At ``lag1`` = 0 that is Sidak's level a = 1 - prob^(1/F); as ``lag1`` -> 1 it tends to
1 - prob, the one-frame bounds.
"""

from __future__ import annotations

from statistics import NormalDist

import numpy as np

from dualsight.nav.relative_filter import chi2_mean_bounds

BAND_SAMPLES = 20_000
"""Simulated runs behind the band: the level's own Monte Carlo spread is then ~0.15 % of probability (1 sigma,
sqrt(0.95 x 0.05 / 20,000)), a few hundredths of a NEES unit at M = 100."""


def lag1_correlation(nees: np.ndarray) -> float:
    """Frame-to-frame persistence of a run's NEES: the correlation over approaches between consecutive frames,
    averaged over the frame pairs.  nees (M, F) per approach and frame (F >= 2, M >= 3); returns a float in
    [-1, 1] (NaN pairs, where a frame's NEES is constant, are left out; NaN when none is left)."""
    nees = np.asarray(nees, np.float64)
    a, b = nees[:, :-1], nees[:, 1:]
    a = a - a.mean(0)
    b = b - b.mean(0)
    den = np.sqrt((a * a).sum(0) * (b * b).sum(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (a * b).sum(0) / den
    r = r[np.isfinite(r)]
    return float(r.mean()) if r.size else float("nan")


def _peaks(frames: int, lag1: float, samples: int, seed: int) -> np.ndarray:
    """(samples,) the largest |score| over ``frames`` frames of simulated runs of the mean NEES's normal score, a
    stationary AR(1) with lag-1 correlation ``lag1`` (clipped to [0, 1); NaN taken as 0)."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    r = float(np.clip(lag1 if np.isfinite(lag1) else 0.0, 0.0, 1.0 - 1e-12))
    rng = np.random.default_rng(seed)
    z = rng.normal(size=samples)
    peak = np.abs(z)
    s = np.sqrt(1.0 - r * r)
    for _ in range(frames - 1):                   # frames: a short recursion over whole arrays of runs
        z = r * z + s * rng.normal(size=samples)
        np.maximum(peak, np.abs(z), out=peak)
    return peak


def simultaneous_level(frames: int, lag1: float, prob: float = 0.95, samples: int = BAND_SAMPLES,
                       seed: int = 0) -> float:
    """The per-frame two-sided level a (probability outside at one frame) at which a consistent filter whose
    mean NEES has lag-1 correlation ``lag1`` from frame to frame stays inside at all ``frames`` frames with
    probability ``prob`` (module docstring: the ``prob`` quantile of the largest |score| of ``samples`` simulated
    runs, ``numpy.random.default_rng(seed)``)."""
    z_star = float(np.quantile(_peaks(frames, lag1, samples, seed), prob))
    return 2.0 * (1.0 - NormalDist().cdf(z_star))


def inside_probability(frames: int, lag1: float, level: float = 0.05, samples: int = BAND_SAMPLES,
                       seed: int = 0) -> float:
    """The probability that a consistent filter's mean NEES, lag-1 correlation ``lag1`` from frame to frame, stays
    inside its one-frame two-sided bounds of level ``level`` (0.05: the 95 % bounds) at every one of ``frames``
    frames (the simulation of :func:`simultaneous_level`)."""
    z = NormalDist().inv_cdf(1.0 - level / 2.0)
    return float(np.mean(_peaks(frames, lag1, samples, seed) <= z))


def simultaneous_mean_bounds(dof: int, runs: int, frames: int, lag1: float, prob: float = 0.95,
                             samples: int = BAND_SAMPLES, seed: int = 0) -> tuple[float, float, float]:
    """(lo, hi, a): the band for the mean of ``runs`` chi-square(``dof``) NEES values held at every one of ``frames``
    frames, and its per-frame level a (:func:`simultaneous_level`); lo, hi are
    :func:`~dualsight.nav.relative_filter.chi2_mean_bounds` at probability 1 - a."""
    a = simultaneous_level(frames, lag1, prob, samples, seed)
    lo, hi = chi2_mean_bounds(dof, runs, 1.0 - a)
    return lo, hi, a
