"""Optional last stage of star identification (dualsight, not in the reference): the attitude check.

After voting, the attitude solved by SVD (Markley 1988, :func:`dualsight.nav.attitude.solve_identified`)
from the accepted stars must put at least ``min_verified`` observed stars within
``attitude_tolerance_rad`` of a catalog star; otherwise the case is rejected (T = 0).  With
``reidentify`` every valid observed star then takes the identity of the catalog star it lands on,
which also identifies the stars beyond ``max_stars`` or missed by voting.  A wrong attitude rarely
puts four observed stars onto catalog stars, so this removes most confident-but-wrong answers.
"""

from __future__ import annotations

import numpy as np

from .attitude import solve_identified
from .candidates import drop_duplicates
from .voting_config import VotingConfig

__all__ = ["confirm_by_attitude", "match_by_attitude"]


def confirm_by_attitude(obs: np.ndarray, valid: np.ndarray, ids: np.ndarray, accepted: np.ndarray, T: np.ndarray,
                        reject: np.ndarray, cat_unit: np.ndarray, cfg: VotingConfig):
    """The attitude check and re-identification on the voting result (when ``cfg.verify_attitude``).

    obs : (B, S, 3) float64 camera-frame unit vectors; valid : (B, S) bool (finite, real entries).
    ids, accepted : (B, S) int catalog rows (-1 = none) and bool accepted, from voting.
    T : (B,) int match threshold; reject : (B,) bool cases already rejected (both from
        :func:`dualsight.nav.verify.accept`).  Only cases with T > 0 and not rejected are checked.
    cat_unit : (N, 3) float64 ICRS unit vectors.
    cfg : uses ``verify_attitude``, ``attitude_tol`` (rad), ``min_verified``, ``reidentify`` and
        ``max_vote_cells``.
    Returns ``ids (B, S)`` int64 (the matches where re-identified), ``accepted (B, S)`` bool,
    ``reject (B,)`` bool (now also the cases with fewer than ``min_verified`` matches) and
    ``n_match (B,)`` int64 observed stars matched (-1 = check not run).  Without
    ``verify_attitude`` the inputs come back unchanged.
    """
    n_att = np.full(ids.shape[0], -1, np.int64)
    run = (T > 0) & ~reject
    if not (cfg.verify_attitude and run.any()):
        return ids, accepted, reject, n_att
    match, n_match = match_by_attitude(obs, valid, ids, accepted & run[:, None], cat_unit, cfg)
    n_att = np.where(run, n_match, -1)
    fail = run & (n_match < int(cfg.min_verified))
    reject = reject | fail
    if cfg.reidentify:
        good = (run & ~fail)[:, None]
        ids = np.where(good, match, ids)
        accepted = good & (match >= 0)
    return ids, accepted & ~reject[:, None], reject, n_att


def match_by_attitude(obs: np.ndarray, valid: np.ndarray, ids: np.ndarray, accepted: np.ndarray,
                      cat_unit: np.ndarray, cfg: VotingConfig) -> tuple[np.ndarray, np.ndarray]:
    """SVD attitude from the accepted stars, then every valid observed star matched to the nearest
    catalog star within ``cfg.attitude_tol`` (rad).

    Shapes as :func:`confirm_by_attitude`.  Returns ``match_ids (B, S)`` int64 (-1 = no match, an
    ambiguous match (two catalog stars within the radius) unless it confirms the star's accepted
    voting identity, or a catalog row matched by two observed stars) and ``n_match (B,)`` int64.
    """
    B, S, _ = obs.shape
    A, ok = solve_identified(obs, ids, accepted, cat_unit)
    A0 = np.where(ok[:, None, None], A, np.eye(3))
    v = np.where(valid[..., None], obs, 0.0) @ A0                                  # rows: A^T b
    idx = np.full((B, S), -1, np.int64)
    cos1 = np.full((B, S), -np.inf)
    cos2 = np.full((B, S), -np.inf)
    blk = max(1, int(cfg.max_vote_cells) // max(1, cat_unit.shape[0]))   # bounded (cases, N) arrays
    for b0 in range(0, B, blk):                                        # a handful of blocks
        sl = slice(b0, b0 + blk)
        idx[sl], cos1[sl], cos2[sl] = _nearest_catalog(v[sl], valid[sl], cat_unit, cfg.attitude_tol)
    c_tol = np.cos(cfg.attitude_tol)
    # an accepted voting identity that the attitude confirms is kept; any other star needs a single
    # catalog star within the radius (two, e.g. a close double, make the match ambiguous: no id)
    cos_own = np.sum(v * cat_unit[np.where(ids >= 0, ids, 0)], axis=-1)
    own = accepted & (ids >= 0) & (cos_own > c_tol)
    hit = valid & ok[:, None] & (own | ((cos1 > c_tol) & ~(cos2 > c_tol)))
    m = np.where(hit, np.where(own, ids, idx), -1)
    m = drop_duplicates(m, np.zeros_like(m))                          # equal "votes": both dropped
    return m, (m >= 0).sum(axis=1)


def _nearest_catalog(v_icrs: np.ndarray, valid: np.ndarray, cat_unit: np.ndarray, pad: float):
    """Nearest catalog row, its cosine and the second-largest cosine for (B, S, 3) ICRS unit vectors.

    Only the catalog stars inside each case's cone are compared: the cone around the mean of the
    case's valid vectors that holds them all, widened by ``pad`` (rad).  Costs O(B N) for the cone
    test plus O(B S K) for K stars per cone (tens), instead of O(B S N).

    Returns ``idx (B, S) int64`` (-1 if none), ``cos1 (B, S)`` and ``cos2 (B, S)`` float64
    (-inf where there is no first / second candidate).
    """
    B, S, _ = v_icrs.shape
    v = np.where(valid[..., None], v_icrs, 0.0)
    c = v.sum(axis=1)
    n = np.sqrt((c * c).sum(axis=-1, keepdims=True))                # np.linalg.norm's own reduction
    c = np.where(n > 0, c / np.where(n > 0, n, 1.0), _Z)
    cos_in = np.where(valid, (v @ c[:, :, None])[..., 0], 1.0).min(axis=1, initial=1.0)  # widest
    radius = np.minimum(np.arccos(np.clip(cos_in, -1.0, 1.0)) + pad, np.pi)
    near = (c @ cat_unit.T) >= np.cos(radius)[:, None]                             # (B, N)
    bi, ni = np.nonzero(near)
    counts = near.sum(axis=1)
    kc = max(2, int(counts.max()) if B else 2)
    pos = np.arange(bi.size) - (np.cumsum(counts) - counts)[bi]
    cand = np.full((B, kc), -1, np.int64)
    cand[bi, pos] = ni
    has = cand >= 0
    dots = v @ np.swapaxes(cat_unit[np.where(has, cand, 0)], 1, 2)                # (B, S, kc)
    dots = np.where(has[:, None, :], dots, -np.inf)
    k = dots.argmax(axis=2)
    cos1 = dots.max(axis=2)
    cos2 = np.partition(dots, kc - 2, axis=2)[..., kc - 2]          # the second largest (a tie of the first too)
    idx = np.where(np.isfinite(cos1), cand[np.arange(B)[:, None], k], -1)
    return idx, cos1, cos2


_Z = np.array([0.0, 0.0, 1.0])
