"""The pair catalog as geometric voting reads it: :class:`VotingIndex`, built once per catalog.

Kolomenkin et al. (2008) vote with every catalog pair whose angle matches an observed pair's within
a tolerance; with the pairs sorted by angle (:mod:`dualsight.catalogs.pairs`), those candidates are
one contiguous window ``[lo, hi)`` of pairs (:func:`dualsight.nav.votes.pair_windows`).  What the
voting round needs beyond the three pair arrays depends on the catalog alone and is derived here
once: both stars of every pair interleaved in one array (the stars of a window are then a contiguous
slice) and, for the one-vote-per-pair option, each star's previous occurrence in the angle order.
:func:`voting_index` keeps the last few indexes, so a job passing the same arrays batch after batch
builds it once.

Construction only computes (in memory).  For a cached, memory-mapped catalog
(:func:`dualsight.catalogs.pair_cache.load_pair_catalog`) the two derived arrays can instead be mapped from
files beside it, written once with bounded memory by whichever process needs them first: that is the explicit
call :meth:`VotingIndex.load_or_build`, which the jobs make when they load their catalogs.
"""

from __future__ import annotations

import functools
import threading

import numpy as np

from dualsight.catalogs import pair_voting_cache

__all__ = ["VotingIndex", "voting_index", "pair_arrays", "previous_occurrence", "PAD"]

PAD = 256
"""Zeros after the interleaved stars, so that a tile of up to ``PAD`` stars read from any window
start stays in bounds (the voting round's longest tile, :data:`dualsight.nav.votes.TILES`)."""


def pair_arrays(pair_i, pair_j=None, pair_angle=None):
    """``(i, j, angle)`` arrays from three arrays or from one object with ``i, j, angle`` attributes
    (a :class:`dualsight.catalogs.pairs.PairCatalog`).

    Returns int32 catalog rows ``i, j`` (M,) and float64 ``angle`` (M,, rad), checked to be sorted
    ascending; raises ``ValueError`` otherwise.
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


def previous_occurrence(pi: np.ndarray, pj: np.ndarray) -> np.ndarray:
    """For each endpoint of each catalog pair, the index of the previous pair (in the catalog's
    angle order) that holds the same star, -1 if none; interleaved like :attr:`VotingIndex.stars_plus_one`
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
    """What :func:`~dualsight.nav.starid.identify` derives from the pair catalog alone, built once
    per catalog.

    Pass it to ``identify`` in place of the pair arrays (``identify(obs, valid, cat_unit, index,
    cfg=cfg)``) to skip the per-call checks and derivations.  Given pair arrays (or an object with
    ``i, j, angle``), ``identify`` gets the index from :func:`voting_index`, which keeps the
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
    From :meth:`load_or_build` on a cached, memory-mapped catalog both are instead read-only maps of files
    beside it, built once with bounded memory (:mod:`dualsight.catalogs.pair_voting_cache`) and shared by
    every process; the constructor itself reads and writes no file.
    tile_dtype : integer type of both (int32 unless the catalog has ~500M pairs).

    The pair arrays must not be modified while the index is in use.
    """

    def __init__(self, pair_i, pair_j=None, pair_angle=None):
        """The index of a pair catalog (three arrays, or one object with ``i, j, angle``), derived in memory."""
        self._set(*pair_arrays(pair_i, pair_j, pair_angle))

    def _set(self, i: np.ndarray, j: np.ndarray, ang: np.ndarray, derived=None) -> None:
        """Fill the index from checked pair arrays (:func:`pair_arrays`); ``derived``: (stars_plus_one,
        prev_padded) as :meth:`load_or_build` maps them, else both derived here in memory."""
        self.i, self.j, self.angle = i, j, ang
        self.star_range = (int(min(i.min(), j.min())), int(max(i.max(), j.max()))) if i.size else (0, -1)
        M2 = 2 * ang.size
        self.tile_dtype = _tile_dtype(ang.size)
        self._prev_padded = None
        if derived is not None:
            self.stars_plus_one, self._prev_padded = derived
            return
        s = np.zeros(M2 + PAD, self.tile_dtype)
        s[0:M2:2] = i
        s[1:M2:2] = j
        s[:M2] += 1
        self.stars_plus_one = s

    @classmethod
    def load_or_build(cls, pair_i, pair_j=None, pair_angle=None) -> "VotingIndex":
        """The index of a pair catalog with its derived arrays from files: for a cached, memory-mapped catalog
        (its ``i`` array the map of ``<stem>.i.npy``), ``<stem>.vstars.npy`` and ``<stem>.vprev.npy`` mapped
        read-only, written first (chunk by chunk, atomically) when missing, damaged or of other pairs
        (:func:`dualsight.catalogs.pair_voting_cache.load_or_build`).  Otherwise (arrays in memory, or a
        folder that is not writable) the same index derived in memory, as the constructor builds it.  The
        values are the same either way."""
        raw_i = pair_i.i if pair_j is None and pair_angle is None else pair_i
        i, j, ang = pair_arrays(pair_i, pair_j, pair_angle)
        index = cls.__new__(cls)
        index._set(i, j, ang, pair_voting_cache.load_or_build(raw_i, i, j, _tile_dtype(ang.size), PAD))
        return index

    def __len__(self) -> int:
        return int(self.angle.size)

    @property
    def prev_padded(self) -> np.ndarray:
        """(2M + pad,) :attr:`prev`, then zeros."""
        if self._prev_padded is None:
            p = np.zeros(2 * self.angle.size + PAD, self.tile_dtype)
            p[:2 * self.angle.size] = previous_occurrence(self.i, self.j)
            self._prev_padded = p
        return self._prev_padded

    @property
    def prev(self) -> np.ndarray:
        return self.prev_padded[:2 * self.angle.size]


def _tile_dtype(n_pairs: int):
    """Integer type of the interleaved stars and ``prev`` of ``n_pairs`` pairs: int32 unless ~500M pairs."""
    return np.int32 if 2 * n_pairs + PAD < np.iinfo(np.int32).max // 2 else np.int64


_INDEX_CACHE: list = []          # [(input arrays, fingerprint, VotingIndex)], most recently used first
_INDEX_CACHE_SIZE = 4
_INDEX_LOCK = threading.Lock()


def _fingerprint(arrays) -> tuple:
    """Shape, dtype and 64 evenly spaced values of each array (O(1)): a cached index is reused only
    for the very same array objects that still hold the same catalog.  A read-only memory map (a cached
    catalog, :mod:`dualsight.catalogs.pair_cache`) cannot change under the same object: its values are not
    sampled (on one frame the sampling's scattered reads cost ~30 us)."""
    out = []
    for a in arrays:
        if isinstance(a, np.memmap) and not a.flags.writeable:
            out.append((a.shape, a.dtype.str, "read-only map"))
            continue
        a = np.asarray(a)
        out.append((a.shape, a.dtype.str, a.ravel()[_sample_positions(a.size)].tobytes()))
    return tuple(out)


@functools.lru_cache(maxsize=16)
def _sample_positions(n: int) -> np.ndarray:
    """(<= 64,) int64 evenly spaced distinct positions in [0, n) (one array per size, reused)."""
    k = np.unique(np.linspace(0, n - 1, min(n, 64)).astype(np.int64))
    k.flags.writeable = False
    return k


def voting_index(pair_i, pair_j=None, pair_angle=None) -> VotingIndex:
    """The :class:`VotingIndex` of a pair catalog given as ``identify`` takes it (three arrays, an
    object with ``i, j, angle``, or an index, returned as is).

    The last ``_INDEX_CACHE_SIZE`` (4) indexes are kept, keyed by the identity of the three arrays
    (which the cache holds, so an identity is never reused while cached) and checked against a
    fingerprint of their shapes and of 64 sampled values each.  Arrays edited in place after a call
    are not detected beyond that fingerprint: build a new :class:`VotingIndex` (or pass new arrays).
    Thread-safe (a lock; the first call on a catalog builds its index under it).  The index is derived in
    memory (no file is read or written); a job whose catalog is cached passes the index of
    :meth:`VotingIndex.load_or_build` instead.
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

