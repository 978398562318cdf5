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

Implementation: all cases at once, no Python loop over cases, stars or pairs.  Everything that
depends on the pair catalog alone (interleaved star lists, the previous-occurrence table of the
one-vote-per-pair rule, range checks) is a :class:`VotingIndex`, built once per catalog and cached
(:func:`voting_index`).  Candidate catalog pairs come from ``np.searchsorted`` (sorted keys) on the
sorted catalog angles; each observed star's row of votes is counted from its pairs' windows of
catalog stars, read as fixed-length tiles (2-D gathers from a strided view) and counted with
``np.bincount`` into dense (stars, catalog row) tables of a few rows at a time (row-major keys,
tables that stay in cache), bounded by ``max_vote_cells``.  One vote per pair needs no sort: a
catalog star occurs for the first time in a window of pairs when its previous pair lies before the
window.  The later steps work on the observed pairs that exist (bit-packed consistency rows for the
greedy set search).  See ``benchmarks/bench_voting.py``.

Measured (2-core Xeon VM, numpy 2.4, one process; ``benchmarks/bench_voting.py``): 256 simulated
cases of the star preset (~11 stars, 2867-star / 138k-pair catalog, 10 arcsec): paper 0.12 ms and
robust 0.25 ms per case; 32 frames on the V 7.0 catalog (15.6k stars / 2.0M pairs, 25 stars,
20 arcsec): paper 6 ms and robust 8.5 ms per frame, plus ~0.4 s once per catalog for the index.

Simulated fields of the reference's camera (star vectors projected, 0.1 px Gaussian centroid noise,
no image rendering) with the 2617 Hipparcos stars of Hp <= 5.5, 4096 random 1-2-3 attitudes:

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

import threading
from dataclasses import dataclass

import numpy as np

from dualsight.errors import ConfigError

from .attitude import solve_identified

__all__ = ["VotingConfig", "Identification", "VotingIndex", "identify", "pair_arrays", "voting_index",
           "ACCEPT_RULES"]

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
    max_vote_cells : memory bound: a dense vote table holds at most this many int64 cells (tables
        are of max(1, min(max_vote_cells, 262144) // W) observed stars, W = N + 1 rounded up to 64),
        at most this many catalog stars are expanded at once (with 262144, or one tile), and the
        later steps work on blocks of cases of about this size.
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
    s = w[..., 0] * w[..., 0]                   # np.sum(w * w, axis=-1) bit for bit (same order), 3x
    s += w[..., 1] * w[..., 1]                  # faster than numpy's reduction over a 3-long axis
    s += w[..., 2] * w[..., 2]
    return 2.0 * np.arcsin(np.minimum(0.5 * np.sqrt(s), 1.0))


def _select_brightest(valid: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns of the first ``k <= S`` valid stars per case (``valid (B, S)``).

    Returns ``cols (B, k) int64`` (distinct columns of the S axis; after the valid ones come invalid
    columns) and ``use (B, k) bool`` (the column is valid).
    """
    order = np.argsort(~valid, axis=1, kind="stable")[:, :k]          # valid columns first, in order
    return order, np.take_along_axis(valid, order, axis=1)


# ------------------------------------------------------------------------------ pair-catalog index

_BLOCK = 64              # vote-table widths are multiples of this
_TILES = (16, 32, 64, 128, 256)   # tile lengths (stars gathered per row of a 2-D gather)
_PAD = max(_TILES)       # padding after the pair catalog's stars, so that every tile is in bounds
_PIECE = 1 << 18         # stars expanded at once, so that the temporaries stay in cache
_TABLE = 1 << 18         # cells of one vote table (2 MB of int64, in cache), unless max_vote_cells is smaller


def _previous_occurrence(pi: np.ndarray, pj: np.ndarray) -> np.ndarray:
    """For each endpoint of each catalog pair, the index of the previous pair (in the catalog's
    angle order) that holds the same star, -1 if none; interleaved like :attr:`VotingIndex.stars`
    (entry 2m = star ``pi[m]``, entry 2m + 1 = star ``pj[m]``).

    In a window [lo, hi) of pairs, the star of entry e occurs for the first time at e's pair exactly
    when ``prev[e] < lo``: this de-duplicates votes without sorting the candidates.  O(M log M), once
    per pair catalog (one sort of the 2M endpoints by star; ~0.2 s for 2M pairs).
    """
    star = np.stack([pi, pj], axis=1).ravel().astype(np.int64)         # entry 2m, 2m + 1
    E = star.size
    # by star, then by entry: a stable sort by star (a radix sort when the rows fit 16 bits), else a
    # value sort of star * E + entry (~3x faster than a stable argsort of 32-bit keys)
    if E and 0 <= star.min() and star.max() < 1 << 16:
        order = np.argsort(star.astype(np.uint16), kind="stable")
        s = star[order]
    else:
        s, order = np.divmod(np.sort(star * E + np.arange(E)), E)
    dt = np.int32 if pi.size < np.iinfo(np.int32).max else np.int64
    prev_sorted = np.full(E, -1, dt)
    if E > 1:
        prev_sorted[1:] = np.where(s[1:] == s[:-1], order[:-1] // 2, -1)
    prev = np.empty(E, dt)
    prev[order] = prev_sorted
    return prev


class VotingIndex:
    """What :func:`identify` derives from the pair catalog alone, built once per catalog.

    Pass it to :func:`identify` in place of the pair arrays (``identify(obs, valid, cat_unit, index,
    cfg=cfg)``) to skip the per-call checks and derivations.  Given pair arrays (or an object with
    ``i, j, angle``), :func:`identify` gets the index from :func:`voting_index`, which keeps the
    last few, so a job that passes the same arrays batch after batch builds it once.

    Attributes
    ----------
    i, j, angle : the pair catalog (:func:`pair_arrays`): (M,) int32 rows and float64 angles, ascending.
    star_range : (lowest, highest) catalog row in the pairs ((0, -1) when there is no pair).
    stars_plus_one : (2M + pad,) both stars of every pair, interleaved, plus one (``[2m] = i[m] + 1``,
        ``[2m + 1] = j[m] + 1``), then zeros: the stars of the pairs [lo, hi) are the contiguous
        ``[2 lo: 2 hi]``, and 0 is the vote tables' column of ignored stars.
    prev : (2M,) for each of those entries, the previous pair holding the same star (-1 = none);
        built on first use (by ``VotingConfig.vote_once_per_pair``; ~0.2 s for 2M pairs).
    tile_dtype : integer type of both (int32 unless the catalog has ~500M pairs).

    The pair arrays must not be modified while the index is in use.
    """

    def __init__(self, pair_i, pair_j=None, pair_angle=None):
        i, j, ang = pair_arrays(pair_i, pair_j, pair_angle)
        self.i, self.j, self.angle = i, j, ang
        self.star_range = (int(min(i.min(), j.min())), int(max(i.max(), j.max()))) if i.size else (0, -1)
        M2 = 2 * ang.size
        self.tile_dtype = np.int32 if M2 + _PAD < np.iinfo(np.int32).max // 2 else np.int64
        s = np.zeros(M2 + _PAD, self.tile_dtype)
        s[0:M2:2] = i
        s[1:M2:2] = j
        s[:M2] += 1
        self.stars_plus_one = s
        self._prev_padded = None

    def __len__(self) -> int:
        return int(self.angle.size)

    @property
    def prev_padded(self) -> np.ndarray:
        """(2M + pad,) :attr:`prev`, then zeros."""
        if self._prev_padded is None:
            p = np.zeros(2 * self.angle.size + _PAD, self.tile_dtype)
            p[:2 * self.angle.size] = _previous_occurrence(self.i, self.j)
            self._prev_padded = p
        return self._prev_padded

    @property
    def prev(self) -> np.ndarray:
        return self.prev_padded[:2 * self.angle.size]


_INDEX_CACHE: list = []          # [(input arrays, fingerprint, VotingIndex)], most recently used first
_INDEX_CACHE_SIZE = 4
_INDEX_LOCK = threading.Lock()


def _fingerprint(arrays) -> tuple:
    """Shape, dtype and 64 evenly spaced values of each array (O(1)): a cached index is reused only
    for the very same array objects that still hold the same catalog."""
    out = []
    for a in arrays:
        a = np.asarray(a)
        k = np.unique(np.linspace(0, a.size - 1, min(a.size, 64)).astype(np.int64))
        out.append((a.shape, a.dtype.str, a.ravel()[k].tobytes()))
    return tuple(out)


def voting_index(pair_i, pair_j=None, pair_angle=None) -> VotingIndex:
    """The :class:`VotingIndex` of a pair catalog given as :func:`identify` takes it (three arrays, an
    object with ``i, j, angle``, or an index, returned as is).

    The last ``_INDEX_CACHE_SIZE`` (4) indexes are kept, keyed by the identity of the three arrays
    (which the cache holds, so an identity is never reused while cached) and checked against a
    fingerprint of their shapes and of 64 sampled values each.  Arrays edited in place after a call
    are not detected beyond that fingerprint: build a new :class:`VotingIndex` (or pass new arrays).
    Thread-safe (a lock; the first call on a catalog builds its index under it).
    """
    if isinstance(pair_i, VotingIndex):
        return pair_i
    arrays = (pair_i.i, pair_i.j, pair_i.angle) if pair_j is None and pair_angle is None else \
        (pair_i, pair_j, pair_angle)
    fp = _fingerprint(arrays)
    with _INDEX_LOCK:
        for k, (inputs, fp_k, index) in enumerate(_INDEX_CACHE):
            if all(a is b for a, b in zip(inputs, arrays)) and fp == fp_k:
                _INDEX_CACHE.insert(0, _INDEX_CACHE.pop(k))            # most recently used first
                return index
        index = VotingIndex(*arrays)
        _INDEX_CACHE.insert(0, (arrays, fp, index))
        del _INDEX_CACHE[_INDEX_CACHE_SIZE:]
    return index


# ---------------------------------------------------------------------------------- voting round


def _tile_length(n_el: np.ndarray) -> int:
    """Tile length for windows of ``n_el`` stars: the least cost of gathered stars (padding included),
    tiles and partial (masked) tiles (rough ns, measured: 2.5 per star, 20 per tile, 2 per masked star)."""
    n_el = n_el[::max(1, n_el.size // 2048)]                          # a sample is enough
    Ls = np.array(_TILES, np.int64)
    tiles = (-(-n_el[None, :] // Ls[:, None])).sum(axis=1)
    partial = np.count_nonzero(n_el[None, :] % Ls[:, None], axis=1)
    cost = tiles * (Ls * 2.5 + 20.0) + partial * Ls * 2.0
    return int(Ls[np.argmin(cost)])


def _top_k(table: np.ndarray, k: int, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` columns with the most votes in each row of ``table (R, W)`` (counts >= 0, column 0 never
    wins), best first, ties to the lower column: ``k`` passes of argmax, each masking its winner.

    bound : an upper bound of the counts (k > 1 copies the table to int16 when it fits).
    Returns ``ids (R, k) int64`` (-1 where the count is 0) and ``counts (R, k) int64`` (0 there).
    """
    R, W = table.shape
    r = np.arange(R)
    if k == 1:
        sub = table
    else:                                                              # a masked copy; narrow = faster
        sub = table.astype(np.int16 if bound < np.iinfo(np.int16).max else np.int64)
    ids = np.full((R, k), -1, np.int64)
    cnt = np.zeros((R, k), np.int64)
    for t in range(min(k, W)):                                         # k passes (k is small)
        best = sub.argmax(axis=1)
        c = sub[r, best].astype(np.int64)
        ids[:, t] = np.where(c > 0, best, -1)
        cnt[:, t] = np.where(c > 0, c, 0)
        if t + 1 < k:
            sub[r, best] = -1                                          # mask the winner
    return ids, cnt


def _vote_rows(e_row: np.ndarray, e_lo: np.ndarray, e_cnt: np.ndarray, n_rows: int, index: VotingIndex,
               n_cat: int, once: bool, k: int, max_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Voting round (Kolomenkin 2008, step 1) and the k best identities of every observed star.

    Rows are observed stars; an *entry* is one of a row's observed pairs with its window [lo, lo + cnt)
    of candidate catalog pairs: it votes for the stars ``index.stars_plus_one[2 lo: 2 (lo + cnt)] - 1``.

    Parameters
    ----------
    e_row, e_lo, e_cnt : (E,) entries (int64), sorted by row, ``cnt > 0``.
    n_rows : number of rows.  index : the pair catalog.  n_cat : catalog size N.
    once : count a catalog star at most once per entry (``VotingConfig.vote_once_per_pair``): a star
        counts where its previous pair (``index.prev``) lies before the window.
    k : identities kept per row (:func:`_top_k`).
    max_cells : memory bound: vote tables of at most this many int64 cells (or one row), and at most
        this many stars expanded at once (or one tile).

    Returns ``ids (n_rows, k)`` and ``counts (n_rows, k)`` int64 (-1 / 0 = none).

    Method: rows go in groups whose dense (rows, W) int64 vote table (W >= N + 1, a multiple of 64)
    stays in cache (``_TABLE`` cells) and within ``max_cells``.  A window's stars are read as tiles
    of L consecutive stars, one 2-D gather from a strided view of the padded ``stars + 1``
    (~memcpy speed, no per-star index arithmetic); a star votes in column ``star + 1`` of its row,
    and the stars to ignore (a partial tile's tail, a star already counted in the window) are sent
    to column 0 with sign-bit masks (no boolean indexing).  A group's tiles are counted in pieces
    of ~``_PIECE`` stars, each with one ``np.bincount`` whose keys are row-major, so the counting
    touches one table row at a time.
    """
    ids = np.full((n_rows, k), -1, np.int64)
    cnt = np.zeros((n_rows, k), np.int64)
    n_e = e_row.size
    if n_e == 0:
        return ids, cnt
    W = -(-(n_cat + 1) // _BLOCK) * _BLOCK
    dt = index.tile_dtype
    n_el = 2 * e_cnt
    L = _tile_length(n_el)
    swin = np.lib.stride_tricks.sliding_window_view(index.stars_plus_one, L)   # row s: stars s .. s + L - 1
    pwin = np.lib.stride_tricks.sliding_window_view(index.prev_padded, L) if once else None
    pos = np.arange(L, dtype=dt)
    sign = np.iinfo(dt).bits - 1
    # vote counts <= the row's stars (<= its entries with ``once``): top-k on an int16 copy when it fits
    per_row = np.bincount(e_row, weights=None if once else n_el, minlength=n_rows)
    bound = int(per_row.max())
    rows_max = max(1, min(int(max_cells), _TABLE) // W)
    per_piece = max(1, min(int(max_cells), _PIECE) // L)
    g_cut = np.flatnonzero(np.diff(e_row // rows_max)) + 1
    g_edges = np.concatenate([[0], g_cut, [n_e]]).tolist()
    for e0, e1 in zip(g_edges[:-1], g_edges[1:]):                      # groups of rows
        # tiles of the group's entries: entry e has ceil(n_el / L) of them, of L stars but the last
        nt = -(-n_el[e0:e1] // L)
        t_e = np.repeat(np.arange(e0, e1), nt)
        t_j = np.arange(t_e.size) - np.repeat(np.cumsum(nt) - nt, nt)  # tile number in its entry
        t_start = 2 * e_lo[t_e] + t_j * L
        t_len = np.minimum(n_el[t_e] - t_j * L, L).astype(dt)
        t_row = e_row[t_e]
        t_lo = e_lo[t_e].astype(dt) if once else None
        ra, rb = int(t_row[0]), int(t_row[-1])
        n_t = t_e.size
        table = None
        for a in range(0, n_t, per_piece):                            # pieces of tiles
            b = min(n_t, a + per_piece)
            pa, pb = int(t_row[a]), int(t_row[b - 1])
            ts = t_start[a:b]
            tl = t_len[a:b]
            G = swin[ts]                                               # (n, L) stars + 1 (a copy)
            part = np.flatnonzero(tl < L)                              # partial tiles (tails masked)
            every = part.size * 4 > b - a                              # mask all tiles at once
            if once:
                D = pwin[ts]                                           # previous pair of each star
                D -= t_lo[a:b, None]                                   # < 0: first in the window
                if every:
                    np.maximum(D, pos - tl[:, None], out=D)
                elif part.size:
                    D[part] = np.maximum(D[part], pos - tl[part, None])
                D >>= sign                                             # -1 = keep, 0 = drop
                G &= D
            elif every:
                G &= (pos - tl[:, None]) >> sign
            elif part.size:
                G[part] &= (pos - tl[part, None]) >> sign
            G += ((t_row[a:b] - pa) * W).astype(dt)[:, None]
            votes = np.bincount(G.ravel(), minlength=(pb - pa + 1) * W).reshape(pb - pa + 1, W)
            if a == 0 and b == n_t:
                table = votes
            else:
                if table is None:
                    table = np.zeros((rb - ra + 1, W), np.int64)
                table[pa - ra:pb - ra + 1] += votes
        table[:, 0] = 0                                                # ignored stars
        i_, c_ = _top_k(table, k, bound)
        ids[ra:rb + 1] = np.where(i_ > 0, i_ - 1, -1)                  # column = star + 1
        cnt[ra:rb + 1] = c_
    return ids, cnt


# ----------------------------------------------------------------------------------- later steps


def _drop_duplicates(ids: np.ndarray, top: np.ndarray) -> np.ndarray:
    """An identity claimed by several stars of a case stays only with a strict vote winner.

    ids, top : (B, K).  Returns the new ids (B, K).
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


def _consistency(d_obs: np.ndarray, ids: np.ndarray, cat_unit: np.ndarray, tol: float) -> np.ndarray:
    """Step 3: (B, K, K) bool, identified stars p != q with |angle(id_p, id_q) - d_pq| < tol.

    d_obs : (B, P) observed angle of the pairs p < q (``np.triu_indices(K, 1)`` order).
    Only the pairs p < q of identified stars are computed (the angles are exactly symmetric: the
    chord of ``u - v`` and of ``v - u`` is the same) and mirrored.
    """
    B, K = ids.shape
    tp, tq = np.triu_indices(K, 1)
    has = ids >= 0
    b, k = np.nonzero(has[:, tp] & has[:, tq])
    p, q = tp[k], tq[k]
    d_obs = d_obs[b, k]
    d_cat = _angles(cat_unit[ids[b, p]], cat_unit[ids[b, q]])
    with np.errstate(invalid="ignore"):
        c = np.abs(d_cat - d_obs) < tol
    out = np.zeros((B, K, K), bool)
    out[b[c], p[c], q[c]] = True
    out[b[c], q[c], p[c]] = True
    return out


def _accept_fraction(vv: np.ndarray, T: np.ndarray, frac: float) -> np.ndarray:
    """Stars with verification votes >= frac * T and > 0.  vv (B, K), T (B,)."""
    return (vv > 0) & (vv >= frac * T[:, None])


def _pack_bits(x: np.ndarray) -> np.ndarray:
    """Pack the last axis (length K) of a bool array into ceil(K / 64) uint64 words (bit j = entry j)."""
    K = x.shape[-1]
    nw = -(-K // 64)
    packed = np.packbits(x, axis=-1, bitorder="little")
    out = np.zeros(x.shape[:-1] + (nw * 8,), np.uint8)
    out[..., :packed.shape[-1]] = packed
    return out.view(np.uint64)


def _greedy_clique(cons: np.ndarray, score: np.ndarray) -> np.ndarray:
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


def _select_candidates(cand: np.ndarray, cand_votes: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray,
                       cat_unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tie-aware step 2 (dualsight): choose one of each star's candidates by geometric consistency.

    Nodes are (star, candidate identity); two nodes of different stars are consistent when the
    catalog angle of their identities matches the observed angle within ``tol``.  The largest
    mutually consistent node set (:func:`_greedy_clique`, tie-break by votes) holds at most one node
    per star; its stars take those identities.

    cand, cand_votes : (B, K, m) candidate rows (-1 = none) and their votes (:func:`_top_k`).
    c_lo, c_hi : (B, K, K) bounds per pair of stars: |d_cat - d_obs| < tol  <=>
        cos(d_obs + tol) < cos_cat < cos(d_obs - tol); ``c_lo`` = inf where the pair does not count
        (same star, unused star).
    Returns ``ids (B, K)`` (-1 = no node chosen) and ``votes (B, K)`` of the chosen candidates.
    """
    B, K, m = cand.shape
    ids_n = cand.reshape(B, K * m)
    has = ids_n >= 0
    ref = np.where(has[..., None], cat_unit[np.where(has, ids_n, 0)], np.nan)   # NaN: never consistent
    cos_cat = (ref @ np.swapaxes(ref, 1, 2)).reshape(B, K, m, K * m)
    cons = cos_cat > np.repeat(c_lo, m, axis=2)[:, :, None, :]         # bounds of (star, node) pairs
    cons &= cos_cat < np.repeat(c_hi, m, axis=2)[:, :, None, :]
    member = _greedy_clique(cons.reshape(B, K * m, K * m), cand_votes.reshape(B, K * m)).reshape(B, K, m)
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
    bi, ni = np.divmod(np.flatnonzero(near), near.shape[1])
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
        sorted ascending; or pass one object with attributes ``i, j, angle`` as ``pair_i``, or its
        :class:`VotingIndex` (what is derived from the catalog once; for arrays or an object,
        :func:`voting_index` keeps the last few, keyed by the arrays' identity).
    cfg : :class:`VotingConfig`.

    Returns
    -------
    :class:`Identification` (arrays of shape (B, S) and (B,)).

    Notes
    -----
    Each case is computed independently: a batch gives the same result as each case alone.
    Invalid or non-finite entries of ``obs`` are ignored (they may hold NaN).
    Cost: O(observed pairs x candidates per pair) for the voting round plus O(B x max_stars x N)
    for the dense vote tables (at most ``cfg.max_vote_cells`` cells at a time); the later steps
    are O(B x max_stars^2) (x ``candidates_per_star``^2), the attitude check O(B x (N + S x 40)).
    The first call on a pair catalog also builds its :class:`VotingIndex` (O(M log M), once).
    Measured: see the module docstring.
    """
    obs = np.asarray(obs, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    cat_unit = np.asarray(cat_unit, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[-1] != 3 or valid.shape != obs.shape[:2]:
        raise ValueError(f"expected obs (B,S,3) and valid (B,S), got {obs.shape} and {valid.shape}")
    if cat_unit.ndim != 2 or cat_unit.shape[1] != 3:
        raise ValueError(f"expected cat_unit (N,3), got {cat_unit.shape}")
    index = voting_index(pair_i, pair_j, pair_angle)
    pang = index.angle
    B, S, _ = obs.shape
    N = cat_unit.shape[0]
    if len(index) and (index.star_range[0] < 0 or index.star_range[1] >= N):
        raise ValueError(f"pair catalog rows must be in [0, {N}) (the star catalog's rows)")
    valid = valid & np.all(np.isfinite(obs), axis=-1)
    K = min(int(cfg.max_stars), int(valid.sum(axis=1).max(initial=0)))   # padding beyond is never used

    # --- the brightest K valid stars of each case, compacted to (B, K)
    cols, use = _select_brightest(valid, K)
    obs_k = np.take_along_axis(obs, cols[..., None], axis=1)
    obs_k = np.where(use[..., None], obs_k, 0.0)

    # --- observed pairs (p < q) of every case and their windows [lo, lo + cnt) of catalog pairs
    tp, tq = np.triu_indices(K, 1)
    P = tp.size
    bl, pk = np.nonzero(use[:, tp] & use[:, tq])
    d = _angles(obs_k[bl, tp[pk]], obs_k[bl, tq[pk]])
    o = np.argsort(d)                                                  # sorted keys: faster searches
    lo = np.empty(d.size, np.int64)
    hi = np.empty(d.size, np.int64)
    lo[o] = np.searchsorted(pang, d[o] - cfg.tolerance_rad, side="right")   # angle > d - tol
    hi[o] = np.searchsorted(pang, d[o] + cfg.tolerance_rad, side="left")    # angle < d + tol
    lo_bp = np.zeros((B, P + 1), np.int64)                             # column P: "no pair" (p = q)
    cnt_bp = np.zeros((B, P + 1), np.int64)
    lo_bp[bl, pk] = lo
    cnt_bp[bl, pk] = np.maximum(hi - lo, 0)

    # --- steps 1-2: each observed star (row) votes with the windows of its pairs, in row order
    pid = np.full((K, K), P, np.int64)
    pid[tp, tq] = pid[tq, tp] = np.arange(P)
    eb, ep, eq = np.nonzero(cnt_bp[:, pid])                            # (case, star, partner), sorted
    e_pair = pid[ep, eq]
    row_of = np.cumsum(use.ravel()).reshape(B, K) - 1                  # rows = used (case, star) slots
    m = int(cfg.candidates_per_star)
    k = m + 1 if m > 1 else (2 if cfg.require_unique_max else 1)       # one more to detect ties
    r_ids, r_cnt = _vote_rows(row_of[eb, ep], lo_bp[eb, e_pair], cnt_bp[eb, e_pair], int(use.sum()), index,
                              N, cfg.vote_once_per_pair, k, cfg.max_vote_cells)
    ok1 = r_cnt[:, 0] > r_cnt[:, 1] if cfg.require_unique_max else r_ids[:, 0] >= 0
    vote_ids = np.full((B, K), -1, np.int64)                           # -1 / 0 outside the used slots
    top = np.zeros((B, K), np.int64)
    vote_ids[use] = np.where(ok1, r_ids[:, 0], -1)
    top[use] = np.where(ok1, r_cnt[:, 0], 0)
    if m > 1:
        # tie-aware assignment: stars in the consistent candidate set take those identities,
        # the others keep the plain (unique, if required) maximum
        cand = np.full((B, K, m), -1, np.int64)
        cand_votes = np.zeros((B, K, m), np.int64)
        cand[use] = r_ids[:, :m]
        cand_votes[use] = r_cnt[:, :m]
        sel_ids = np.full((B, K), -1, np.int64)
        sel_votes = np.zeros((B, K), np.int64)
        # cosine bounds of the observed pairs (p < q); column P (p = q, or a missing star): inf = never
        tol_v = cfg.verify_tol
        c_lo = np.full((B, P + 1), np.inf)
        c_hi = np.full((B, P + 1), 2.0)
        c_lo[bl, pk] = np.cos(np.minimum(d + tol_v, np.pi))
        c_hi[bl, pk] = np.where(d > tol_v, np.cos(d - tol_v), 2.0)
        blk = max(1, int(cfg.max_vote_cells) // max(1, (K * m) ** 2))   # bounded (cases, Km, Km) arrays
        for b0 in range(0, B, blk):                                    # a handful of blocks
            sl = slice(b0, b0 + blk)
            sel_ids[sl], sel_votes[sl] = _select_candidates(cand[sl], cand_votes[sl], c_lo[sl][:, pid],
                                                            c_hi[sl][:, pid], cat_unit)
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
    d_bp = np.zeros((B, P))                                            # used where both stars are
    d_bp[bl, pk] = d
    cons = _consistency(d_bp, vote_ids, cat_unit, cfg.verify_tol)
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
