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
:mod:`~dualsight.nav.residual_check`    (option) blended doubles out; iterated residual test
                                        against the other stars' scatter, re-solved
:mod:`~dualsight.nav.widen`             (option) a failing case votes again with the next block
                                        of stars in brightness order (only those cases)
:mod:`~dualsight.nav.chance`            every answer's chance-match probability ``p_chance``
                                        (and, option, rejection of improbable answers)
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

from . import widen
from .attitude import solve_identified
from .attitude_check import confirm_by_attitude
from .candidates import assign_identities, assign_identities_taichi
from .chance import catalog_density, chance_probability, pair_hypotheses
from .pair_index import VotingIndex, voting_index
from .residual_check import drop_blends, residual_check
from .verify import accept, verify, verify_accept_taichi
from .votes import observed_pairs, vote, vote_taichi
from .voting_config import VotingConfig

__all__ = ["Identification", "identify", "ENGINES"]

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
        (reference definition); set to 0 when the case was rejected by ``min_accepted``, the
        attitude check, the residual test or ``max_p_chance``.  ``T <= 0`` = no confident solution.
    vote_ids : (B, S) int32 identity assigned by step 2 (with ``candidates_per_star`` > 1 the
        tie-aware choice), -1 = none (tie, no vote, duplicate, invalid or not a voter).
    votes : (B, S) int32 voting-round vote count of ``vote_ids`` (0 where none).
    verify_votes : (B, S) int32 verification votes (number of other identified stars consistent).
    rejected : (B,) bool, the verification round gave T > 0 but the case was rejected.
    n_attitude_matches : (B,) int32 observed stars matched by the attitude check, after the residual
        test (-1 = check not run).
    p_chance : (B,) float64 probability that observed directions unrelated to the catalog verify as
        well as the answer (:func:`dualsight.nav.chance.chance_probability`); NaN where no answer.
    n_rounds : (B,) int32 voting rounds run (1 without widening, :mod:`dualsight.nav.widen`).
    answer_round : (B,) int32 the round whose answer (or, without one, whose outputs) is reported.
    n_residual_rejected : (B,) int32 stars taken out by the blend and residual tests in the reported
        round (:mod:`dualsight.nav.residual_check`).

    The per-star and per-case fields other than ``p_chance`` and ``n_rounds`` are those of the
    reported round (the one with the most verified stars; round 0 when no round answers).
    """

    ids: np.ndarray
    accepted: np.ndarray
    T: np.ndarray
    vote_ids: np.ndarray
    votes: np.ndarray
    verify_votes: np.ndarray
    rejected: np.ndarray
    n_attitude_matches: np.ndarray
    p_chance: np.ndarray
    n_rounds: np.ndarray
    answer_round: np.ndarray
    n_residual_rejected: np.ndarray


_ROUND_FIELDS = ("ids", "accepted", "T", "vote_ids", "votes", "verify_votes", "rejected", "n_attitude_matches",
                 "n_residual_rejected")


def identify(obs: np.ndarray, valid: np.ndarray, cat_unit: np.ndarray, pair_i, pair_j=None,
             pair_angle=None, cfg: VotingConfig = VotingConfig(), engine: str = "taichi",
             cat_vmag: np.ndarray | None = None, chance: bool = True) -> Identification:
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
    chance : compute ``p_chance`` (False: NaN, and the hypothesis count is skipped; only when
        ``cfg.max_p_chance`` does not need it).
    cat_vmag : optional (N,) catalog V magnitudes, for the blend test (``cfg.reject_blends``): with them
        only doubles of similar brightness are ambiguous (:func:`~dualsight.nav.residual_check.drop_blends`).
    engine : :data:`ENGINES`: ``"taichi"`` (Taichi CPU kernels for the vote counting, candidate
        selection and verification, parallel over cases and observed stars) or ``"numpy"`` (the
        reference stages).  Both give the same outputs bit for bit; the attitude check, the residual
        test and the chance probability are numpy in both.

    Returns
    -------
    :class:`Identification` (arrays of shape (B, S) and (B,)).

    Notes
    -----
    Each case is computed independently: a batch gives the same result as each case alone.
    Invalid or non-finite entries of ``obs`` are ignored (they may hold NaN).  Only the first
    ``cfg.max_stars`` valid stars of a case vote (with ``cfg.first_stars``, first only that many, and the
    ``max_stars`` when that answer fails); with widening (``cfg.max_stars_total``) the cases
    that fail vote again with the next blocks (:mod:`dualsight.nav.widen`), each round the whole chain
    below on those cases only.
    Cost: O(observed pairs x candidates per pair) for the voting round plus O(B x max_stars x N)
    for the dense vote tables (at most ``cfg.max_vote_cells`` cells at a time); the later steps
    are O(B x max_stars^2) (x ``candidates_per_star``^2), the attitude check O(B x (N + S x 40));
    times the rounds run (at most ``len(cfg.widen_schedule)``).
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

    # round 0: the first max_stars valid stars vote (the reference's method)
    chance = chance or cfg.max_p_chance < 1.0
    schedule = cfg.widen_schedule
    first = schedule[0][1] if schedule[0][1] < int(cfg.max_stars) else None      # the cheaper first round
    voters0 = widen.block_voters(valid, 0, first) if first else valid
    res = _round(obs, valid, voters0, cat_unit, index, cfg, engine, cat_vmag, chance)
    res = {k: np.array(v, copy=True) for k, v in res.items()}          # no two fields share memory
    hyp = res.pop("hypotheses")
    n_rounds = np.ones(B, np.int64)
    answer_round = np.zeros(B, np.int64)
    n_valid = valid.sum(axis=1)
    for r, (start, stop) in enumerate(schedule[1:], start=1):           # widening: a handful of rounds
        # enough valid stars for a new block: two from ``start``, or (the full block after the first round)
        # more than the first round had
        more = n_valid >= start + 2 if start > 0 else n_valid > first
        todo = widen.needs_widening(res["T"], res["accepted"].sum(axis=1), cfg) & more
        if cfg.max_p_chance < 1.0:                                      # an improbable answer: widen too
            todo |= (res["T"] > 0) & ~(_chance(obs, valid, res, hyp, cat_unit, cfg) <= cfg.max_p_chance) & more
        idx = np.flatnonzero(todo)
        if idx.size == 0:
            break
        voters = widen.block_voters(valid[idx], start, stop)
        new = _round(obs[idx], valid[idx], voters, cat_unit, index, cfg, engine, cat_vmag, chance)
        hyp[idx] += new.pop("hypotheses")
        n_rounds[idx] += 1
        take = widen.better_answer(new["T"], new["accepted"].sum(axis=1), res["T"][idx],
                                   res["accepted"][idx].sum(axis=1))
        for f in _ROUND_FIELDS:
            res[f][idx[take]] = new[f][take]
        answer_round[idx[take]] = r

    p = _chance(obs, valid, res, hyp, cat_unit, cfg) if chance else np.full(B, np.nan)
    if cfg.max_p_chance < 1.0:                                          # improbable answers are rejected
        drop = (res["T"] > 0) & ~(p <= cfg.max_p_chance)
        res["rejected"] = res["rejected"] | drop
        res["T"] = np.where(drop, 0, res["T"])
        res["accepted"] = res["accepted"] & ~drop[:, None]
    p = np.where(res["T"] > 0, p, np.nan)
    return Identification(
        ids=res["ids"].astype(np.int32), accepted=res["accepted"], T=res["T"].astype(np.int32),
        vote_ids=res["vote_ids"].astype(np.int32), votes=res["votes"].astype(np.int32),
        verify_votes=res["verify_votes"].astype(np.int32), rejected=res["rejected"],
        n_attitude_matches=res["n_attitude_matches"].astype(np.int32), p_chance=p.astype(np.float64),
        n_rounds=n_rounds.astype(np.int32), answer_round=answer_round.astype(np.int32),
        n_residual_rejected=res["n_residual_rejected"].astype(np.int32))


def _round(obs: np.ndarray, valid: np.ndarray, voters: np.ndarray, cat_unit: np.ndarray, index: VotingIndex,
           cfg: VotingConfig, engine: str, cat_vmag: np.ndarray | None = None, chance: bool = True) -> dict:
    """One identification round: steps 1-5 with the first ``cfg.max_stars`` stars of ``voters``, the
    attitude check and re-identification over every ``valid`` star, the residual test.

    obs : (B, S, 3); valid, voters : (B, S) bool (voters within valid).  Returns a dict of the round's
    (B, S) ``ids``, ``accepted``, ``vote_ids``, ``votes``, ``verify_votes`` and (B,) ``T`` (0 =
    rejected), ``rejected``, ``n_attitude_matches``, ``n_residual_rejected`` and ``hypotheses``
    (float64, :func:`dualsight.nav.chance.pair_hypotheses` of the round's voting pairs).
    """
    B, S, _ = obs.shape
    N = cat_unit.shape[0]
    # the voting stars: the first max_stars voters of each case, in K slots
    K = min(int(cfg.max_stars), int(voters.sum(axis=1).max(initial=0)))   # padding beyond is never used
    cols = np.argsort(~voters, axis=1, kind="stable")[:, :K]            # voter columns first, in order
    use = np.take_along_axis(voters, cols, axis=1)
    obs_k = np.where(use[..., None], np.take_along_axis(obs, cols[..., None], axis=1), 0.0)

    pairs = observed_pairs(obs_k, use)
    windows = chance and cfg.verify_tol == cfg.tolerance_rad      # the hypotheses count the voting windows
    if engine == "taichi":
        cand_ids, cand_votes, *counts = vote_taichi(pairs, use, index, N, cfg, windows)   # step 1
        vote_ids, top = assign_identities_taichi(cand_ids, cand_votes, pairs, cat_unit, cfg)   # step 2
        vv, T, acc_k, reject = verify_accept_taichi(pairs, vote_ids, top, cat_unit, cfg)   # steps 3-5
        vote_ids, top, vv, T = (x.astype(np.int64) for x in (vote_ids, top, vv, T))
    else:
        cand_ids, cand_votes, *counts = vote(pairs, use, index, N, cfg, windows)           # step 1
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
    n_res = np.zeros(B, np.int64)
    if cfg.reject_blends:                                              # unresolvable doubles
        radius = 2.0 * (cfg.attitude_tol if cfg.verify_attitude else cfg.verify_tol)
        acc_s, n_res = drop_blends(ids_s, acc_s, index.i, index.j, index.angle, N, radius, vmag=cat_vmag,
                                   max_dmag=cfg.blend_max_dmag)
    acc_s, n_out = residual_check(obs, ids_s, acc_s, cat_unit, cfg)
    n_res = n_res + n_out
    if cfg.residual_k > 0 or cfg.reject_blends:                       # too few stars left: no answer
        fail = (T > 0) & ~reject & (n_res > 0) & (acc_s.sum(axis=1) < cfg.min_answer)
        reject = reject | fail
        acc_s &= ~reject[:, None]
        n_att = np.where(n_att >= 0, n_att - n_res, n_att)
    return dict(ids=ids_s, accepted=acc_s, T=np.where(reject, 0, T), vote_ids=vote_ids_s, votes=scatter(top, 0),
                verify_votes=scatter(vv, 0), rejected=reject, n_attitude_matches=n_att, n_residual_rejected=n_res,
                hypotheses=(pair_hypotheses(pairs.angle, pairs.case, B, index.angle, cfg.verify_tol,
                                            counts[0] if windows else None) if chance else np.zeros(B)))


def _chance(obs: np.ndarray, valid: np.ndarray, res: dict, hyp: np.ndarray, cat_unit: np.ndarray,
            cfg: VotingConfig) -> np.ndarray:
    """(B,) chance-match probability of each case's answer (:mod:`dualsight.nav.chance`; NaN = none):
    n = the accepted stars; tested = every valid star with the attitude check, else the voters; match
    radius ``attitude_tol`` with the attitude check, else ``verify_tol``; density in the cap around the
    answer's boresight that holds the case's detections."""
    B = obs.shape[0]
    p = np.full(B, np.nan)
    ans = np.flatnonzero(res["T"] > 0)
    if ans.size == 0:
        return p
    acc = res["accepted"][ans]
    ids = res["ids"][ans]
    v = valid[ans]
    A, ok = solve_identified(obs[ans], ids, acc, cat_unit)
    bore = np.where(ok[:, None], A[:, 2, :] if A.size else np.zeros((0, 3)), np.nan)   # camera z in ICRS
    off = np.where(v, np.arccos(np.clip(np.where(v, obs[ans][..., 2], 1.0), -1.0, 1.0)), 0.0)
    radius = np.maximum(off.max(axis=1, initial=0.0), 1e-3)
    rho = catalog_density(cat_unit, bore, radius, block=cfg.max_vote_cells)
    tested = v.sum(axis=1) if cfg.verify_attitude else np.minimum(v.sum(axis=1), int(cfg.max_stars))
    radius_match = cfg.attitude_tol if cfg.verify_attitude else cfg.verify_tol
    p[ans] = chance_probability(acc.sum(axis=1), tested, hyp[ans], rho, radius_match)
    return p
