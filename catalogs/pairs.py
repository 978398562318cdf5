"""Catalog of star pairs closer than a maximum angle, sorted by angle (for geometric voting).

Kolomenkin et al. (2008) vote with every catalog pair whose angular distance matches an observed
pair's within a tolerance; with the pairs sorted by angle, the candidates for one observed angle are
one contiguous slice found by two binary searches (:func:`dualsight.nav.votes.pair_windows`).
Angles are :func:`dualsight.scene.units.angle_between` (atan2 of |a x b| and a . b), the same
function that measures the observed pairs.

Building (:func:`build_pair_catalog`) is O(N * band) rather than O(N^2): stars are sorted by
declination, and a chunk of rows is only dotted with the stars whose declination is within
``max_angle`` of the chunk's (two stars closer than theta differ in declination by at most theta).

Memory is bounded whatever the catalog's size (``max_bytes``, default :data:`DEFAULT_MAX_BYTES` = 512 MiB:
a V 9 catalog over a 28 deg diagonal has ~10^8-10^9 pairs, 16 bytes each).  The build is an external
bucket sort:

1. one pass over the declination chunks; each chunk's pairs (at most ``max_block`` dot products, from the
   budget) are routed by angle into K angle buckets (edges equally spaced in 1 - cos(angle), i.e. about
   equally many pairs each for a uniform sky) and appended to temporary binary files;
2. each bucket, in angle order, is sorted in memory by (angle, i, j) and appended to the final arrays; a
   bucket larger than the budget allows (a clustered sky) is first split again by angle, recursively;
3. the arrays are ``.npy`` files (i int32, j int32, angle float64), written to temporary names and renamed.

The result equals, element for element, the whole catalog sorted at once by (angle, i, j).

Built with ``out=<stem>``, the three arrays are the files :func:`column_path` names (layout :data:`COLUMNS`);
the on-disk cache of built catalogs (keys, manifest, lock, damage checks) is
:mod:`dualsight.catalogs.pair_cache`.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualsight.catalogs.cache import resolve_cache_dir
from dualsight.errors import ConfigError
from dualsight.scene.units import angle_between

__all__ = ["FORMAT_VERSION", "DEFAULT_MAX_BYTES", "COLUMNS", "PairCatalog", "build_pair_catalog", "check_max_angle",
           "column_path"]

FORMAT_VERSION = 3
"""Bump when the build or the stored layout changes: old cache files are then ignored.
(2: angles by ``scene.units.angle_between``; version 1's einsum sums could differ by an ulp.
3: memory-mapped ``.npy`` arrays and a JSON manifest instead of one Parquet file.)"""

DEFAULT_MAX_BYTES = 512 << 20
"""Default memory budget of a build (bytes): 512 MiB."""

CHUNK_BYTES_PER_DOT = 200
"""Bytes a declination chunk needs per dot product when every one is a candidate pair (the dot, the
candidate indices, both unit vectors, the angle's temporaries and the routed record); the chunks get half
the budget: ``max_block = max_bytes / 2 / CHUNK_BYTES_PER_DOT``."""

SORT_BYTES_PER_PAIR = 64
"""Bytes per pair while a bucket is sorted (the 16-byte record, the sort's int64 order and scratch, the
gathered output columns); a bucket holds at most ``max_bytes / SORT_BYTES_PER_PAIR`` pairs."""

MAX_OPEN_BUCKETS = 256
"""Most bucket files written at once (a larger catalog's buckets are split again when sorted)."""

_REC = np.dtype([("angle", "<f8"), ("i", "<i4"), ("j", "<i4")])
COLUMNS = (("i", np.dtype("<i4")), ("j", np.dtype("<i4")), ("angle", np.dtype("<f8")))
"""(name, dtype) of the three arrays of a catalog, in file order: ``i``, ``j`` little-endian int32 catalog rows,
``angle`` little-endian float64 (rad); each is one ``.npy`` file (:func:`column_path`)."""
_WRITE_BUFFER = 1 << 16


@dataclass(frozen=True, eq=False)
class PairCatalog:
    """Star pairs, ascending by angle.

    i, j : (M,) int32 row indices into the :class:`~dualsight.catalogs.stars.StarCatalog`, i < j.
    angle : (M,) float64 angular distance (rad), ascending (ties by i, then j).
    limit_rad : the maximum angle the catalog was built with (every ``angle < limit_rad``), or
        None when unknown (then :attr:`max_angle` is the largest angle present).

    The arrays may be read-only memory maps (:func:`dualsight.catalogs.pair_cache.load_pair_catalog`).
    """

    i: np.ndarray
    j: np.ndarray
    angle: np.ndarray
    limit_rad: float | None = None

    def __post_init__(self):
        if not (self.i.shape == self.j.shape == self.angle.shape and self.angle.ndim == 1):
            raise ValueError(f"i, j, angle must be 1-D of one length, got {self.i.shape}, {self.j.shape}, "
                             f"{self.angle.shape}")

    def __len__(self) -> int:
        return int(self.angle.shape[0])

    @property
    def nbytes(self) -> int:
        """Size of the arrays (bytes): 16 per pair (two int32 and one float64), mapped or in memory."""
        return int(self.i.nbytes + self.j.nbytes + self.angle.nbytes)

    @property
    def max_angle(self) -> float:
        """Build limit (rad) if known, else the largest angle present (0 for an empty catalog)."""
        if self.limit_rad is not None:
            return float(self.limit_rad)
        return float(self.angle[-1]) if len(self) else 0.0


def check_max_angle(max_angle_rad) -> float:
    """``max_angle_rad`` as a float (rad) if it is a finite real number in (0, pi], else ConfigError (field
    ``catalog.max_pair_angle``)."""
    ok = isinstance(max_angle_rad, (int, float, np.integer, np.floating)) and not isinstance(max_angle_rad, bool)
    if not ok or not math.isfinite(max_angle_rad) or not 0.0 < max_angle_rad <= math.pi:
        raise ConfigError(f"must be a finite angle in (0, pi] rad, got {max_angle_rad!r}",
                          field="catalog.max_pair_angle")
    return float(max_angle_rad)


# ============================================================================================ pass 1: chunks
def _chunk_pairs(u: np.ndarray, theta: float, max_block: int):
    """Yield ``(i, j, angle)`` of every pair closer than ``theta``, one declination chunk at a time:
    (k,) int64 rows i < j of ``u`` and float64 angles, in no particular order.  A chunk dots at most
    ``max_block`` pairs of stars (at least one row's band)."""
    n = u.shape[0]
    if n < 2:
        return
    dec = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    order = np.argsort(dec, kind="stable")
    us, ds = u[order], dec[order]
    # cheap prefilter on the dot product, loosened so that no pair with angle < theta is lost;
    # the exact test is on the atan2 angle below
    cos_cut = math.cos(theta) - 1e-9
    a, width = 0, n
    while a < n:  # loop over chunks of rows, not over stars
        b = min(n, a + max(1, max_block // max(width, 1)))
        while True:                                                  # (b - a)(hi - a) <= max_block, or one row
            hi = int(np.searchsorted(ds, ds[b - 1] + theta + 1e-9, side="right"))
            if (b - a) * (hi - a) <= max_block or b - a == 1:
                break
            b = a + max(1, (b - a) // 2)
        width = hi - a
        dots = us[a:b] @ us[a:hi].T                                  # (b-a, hi-a)
        r, c = np.nonzero(dots >= cos_cut)
        del dots
        keep = c > r                                                 # column index is j_s - a, row is i_s - a
        r, c = r[keep] + a, c[keep] + a
        del keep
        ang = angle_between(us[r], us[c])
        ok = ang < theta
        oi, oj = order[r[ok]], order[c[ok]]
        res = (np.minimum(oi, oj), np.maximum(oi, oj), ang[ok])
        del r, c, ang, ok, oi, oj                                    # not held while the consumer works
        yield res
        del res
        a = b


def _bucket_edges(n_buckets: int, theta: float) -> np.ndarray:
    """(K - 1,) inner edges of K angle buckets, equally spaced in 1 - cos(angle) over [0, theta)."""
    k = np.arange(1, n_buckets, dtype=np.float64)
    return np.arccos(1.0 - k / n_buckets * (1.0 - math.cos(theta)))


def _sort_order(rec: np.ndarray) -> np.ndarray:
    """Order of records by (angle, i, j): ``np.lexsort((j, i, angle))``, computed as a sort by angle with
    the (rare) runs of equal angles then sorted by (i, j)."""
    s = np.argsort(rec["angle"])
    a = rec["angle"][s]
    tie = np.flatnonzero(a[1:] == a[:-1])
    del a
    if tie.size:
        members = np.unique(np.concatenate([tie, tie + 1]))          # positions (in s) inside a run of ties
        am = rec["angle"][s[members]]
        run = np.cumsum(np.r_[True, (np.diff(members) > 1) | (am[1:] != am[:-1])])
        sub = s[members]
        s[members] = sub[np.lexsort((rec["j"][sub], rec["i"][sub], run))]
    return s


class _Builder:
    """One build's buckets (temporary files in ``work``) and the three output files."""

    def __init__(self, work: Path, theta: float, max_bytes: int, n_buckets: int | None, n_est: float,
                 progress=None):
        self.work, self.theta = work, theta
        self.progress = progress
        self.cap = max(2, int(max_bytes) // SORT_BYTES_PER_PAIR)         # pairs a bucket may hold to be sorted
        k = int(n_buckets) if n_buckets is not None else int(math.ceil(1.5 * n_est / self.cap))
        self.k = min(max(1, k), MAX_OPEN_BUCKETS)
        self.edges = _bucket_edges(self.k, theta)
        self.counts = np.zeros(self.k, np.int64)
        self._serial = 0
        self.splits = 0

    def _new_file(self) -> Path:
        self._serial += 1
        return self.work / f"b{self._serial:08d}.rec"

    def route(self, chunks) -> list[tuple[Path, int]]:
        """Pass 1: every chunk's pairs appended to the bucket files; returns the buckets in angle order."""
        paths = [self._new_file() for _ in range(self.k)]
        files = [None] * self.k
        try:
            for i, j, ang in chunks:
                if ang.size == 0:
                    continue
                rec = np.empty(ang.size, _REC)
                rec["angle"], rec["i"], rec["j"] = ang, i, j
                del i, j, ang
                _append_routed(rec, self.edges, paths, files, self.counts)
                if self.progress is not None:
                    self.progress.update(rec.size)
        finally:
            for f in files:
                if f is not None:
                    f.close()
        return [(p, int(c)) for p, c in zip(paths, self.counts)]

    def emit(self, path: Path, count: int, outs) -> None:
        """Pass 2: the bucket sorted by (angle, i, j) and appended to ``outs`` (i, j, angle files), split
        again by angle first when it holds more than ``cap`` pairs."""
        if count == 0:
            path.unlink(missing_ok=True)
            return
        if count > self.cap:
            children = self._split(path, count)
            if children is not None:
                path.unlink()
                for p, c in children:
                    self.emit(p, c, outs)
                return
        rec = np.fromfile(path, dtype=_REC)
        path.unlink()
        if rec.size != count:
            raise OSError(f"bucket file {path} holds {rec.size} pairs, expected {count}")
        s = _sort_order(rec)
        for (name, dt), f in zip(COLUMNS, outs):
            f.write(np.ascontiguousarray(rec[name][s], dtype=dt).data)
        if self.progress is not None:
            self.progress.update(count)

    def _slices(self, path: Path, count: int):
        step = max(1, self.cap // 2)
        with open(path, "rb") as f:
            for start in range(0, count, step):
                yield np.fromfile(f, dtype=_REC, count=min(step, count - start))

    def _split(self, path: Path, count: int):
        """Route a too-large bucket into sub-buckets by angle (edges from a histogram of its angles), each
        aimed at <= cap pairs; None when its angles are all equal (it is then sorted whole)."""
        lo, hi = math.inf, -math.inf
        for rec in self._slices(path, count):
            lo, hi = min(lo, float(rec["angle"].min())), max(hi, float(rec["angle"].max()))
        if not lo < hi:
            return None
        bins = 4096
        grid = lo + (hi - lo) * np.arange(1, bins, dtype=np.float64) / bins
        hist = np.zeros(bins, np.int64)
        for rec in self._slices(path, count):
            hist += np.bincount(np.searchsorted(grid, rec["angle"], side="right"), minlength=bins)
        target = max(self.cap, -(-count // (MAX_OPEN_BUCKETS // 2)))   # greedy: <= 2 count / target + 1 files
        cuts, run = [], 0
        for b in range(bins):                                        # greedy: cut before a bin that overflows
            if run and run + hist[b] > target:
                cuts.append(grid[b - 1])
                run = 0
            run += hist[b]
        edges = np.unique(np.array([e for e in cuts if lo < e <= hi] or [hi], np.float64))
        paths = [self._new_file() for _ in range(edges.size + 1)]
        files = [None] * len(paths)
        counts = np.zeros(len(paths), np.int64)
        try:
            for rec in self._slices(path, count):
                _append_routed(rec, edges, paths, files, counts)
        finally:
            for f in files:
                if f is not None:
                    f.close()
        self.splits += 1
        return [(p, int(c)) for p, c in zip(paths, counts)]


def _append_routed(rec: np.ndarray, edges: np.ndarray, paths, files, counts) -> None:
    """Append each record to the file of its angle bucket (bucket k: edges[k-1] <= angle < edges[k])."""
    b = np.searchsorted(edges, rec["angle"], side="right")
    s = np.argsort(b, kind="stable")
    rec, b = rec[s], b[s]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    ends = np.r_[starts[1:], b.size]
    for st, en in zip(starts, ends):
        k = int(b[st])
        if files[k] is None:
            files[k] = open(paths[k], "ab", buffering=_WRITE_BUFFER)
        files[k].write(rec[st:en].data)
        counts[k] += en - st


def _npy_header(f, dtype: np.dtype, n: int) -> None:
    np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                                             "shape": (int(n),)})


def _write_arrays(u: np.ndarray, theta: float, targets: dict[str, Path], work: Path, max_bytes: int,
                  max_block: int | None, n_buckets: int | None, progress=None) -> dict:
    """Build the catalog of ``u`` into the ``.npy`` files ``targets`` (name -> path; written to temporary
    names and renamed); bucket files go to ``work``.  ``progress`` (a tqdm-like bar or None) advances by the
    pairs routed (pass 1), then by the pairs sorted and written (pass 2): 2 per pair in all.  Returns build
    statistics."""
    n = u.shape[0]
    if max_block is None:
        max_block = max(1024, int(max_bytes) // 2 // CHUNK_BYTES_PER_DOT)
    n_est = n * (n - 1) / 2 * (1.0 - math.cos(theta)) / 2                 # pairs for a uniform sky
    bld = _Builder(work, theta, max_bytes, n_buckets, n_est, progress)
    buckets = bld.route(_chunk_pairs(u, theta, int(max_block)))
    total = sum(c for _, c in buckets)
    if progress is not None:
        progress.total = max(2 * total, 1)                           # the estimate's total, now exact
    tmps, outs = {}, []
    try:
        for name, dt in COLUMNS:
            fd, tmp = tempfile.mkstemp(prefix=f".{targets[name].name}.", suffix=".tmp", dir=targets[name].parent)
            tmps[name] = Path(tmp)
            f = os.fdopen(fd, "wb", buffering=_WRITE_BUFFER)
            outs.append(f)
            _npy_header(f, dt, total)
        starts = [f.tell() for f in outs]
        for p, c in buckets:
            bld.emit(p, c, outs)
        for (name, dt), f, st in zip(COLUMNS, outs, starts):
            if f.tell() - st != total * dt.itemsize:                 # every pair routed is written once
                raise OSError(f"pair catalog build wrote {(f.tell() - st) // dt.itemsize} {name} values, "
                              f"expected {total}")
        for f in outs:
            f.flush()
            os.fsync(f.fileno())
            f.close()
        for name, _ in COLUMNS:
            os.replace(tmps[name], targets[name])
    except BaseException:
        for f in outs:
            f.close()
        for t in tmps.values():
            t.unlink(missing_ok=True)
        raise
    return {"pairs": total, "buckets": bld.k, "splits": bld.splits, "max_block": int(max_block)}


def build_pair_catalog(unit: np.ndarray, max_angle_rad: float, max_block: int | None = None, *,
                       max_bytes: int = DEFAULT_MAX_BYTES, n_buckets: int | None = None,
                       out: str | Path | None = None, work_dir: str | Path | None = None,
                       progress=None) -> PairCatalog:
    """Every pair of stars closer than ``max_angle_rad`` (module docstring: an external bucket sort).

    Parameters
    ----------
    unit : (N, 3) float64 unit vectors (the StarCatalog's ``unit``); row numbers become ``i``/``j``.
    max_angle_rad : keep pairs with angle < max_angle_rad (rad), in (0, pi].
    max_block : most dot products computed at once; None = from the budget
        (``max_bytes / 2 / CHUNK_BYTES_PER_DOT``).  A tuning knob only: the result does not depend on it.
    max_bytes : memory budget of the build (bytes; the pairs themselves live in files until sorted).
    n_buckets : number of angle buckets of the first pass (None = from the budget and an estimate of the
        pair count); a tuning knob only.
    out : None = return the arrays in memory; a path stem = write ``<stem>.i.npy``, ``<stem>.j.npy``,
        ``<stem>.angle.npy`` (atomically) and return them memory-mapped read-only.
    work_dir : folder of the temporary bucket files (default: the folder of ``out``, else the cache
        folder, :func:`dualsight.catalogs.cache.resolve_cache_dir`); they are removed when done.
    progress : None, or a tqdm-like bar (``update(n)``, ``total``) advanced by 2 per pair (routed, then sorted)
        chunk by chunk (:func:`dualsight.catalogs.build_progress.build_bar`); the caller closes it.

    Returns
    -------
    :class:`PairCatalog` with i < j, sorted by angle (ties by i, j).
    """
    theta = check_max_angle(max_angle_rad)
    if not (isinstance(max_bytes, (int, np.integer)) and max_bytes > 0):
        raise ValueError(f"max_bytes must be a positive integer, got {max_bytes!r}")
    u = np.ascontiguousarray(np.asarray(unit, dtype=np.float64).reshape(-1, 3))
    if out is not None:
        stem = Path(out)
        stem.parent.mkdir(parents=True, exist_ok=True)
        base = Path(work_dir) if work_dir is not None else stem.parent
    else:
        stem = None
        base = Path(work_dir) if work_dir is not None else resolve_cache_dir(None)
    base.mkdir(parents=True, exist_ok=True)
    prefix = f".{stem.name}.build-" if stem is not None else ".pairs-build-"
    with tempfile.TemporaryDirectory(prefix=prefix, dir=base) as tmp:
        work = Path(tmp)
        targets = {name: (column_path(stem, name) if stem is not None else work / f"out.{name}.npy")
                   for name, _ in COLUMNS}
        _write_arrays(u, theta, targets, work, int(max_bytes), max_block, n_buckets, progress)
        arrays = {name: np.load(targets[name], mmap_mode="r" if stem is not None else None) for name, _ in COLUMNS}
    return PairCatalog(i=arrays["i"], j=arrays["j"], angle=arrays["angle"], limit_rad=theta)


def column_path(stem: Path, name: str) -> Path:
    """The ``.npy`` file of array ``name`` (a :data:`COLUMNS` name) of the catalog written to ``stem``:
    ``<stem>.<name>.npy``."""
    return stem.with_name(f"{stem.name}.{name}.npy")
