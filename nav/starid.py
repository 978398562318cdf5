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
choices are options of :class:`VotingConfig`:

- ``accept_rule="fraction"`` (:meth:`VotingConfig.paper`): accept the stars whose verification votes
  are >= ``accept_fraction * T`` (and > 0); ties in step 2 go to the lowest catalog row, as
  ``argmax`` (and MATLAB's ``max``) break them.
- ``accept_rule="clique"`` (:meth:`VotingConfig.robust`): accept the largest *mutually consistent*
  set found by greedy pruning (repeatedly drop the star consistent with the fewest others, until
  every remaining pair passes verification), require a unique vote maximum in step 2, drop an
  identity claimed by two observed stars, require ``min_accepted`` (3) stars, and optionally check
  the attitude against the whole catalog (``verify_attitude``).  A confident but wrong answer then
  needs a wrong set of >= 3 stars whose every pairwise angle matches the catalog.

An accepted set that fails ``min_accepted`` or the attitude check is *rejected*: the case reports
``T = 0`` (no confident solution) and no accepted star, and ``rejected`` records why T was zeroed.

Implementation: all cases at once; observed pairs come from a fixed upper-triangle table, candidate
catalog pairs from ``np.searchsorted`` on the sorted catalog angles, expanded to flat lists with the
``np.repeat`` + ``arange`` trick, and votes accumulate with ``np.bincount`` into a dense
(case, star, catalog row) table, processed in chunks of cases so memory stays bounded
(``max_vote_cells`` int64 cells, 8 bytes each, plus the candidate lists of one chunk).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .attitude import solve_identified

__all__ = ["VotingConfig", "Identification", "identify", "pair_arrays", "ACCEPT_RULES"]

ACCEPT_RULES = ("fraction", "clique")


@dataclass(frozen=True)
class VotingConfig:
    """Options of :func:`identify`.  Defaults are the reference-faithful method (:meth:`paper`).

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
    accept_rule : "fraction" (verification votes >= accept_fraction * T, and > 0) or "clique"
        (largest mutually consistent set by greedy pruning; ``accept_fraction`` is unused).
    accept_fraction : see ``accept_rule``.  The reference does not give its value; 0.5 by default.
    min_accepted : a case with fewer accepted stars is rejected (T = 0).  2 is the minimum for an
        attitude; 3 removes the confident-but-wrong two-star answers.
    verify_tolerance_rad : tolerance (rad) of the verification round; None = ``tolerance_rad``.
    verify_attitude : after voting, solve the attitude (SVD) from the accepted stars, rotate every valid
        observed star into the catalog frame and match it to the nearest catalog star within
        ``attitude_tolerance_rad``; reject the case when fewer than ``min_verified`` observed stars
        match.  Not in the reference (off in :meth:`paper`).
    attitude_tolerance_rad : match radius (rad) of the attitude check; None = 2 x ``tolerance_rad``.
    min_verified : minimum number of observed stars matched by the attitude check.
    reidentify : with ``verify_attitude``, replace the final ids by the attitude matches (this also
        identifies stars beyond ``max_stars`` or missed by voting) and accept exactly the matched stars.
    max_vote_cells : memory bound: the dense vote table of one chunk of cases holds at most this many
        int64 cells (chunk = max(1, max_vote_cells // (max_stars * N)) cases).
    """

    tolerance_rad: float = 1.5e-4
    max_stars: int = 20
    require_unique_max: bool = False
    vote_once_per_pair: bool = False
    accept_rule: str = "fraction"
    accept_fraction: float = 0.5
    min_accepted: int = 2
    verify_tolerance_rad: float | None = None
    verify_attitude: bool = False
    attitude_tolerance_rad: float | None = None
    min_verified: int = 4
    reidentify: bool = True
    max_vote_cells: int = 4_000_000

    def __post_init__(self):
        if not (np.isfinite(self.tolerance_rad) and self.tolerance_rad > 0):
            raise ValueError(f"tolerance_rad must be > 0, got {self.tolerance_rad}")
        if int(self.max_stars) < 2:
            raise ValueError(f"max_stars must be >= 2, got {self.max_stars}")
        if self.accept_rule not in ACCEPT_RULES:
            raise ValueError(f"accept_rule must be one of {ACCEPT_RULES}, got {self.accept_rule!r}")
        if not (0.0 <= self.accept_fraction <= 1.0):
            raise ValueError(f"accept_fraction must be in [0, 1], got {self.accept_fraction}")
        if int(self.min_accepted) < 2:
            raise ValueError(f"min_accepted must be >= 2 (an attitude needs 2 stars), got {self.min_accepted}")
        for name in ("verify_tolerance_rad", "attitude_tolerance_rad"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0 or None, got {v}")
        if int(self.min_verified) < 2:
            raise ValueError(f"min_verified must be >= 2, got {self.min_verified}")
        if int(self.max_vote_cells) < 1:
            raise ValueError(f"max_vote_cells must be >= 1, got {self.max_vote_cells}")

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
                    accept_rule="clique", min_accepted=2, verify_attitude=True, min_verified=4,
                    reidentify=True)
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
    vote_ids : (B, S) int32 identity assigned by the voting round (step 2), -1 = none (tie, no vote,
        duplicate, invalid or beyond ``max_stars``).
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

    Returns int64 ``i, j`` (M,) and float64 ``angle`` (M,), checked to be sorted ascending.
    """
    if pair_j is None and pair_angle is None:
        obj = pair_i
        pair_i, pair_j, pair_angle = obj.i, obj.j, obj.angle
    i = np.asarray(pair_i).astype(np.int64, copy=False)
    j = np.asarray(pair_j).astype(np.int64, copy=False)
    ang = np.asarray(pair_angle, dtype=np.float64)
    if not (i.shape == j.shape == ang.shape) or ang.ndim != 1:
        raise ValueError(f"pair arrays must be (M,) of equal length, got {i.shape}, {j.shape}, {ang.shape}")
    if ang.size > 1 and np.any(ang[1:] < ang[:-1]):
        raise ValueError("pair angles must be sorted ascending")
    return i, j, ang


# --------------------------------------------------------------------------------------- helpers


def _angles(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (rad) between (..., 3) unit vectors: atan2(|u x v|, u . v), accurate at small angles."""
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def _select_brightest(valid: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns of the first ``k <= S`` valid stars per case (``valid (B, S)``).

    Returns ``cols (B, k) int64`` (distinct columns of the S axis; after the valid ones come invalid
    columns) and ``use (B, k) bool`` (the column is valid).
    """
    order = np.argsort(~valid, axis=1, kind="stable")[:, :k]          # valid columns first, in order
    return order, np.take_along_axis(valid, order, axis=1)


def _expand_ranges(lo: np.ndarray, cnt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flatten ranges [lo_k, lo_k + cnt_k): returns (owner k, value) for every element (repeat+arange)."""
    total = int(cnt.sum())
    owner = np.repeat(np.arange(cnt.size), cnt)
    start = np.cumsum(cnt) - cnt
    val = lo[owner] + (np.arange(total) - start[owner])
    return owner, val


def _vote_chunk(d: np.ndarray, slot_p: np.ndarray, slot_q: np.ndarray, n_slots: int,
                pi: np.ndarray, pj: np.ndarray, pang: np.ndarray, n_cat: int, tol: float,
                max_candidates: int, once_per_pair: bool = False) -> np.ndarray:
    """Voting round (Kolomenkin 2008, step 1) for one chunk of cases.

    Parameters
    ----------
    d : (P,) observed pair angles (rad); slot_p, slot_q : (P,) row of each pair's stars in the table.
    n_slots : rows of the vote table (cases x stars of the chunk).
    pi, pj, pang : catalog pairs (M,), angles sorted ascending.
    n_cat : catalog size N.  tol : window half-width (rad).
    max_candidates : candidate pairs expanded at once (bounds the temporary lists).
    once_per_pair : count a catalog row at most once per observed pair (see
        ``VotingConfig.vote_once_per_pair``); otherwise every candidate pair votes (Kolomenkin 2008).

    Returns
    -------
    (n_slots, N) int64 vote table.
    """
    lo = np.searchsorted(pang, d - tol, side="right")                 # angle > d - tol
    hi = np.searchsorted(pang, d + tol, side="left")                  # angle < d + tol
    cnt = np.maximum(hi - lo, 0)
    votes = np.zeros(n_slots * n_cat, dtype=np.int64)
    csum = np.cumsum(cnt)
    # split the observed pairs into pieces of <= max_candidates candidates (usually one piece)
    n_pieces = int(csum[-1] // max_candidates) + 1 if csum.size else 0
    cuts = np.searchsorted(csum, np.arange(1, n_pieces) * max_candidates, side="right")
    edges = np.unique(np.concatenate([[0], cuts, [cnt.size]]))
    for a, b in zip(edges[:-1], edges[1:]):                           # a handful of pieces
        owner, cand = _expand_ranges(lo[a:b], cnt[a:b])
        if once_per_pair:
            # one vote per (observed pair, catalog row): sort owner * N + row and drop repeats
            # (an explicit sort: numpy 2.x's hash-based np.unique is several times slower here)
            u = np.concatenate([owner * n_cat + pi[cand], owner * n_cat + pj[cand]])
            u.sort()
            if u.size:
                u = u[np.concatenate([[True], u[1:] != u[:-1]])]
            own, row = u // n_cat, u % n_cat
            keys = np.concatenate([slot_p[a:b][own] * n_cat + row, slot_q[a:b][own] * n_cat + row])
        else:
            ca, cb = pi[cand], pj[cand]
            sp = slot_p[a:b][owner] * n_cat
            sq = slot_q[a:b][owner] * n_cat
            keys = np.concatenate([sp + ca, sp + cb, sq + ca, sq + cb])
        votes += np.bincount(keys, minlength=n_slots * n_cat)
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


def _accept_clique(cons: np.ndarray, votes: np.ndarray) -> np.ndarray:
    """Largest mutually consistent set by greedy pruning, all cases at once.

    Start from the stars with at least one verification vote; while some member is inconsistent with
    another member, drop the member consistent with the fewest members (ties: fewer voting-round
    votes, then the fainter star).  At most K iterations, each vectorised over cases.

    cons : (B, K, K) bool symmetric consistency; votes : (B, K) voting-round counts.
    Returns (B, K) bool members.
    """
    B, K, _ = cons.shape
    member = cons.any(axis=2)
    fainter = np.arange(K)[None, :]                                    # higher column = fainter
    vmax = int(votes.max()) + 1 if votes.size else 1
    for _ in range(K):
        deg = np.sum(cons & member[:, None, :], axis=2)                # consistent members
        size = member.sum(axis=1)
        bad = member & (deg < size[:, None] - 1)
        todo = bad.any(axis=1)
        if not todo.any():
            break
        key = (deg * vmax + votes) * K + (K - 1 - fainter)             # smallest = drop first
        key = np.where(member, key, np.iinfo(np.int64).max)
        drop = key.argmin(axis=1)
        rows = np.nonzero(todo)[0]
        member[rows, drop[rows]] = False
    return member


def _nearest_catalog(v_icrs: np.ndarray, cat_unit: np.ndarray, chunk_cells: int):
    """Nearest catalog row, its cosine and the second-largest cosine for (B, S, 3) ICRS vectors.

    Chunked over cases (``chunk_cells`` float64 cells of the (cases, S, N) dot table at a time).
    Returns ``idx (B, S) int64``, ``cos1 (B, S)`` and ``cos2 (B, S)`` float64.
    """
    B, S, _ = v_icrs.shape
    N = cat_unit.shape[0]
    step = max(1, chunk_cells // max(1, S * N))
    idx = np.zeros((B, S), np.int64)
    cos1 = np.full((B, S), -np.inf)
    cos2 = np.full((B, S), -np.inf)
    catT = np.ascontiguousarray(cat_unit.T)
    for b0 in range(0, B, step):                                       # a handful of chunks
        dots = v_icrs[b0:b0 + step] @ catT                              # (b, S, N)
        k = dots.argmax(axis=2)
        c1 = np.take_along_axis(dots, k[..., None], axis=2)
        np.put_along_axis(dots, k[..., None], -np.inf, axis=2)
        idx[b0:b0 + step] = k
        cos1[b0:b0 + step] = c1[..., 0]
        if N > 1:
            cos2[b0:b0 + step] = dots.max(axis=2)
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
    v = np.einsum("bji,bsj->bsi", A0, np.where(valid[..., None], obs, 0.0))   # A^T b
    idx, cos1, cos2 = _nearest_catalog(v, cat_unit, 4 * 1024 * 1024)
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
    Cost: O(pairs x candidates) for voting plus O(B x max_stars x N) for the dense vote table.
    """
    obs = np.asarray(obs, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    cat_unit = np.asarray(cat_unit, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[-1] != 3 or valid.shape != obs.shape[:2]:
        raise ValueError(f"expected obs (B,S,3) and valid (B,S), got {obs.shape} and {valid.shape}")
    if cat_unit.ndim != 2 or cat_unit.shape[1] != 3:
        raise ValueError(f"expected cat_unit (N,3), got {cat_unit.shape}")
    pi, pj, pang = pair_arrays(pair_i, pair_j, pair_angle)
    valid = valid & np.all(np.isfinite(obs), axis=-1)
    B, S, _ = obs.shape
    N = cat_unit.shape[0]
    K = min(int(cfg.max_stars), S)

    # --- the brightest K valid stars of each case, compacted to (B, K)
    cols, use = _select_brightest(valid, K)
    obs_k = np.take_along_axis(obs, cols[..., None], axis=1)
    obs_k = np.where(use[..., None], obs_k, 0.0)

    # --- observed pairs (p < q) of every case
    tp, tq = np.triu_indices(K, 1)
    pmask = use[:, tp] & use[:, tq]                                    # (B, P)
    d_all = _angles(obs_k[:, tp], obs_k[:, tq])                        # (B, P)

    # --- steps 1-2 in chunks of cases
    vote_ids = np.full((B, K), -1, np.int64)
    top = np.zeros((B, K), np.int64)
    step = max(1, int(cfg.max_vote_cells) // max(1, K * N))
    max_cand = max(1, int(cfg.max_vote_cells) // 4)
    for b0 in range(0, B, step):                                       # a handful of chunks
        b1 = min(B, b0 + step)
        bl, pk = np.nonzero(pmask[b0:b1])
        table = _vote_chunk(d_all[b0:b1][bl, pk], bl * K + tp[pk], bl * K + tq[pk], (b1 - b0) * K,
                            pi, pj, pang, N, cfg.tolerance_rad, max_cand, cfg.vote_once_per_pair)
        ids_c, top_c = _assign(table, cfg.require_unique_max)
        vote_ids[b0:b1] = ids_c.reshape(b1 - b0, K)
        top[b0:b1] = top_c.reshape(b1 - b0, K)
    vote_ids = np.where(use, vote_ids, -1)
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
        acc_k = _accept_clique(cons, top)
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
    if cfg.verify_attitude:
        run = (T > 0) & ~reject
        m, n_match = _attitude_check(obs, valid, vote_ids_s, acc_s & run[:, None], cat_unit, cfg)
        n_att = np.where(run, n_match, -1)
        fail = run & (n_match < int(cfg.min_verified))
        reject |= fail
        if cfg.reidentify:
            good = (run & ~fail)[:, None]
            ids_s = np.where(good, m, ids_s)
            acc_s = good & (m >= 0)
        acc_s &= ~reject[:, None]

    T_out = np.where(reject, 0, T)
    return Identification(
        ids=ids_s.astype(np.int32), accepted=acc_s, T=T_out.astype(np.int32),
        vote_ids=vote_ids_s.astype(np.int32), votes=top_s.astype(np.int32), verify_votes=vv_s.astype(np.int32),
        rejected=reject, n_attitude_matches=n_att.astype(np.int32))
