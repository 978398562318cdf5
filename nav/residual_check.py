"""Residual test (dualsight, not in the reference): a wrong identity inside the tolerance must not
reach the attitude.

The attitude check (:mod:`dualsight.nav.attitude_check`) accepts any star within
``attitude_tolerance_rad`` of a catalog star; a blend (two catalog stars merged into one detection)
or a neighbour taken for the true star can sit inside that radius yet far outside the scatter of the
other stars, and pull the attitude (README quickstart, paper method, case 185: HIP 26221 taken for the
blended HIP 26224 at 20.6 arcsec while 18 other stars sit at 0.5-3 arcsec; roll error 19 arcsec
instead of ~1).  The test, per case, iterated:

1. SVD attitude from the accepted stars (Markley 1988, :func:`dualsight.nav.attitude.solve_identified`)
   and each accepted star's residual = angle between the observed direction and the catalog star
   rotated into the camera frame; ``s*`` = the star with the largest residual;
2. the attitude again *without* ``s*`` (so that an outlier cannot pull the fit towards itself and
   inflate the others' residuals), its residuals ``r_s`` (``s*`` included, predicted by the others);
   ``s*`` is rejected when ``r_s* > k * sigma``, ``k = residual_k``, with ``sigma`` the robust scatter
   of the ``n' = n - 1`` other accepted stars:

       sigma = max( median_{s != s*}(r_s) / sqrt(2 ln 2) * sqrt(2 n' / (2 n' - 3)),  residual_floor )

   For isotropic Gaussian centroid errors of sigma per axis the residual's magnitude is Rayleigh
   distributed, whose median is ``sigma sqrt(2 ln 2)`` (a MAD about the zero centre; Rousseeuw &
   Croux 1993 for the MAD as a robust scale); the second factor undoes the fit's 3 degrees of freedom
   out of the ``2 n'`` residual components of the ``n'`` fitted stars; the floor (``residual_floor``,
   from the tolerance) keeps noise-free frames, whose scatter is a fraction of an arcsecond, from
   rejecting true stars for sub-arcsecond model errors.  A true star exceeds ``k sigma`` with
   probability about ``exp(-k^2 / 2)`` (3.7e-6 for k = 5; a little more, since a star predicted by the
   others has the others' attitude error on top of its own);
3. repeat with the re-solved attitude until no star is rejected; the test runs while at least five
   stars are accepted: with three others the scatter is a median of three residuals, too noisy to
   veto a four-star answer (e.g. the paper preset's case 158, four true stars, one 0.9 px from the
   image edge: its truncated spot puts it 11.5 arcsec off, and rejecting it would leave no answer).

Before it, :func:`drop_blends` (``reject_blends``) takes out the identities that no residual can
settle: a catalog star with another catalog star closer than twice the match radius (a double the
detector merges into one blob, whose centroid may lie within the radius of either star; e.g. the
paper preset's case 163 with 11 false stars, HIP 103569/103571, 10.3 arcsec apart and of equal
brightness: the blend sits 4.7 arcsec from the identity taken, well inside the match radius, yet the
truth is the other star).  Such a star carries no reliable identity and a centroid biased by up to half
the separation.  (The residual test also rejects that one; the blend test does not depend on the
others' scatter.)

The case is rejected (T = 0) by :func:`dualsight.nav.starid.identify` when fewer than the answer's
minimum stars (:attr:`~dualsight.nav.voting_config.VotingConfig.min_answer`) remain.
"""

from __future__ import annotations

import math

import numpy as np

from dualsight.scene.units import angle_between

from .attitude import solve_identified
from .voting_config import VotingConfig

__all__ = ["residual_check", "drop_blends", "RAYLEIGH_MEDIAN"]

RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
"""Median of a Rayleigh variable with unit scale: the median residual magnitude per unit sigma per axis."""

_MIN_TESTED = 5
"""Fewest accepted stars for the test to run (the others' median of at least four)."""


def residual_check(obs: np.ndarray, ids: np.ndarray, accepted: np.ndarray, cat_unit: np.ndarray,
                   cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Iterated residual test on the accepted identities, all cases at once.

    Parameters
    ----------
    obs : (B, S, 3) float64 camera-frame unit vectors (any value where not accepted).
    ids : (B, S) int catalog rows (-1 = none).
    accepted : (B, S) bool identities used for the attitude.
    cat_unit : (N, 3) float64 ICRS unit vectors.
    cfg : uses ``residual_k`` (0 = off: the inputs come back) and ``residual_floor`` (rad).

    Returns
    -------
    accepted : (B, S) bool, without the rejected stars.
    n_rejected : (B,) int64 stars rejected per case.

    Cost: one batched SVD and a (B, S) median per iteration over the cases still rejecting (at most
    one iteration per rejected star; usually one or two).
    """
    acc = np.asarray(accepted, dtype=bool) & (np.asarray(ids) >= 0)
    B, S = acc.shape
    n_rej = np.zeros(B, np.int64)
    k = float(cfg.residual_k)
    if k <= 0 or B == 0 or S == 0:
        return acc, n_rej
    floor = float(cfg.residual_floor)
    ids = np.asarray(ids)
    act = np.flatnonzero(acc.sum(axis=1) >= _MIN_TESTED)
    for _ in range(S):                                                  # ends when no case rejects
        if act.size == 0:
            break
        a_acc = acc[act]
        a_ids = ids[act]
        a_obs = np.where(a_acc[..., None], obs[act], 0.0)
        rows = np.arange(act.size)
        r = _residuals(a_obs, a_ids, a_acc, a_acc, cat_unit)[0]
        worst = np.argmax(np.where(a_acc, r, -np.inf), axis=1)
        rest = a_acc.copy()
        rest[rows, worst] = False
        r, ok = _residuals(a_obs, a_ids, rest, a_acc, cat_unit)             # predicted by the others
        r_worst = r[rows, worst]
        others = np.where(rest, r, np.nan)
        n = rest.sum(axis=1)                                               # n' = n - 1 >= 3
        med = row_nanmedian(np.where((n >= _MIN_TESTED - 1)[:, None], others, 0.0))
        dof = np.sqrt(2.0 * n / np.maximum(2.0 * n - 3.0, 1.0))
        sigma = np.maximum(med / RAYLEIGH_MEDIAN * dof, floor)
        n = n + 1
        drop = ok & (n >= _MIN_TESTED) & (r_worst > k * sigma)
        acc[act[drop], worst[drop]] = False
        n_rej[act[drop]] += 1
        act = act[drop & (n - 1 >= _MIN_TESTED)]
    return acc, n_rej


def row_nanmedian(x: np.ndarray) -> np.ndarray:
    """``np.nanmedian(x, axis=1)`` of a (B, S) float array, without its per-call overhead: one sort (NaN
    last), then the mean of the two middle finite values of each row (NaN for a row with none)."""
    x = np.asarray(x, np.float64)
    B = x.shape[0]
    if B == 0 or x.shape[1] == 0:
        return np.full(B, np.nan)
    xs = np.sort(x, axis=1)
    n = (~np.isnan(xs)).sum(axis=1)
    rows = np.arange(B)
    lo = xs[rows, np.maximum(n - 1, 0) // 2]
    hi = xs[rows, n // 2]
    med = (lo + hi) / 2.0
    return np.where(n > 0, med, np.nan)


def _residuals(obs, ids, fit, show, cat_unit):
    """Residuals (rad, NaN outside ``show``) of the attitude fitted to the ``fit`` stars, and ok (B,)."""
    A, ok = solve_identified(obs, ids, fit, cat_unit)
    pred = np.einsum("bij,bsj->bsi", np.where(ok[:, None, None], A, np.eye(3)), cat_unit[np.where(show, ids, 0)])
    return np.where(show, angle_between(pred, obs), np.nan), ok


def drop_blends(ids: np.ndarray, accepted: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray,
                pair_angle: np.ndarray, n_cat: int, radius: float, vmag: np.ndarray | None = None,
                max_dmag: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Un-accept the identities that a close catalog double makes ambiguous.

    ids, accepted : (B, S) int catalog rows (-1 = none) and bool.
    pair_i, pair_j, pair_angle : the pair catalog ((M,) rows and angles in rad, ascending: the close
        pairs are its first entries, found by one binary search).  n_cat : N catalog stars.
    radius : rad, twice the match radius (:func:`dualsight.nav.starid.identify` passes
        ``2 * attitude_tol``, or ``2 * verify_tol`` without the attitude check).
    vmag : optional (N,) V magnitudes.  Without them, both stars of every pair closer than ``radius``
        are ambiguous.  With them, a pair whose magnitudes differ by less than ``max_dmag`` makes both
        ambiguous (the merged centroid lies between them: either identity may be the truth), while a
        pair of unequal stars makes only the fainter one ambiguous: the brighter dominates the merged
        centroid (a companion ``dm`` magnitudes fainter pulls it by ``sep / (1 + 10^(0.4 dm))``, under
        7 % of the separation for dm >= 3, 28 % for dm = 1), so its identity stands (e.g. Albireo A with
        B 2 mag fainter, 35 arcsec away, in one blob of a 40 arcsec-pixel camera).
    Returns ``accepted (B, S)`` bool and ``n_dropped (B,)`` int64.
    """
    ids = np.asarray(ids)
    acc = np.asarray(accepted, dtype=bool)
    hi = int(np.searchsorted(pair_angle, float(radius), side="left"))     # pairs with angle < radius
    pi_, pj_ = np.asarray(pair_i[:hi], np.int64), np.asarray(pair_j[:hi], np.int64)
    double = np.zeros(int(n_cat) + 1, bool)
    if vmag is None:
        double[pi_] = True
        double[pj_] = True
    else:
        vi, vj = np.asarray(vmag, np.float64)[pi_], np.asarray(vmag, np.float64)[pj_]
        similar = np.abs(vi - vj) < max_dmag
        double[pi_[similar | (vi > vj)]] = True
        double[pj_[similar | (vj >= vi)]] = True
    drop = acc & (ids >= 0) & double[np.where(ids >= 0, ids, n_cat)]
    return acc & ~drop, drop.sum(axis=1).astype(np.int64)
