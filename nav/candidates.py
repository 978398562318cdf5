"""Step 2 of geometric voting: each observed star's identity from its best-voted candidates.

Kolomenkin et al. (2008), step 2 (the reference's Sec. 3.1): each observed star takes the catalog
identity with the most votes.  Options of :class:`~dualsight.nav.voting_config.VotingConfig`
(dualsight, not in the reference): ``require_unique_max`` (a tie leaves the star unidentified, and
an identity claimed by two stars stays with the strict winner) and ``candidates_per_star`` > 1
(choose among each star's best few identities by geometric consistency, :func:`select_candidates`).
"""

from __future__ import annotations

import numpy as np

from .cliques import greedy_clique
from .votes import ObservedPairs, pair_slots
from .voting_config import VotingConfig

__all__ = ["assign_identities", "assign_identities_taichi", "select_candidates", "drop_duplicates"]


def assign_identities(cand_ids: np.ndarray, cand_votes: np.ndarray, pairs: ObservedPairs, cat_unit: np.ndarray,
                      cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Step 2: one catalog identity per observed star (or none).

    cand_ids, cand_votes : (B, K, k) int64 best-voted catalog rows and their votes, best first
        (:func:`dualsight.nav.votes.vote`; -1 / 0 = none).
    pairs : the observed pairs (their angles, rad, bound the candidates' consistency).
    cat_unit : (N, 3) float64 ICRS unit vectors of the catalog.
    cfg : uses ``require_unique_max``, ``candidates_per_star``, ``verify_tol`` (rad) and ``max_vote_cells``.
    Returns ``vote_ids (B, K)`` int64 catalog rows (-1 = unidentified) and ``top (B, K)`` int64 the
    voting-round votes of that identity (0 where none).

    Plain (reference): the top candidate; ties go to the lower catalog row.  With
    ``require_unique_max``: only a strict maximum (``cand_votes[..., 0] > cand_votes[..., 1]``).  With
    ``candidates_per_star`` = m > 1: the stars of the consistent candidate set
    (:func:`select_candidates`) take those identities, the others keep the plain (unique, if
    required) maximum; an identity both chosen geometrically and claimed by another star's plain
    maximum stays with the chosen star.
    """
    B, K, _ = cand_ids.shape
    m = int(cfg.candidates_per_star)
    ok1 = cand_votes[..., 0] > cand_votes[..., 1] if cfg.require_unique_max else cand_ids[..., 0] >= 0
    vote_ids = np.where(ok1, cand_ids[..., 0], -1)
    top = np.where(ok1, cand_votes[..., 0], 0)
    if m > 1:
        cand = np.ascontiguousarray(cand_ids[..., :m])
        votes = np.ascontiguousarray(cand_votes[..., :m])
        # cosine bounds of the observed pairs (p < q); column P (p = q, or a missing star): inf = never
        c_lo, c_hi = _pair_cosine_bounds(pairs, B, K, cfg.verify_tol)
        sel_ids = np.full((B, K), -1, np.int64)
        sel_votes = np.zeros((B, K), np.int64)
        blk = max(1, int(cfg.max_vote_cells) // max(1, (K * m) ** 2))   # bounded (cases, Km, Km) arrays
        for b0 in range(0, B, blk):                                    # a handful of blocks
            sl = slice(b0, b0 + blk)
            sel_ids[sl], sel_votes[sl] = select_candidates(cand[sl], votes[sl], c_lo[sl], c_hi[sl], cat_unit)
        chosen = sel_ids >= 0
        vote_ids = np.where(chosen, sel_ids, vote_ids)
        top = np.where(chosen, sel_votes, top)
        prio = top + chosen * (int(top.max(initial=0)) + 1)
        vote_ids = drop_duplicates(vote_ids, prio)
    if cfg.require_unique_max:
        vote_ids = drop_duplicates(vote_ids, top)
    return vote_ids, np.where(vote_ids >= 0, top, 0)


def _pair_cosine_bounds(pairs: ObservedPairs, B: int, K: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(B, K, K) float64 cosine bounds of the observed pairs, ``c_lo = cos(min(d + tol, pi))`` and
    ``c_hi = cos(d - tol)`` (2 where d <= tol); inf / 2 on the diagonal and for unused stars."""
    P = K * (K - 1) // 2
    d = pairs.angle
    c_lo = np.full((B, P + 1), np.inf)
    c_hi = np.full((B, P + 1), 2.0)
    c_lo[pairs.case, pairs.pair] = np.cos(np.minimum(d + tol, np.pi))
    c_hi[pairs.case, pairs.pair] = np.where(d > tol, np.cos(d - tol), 2.0)
    pid = pair_slots(K)
    return c_lo[:, pid], c_hi[:, pid]


def _node_cosines(cand: np.ndarray, cat_unit: np.ndarray) -> np.ndarray:
    """(b, K m, K m) float64 catalog cosines between the candidate nodes of ``cand (b, K, m)`` (NaN
    where a node has no candidate), by the one matrix product of :func:`select_candidates`."""
    B, K, m = cand.shape
    ids_n = cand.reshape(B, K * m)
    has = ids_n >= 0
    ref = np.where(has[..., None], cat_unit[np.where(has, ids_n, 0)], np.nan)
    return ref @ np.swapaxes(ref, 1, 2)


def assign_identities_taichi(cand_ids: np.ndarray, cand_votes: np.ndarray, pairs: ObservedPairs,
                             cat_unit: np.ndarray, cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`assign_identities` by the Taichi kernel ``select`` of :mod:`dualsight.kernels.voting`
    (same arguments, the same results bit for bit, as int32).  The floating-point inputs of the
    candidate cliques (the observed pairs' cosine bounds, the catalog cosines of the nodes) are
    computed here with the very numpy expressions, in the same blocks of cases, as the numpy stage;
    the kernel compares, prunes the cliques and drops duplicates, in parallel over cases."""
    from dualsight.kernels import voting_select as kselect

    B, K, _ = cand_ids.shape
    m = int(cfg.candidates_per_star)
    blocks = None
    if m > 1 and B and K:
        c_lo, c_hi = _pair_cosine_bounds(pairs, B, K, cfg.verify_tol)
        cand = np.ascontiguousarray(cand_ids[..., :m])
        blk = max(1, int(cfg.max_vote_cells) // max(1, (K * m) ** 2))   # bounded (cases, Km, Km) arrays
        blocks = ((b0, _node_cosines(cand[b0:b0 + blk], cat_unit), c_lo[b0:b0 + blk], c_hi[b0:b0 + blk])
                  for b0 in range(0, B, blk))
    return kselect.select_identities(cand_ids, cand_votes, m, cfg.require_unique_max, blocks)


def select_candidates(cand: np.ndarray, cand_votes: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray,
                      cat_unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tie-aware step 2 (dualsight): choose one of each star's candidates by geometric consistency.

    Nodes are (star, candidate identity); two nodes of different stars are consistent when the
    catalog angle of their identities matches the observed angle within the verification tolerance.
    The largest mutually consistent node set (:func:`dualsight.nav.cliques.greedy_clique`, tie-break
    by votes) holds at most one node per star; its stars take those identities.

    cand, cand_votes : (B, K, m) int64 candidate rows (-1 = none) and their votes.
    c_lo, c_hi : (B, K, K) float64 bounds per pair of stars: |d_cat - d_obs| < tol  <=>
        cos(d_obs + tol) < cos_cat < cos(d_obs - tol); ``c_lo`` = inf where the pair does not count
        (same star, unused star).
    cat_unit : (N, 3) float64 catalog unit vectors.
    Returns ``ids (B, K)`` int64 (-1 = no node chosen) and ``votes (B, K)`` int64 of the chosen candidates.
    """
    B, K, m = cand.shape
    ids_n = cand.reshape(B, K * m)
    has = ids_n >= 0
    ref = np.where(has[..., None], cat_unit[np.where(has, ids_n, 0)], np.nan)   # NaN: never consistent
    cos_cat = (ref @ np.swapaxes(ref, 1, 2)).reshape(B, K, m, K * m)
    cons = cos_cat > np.repeat(c_lo, m, axis=2)[:, :, None, :]         # bounds of (star, node) pairs
    cons &= cos_cat < np.repeat(c_hi, m, axis=2)[:, :, None, :]
    member = greedy_clique(cons.reshape(B, K * m, K * m), cand_votes.reshape(B, K * m)).reshape(B, K, m)
    k = member.argmax(axis=2)
    chosen = member.any(axis=2)
    ids = np.where(chosen, np.take_along_axis(cand, k[..., None], axis=2)[..., 0], -1)
    votes = np.where(chosen, np.take_along_axis(cand_votes, k[..., None], axis=2)[..., 0], 0)
    return ids, votes


def drop_duplicates(ids: np.ndarray, top: np.ndarray) -> np.ndarray:
    """An identity claimed by several stars of a case stays only with a strict winner by ``top``.

    ids : (B, K) int catalog rows (-1 = none).  top : (B, K) int priority (e.g. votes); with equal
    top values every claimant loses.  Returns the new ids (B, K), a copy of the same dtype.
    """
    out = ids.copy()
    b, k = np.nonzero(ids >= 0)
    if b.size < 2:
        return out
    g = b * (int(ids.max()) + 1) + ids[b, k]                            # (case, identity) groups
    t = np.asarray(top)[b, k]
    o = np.lexsort((-t, g))                                            # by group, most votes first
    gs, ts = g[o], t[o]
    first = np.ones(gs.size, bool)
    first[1:] = gs[1:] != gs[:-1]
    alone = np.ones(gs.size, bool)                                     # next entry: other group or fewer
    alone[:-1] = (gs[1:] != gs[:-1]) | (ts[1:] < ts[:-1])
    lose = o[~(first & alone)]
    out[b[lose], k[lose]] = -1
    return out
