"""Widening (dualsight, not in the reference): vote again with fainter stars when the brightest fail.

Only the ``max_stars`` brightest detections vote (Kolomenkin's voting grows with the square of the
stars), so bright false stars (glints, debris, planets, hot clusters) can crowd the true ones out of the
voting set.  Widening votes in rounds: round 0 with the brightest block of ``max_stars`` valid stars,
and a case whose answer fails verification goes to round r with the valid stars of brightness ranks
``[r * widen_step, r * widen_step + max_stars)`` (cut at ``max_stars_total``;
:attr:`~dualsight.nav.voting_config.VotingConfig.widen_schedule`).  Every round is the whole
identification of :func:`dualsight.nav.starid.identify` (voting, verification, attitude check with
re-identification of *every* detection, residual test) on the failing cases only, so the work is at
most ``len(widen_schedule)`` rounds of one block each, whatever the number of detections.  A case keeps
the answer with the most verified stars (earlier round on a tie).

The stages here are pure functions over whole batches (no loop over cases or stars); the loop over
rounds (a handful) is in :func:`dualsight.nav.starid.identify`.
"""

from __future__ import annotations

import numpy as np

from .voting_config import VotingConfig

__all__ = ["block_voters", "needs_widening", "better_answer", "valid_rank"]


def valid_rank(valid: np.ndarray) -> np.ndarray:
    """(B, S) int64 brightness rank of each valid star among its case's valid stars (0 = brightest: the
    inputs are ordered brightest first); -1 where not valid."""
    valid = np.asarray(valid, dtype=bool)
    return np.where(valid, np.cumsum(valid, axis=1) - 1, -1)


def block_voters(valid: np.ndarray, start: int, stop: int) -> np.ndarray:
    """(B, S) bool: the valid stars of brightness ranks ``[start, stop)`` (the voters of one round).

    valid : (B, S) bool (finite, real observations), brightest first.
    """
    r = valid_rank(valid)
    return (r >= int(start)) & (r < int(stop))


def needs_widening(T: np.ndarray, n_verified: np.ndarray, cfg: VotingConfig) -> np.ndarray:
    """(B,) bool: the round's answer fails verification and the case should vote with the next block.

    T : (B,) int match threshold of the round (0 = no answer, or rejected).
    n_verified : (B,) int stars accepted by the round (after the attitude check and residual test).
    cfg : uses ``widen_min_verified`` (None = :attr:`VotingConfig.min_answer`).
    """
    need = cfg.min_answer if cfg.widen_min_verified is None else int(cfg.widen_min_verified)
    return (np.asarray(T) <= 0) | (np.asarray(n_verified) < need)


def better_answer(T_new: np.ndarray, n_new: np.ndarray, T_old: np.ndarray, n_old: np.ndarray) -> np.ndarray:
    """(b,) bool: the new round's answer replaces the kept one: it is an answer (T > 0) and verifies
    more stars than the kept answer (0 for none); a tie keeps the earlier (brighter) round."""
    n_old = np.where(np.asarray(T_old) > 0, n_old, 0)
    return (np.asarray(T_new) > 0) & (np.asarray(n_new) > n_old)
