"""Star identification by geometric voting (Kolomenkin et al. 2008), batched over cases.

Kolomenkin, Pollak, Shimshoni & Lindenbaum, "Geometric voting algorithm for star trackers",
IEEE Trans. Aerosp. Electron. Syst. 44(2), 441-456 (2008), as the reference (McBryde & Lightsey,
Sec. 3.1) used it.  :func:`identify` chains one stage per module, each a pure function of arrays and
the :class:`VotingConfig`:

=====================================  ==========================================================
stage (module)                          what it does
=====================================  ==========================================================
:mod:`~dualsight.nav.pair_index`        the pair catalog as voting reads it (:class:`VotingIndex`,
                                        built once per catalog)
:mod:`~dualsight.nav.votes`             1. observed pairs, their windows of catalog pairs with
                                        ``|angle_ab - d_pq| < tolerance``, votes for both stars
:mod:`~dualsight.nav.candidates`        2. each star takes its best-voted identity
:mod:`~dualsight.nav.verify`            3. verification votes, 4. match threshold T,
                                        5. acceptance of the stars with "high" verification votes
:mod:`~dualsight.nav.attitude_check`    (option) SVD attitude from the accepted stars must land
                                        ``min_verified`` observed stars on catalog stars;
                                        re-identification from that attitude
=====================================  ==========================================================

Stages 1-5 run as Taichi kernels (:mod:`dualsight.kernels.voting`, ``engine="taichi"``, the default)
or as the numpy stages (``engine="numpy"``, the reference the kernels are tested against bit for bit);
the floating-point values the decisions read are computed by numpy in both.
:mod:`~dualsight.nav.cliques` (largest consistent set) serves the robust options of stages 2 and 5;
:mod:`~dualsight.nav.voting_config` holds :class:`VotingConfig` and its two presets, ``paper``
(reference-faithful) and ``robust`` (dualsight).  An accepted set that fails ``min_accepted`` or the
attitude check is *rejected*: the case reports ``T = 0`` (no confident solution) and no accepted
star, and ``rejected`` records why T was zeroed.

Measured reliability of both presets: ``dualsight star report`` on a ``dualsight star run`` (README,
"Measured on this machine"); speed: ``benchmarks/bench_voting.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .attitude_check import confirm_by_attitude
from .candidates import assign_identities, assign_identities_taichi
from .pair_index import VotingIndex, pair_arrays, voting_index
from .verify import accept, verify, verify_accept_taichi
from .votes import observed_pairs, vote, vote_taichi
from .voting_config import ACCEPT_RULES, VotingConfig

__all__ = ["VotingConfig", "Identification", "VotingIndex", "identify", "pair_arrays", "voting_index",
           "ACCEPT_RULES", "ENGINES"]

ENGINES = ("taichi", "numpy")
"""Implementations of steps 1-5 (:func:`identify`'s ``engine``): ``"taichi"`` (default), the kernels of
:mod:`dualsight.kernels.voting` over the whole batch; ``"numpy"``, the vectorised numpy stages, kept as
the reference the kernels are tested against bit for bit (``tests/test_voting_kernel.py``)."""


@dataclass(frozen=True)
class Identification:
    """Result of :func:`identify` for B cases of S (padded) observed stars.

    Attributes
    ----------
    ids : (B, S) int32 final catalog row of each observed star, -1 = unidentified.  Equal to
        ``vote_ids`` unless the attitude check re-identified the stars (``reidentify``).
    accepted : (B, S) bool, stars whose identity is confirmed (to pass to the attitude solver).
    T : (B,) int32 match threshold: the most verification votes of any star in the case
        (reference definition); set to 0 when the case was rejected by ``min_accepted`` or the
        attitude check.  ``T <= 0`` = no confident solution.
    vote_ids : (B, S) int32 identity assigned by step 2 (with ``candidates_per_star`` > 1 the
        tie-aware choice), -1 = none (tie, no vote, duplicate, invalid or beyond ``max_stars``).
    votes : (B, S) int32 voting-round vote count of ``vote_ids`` (0 where none).
    verify_votes : (B, S) int32 verification votes (number of other identified stars consistent).
    rejected : (B,) bool, the verification round gave T > 0 but the case was rejected.
    n_attitude_matches : (B,) int32 observed stars matched by the attitude check (-1 = check not run).
    """

    ids: np.ndarray
    accepted: np.ndarray
    T: np.ndarray
    vote_ids: np.ndarray
    votes: np.ndarray
    verify_votes: np.ndarray
    rejected: np.ndarray
    n_attitude_matches: np.ndarray



def identify(obs: np.ndarray, valid: np.ndarray, cat_unit: np.ndarray, pair_i, pair_j=None,
             pair_angle=None, cfg: VotingConfig = VotingConfig(), engine: str = "taichi") -> Identification:
    """Identify observed stars by geometric voting (Kolomenkin et al. 2008), all cases at once.

    Parameters
    ----------
    obs : (B, S, 3) float64 camera-frame unit vectors of the observed stars, brightest first (padded).
    valid : (B, S) bool, real entries of ``obs``.
    cat_unit : (N, 3) float64 ICRS unit vectors of the star catalog (row = catalog index).
    pair_i, pair_j, pair_angle : the pair catalog, (M,) int rows i < j and (M,) float64 angles (rad)
        sorted ascending; or pass one object with attributes ``i, j, angle`` as ``pair_i``, or its
        :class:`VotingIndex` (what is derived from the catalog once; for arrays or an object,
        :func:`voting_index` keeps the last few, keyed by the arrays' identity).
    cfg : :class:`VotingConfig` (angles in rad).
    engine : :data:`ENGINES`: ``"taichi"`` (Taichi CPU kernels for the vote counting, candidate
        selection and verification, parallel over cases and observed stars) or ``"numpy"`` (the
        reference stages).  Both give the same outputs bit for bit; the attitude check is numpy in both.

    Returns
    -------
    :class:`Identification` (arrays of shape (B, S) and (B,)).

    Notes
    -----
    Each case is computed independently: a batch gives the same result as each case alone.
    Invalid or non-finite entries of ``obs`` are ignored (they may hold NaN).  Only the first
    ``cfg.max_stars`` valid stars of a case vote.
    Cost: O(observed pairs x candidates per pair) for the voting round plus O(B x max_stars x N)
    for the dense vote tables (at most ``cfg.max_vote_cells`` cells at a time); the later steps
    are O(B x max_stars^2) (x ``candidates_per_star``^2), the attitude check O(B x (N + S x 40)).
    The first call on a pair catalog also builds its :class:`VotingIndex` (O(M log M), once).
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    obs = np.asarray(obs, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    cat_unit = np.asarray(cat_unit, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[-1] != 3 or valid.shape != obs.shape[:2]:
        raise ValueError(f"expected obs (B,S,3) and valid (B,S), got {obs.shape} and {valid.shape}")
    if cat_unit.ndim != 2 or cat_unit.shape[1] != 3:
        raise ValueError(f"expected cat_unit (N,3), got {cat_unit.shape}")
    index = voting_index(pair_i, pair_j, pair_angle)
    B, S, _ = obs.shape
    N = cat_unit.shape[0]
    if len(index) and (index.star_range[0] < 0 or index.star_range[1] >= N):
        raise ValueError(f"pair catalog rows must be in [0, {N}) (the star catalog's rows)")
    valid = valid & np.all(np.isfinite(obs), axis=-1)

    # the voting stars: the first max_stars valid ones of each case, in K slots
    K = min(int(cfg.max_stars), int(valid.sum(axis=1).max(initial=0)))   # padding beyond is never used
    cols = np.argsort(~valid, axis=1, kind="stable")[:, :K]             # valid columns first, in order
    use = np.take_along_axis(valid, cols, axis=1)
    obs_k = np.where(use[..., None], np.take_along_axis(obs, cols[..., None], axis=1), 0.0)

    pairs = observed_pairs(obs_k, use)
    if engine == "taichi":
        cand_ids, cand_votes = vote_taichi(pairs, use, index, N, cfg)                      # step 1
        vote_ids, top = assign_identities_taichi(cand_ids, cand_votes, pairs, cat_unit, cfg)   # step 2
        vv, T, acc_k, reject = verify_accept_taichi(pairs, vote_ids, top, cat_unit, cfg)   # steps 3-5
        vote_ids, top, vv, T = (x.astype(np.int64) for x in (vote_ids, top, vv, T))
    else:
        cand_ids, cand_votes = vote(pairs, use, index, N, cfg)                             # step 1
        vote_ids, top = assign_identities(cand_ids, cand_votes, pairs, cat_unit, cfg)      # step 2
        cons, vv, T = verify(pairs, vote_ids, cat_unit, cfg)                              # steps 3-4
        acc_k, reject = accept(cons, vv, T, top, cfg)                                     # step 5

    def scatter(x_k, fill):                                            # (B, K) slots -> (B, S) columns
        out = np.full((B, S), fill, dtype=x_k.dtype)
        out[np.arange(B)[:, None], cols] = np.where(use, x_k, fill)     # padded cols hold fill only
        return out

    vote_ids_s = scatter(vote_ids, -1)
    ids_s, acc_s, reject, n_att = confirm_by_attitude(obs, valid, vote_ids_s, scatter(acc_k & ~reject[:, None], False),
                                                      T, reject, cat_unit, cfg)
    return Identification(
        ids=ids_s.astype(np.int32), accepted=acc_s, T=np.where(reject, 0, T).astype(np.int32),
        vote_ids=vote_ids_s.astype(np.int32), votes=scatter(top, 0).astype(np.int32),
        verify_votes=scatter(vv, 0).astype(np.int32), rejected=reject, n_attitude_matches=n_att.astype(np.int32))
