"""Star identification by geometric voting (Kolomenkin et al. 2008), batched over cases.

Kolomenkin, Pollak, Shimshoni & Lindenbaum, "Geometric voting algorithm for star trackers",
IEEE Trans. Aerosp. Electron. Syst. 44(2), 441-456 (2008), as the reference (Sec. 3.1) used it:

1. **Voting.**  Every observed pair (p, q) with angle ``d_pq`` votes, for every catalog pair (a, b)
   with ``|angle_ab - d_pq| < tolerance``, for the identities a and b of *both* p and q.
2. **Assignment.**  Each observed star takes the catalog identity with the most votes.
3. **Verification.**  For each pair of identified stars (p, q) with identities (a, b), if
   ``|angle(a, b) - d_pq| < tolerance`` then p and q each get a verification vote.
4. **Match threshold.**  ``T`` = the most verification votes any star of the case received;
   ``T <= 0`` means no confident solution (reference Sec. 3.3).
5. **Acceptance.**  The stars "with a high number of votes" are confirmed and go to the attitude
   solver (:func:`dualsight.nav.attitude.solve_identified`).

The reference does not say how ties are broken or which verification counts are "high"; the
choices are options of :class:`VotingConfig`, grouped in two presets:

- :meth:`VotingConfig.paper` (reference-faithful): every candidate pair votes, step 2 takes the
  ``argmax`` (ties go to the lowest catalog row, as numpy's ``argmax`` and MATLAB's ``max`` break
  them), step 5 accepts the stars whose verification votes are >= ``accept_fraction * T`` (0.5) and
  > 0.  On ideal simulated fields of the reference's camera with the Hipparcos catalog to magnitude
  5.5 it reproduces the reference: about 95 % success and 0.6-1 % confident but wrong.
- :meth:`VotingConfig.robust` (dualsight): a catalog star gets at most one vote per observed pair;
  step 2 keeps each star's 3 best-voted identities and picks, among all (star, identity)
  candidates, the largest set whose every pairwise angle matches the catalog (so a tie with a
  chance coincidence is settled by geometry, not by the catalog order); a remaining star takes an
  identity only with a strict vote maximum and an identity claimed twice stays with the strict
  winner; step 5 accepts the largest mutually consistent set (greedy pruning); finally the
  attitude from the accepted stars must place at least ``min_verified`` (4) observed stars within
  ``attitude_tolerance_rad`` of a catalog star, and then every observed star is re-identified from
  that attitude.  A confident but wrong answer needs four observed stars that all land on catalog
  stars under a wrong attitude.

An accepted set that fails ``min_accepted`` or the attitude check is *rejected*: the case reports
``T = 0`` (no confident solution) and no accepted star, and ``rejected`` records why T was zeroed.

Implementation: all cases at once; observed pairs come from a fixed upper-triangle table, candidate
catalog pairs from ``np.searchsorted`` on the sorted catalog angles, expanded to flat lists with the
``np.repeat`` + ``arange`` trick, and votes accumulate with ``np.bincount`` into a dense
(case, star, catalog row) table, processed in chunks of cases so memory stays bounded
(``max_vote_cells`` int64 cells, 2 MB by default, plus the candidate lists of one chunk; the later
steps work on blocks of cases of the same size).  One vote per pair needs no sort: a catalog star
occurs for the first time in a window of pairs when its previous pair lies before the window.

Measured (2-core Xeon, numpy 2.4, 256 cases of ~13 stars, 125k-pair catalog, tolerance 31 arcsec):
paper 0.31 ms and robust 0.7 ms per case.  Simulated fields of the reference's camera (star
vectors projected, 0.1 px Gaussian centroid noise, no image rendering) with the 2617 Hipparcos
stars of Hp <= 5.5, 4096 random 1-2-3 attitudes:

=========================================  ===================  ==================
fields                                      paper: success / CW  robust
=========================================  ===================  ==================
ideal (all stars in view, no false star)    95.1 % / 0.63 %      97.9 % / 0.07 %
1-2 stars dropped, 0-3 false stars          81.5 % / 2.9 %       90.8 % / 0.07 %
=========================================  ===================  ==================

(CW = confident but wrong.  Robust's remaining CW cases have every identity right: few stars
leave the roll about the boresight above the 100 arcsec limit.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.errors import ConfigError

from .attitude import solve_identified

__all__ = ["VotingConfig", "Identification", "identify", "pair_arrays", "ACCEPT_RULES"]

ACCEPT_RULES = ("fraction", "clique")


@dataclass(frozen=True)
class VotingConfig:
    """Options of :func:`identify`.  Defaults are the reference-faithful method (:meth:`paper`).

    Invalid values raise :class:`dualsight.errors.ConfigError` (a ``ValueError``) naming
    ``voting.<field>``.

    Attributes
    ----------
    tolerance_rad : half-width (rad) of the angle window in the voting round: a catalog pair votes
        when ``|angle_ab - d_pq| < tolerance_rad``.  Should cover the error of an observed pair angle
        (about sqrt(2) x the centroid error); the 17 mm / 4.65 um camera has 56.4 arcsec pixels, so the
        default 1.5e-4 rad (31 arcsec, 0.55 px) suits ~0.1-0.2 px centroids.
    max_stars : use only the ``max_stars`` brightest valid observed stars (the first valid ones; the
        inputs are ordered brightest first) in voting and verification.
    require_unique_max : step 2 assigns an identity only when its vote count is strictly above every
        other catalog row's (a tie leaves the star unidentified, id -1), and an identity claimed by
        two observed stars stays only with the star that has strictly more votes for it.  Off: ties
        go to the lowest catalog row and duplicates are left to verification.
    vote_once_per_pair : a catalog star gets at most one vote per observed pair, however many of its
        catalog pairs fall in the window (Kolomenkin 2008 counts every candidate pair, so a star
        with many neighbours, e.g. in a cluster, collects spurious votes).  Then a star's votes are
        at most the number of its observed pairs, and the true identity reaches that bound when
        all its partners are real stars.
    candidates_per_star : 1 = Kolomenkin's step 2 (each star takes its top-voted identity).  m > 1 =
        tie-aware step 2: keep each star's m best-voted identities (ties to the lower row) and pick,
        among all (star, identity) candidates, the largest set whose every pairwise catalog angle
        matches the observed one (greedy pruning); stars outside that set keep the plain maximum.
        Sparse fields, where the true identity often ties with chance coincidences, gain most.
    accept_rule : "fraction" (verification votes >= accept_fraction * T, and > 0) or "clique"
        (largest mutually consistent set by greedy pruning; ``accept_fraction`` is unused).
    accept_fraction : see ``accept_rule``.  The reference does not give its value; 0.5 by default.
    min_accepted : a case with fewer accepted stars is rejected (T = 0).  2 is the minimum for an
        attitude; without the attitude check, 3 removes most confident-but-wrong answers.
    verify_tolerance_rad : tolerance (rad) of the verification round; None = ``tolerance_rad``.
    verify_attitude : after voting, solve the attitude (SVD) from the accepted stars, rotate every valid
        observed star into the catalog frame and match it to the nearest catalog star within
        ``attitude_tolerance_rad``; reject the case when fewer than ``min_verified`` observed stars
        match.  Not in the reference (off in :meth:`paper`).
    attitude_tolerance_rad : match radius (rad) of the attitude check; None = 2 x ``tolerance_rad``.
    min_verified : minimum number of observed stars matched by the attitude check (including the
        accepted ones): 4 = a pair needs two independent confirmations, a triple one.  3 solves a few
        more three- and four-star fields at a small risk of a wrong triple.
    reidentify : with ``verify_attitude``, replace the final ids by the attitude matches (this also
        identifies stars beyond ``max_stars`` or missed by voting) and accept exactly the matched stars.
    max_vote_cells : memory bound: the dense vote table of one chunk of cases holds at most this many
        int64 cells (chunk = max(1, max_vote_cells // (max_stars * N)) cases).
    """

    tolerance_rad: float = 1.5e-4
    max_stars: int = 20
    require_unique_max: bool = False
    vote_once_per_pair: bool = False
    candidates_per_star: int = 1
    accept_rule: str = "fraction"
    accept_fraction: float = 0.5
    min_accepted: int = 2
    verify_tolerance_rad: float | None = None
    verify_attitude: bool = False
    attitude_tolerance_rad: float | None = None
    min_verified: int = 4
    reidentify: bool = True
    max_vote_cells: int = 250_000

    def __post_init__(self):
        def bad(name, allowed):
            raise ConfigError(f"must be {allowed}, got {getattr(self, name)!r}", field=f"voting.{name}")

        def pos(name, optional=False):
            v = getattr(self, name)
            if optional and v is None:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                bad(name, "a number > 0 (rad)" + (" or None" if optional else ""))

        def integer(name, lo):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                bad(name, f"an integer >= {lo}")

        pos("tolerance_rad")
        pos("verify_tolerance_rad", optional=True)
        pos("attitude_tolerance_rad", optional=True)
        integer("max_stars", 2)
        integer("candidates_per_star", 1)
        integer("min_accepted", 2)
        integer("min_verified", 2)
        integer("max_vote_cells", 1)
        if self.accept_rule not in ACCEPT_RULES:
            bad("accept_rule", f"one of {ACCEPT_RULES}")
        if isinstance(self.accept_fraction, bool) or not (0.0 <= self.accept_fraction <= 1.0):
            bad("accept_fraction", "a number in [0, 1]")

    @property
    def verify_tol(self) -> float:
        """Effective verification tolerance (rad)."""
        return self.tolerance_rad if self.verify_tolerance_rad is None else self.verify_tolerance_rad

    @property
    def attitude_tol(self) -> float:
        """Effective match radius (rad) of the attitude check."""
        return 2.0 * self.tolerance_rad if self.attitude_tolerance_rad is None else self.attitude_tolerance_rad

    @classmethod
    def paper(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """Reference-faithful method: plain argmax, accept >= T/2, no attitude check."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=False, accept_rule="fraction",
                    accept_fraction=0.5, min_accepted=2, verify_attitude=False)
        base.update(kw)
        return cls(**base)

    @classmethod
    def robust(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """dualsight's method: unique maxima, consistent-set acceptance, >= 3 stars, attitude check."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=True, vote_once_per_pair=True,
                    candidates_per_star=3, accept_rule="clique", min_accepted=2, verify_attitude=True,
                    min_verified=4, reidentify=True)
        base.update(kw)
        return cls(**base)


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

    @property
    def confident(self) -> np.ndarray:
        """(B,) bool, T > 0."""
        return self.T > 0


def pair_arrays(pair_i, pair_j=None, pair_angle=None):
    """``(i, j, angle)`` arrays from three arrays or from one object with ``i, j, angle`` attributes.

    Returns int32 ``i, j`` (M,) and float64 ``angle`` (M,), checked to be sorted ascending.
    """
    if pair_j is None and pair_angle is None:
        obj = pair_i
        pair_i, pair_j, pair_angle = obj.i, obj.j, obj.angle
    i = np.asarray(pair_i).astype(np.int32, copy=False)
    j = np.asarray(pair_j).astype(np.int32, copy=False)
    ang = np.asarray(pair_angle, dtype=np.float64)
    if not (i.shape == j.shape == ang.shape) or ang.ndim != 1:
        raise ValueError(f"pair arrays must be (M,) of equal length, got {i.shape}, {j.shape}, {ang.shape}")
    if ang.size > 1 and np.any(ang[1:] < ang[:-1]):
        raise ValueError("pair angles must be sorted ascending")
    return i, j, ang


# --------------------------------------------------------------------------------------- helpers


def _angles(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (rad) between (..., 3) unit vectors from the chord: 2 asin(|u - v| / 2).

    Accurate to rounding for small angles (unlike acos of the dot product) and cheaper than
    atan2(|u x v|, u . v); loses precision only near pi, far outside any field of view.
    """
    w = u - v
    return 2.0 * np.arcsin(np.minimum(0.5 * np.sqrt(np.sum(w * w, axis=-1)), 1.0))


def _select_brightest(valid: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns of the first ``k <= S`` valid stars per case (``valid (B, S)``).

    Returns ``cols (B, k) int64`` (distinct columns of the S axis; after the valid ones come invalid
    columns) and ``use (B, k) bool`` (the column is valid).
    """
    order = np.argsort(~valid, axis=1, kind="stable")[:, :k]          # valid columns first, in order
    return order, np.take_along_axis(valid, order, axis=1)


def _expand_ranges(lo: np.ndarray, cnt: np.ndarray, dtype=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """Flatten ranges [lo_k, lo_k + cnt_k): returns (owner k, value) for every element (repeat+arange)."""
    total = int(cnt.sum())
    owner = np.repeat(np.arange(cnt.size, dtype=dtype), cnt)
    start = (np.cumsum(cnt) - cnt).astype(dtype, copy=False)
    val = lo.astype(dtype, copy=False)[owner] + (np.arange(total, dtype=dtype) - start[owner])
    return owner, val


def _key_dtype(n_max: int):
    """Smallest of int32/int64 that holds integers up to ``n_max``."""
    return np.int32 if n_max < np.iinfo(np.int32).max else np.int64


def _previous_occurrence(pi: np.ndarray, pj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each catalog pair m and each of its stars, the index of the previous pair (in the
    catalog's angle order) that holds the same star, -1 if none.

    In a window [lo, hi) of pairs, star ``pi[m]`` occurs for the first time at m exactly when
    ``prev_i[m] < lo``: this de-duplicates votes without sorting the candidates.  O(M log M) once
    per call (one sort of the 2M endpoints by star; ~4 ms for 126k pairs).
    Returns ``prev_i, prev_j`` (M,) int64.
    """
    star = np.stack([pi, pj], axis=1).ravel().astype(np.int64)         # entry 2m, 2m + 1
    E = star.size
    # by star, then by entry: a value sort of star * E + entry (~3x faster than a stable argsort)
    s, order = np.divmod(np.sort(star * E + np.arange(E)), E)
    prev_sorted = np.full(star.size, -1, np.int64)
    if star.size > 1:
        prev_sorted[1:] = np.where(s[1:] == s[:-1], order[:-1] // 2, -1)
    prev = np.empty(star.size, np.int64)
    prev[order] = prev_sorted
    return prev[0::2], prev[1::2]


def _vote_chunk(d: np.ndarray, slot_p: np.ndarray, slot_q: np.ndarray, n_slots: int,
                pi: np.ndarray, pj: np.ndarray, pang: np.ndarray, n_cat: int, tol: float,
                max_candidates: int, prev: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Voting round (Kolomenkin 2008, step 1) for one chunk of cases.

    Parameters
    ----------
    d : (P,) observed pair angles (rad); slot_p, slot_q : (P,) row of each pair's stars in the table.
    n_slots : rows of the vote table (cases x stars of the chunk).
    pi, pj, pang : catalog pairs (M,), angles sorted ascending.
    n_cat : catalog size N.  tol : window half-width (rad).
    max_candidates : candidate pairs expanded at once (bounds the temporary lists).
    prev : None = every candidate pair votes for both its stars (Kolomenkin 2008); or the output of
        :func:`_previous_occurrence`, to count a catalog row at most once per observed pair
        (``VotingConfig.vote_once_per_pair``).

    Returns
    -------
    (n_slots, N) int64 vote table.
    """
    lo = np.searchsorted(pang, d - tol, side="right")                 # angle > d - tol
    hi = np.searchsorted(pang, d + tol, side="left")                  # angle < d + tol
    cnt = np.maximum(hi - lo, 0)
    n_cells = n_slots * n_cat
    kt = _key_dtype(max(n_cells, pang.size))
    slot_p = (slot_p * n_cat).astype(kt)
    slot_q = (slot_q * n_cat).astype(kt)
    # split the observed pairs into pieces of <= max_candidates candidates (usually one piece)
    csum = np.cumsum(cnt)
    n_pieces = int(csum[-1] // max_candidates) + 1 if csum.size else 0
    cuts = np.searchsorted(csum, np.arange(1, n_pieces) * max_candidates, side="right")
    edges = np.unique(np.concatenate([[0], cuts, [cnt.size]]))
    votes = None
    for a, b in zip(edges[:-1], edges[1:]):                           # a handful of pieces
        owner, cand = _expand_ranges(lo[a:b], cnt[a:b], kt)
        ca, cb = pi[cand], pj[cand]
        sp = slot_p[a:b][owner]
        sq = slot_q[a:b][owner]
        if prev is not None:
            # one vote per (observed pair, catalog row): keep an endpoint only at its first
            # occurrence in the window, i.e. when its previous pair lies before the window start
            start = lo[a:b].astype(kt, copy=False)[owner]
            ka = prev[0][cand] < start
            kb = prev[1][cand] < start
            keys = np.concatenate([(sp + ca)[ka], (sq + ca)[ka], (sp + cb)[kb], (sq + cb)[kb]])
        else:
            keys = np.concatenate([sp + ca, sp + cb, sq + ca, sq + cb])
        v = np.bincount(keys, minlength=n_cells)
        votes = v if votes is None else votes + v
    if votes is None:
        votes = np.zeros(n_cells, np.int64)
    return votes.reshape(n_slots, n_cat)


def _assign(votes: np.ndarray, unique: bool) -> tuple[np.ndarray, np.ndarray]:
    """Step 2: identity with the most votes per row of ``votes (R, N)`` (modified in place).

    Returns ``ids (R,) int64`` (-1 if no vote, or a tie when ``unique``) and ``top (R,)`` vote counts.
    """
    r = np.arange(votes.shape[0])
    best = votes.argmax(axis=1)                                       # ties -> lowest catalog row
    top = votes[r, best]
    ids = np.where(top > 0, best, -1)
    if unique:
        votes[r, best] = -1
        second = votes.max(axis=1)
        votes[r, best] = top
        ids = np.where(top > second, ids, -1)
    return ids, np.where(ids >= 0, top, 0)


def _drop_duplicates(ids: np.ndarray, top: np.ndarray) -> np.ndarray:
    """An identity claimed by several stars of a case stays only with a strict vote winner.

    ids, top : (B, K).  Returns the new ids (B, K).
    """
    same = (ids[:, :, None] == ids[:, None, :]) & (ids[:, :, None] >= 0)
    K = ids.shape[1]
    same &= ~np.eye(K, dtype=bool)
    loses = np.any(same & (top[:, None, :] >= top[:, :, None]), axis=2)
    return np.where(loses, -1, ids)


def _consistency(obs_k: np.ndarray, ids: np.ndarray, cat_unit: np.ndarray, tol: float) -> np.ndarray:
    """Step 3: (B, K, K) bool, identified stars p != q with |angle(id_p, id_q) - d_pq| < tol."""
    has = ids >= 0
    ref = cat_unit[np.where(has, ids, 0)]
    d_obs = _angles(obs_k[:, :, None, :], obs_k[:, None, :, :])
    d_cat = _angles(ref[:, :, None, :], ref[:, None, :, :])
    K = ids.shape[1]
    with np.errstate(invalid="ignore"):
        c = np.abs(d_cat - d_obs) < tol
    return c & has[:, :, None] & has[:, None, :] & ~np.eye(K, dtype=bool)


def _accept_fraction(vv: np.ndarray, T: np.ndarray, frac: float) -> np.ndarray:
    """Stars with verification votes >= frac * T and > 0.  vv (B, K), T (B,)."""
    return (vv > 0) & (vv >= frac * T[:, None])


def _greedy_clique(cons: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Largest mutually consistent set by greedy pruning, all cases at once.

    Start from the nodes with at least one consistent partner.  While some member is inconsistent
    with another member: drop every member consistent with no other member (it cannot be in a set
    of two or more), or, if there is none, the single member consistent with the fewest members
    (ties: the lowest ``score``, then the highest index).  Each pass is vectorised over cases;
    there are at most as many passes as nodes, usually a few.

    cons : (B, K, K) bool symmetric consistency (False on the diagonal).
    score : (B, K) int >= 0 tie-break (higher = keep longer), e.g. voting-round votes.
    Returns (B, K) bool members (a clique; empty or >= 2 members).
    """
    B, K, _ = cons.shape
    member = cons.any(axis=2)
    score = np.asarray(score, dtype=np.int64)
    smax = int(score.max()) + 1 if score.size else 1
    later = np.arange(K)[None, :]                                      # higher index = fainter
    for _ in range(K):
        deg = np.sum(cons & member[:, None, :], axis=2)                # consistent members
        size = member.sum(axis=1)
        todo = np.any(member & (deg < size[:, None] - 1), axis=1)
        if not todo.any():
            break
        lonely = member & (deg == 0) & todo[:, None]
        member &= ~lonely
        one = todo & ~lonely.any(axis=1)                               # cases with no lonely member
        if one.any():
            key = (deg * smax + score) * K + (K - 1 - later)           # smallest = drop first
            key = np.where(member, key, np.iinfo(np.int64).max)
            rows = np.nonzero(one)[0]
            member[rows, key[rows].argmin(axis=1)] = False
    return member


def _top_candidates(votes: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``m`` catalog rows with the most votes per row of ``votes (R, N)`` (restored on return).

    ``m`` passes of argmax, masking each winner (ties go to the lower catalog row, as ``argmax``).
    Returns ``ids (R, m) int64`` (-1 where the vote count is 0) and ``counts (R, m) int64``, best first.
    """
    R, N = votes.shape
    r = np.arange(R)
    ids = np.full((R, m), -1, np.int64)
    cnt = np.zeros((R, m), np.int64)
    taken = []
    for k in range(min(m, N)):                                         # m passes (m is small)
        best = votes.argmax(axis=1)
        c = votes[r, best]
        ids[:, k] = np.where(c > 0, best, -1)
        cnt[:, k] = c
        votes[r, best] = -1                                            # mask the winner
        taken.append(best)
    for k, best in enumerate(taken):                                   # restore
        votes[r, best] = cnt[:, k]
    return ids, np.where(ids >= 0, cnt, 0)


def _select_candidates(obs_k: np.ndarray, cand: np.ndarray, cand_votes: np.ndarray,
                       cat_unit: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Tie-aware step 2 (dualsight): choose one of each star's candidates by geometric consistency.

    Nodes are (star, candidate identity); two nodes of different stars are consistent when the
    catalog angle of their identities matches the observed angle within ``tol``.  The largest
    mutually consistent node set (:func:`_greedy_clique`, tie-break by votes) holds at most one node
    per star; its stars take those identities.

    obs_k : (B, K, 3); cand, cand_votes : (B, K, m) from :func:`_top_candidates`.
    Returns ``ids (B, K)`` (-1 = no node chosen) and ``votes (B, K)`` of the chosen candidates.
    """
    B, K, m = cand.shape
    ids_n = cand.reshape(B, K * m)
    has = ids_n >= 0
    star = np.repeat(np.arange(K), m)
    ref = cat_unit[np.where(has, ids_n, 0)]
    # |d_cat - d_obs| < tol  <=>  cos(d_obs + tol) < cos_cat < cos(d_obs - tol): bounds per star pair
    d_obs = _angles(obs_k[:, :, None, :], obs_k[:, None, :, :])
    c_lo = np.cos(np.minimum(d_obs + tol, np.pi))[:, star][:, :, star]
    c_hi = np.where(d_obs > tol, np.cos(d_obs - tol), 2.0)[:, star][:, :, star]
    cos_cat = ref @ np.swapaxes(ref, 1, 2)
    cons = (cos_cat > c_lo) & (cos_cat < c_hi) & has[:, :, None] & has[:, None, :]
    cons &= star[:, None] != star[None, :]
    member = _greedy_clique(cons, cand_votes.reshape(B, K * m)).reshape(B, K, m)
    k = member.argmax(axis=2)
    chosen = member.any(axis=2)
    ids = np.where(chosen, np.take_along_axis(cand, k[..., None], axis=2)[..., 0], -1)
    votes = np.where(chosen, np.take_along_axis(cand_votes, k[..., None], axis=2)[..., 0], 0)
    return ids, votes


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
    n = np.linalg.norm(c, axis=-1, keepdims=True)
    c = np.where(n > 0, c / np.where(n > 0, n, 1.0), np.array([0.0, 0.0, 1.0]))
    cos_in = np.where(valid, (v @ c[:, :, None])[..., 0], 1.0).min(axis=1, initial=1.0)  # widest
    radius = np.minimum(np.arccos(np.clip(cos_in, -1.0, 1.0)) + pad, np.pi)
    near = (c @ cat_unit.T) >= np.cos(radius)[:, None]                             # (B, N)
    bi, ni = np.nonzero(near)
    counts = near.sum(axis=1)
    kc = max(2, int(counts.max()) if B else 2)
    pos = np.arange(bi.size) - (np.cumsum(counts) - counts)[bi]
    cand = np.full((B, kc), -1, np.int64)
    cand[bi, pos] = ni
    dots = v @ np.swapaxes(cat_unit[np.where(cand >= 0, cand, 0)], 1, 2)          # (B, S, kc)
    dots = np.where((cand >= 0)[:, None, :], dots, -np.inf)
    k = dots.argmax(axis=2)
    cos1 = np.take_along_axis(dots, k[..., None], axis=2)[..., 0]
    np.put_along_axis(dots, k[..., None], -np.inf, axis=2)
    cos2 = dots.max(axis=2)
    idx = np.where(np.isfinite(cos1), np.take_along_axis(cand, k, axis=1), -1)
    return idx, cos1, cos2


def _attitude_check(obs, valid, ids, accepted, cat_unit, cfg: VotingConfig):
    """Optional final check (dualsight, not in the reference): SVD attitude from the accepted stars,
    then every valid observed star is matched to the nearest catalog star within ``attitude_tol``.

    Returns ``match_ids (B, S)`` (-1 = no match, an ambiguous match (two catalog stars within the
    radius) unless it confirms the star's accepted voting identity, or a catalog row matched by two
    observed stars) and ``n_match (B,)``.
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
    m = _drop_duplicates(m, np.zeros_like(m))                          # equal "votes": both dropped
    return m, (m >= 0).sum(axis=1)


# --------------------------------------------------------------------------------------- main


def identify(obs: np.ndarray, valid: np.ndarray, cat_unit: np.ndarray, pair_i, pair_j=None,
             pair_angle=None, cfg: VotingConfig = VotingConfig()) -> Identification:
    """Identify observed stars by geometric voting (Kolomenkin et al. 2008), all cases at once.

    Parameters
    ----------
    obs : (B, S, 3) camera-frame unit vectors of the observed stars, brightest first (padded).
    valid : (B, S) bool, real entries of ``obs``.
    cat_unit : (N, 3) ICRS unit vectors of the star catalog (row = catalog index).
    pair_i, pair_j, pair_angle : the pair catalog, (M,) int rows i < j and (M,) float64 angles (rad)
        sorted ascending; or pass one object with attributes ``i, j, angle`` as ``pair_i``.
    cfg : :class:`VotingConfig`.

    Returns
    -------
    :class:`Identification` (arrays of shape (B, S) and (B,)).

    Notes
    -----
    Each case is computed independently: a batch gives the same result as each case alone.
    Invalid or non-finite entries of ``obs`` are ignored (they may hold NaN).
    Cost: O(observed pairs x candidates per pair) for the voting round plus O(B x max_stars x N)
    for the dense vote tables (one chunk of ``cfg.max_vote_cells`` cells at a time); the later steps
    are O(B x max_stars^2) (x ``candidates_per_star``^2), the attitude check O(B x (N + S x 40)).
    Measured on 2 cores, 256 cases of ~13 stars, ~126k pairs: see the module docstring.
    """
    obs = np.asarray(obs, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    cat_unit = np.asarray(cat_unit, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[-1] != 3 or valid.shape != obs.shape[:2]:
        raise ValueError(f"expected obs (B,S,3) and valid (B,S), got {obs.shape} and {valid.shape}")
    if cat_unit.ndim != 2 or cat_unit.shape[1] != 3:
        raise ValueError(f"expected cat_unit (N,3), got {cat_unit.shape}")
    pi, pj, pang = pair_arrays(pair_i, pair_j, pair_angle)
    B, S, _ = obs.shape
    N = cat_unit.shape[0]
    if pi.size and (min(pi.min(), pj.min()) < 0 or max(pi.max(), pj.max()) >= N):
        raise ValueError(f"pair catalog rows must be in [0, {N}) (the star catalog's rows)")
    valid = valid & np.all(np.isfinite(obs), axis=-1)
    K = min(int(cfg.max_stars), int(valid.sum(axis=1).max(initial=0)))   # padding beyond is never used

    # --- the brightest K valid stars of each case, compacted to (B, K)
    cols, use = _select_brightest(valid, K)
    obs_k = np.take_along_axis(obs, cols[..., None], axis=1)
    obs_k = np.where(use[..., None], obs_k, 0.0)

    # --- observed pairs (p < q) of every case
    tp, tq = np.triu_indices(K, 1)
    pmask = use[:, tp] & use[:, tq]                                    # (B, P)
    d_all = _angles(obs_k[:, tp], obs_k[:, tq])                        # (B, P)

    # --- steps 1-2 in chunks of cases
    m = int(cfg.candidates_per_star)
    vote_ids = np.full((B, K), -1, np.int64)
    top = np.zeros((B, K), np.int64)
    cand = np.full((B, K, m), -1, np.int64)
    cand_votes = np.zeros((B, K, m), np.int64)
    step = max(1, int(cfg.max_vote_cells) // max(1, K * N))
    max_cand = max(1, int(cfg.max_vote_cells) // 4)
    prev = _previous_occurrence(pi, pj) if cfg.vote_once_per_pair else None
    for b0 in range(0, B, step):                                       # a handful of chunks
        b1 = min(B, b0 + step)
        bl, pk = np.nonzero(pmask[b0:b1])
        table = _vote_chunk(d_all[b0:b1][bl, pk], bl * K + tp[pk], bl * K + tq[pk], (b1 - b0) * K,
                            pi, pj, pang, N, cfg.tolerance_rad, max_cand, prev)
        if m > 1:
            c_ids, c_cnt = _top_candidates(table, m + 1)                # one more to detect ties
            cand[b0:b1] = c_ids[:, :m].reshape(b1 - b0, K, m)
            cand_votes[b0:b1] = c_cnt[:, :m].reshape(b1 - b0, K, m)
            unique = c_cnt[:, 0] > c_cnt[:, 1]
            ok1 = unique if cfg.require_unique_max else c_ids[:, 0] >= 0
            ids_c = np.where(ok1, c_ids[:, 0], -1)
            top_c = np.where(ok1, c_cnt[:, 0], 0)
        else:
            ids_c, top_c = _assign(table, cfg.require_unique_max)
        vote_ids[b0:b1] = ids_c.reshape(b1 - b0, K)
        top[b0:b1] = top_c.reshape(b1 - b0, K)
    vote_ids = np.where(use, vote_ids, -1)
    if m > 1:
        # tie-aware assignment: stars in the consistent candidate set take those identities,
        # the others keep the plain (unique, if required) maximum
        cand = np.where(use[..., None], cand, -1)
        sel_ids = np.full((B, K), -1, np.int64)
        sel_votes = np.zeros((B, K), np.int64)
        blk = max(1, int(cfg.max_vote_cells) // max(1, (K * m) ** 2))   # bounded (cases, Km, Km) arrays
        for b0 in range(0, B, blk):                                    # a handful of blocks
            sel_ids[b0:b0 + blk], sel_votes[b0:b0 + blk] = _select_candidates(
                obs_k[b0:b0 + blk], cand[b0:b0 + blk], cand_votes[b0:b0 + blk], cat_unit, cfg.verify_tol)
        chosen = sel_ids >= 0
        vote_ids = np.where(chosen, sel_ids, vote_ids)
        top = np.where(chosen, sel_votes, top)
        # an identity both chosen geometrically and claimed by another star's plain maximum stays
        # with the chosen star
        prio = top + chosen * (int(top.max(initial=0)) + 1)
        vote_ids = _drop_duplicates(vote_ids, prio)
    if cfg.require_unique_max:
        vote_ids = _drop_duplicates(vote_ids, top)
    top = np.where(vote_ids >= 0, top, 0)

    # --- step 3: verification; step 4: match threshold
    cons = _consistency(obs_k, vote_ids, cat_unit, cfg.verify_tol)
    vv = cons.sum(axis=2)
    T = vv.max(axis=1) if K else np.zeros(B, np.int64)

    # --- step 5: acceptance
    if cfg.accept_rule == "fraction":
        acc_k = _accept_fraction(vv, T, cfg.accept_fraction)
    else:
        acc_k = _greedy_clique(cons, top)
    reject = (T > 0) & (acc_k.sum(axis=1) < int(cfg.min_accepted))

    # --- scatter back to (B, S)
    rows = np.arange(B)[:, None]

    def scatter(x_k, fill):
        out = np.full((B, S), fill, dtype=x_k.dtype)
        out[rows, cols] = np.where(use, x_k, fill)                      # padded cols hold fill only
        return out

    vote_ids_s = scatter(vote_ids, -1)
    top_s = scatter(top, 0)
    vv_s = scatter(vv, 0)
    acc_s = scatter(acc_k & ~reject[:, None], False)
    ids_s = vote_ids_s.copy()
    n_att = np.full(B, -1, np.int64)

    # --- optional attitude check (dualsight)
    run = (T > 0) & ~reject
    if cfg.verify_attitude and run.any():
        match, n_match = _attitude_check(obs, valid, vote_ids_s, acc_s & run[:, None], cat_unit, cfg)
        n_att = np.where(run, n_match, -1)
        fail = run & (n_match < int(cfg.min_verified))
        reject |= fail
        if cfg.reidentify:
            good = (run & ~fail)[:, None]
            ids_s = np.where(good, match, ids_s)
            acc_s = good & (match >= 0)
        acc_s &= ~reject[:, None]

    T_out = np.where(reject, 0, T)
    return Identification(
        ids=ids_s.astype(np.int32), accepted=acc_s, T=T_out.astype(np.int32),
        vote_ids=vote_ids_s.astype(np.int32), votes=top_s.astype(np.int32), verify_votes=vv_s.astype(np.int32),
        rejected=reject, n_attitude_matches=n_att.astype(np.int32))
