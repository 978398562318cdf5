"""Largest mutually consistent set of nodes by greedy pruning (the robust option of geometric voting).

Used twice by :func:`dualsight.nav.starid.identify` (not in the reference, which uses plain argmax
and a vote fraction): to choose among each star's candidate identities
(:func:`dualsight.nav.candidates.assign_identities`, nodes = (star, identity)) and to accept the
identified stars (:func:`dualsight.nav.verify.accept` with ``accept_rule="clique"``, nodes = stars).
Two nodes are consistent when the catalog angle of their identities matches the observed angle of
their stars (Kolomenkin et al. 2008's verification test, step 3).  The exact maximum clique is
NP-hard; greedy pruning (drop the node consistent with the fewest others until all remaining are
mutually consistent) is a heuristic that keeps the true set when wrong nodes have fewer consistent
partners than right ones, as chance matches usually do.
"""

from __future__ import annotations

import numpy as np

__all__ = ["greedy_clique"]


def _pack_bits(x: np.ndarray) -> np.ndarray:
    """Pack the last axis (length K) of a bool array into ceil(K / 64) uint64 words (bit j = entry j)."""
    K = x.shape[-1]
    nw = -(-K // 64)
    packed = np.packbits(x, axis=-1, bitorder="little")
    out = np.zeros(x.shape[:-1] + (nw * 8,), np.uint8)
    out[..., :packed.shape[-1]] = packed
    return out.view(np.uint64)


def greedy_clique(cons: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Largest mutually consistent set by greedy pruning, all cases at once.

    Start from the nodes with at least one consistent partner.  While some member is inconsistent
    with another member: drop every member consistent with no other member (it cannot be in a set
    of two or more), or, if there is none, the single member consistent with the fewest members
    (ties: the lowest ``score``, then the highest index).  Each pass is vectorised over the cases
    not yet done (a case that is done stays done); there are at most as many passes as nodes,
    usually a few.  The consistent members of a node are counted as the popcount of its
    consistency row, bit-packed once, AND the members' bits: O(K^2 / 64) per case and pass.

    cons : (B, K, K) bool symmetric consistency (False on the diagonal).
    score : (B, K) int >= 0 tie-break (higher = keep longer), e.g. voting-round votes.
    Returns (B, K) bool members (a clique; empty or >= 2 members).
    """
    B, K, _ = cons.shape
    if K == 0:
        return np.zeros((B, 0), bool)
    score = np.asarray(score, dtype=np.int64)
    smax = int(score.max()) + 1 if score.size else 1
    later = np.arange(K)[None, :]                                      # higher index = fainter
    bits = _pack_bits(cons)                                            # (B, K, words)
    member = (bits != 0).any(axis=2)                                   # = cons.any(axis=2)
    act = np.arange(B)                                                 # cases not done yet
    for _ in range(K):
        mem = member[act]
        both = bits[act] & _pack_bits(mem)[:, None, :]
        deg = np.bitwise_count(both).sum(axis=2, dtype=np.int64)       # consistent members
        size = mem.sum(axis=1)
        todo = np.any(mem & (deg < size[:, None] - 1), axis=1)
        if not todo.any():
            break
        act, mem, deg = act[todo], mem[todo], deg[todo]
        lonely = mem & (deg == 0)
        mem &= ~lonely
        one = ~lonely.any(axis=1)                                      # cases with no lonely member
        if one.any():
            key = (deg[one] * smax + score[act[one]]) * K + (K - 1 - later)   # smallest = drop first
            key = np.where(mem[one], key, np.iinfo(np.int64).max)
            mem[np.nonzero(one)[0], key.argmin(axis=1)] = False
        member[act] = mem
    return member
