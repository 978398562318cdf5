"""Chance-match probability of an identification (dualsight, not in the reference).

Every answer of :func:`dualsight.nav.starid.identify` carries ``p_chance``: an upper bound of the
probability that observed directions unrelated to the catalog at the claimed attitude (false stars, or
true stars under a wrong attitude) verify against the catalog as well as the answer did.

Model and formula
-----------------
An answer is an attitude with ``n`` verified stars: observed directions that land within the match
radius ``r`` of a catalog star (``attitude_tolerance_rad`` with the attitude check, else the
verification tolerance) out of ``m_tot`` directions tested (every valid detection with the attitude
check, else the voters).  Under the null hypothesis the observed directions are random on the sky
relative to the catalog (isotropic and independent), and the catalog stars near the claimed pointing
are a Poisson field of density ``rho`` (stars per steradian).

1. *Hypotheses.*  A chance answer is anchored on one observed pair (p, q) whose angle matches a
   catalog pair (a, b) within the tolerance (the voting and verification rounds only ever build on
   such pairs); each such match, in either assignment (a -> p or a -> q), fixes one candidate
   attitude.  ``H = 2 * sum over the voting pairs of every round run of #{catalog pairs with
   |angle_ab - d_pq| < verify_tol}`` (the pair windows of :func:`dualsight.nav.votes.pair_windows`).
2. *One extra star.*  Under a candidate attitude, a random direction has a catalog star within ``r``
   with probability ``q = 1 - exp(-rho * 2 pi (1 - cos r))`` (Poisson: ``~ rho pi r^2``).
3. *The rest.*  The anchor pair verifies by construction; the other ``m = m_tot - 2`` directions are
   independent trials, so at least ``k = n - 2`` of them verify with probability
   ``P_tail = P[Binomial(m, q) >= k] = sum_{j >= k} C(m, j) q^j (1 - q)^(m - j)`` (summed exactly, in
   log space).
4. *Union bound* (Bonferroni) over the hypotheses: ``p_chance = min(1, H * P_tail)``.

``rho`` is the catalog density at the claimed pointing: the catalog stars (to the catalog's magnitude
limit) inside the cap that holds the case's detections, per steradian of that cap, but never below the
whole catalog's mean ``N / 4 pi`` (a chance attitude prefers dense sky, where pairs and extra matches are
both more likely).  This is the odds calculation of tetra3 (Brown; "probability of mismatch", a binomial
tail over the extracted stars with the two pattern stars taken off) and the look-elsewhere factor of
astrometry.net (Lang et al. 2010, AJ 139, 1782, Sec. 2.2: the hypotheses tried), with the hypothesis count
measured from the pair windows instead of a pattern-catalog size.

Assumptions (where the bound can fail): isotropic, independent false directions (a false star placed
on purpose, or a cluster of ghosts with the geometry of a star pattern, is not random); a Poisson catalog
locally (close doubles make a neighbour's identity *not* a chance event: that is the residual test's case,
:mod:`dualsight.nav.residual_check`); the candidate attitude known to better than ``r`` at the extra stars
(a short anchor pair lets the first extra star's position swing by ``tol * lever / baseline``; the union
bound's slack covers this in the Monte Carlo of ``tests/test_false_stars.py``, which measures the
calibration).
"""

from __future__ import annotations

import math

import numpy as np

from .votes import pair_windows

__all__ = ["pair_hypotheses", "catalog_density", "binomial_tail", "chance_probability"]

_LOG_FACT = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, 4097, dtype=np.float64)))])
"""log(j!) for j = 0 .. 4096 (the trials m are at most the observations per case, <= 1000)."""


def pair_hypotheses(d_obs: np.ndarray, case: np.ndarray, n_cases: int, catalog_angle: np.ndarray,
                    tol: float, counts: np.ndarray | None = None) -> np.ndarray:
    """Candidate attitudes of step 1: ``2 * sum`` over each case's observed pairs of the catalog pairs
    whose angle matches within ``tol``.

    d_obs : (E,) float64 observed pair angles (rad).  case : (E,) int case of each pair.
    n_cases : B.  catalog_angle : (M,) float64 catalog pair angles (rad), ascending.  tol : rad.
    counts : optional (E,) int, those numbers of catalog pairs when already known (the voting round's
        windows, when its tolerance is ``tol``: :func:`dualsight.nav.votes.vote`'s ``window_counts``);
        else they are searched here (:func:`~dualsight.nav.votes.pair_windows`).
    Returns (B,) float64.
    """
    cnt = counts if counts is not None else pair_windows(np.asarray(d_obs, np.float64), catalog_angle, float(tol))[1]
    return 2.0 * np.bincount(np.asarray(case, np.int64), weights=cnt.astype(np.float64), minlength=n_cases)


def catalog_density(cat_unit: np.ndarray, center: np.ndarray, radius: np.ndarray,
                    block: int = 250_000) -> np.ndarray:
    """Catalog stars per steradian in the cap of ``radius`` (rad) around ``center``, floored at the
    whole sky's mean ``N / (4 pi)``.

    cat_unit : (N, 3) float64 ICRS unit vectors.  center : (B, 3) unit vectors (NaN = none: NaN out).
    radius : (B,) rad, in (0, pi].  block : bound of the (cases, N) cosine table (cells).
    Returns (B,) float64 stars / sr.
    """
    N = cat_unit.shape[0]
    B = center.shape[0]
    out = np.full(B, np.nan)
    good = np.all(np.isfinite(center), axis=1) & np.isfinite(radius) & (radius > 0)
    g = np.flatnonzero(good)
    step = max(1, int(block) // max(1, N))
    for b0 in range(0, g.size, step):                                    # a handful of blocks
        sl = g[b0:b0 + step]
        inside = (center[sl] @ cat_unit.T) >= np.cos(radius[sl])[:, None]
        area = 2.0 * np.pi * (1.0 - np.cos(radius[sl]))
        out[sl] = inside.sum(axis=1) / area
    return np.maximum(out, N / (4.0 * np.pi))


def binomial_tail(m: np.ndarray, k: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``P[Binomial(m, q) >= k]``, elementwise, summed exactly in log space (no scipy).

    m, k : (B,) int trials and successes (k <= 0 gives 1, k > m gives 0); q : (B,) float64 in [0, 1].
    Returns (B,) float64.
    """
    m = np.asarray(m, np.int64)
    k = np.asarray(k, np.int64)
    q = np.asarray(q, np.float64)
    out = np.where((k <= 0) | ((k <= m) & (q >= 1.0)), 1.0, 0.0)
    run = (k > 0) & (k <= m) & (q > 0) & (q < 1.0)
    if not run.any():
        return out
    mm, kk, qq = m[run], k[run], q[run]
    j = np.arange(int(mm.max()) + 1)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        logt = (_LOG_FACT[mm][:, None] - _LOG_FACT[np.minimum(j, mm[:, None])]
                - _LOG_FACT[np.maximum(mm[:, None] - j, 0)]
                + j * np.log(qq)[:, None] + (mm[:, None] - j) * np.log1p(-qq)[:, None])
    logt = np.where((j >= kk[:, None]) & (j <= mm[:, None]), logt, -np.inf)
    top = logt.max(axis=1)
    s = np.exp(top) * np.exp(logt - np.where(np.isfinite(top), top, 0.0)[:, None]).sum(axis=1)
    out[run] = np.where(np.isfinite(top), s, 0.0)
    return np.minimum(out, 1.0)


def chance_probability(n_verified: np.ndarray, n_tested: np.ndarray, n_hypotheses: np.ndarray,
                       density_sr: np.ndarray, radius_rad: float) -> np.ndarray:
    """``p_chance = min(1, H * P[Binomial(m_tot - 2, q) >= n - 2])``, ``q = 1 - exp(-rho 2 pi (1 - cos r))``
    (module docstring: model, sources, assumptions).

    n_verified : (B,) int verified stars n of each answer.  n_tested : (B,) int directions tested
    m_tot (>= n).  n_hypotheses : (B,) float candidate attitudes H (:func:`pair_hypotheses`).
    density_sr : (B,) catalog stars per steradian rho (:func:`catalog_density`).  radius_rad : match
    radius r (rad).
    Returns (B,) float64 in [0, 1]; 1 for n <= 2 (a pair always matches some catalog pair).
    """
    n = np.asarray(n_verified, np.int64)
    m_tot = np.maximum(np.asarray(n_tested, np.int64), n)
    cap = 2.0 * math.pi * (1.0 - math.cos(float(radius_rad)))
    q = -np.expm1(-np.asarray(density_sr, np.float64) * cap)
    tail = binomial_tail(m_tot - 2, n - 2, q)
    with np.errstate(invalid="ignore"):
        p = np.minimum(1.0, np.asarray(n_hypotheses, np.float64) * tail)
    return np.where(n <= 2, 1.0, p)
