"""What the voting derives from a cached pair catalog, cached beside it as memory-mapped ``.npy`` files.

The voting round (:mod:`dualsight.nav.votes`) reads two arrays derived from the pair catalog alone
(:class:`dualsight.nav.pair_index.VotingIndex`): both stars of every pair interleaved, plus one
(``stars_plus_one``), and each endpoint's previous pair holding the same star (``prev``).  Built in memory
they cost ~16 bytes per pair and, for ``prev``, a sort of every endpoint (~50 bytes per pair at its peak): 3-4 GiB
for the V 8 catalog (54 M pairs), ~12 GiB for V 9 -- against the bounded build of the pairs themselves
(:mod:`dualsight.catalogs.pairs`, <= 512 MiB).  Here they are written once per cached catalog, in chunks of
``CHUNK_PAIRS`` pairs (a few hundred MiB whatever the catalog), next to its ``.i/.j/.angle.npy`` files
(``<stem>.vstars.npy``, ``<stem>.vprev.npy``), and every later process maps them read-only: no derivation at
start-up (0.25-0.45 s per ``hil star`` process with the V 7 catalog) and no private copy in each worker.

``prev`` in chunks: walking the pairs in angle order, a star's previous pair is the previous occurrence inside
the chunk (a stable sort of the chunk's endpoints by star) or, for its first occurrence in the chunk, the last
pair of the earlier chunks that held it (one int64 per catalog star, carried from chunk to chunk).  The result
equals :func:`dualsight.nav.pair_index.previous_occurrence` (tested).

Writes go to temporary names in the same folder and are renamed, so a killed build leaves no half file under
the final name; a file whose shape, dtype or sampled stars disagree with the pairs is rebuilt.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.catalogs.build_progress import build_bar
from dualsight.catalogs.cache import atomic_file
from dualsight.catalogs.cache_budget import enforce_limit, mark_in_use

__all__ = ["CHUNK_PAIRS", "derived_paths", "load_or_build", "write_stars_plus_one", "write_prev"]

CHUNK_PAIRS = 1 << 22
"""Pairs per chunk of a build (~4 M: ~200 MiB of temporaries for ``prev``)."""

SECONDS_PER_PAIR = 2.5e-7
"""Seconds per pair to write both arrays (measured: 0.21-0.25 us at 2-28 M pairs, 2 cores): picks whether the
build shows a progress bar (:mod:`dualsight.catalogs.build_progress`)."""


def derived_paths(i_array) -> tuple[Path, Path] | None:
    """(``<stem>.vstars.npy``, ``<stem>.vprev.npy``) when ``i_array`` is the memory-mapped ``<stem>.i.npy`` of a
    cached pair catalog (:func:`dualsight.catalogs.pair_cache.load_pair_catalog`), else None."""
    fn = getattr(i_array, "filename", None) if isinstance(i_array, np.memmap) else None
    if fn is None or not str(fn).endswith(".i.npy"):
        return None
    stem = str(fn)[:-len(".i.npy")]
    return Path(stem + ".vstars.npy"), Path(stem + ".vprev.npy")


def _atomic_npy(path: Path, dtype: np.dtype, n: int, fill) -> None:
    """Write ``n`` values of ``dtype`` to ``path`` through ``fill(f)`` (which writes the raw values), atomically."""
    with atomic_file(path) as f:
        np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                 "fortran_order": False, "shape": (int(n),)})
        start = f.tell()
        fill(f)
        if f.tell() - start != n * np.dtype(dtype).itemsize:
            raise OSError(f"{path}: wrote {(f.tell() - start) // np.dtype(dtype).itemsize} values, expected {n}")


def write_stars_plus_one(path: Path, i: np.ndarray, j: np.ndarray, dtype, pad: int,
                         chunk: int = CHUNK_PAIRS, progress=None) -> None:
    """``[i0 + 1, j0 + 1, i1 + 1, j1 + 1, ...]`` then ``pad`` zeros, as ``dtype``, chunk by chunk (``progress``: a
    tqdm-like bar advanced by the pairs of each chunk, or None)."""
    M = int(i.shape[0])

    def fill(f):
        for a in range(0, M, chunk):
            b = min(M, a + chunk)
            s = np.empty(2 * (b - a), dtype)
            s[0::2] = i[a:b]
            s[1::2] = j[a:b]
            s += 1
            f.write(s.tobytes())
            if progress is not None:
                progress.update(b - a)
        f.write(np.zeros(pad, dtype).tobytes())

    _atomic_npy(path, np.dtype(dtype), 2 * M + pad, fill)


def write_prev(path: Path, i: np.ndarray, j: np.ndarray, dtype, pad: int, chunk: int = CHUNK_PAIRS,
               progress=None) -> None:
    """Each endpoint's previous pair holding the same star (-1 = none), interleaved like the stars, then ``pad``
    zeros (module docstring: chunk by chunk, the last pair of each star carried between chunks; ``progress`` as
    :func:`write_stars_plus_one`'s)."""
    M = int(i.shape[0])
    n_star = int(max(int(np.max(i)) if M else -1, int(np.max(j)) if M else -1)) + 1
    last = np.full(max(n_star, 1), -1, np.int64)

    def fill(f):
        for a in range(0, M, chunk):
            b = min(M, a + chunk)
            star = np.empty(2 * (b - a), np.int64)
            star[0::2] = i[a:b]
            star[1::2] = j[a:b]
            E = star.size
            order = np.argsort(star, kind="stable")          # by star, then by entry (pair order)
            s = star[order]
            pair = order // 2 + a                             # the catalog pair of each sorted entry
            first = np.ones(E, bool)
            first[1:] = s[1:] != s[:-1]
            prev_sorted = np.empty(E, np.int64)
            prev_sorted[1:] = pair[:-1]
            prev_sorted[first] = last[s[first]]
            out = np.empty(E, dtype)
            out[order] = prev_sorted
            f.write(out.tobytes())
            lastpos = np.ones(E, bool)                        # the chunk's last occurrence of each star
            lastpos[:-1] = s[1:] != s[:-1]
            last[s[lastpos]] = pair[lastpos]
            if progress is not None:
                progress.update(b - a)
        f.write(np.zeros(pad, dtype).tobytes())

    _atomic_npy(path, np.dtype(dtype), 2 * M + pad, fill)


def _usable(path: Path, n: int, dtype) -> np.ndarray | None:
    try:
        a = np.load(path, mmap_mode="r")
    except (OSError, ValueError):
        return None
    return a if a.shape == (n,) and a.dtype == np.dtype(dtype) else None


def load_or_build(i_raw, i: np.ndarray, j: np.ndarray, dtype, pad: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The memory-mapped (stars_plus_one, prev_padded) of a cached pair catalog, built first if missing or
    damaged; None when ``i_raw`` is not a cached catalog's file or its folder is not writable (the caller then
    derives them in memory).  A build expected to last more than ~2 s (:data:`SECONDS_PER_PAIR`) shows a
    progress bar on stderr when stderr is a terminal; after one the cache is held under its size limit
    (:func:`dualsight.catalogs.cache_budget.enforce_limit`; this entry, in use, is never the one removed)."""
    paths = derived_paths(i_raw)
    if paths is None:
        return None
    M = int(i.shape[0])
    n = 2 * M + pad
    vs, vp = paths
    stars = _usable(vs, n, dtype)
    if stars is not None and M:                    # sampled consistency with the pairs (a stale or foreign file)
        k = np.unique(np.linspace(0, M - 1, min(M, 257)).astype(np.int64))
        if not (np.array_equal(stars[2 * k], i[k] + 1) and np.array_equal(stars[2 * k + 1], j[k] + 1)):
            stars = None
    prev = _usable(vp, n, dtype) if stars is not None else None
    folder = vs.parent
    mark_in_use(folder, vs)
    todo = (stars is None) + (prev is None)
    if todo:
        bar = build_bar(f"voting index ({M:,} pairs)", todo * M, todo * M * SECONDS_PER_PAIR / 2)
        try:
            if stars is None:
                write_stars_plus_one(vs, i, j, dtype, pad, progress=bar)
                stars = _usable(vs, n, dtype)
            if prev is None:
                write_prev(vp, i, j, dtype, pad, progress=bar)
                prev = _usable(vp, n, dtype)
        except OSError:
            return None
        finally:
            bar.close()
        enforce_limit(folder)
    if stars is None or prev is None:
        return None
    return stars, prev
