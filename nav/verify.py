"""Steps 3-5 of geometric voting: verification round, match threshold T, acceptance.

Kolomenkin et al. (2008), as the reference (McBryde & Lightsey, Secs. 3.1 and 3.3) used it:

3. **Verification.**  For each pair of identified stars (p, q) with identities (a, b), if
   ``|angle(a, b) - d_pq| < tolerance`` then p and q each get a verification vote.
4. **Match threshold.**  ``T`` = the most verification votes any star of the case received;
   ``T <= 0`` means no confident solution (reference Sec. 3.3).
5. **Acceptance.**  The stars "with a high number of votes" are confirmed and go to the attitude
   solver.  The reference does not say which counts are "high": ``accept_rule="fraction"`` accepts
   verification votes >= ``accept_fraction * T`` (and > 0); ``"clique"`` (dualsight) the largest
   mutually consistent set (:func:`dualsight.nav.cliques.greedy_clique`).  A case with fewer than
   ``min_accepted`` accepted stars is rejected.
"""

from __future__ import annotations

import numpy as np

from dualsight.scene.units import angle_between

from .cliques import greedy_clique
from .votes import ObservedPairs
from .voting_config import VotingConfig

__all__ = ["verify", "accept", "verify_accept_taichi"]


def verify(pairs: ObservedPairs, ids: np.ndarray, cat_unit: np.ndarray,
           cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 3-4: verification votes and the match threshold T.

    pairs : the observed pairs of the (B, K) star slots, angles d_pq in rad.
    ids : (B, K) int catalog rows from step 2 (-1 = unidentified).
    cat_unit : (N, 3) float64 ICRS unit vectors.  cfg : uses ``verify_tol`` (rad).
    Returns ``cons (B, K, K)`` bool symmetric, identified stars p != q with
    ``|angle(id_p, id_q) - d_pq| < verify_tol``; ``vv (B, K)`` int64 verification votes (row sums of
    ``cons``); ``T (B,)`` int64 the most votes of any star of the case (0 for an empty case).
    """
    B, K = ids.shape
    cons = _consistent_pairs(pairs, ids, cat_unit, cfg)
    vv = cons.sum(axis=2)
    T = vv.max(axis=1) if K else np.zeros(B, np.int64)
    return cons, vv, T


def verify_accept_taichi(pairs: ObservedPairs, ids: np.ndarray, top: np.ndarray, cat_unit: np.ndarray,
                         cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 3-5 (:func:`verify` then :func:`accept`) with the counting, T, acceptance and rejection in
    the Taichi kernel ``verify_accept`` of :mod:`dualsight.kernels.voting` (parallel over cases); the
    consistency of the identified pairs (catalog angles, the tolerance test) is computed here with
    numpy, as :func:`verify` does.  Returns ``vv (B, K)`` int32, ``T (B,)`` int32, ``accepted (B, K)``
    and ``reject (B,)`` bool, bit for bit those of the numpy stages.
    """
    from dualsight.kernels import voting_select as kselect

    cons = _consistent_pairs(pairs, ids, cat_unit, cfg)
    return kselect.verify_accept(cons, top, cfg.accept_rule == "clique", cfg.accept_fraction, int(cfg.min_accepted))


def _consistent_pairs(pairs: ObservedPairs, ids: np.ndarray, cat_unit: np.ndarray, cfg: VotingConfig) -> np.ndarray:
    """(B, K, K) bool symmetric: identified stars p != q with ``|angle(id_p, id_q) - d_pq| < verify_tol``."""
    B, K = ids.shape
    has = ids >= 0
    both = has[pairs.case, pairs.p] & has[pairs.case, pairs.q]
    b, p, q = pairs.case[both], pairs.p[both], pairs.q[both]
    d_cat = angle_between(cat_unit[ids[b, p]], cat_unit[ids[b, q]])   # symmetric: only p < q computed
    with np.errstate(invalid="ignore"):
        c = np.abs(d_cat - pairs.angle[both]) < cfg.verify_tol
    cons = np.zeros((B, K, K), bool)
    cons[b[c], p[c], q[c]] = True
    cons[b[c], q[c], p[c]] = True
    return cons


def accept(cons: np.ndarray, vv: np.ndarray, T: np.ndarray, top: np.ndarray,
           cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Step 5: the confirmed stars, and the cases rejected for too few of them.

    cons, vv, T : from :func:`verify` ((B, K, K) bool, (B, K) and (B,) int).
    top : (B, K) int voting-round votes of each star's identity (the clique's tie-break).
    cfg : uses ``accept_rule``, ``accept_fraction`` and ``min_accepted``.
    Returns ``accepted (B, K)`` bool and ``reject (B,)`` bool: T > 0 but fewer than ``min_accepted``
    stars accepted (the caller then reports T = 0 and no accepted star).
    """
    if cfg.accept_rule == "fraction":
        acc = (vv > 0) & (vv >= cfg.accept_fraction * T[:, None])
    else:
        acc = greedy_clique(cons, top)
    return acc, (T > 0) & (acc.sum(axis=1) < int(cfg.min_accepted))
