"""Step 1 of geometric voting (Kolomenkin et al. 2008): observed pairs, their catalog windows, votes.

Kolomenkin, Pollak, Shimshoni & Lindenbaum, "Geometric voting algorithm for star trackers", IEEE
Trans. Aerosp. Electron. Syst. 44(2), 441-456 (2008), Sec. III; the reference's Sec. 3.1:
every observed pair (p, q) with angle ``d_pq`` votes, for every catalog pair (a, b) with
``|angle_ab - d_pq| < tolerance``, for the identities a and b of *both* p and q.  Each observed
star then has one vote count per catalog star; the stages after this one read its best few.

Stages (pure functions, all cases at once, no Python loop over cases, stars or pairs):

- :func:`observed_pairs`: the pairs p < q of the observed stars and their angles.
- :func:`pair_windows`: each pair's window ``[lo, lo + cnt)`` of catalog pairs (binary search on the
  sorted catalog angles).
- :func:`vote`: the vote counts, reduced to each star's ``cfg.candidates_kept`` best identities.

Implementation of the counting (:func:`_vote_rows`): each observed star's row of votes is counted
from its pairs' windows of catalog stars, read as fixed-length tiles (2-D gathers from a strided view
of :attr:`VotingIndex.stars_plus_one`) and counted with ``np.bincount`` into dense (stars, catalog
row) tables of a few rows at a time (row-major keys, tables that stay in cache), bounded by
``cfg.max_vote_cells``.  One vote per pair needs no sort: a catalog star occurs for the first time in
a window of pairs when its previous pair (:attr:`VotingIndex.prev`) lies before the window.

:func:`vote_taichi` is the same stage by the Taichi kernels of :mod:`dualsight.kernels.voting` (the
default engine of :func:`dualsight.nav.starid.identify`; :func:`vote` stays as the reference it is
tested against bit for bit, ``tests/test_voting_kernel.py``).  Speed of both:
``benchmarks/bench_voting.py``.
"""

from __future__ import annotations

import functools
import weakref
from typing import NamedTuple

import numpy as np

from dualsight.scene.units import angle_between

from .pair_index import PAD, VotingIndex
from .voting_config import VotingConfig

__all__ = ["ObservedPairs", "observed_pairs", "pair_slots", "pair_windows", "vote", "vote_taichi", "TILES"]

TILES = (16, 32, 64, 128, PAD)   # tile lengths (stars gathered per row of a 2-D gather)
_BLOCK = 64              # vote-table widths are multiples of this
_PIECE = 1 << 18         # stars expanded at once, so that the temporaries stay in cache
_TABLE = 1 << 18         # cells of one vote table (2 MB of int64, in cache), unless max_vote_cells is smaller
_BUCKETS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()   # VotingIndex -> its window buckets


class ObservedPairs(NamedTuple):
    """The pairs p < q of the observed stars that take part in voting, in (case, p, q) order.

    case : (E,) int64 case index b.   pair : (E,) int64 index of (p, q) in ``np.triu_indices(K, 1)``.
    p, q : (E,) int64 star slots, p < q (slots of the (B, K) arrays of the voting stars).
    angle : (E,) float64 observed angle d_pq (rad), :func:`dualsight.scene.units.angle_between`.
    n_stars : K, the number of star slots per case.
    """

    case: np.ndarray
    pair: np.ndarray
    p: np.ndarray
    q: np.ndarray
    angle: np.ndarray
    n_stars: int


def observed_pairs(obs_k: np.ndarray, use: np.ndarray) -> ObservedPairs:
    """Every pair p < q of used stars and its angle (the observed pairs of Kolomenkin's step 1).

    obs_k : (B, K, 3) float64 camera-frame unit vectors of the voting stars (finite where ``use``).
    use : (B, K) bool, the slot holds a star.
    Returns :class:`ObservedPairs` (E = the number of such pairs over all cases).
    """
    B, K = use.shape
    tp, tq = _triu(K)
    case, pair = np.nonzero(use[:, tp] & use[:, tq])
    p, q = tp[pair], tq[pair]
    return ObservedPairs(case, pair, p, q, angle_between(obs_k[case, p], obs_k[case, q]), K)


@functools.lru_cache(maxsize=64)
def pair_slots(K: int) -> np.ndarray:
    """(K, K) int64: the index of pair (p, q) (or (q, p)) in ``np.triu_indices(K, 1)``; the diagonal
    holds P = K (K - 1) / 2, one past the last pair ("no pair"), so arrays of (B, P + 1) values per
    pair read as (B, K, K) matrices with ``values[:, pair_slots(K)]``.  Made once per K (read-only)."""
    P = K * (K - 1) // 2
    tp, tq = _triu(K)
    pid = np.full((K, K), P, np.int64)
    pid[tp, tq] = pid[tq, tp] = np.arange(P)
    pid.flags.writeable = False
    return pid


@functools.lru_cache(maxsize=64)
def _triu(K: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(K, 1)``, made once per K (read-only)."""
    tp, tq = np.triu_indices(K, 1)
    tp.flags.writeable = tq.flags.writeable = False
    return tp, tq


def pair_windows(d: np.ndarray, catalog_angle: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Window of catalog pairs whose angle matches each observed angle: ``|angle - d| < tol``.

    d : (E,) float64 observed angles (rad).  catalog_angle : (M,) float64 catalog pair angles (rad),
    ascending.  tol : half-width (rad).
    Returns ``lo, cnt`` (E,) int64: the matching pairs are ``lo .. lo + cnt - 1`` (``angle > d - tol``
    and ``angle < d + tol``; cnt = 0 when none).  The searches run on sorted keys (faster).
    """
    o = np.argsort(d)
    lo = np.empty(d.size, np.int64)
    hi = np.empty(d.size, np.int64)
    lo[o] = np.searchsorted(catalog_angle, d[o] - tol, side="right")   # angle > d - tol
    hi[o] = np.searchsorted(catalog_angle, d[o] + tol, side="left")    # angle < d + tol
    return lo, np.maximum(hi - lo, 0)


def vote(pairs: ObservedPairs, use: np.ndarray, index: VotingIndex, n_cat: int,
         cfg: VotingConfig, window_counts: bool = False) -> tuple[np.ndarray, ...]:
    """Voting round (Kolomenkin 2008, step 1) and each observed star's best-voted identities.

    pairs : :class:`ObservedPairs` of the (B, K) voting stars ``use``.
    index : the pair catalog (:class:`VotingIndex`).  n_cat : N, the star catalog's size.
    cfg : uses ``tolerance_rad`` (window half-width, rad), ``vote_once_per_pair`` (a catalog star
        counts at most once per observed pair), ``candidates_kept`` and ``max_vote_cells``.
    Returns ``cand_ids (B, K, k)`` int64 catalog rows, best first (most votes, ties to the lower row;
    -1 = none) and ``cand_votes (B, K, k)`` int64 their vote counts (0 = none), k =
    ``cfg.candidates_kept``; unused slots hold -1 / 0; with ``window_counts`` also ``(E,)`` int64 the
    size of each observed pair's window (the catalog pairs within the tolerance, for
    :func:`dualsight.nav.chance.pair_hypotheses`).
    """
    B, K = use.shape
    P = K * (K - 1) // 2
    lo, cnt = pair_windows(pairs.angle, index.angle, cfg.tolerance_rad)
    lo_bp = np.zeros((B, P + 1), np.int64)                             # column P: "no pair" (p = q)
    cnt_bp = np.zeros((B, P + 1), np.int64)
    lo_bp[pairs.case, pairs.pair] = lo
    cnt_bp[pairs.case, pairs.pair] = cnt
    # each observed star (a row) votes with the windows of its pairs, in row order
    pid = pair_slots(K)
    eb, ep, eq = np.nonzero(cnt_bp[:, pid])                            # (case, star, partner), sorted
    e_pair = pid[ep, eq]
    row_of = np.cumsum(use.ravel()).reshape(B, K) - 1                  # rows = used (case, star) slots
    k = cfg.candidates_kept
    r_ids, r_cnt = _vote_rows(row_of[eb, ep], lo_bp[eb, e_pair], cnt_bp[eb, e_pair], int(use.sum()), index,
                              n_cat, cfg.vote_once_per_pair, k, cfg.max_vote_cells)
    cand_ids = np.full((B, K, k), -1, np.int64)
    cand_votes = np.zeros((B, K, k), np.int64)
    cand_ids[use] = r_ids
    cand_votes[use] = r_cnt
    return (cand_ids, cand_votes, cnt) if window_counts else (cand_ids, cand_votes)


def vote_taichi(pairs: ObservedPairs, use: np.ndarray, index: VotingIndex, n_cat: int,
                cfg: VotingConfig, window_counts: bool = False) -> tuple[np.ndarray, ...]:
    """:func:`vote` by the Taichi kernel ``vote`` of :mod:`dualsight.kernels.voting` (same arguments, same
    results bit for bit, as int32): windows by binary search per observed pair, votes counted per
    observed star in a row of N int32 counts per thread (``min(threads, max(1, cfg.max_vote_cells //
    N))`` rows), then the ``cfg.candidates_kept`` best read off while the row is cleared.  The window
    keys ``d - tol`` and ``d + tol`` are computed here, with numpy, exactly as :func:`pair_windows`
    does; the window buckets of the catalog (:func:`dualsight.kernels.voting.bucket_starts`) are built
    once per :class:`VotingIndex` and kept while it lives.
    """
    if np.dtype(index.tile_dtype) != np.int32:                          # ~500M pairs: beyond int32
        ids, cnt, *windows = vote(pairs, use, index, n_cat, cfg, window_counts)
        return ids.astype(np.int32), cnt.astype(np.int32), *windows
    from dualsight.kernels import voting as kvoting

    tol = cfg.tolerance_rad
    once = cfg.vote_once_per_pair
    buckets = _BUCKETS.get(index)
    if buckets is None:
        buckets = _BUCKETS[index] = kvoting.bucket_starts(index.angle)
    return kvoting.vote_top_k(pairs.case, pairs.p, pairs.q, pairs.angle - tol, pairs.angle + tol, index.angle,
                              buckets, index.stars_plus_one, index.prev_padded if once else None, use.shape,
                              cfg.candidates_kept, n_cat, cfg.max_vote_cells, window_counts=window_counts)


def _tile_length(n_el: np.ndarray) -> int:
    """Tile length for windows of ``n_el`` stars: the least cost of gathered stars (padding included),
    tiles and partial (masked) tiles (rough ns, measured: 2.5 per star, 20 per tile, 2 per masked star)."""
    n_el = n_el[::max(1, n_el.size // 2048)]                          # a sample is enough
    Ls = np.array(TILES, np.int64)
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
