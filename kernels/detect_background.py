"""Stage 1 of the real-sensor detector (:mod:`dualsight.kernels.detect_local`, step 1 of its docstring): the
sky's level and noise per frame from tiled, sigma-clipped statistics, median-filtered over the tile grid
(:func:`tile_background`) and interpolated between tile centres (:func:`interpolate_tiles`); and the
sigma-clipped statistics themselves: of sorted rows (:func:`clipped_stats`, the tiles) and of one sample
(:func:`robust_std`, the matched filter's noise measurement in :mod:`dualsight.kernels.detect_candidates`),
with the exact :func:`median_1d`.  Pure numpy/OpenCV functions over arrays (ADU in, ADU out); the tiles' clipping
optionally as a compiled pass (``engine`` "taichi": :mod:`dualsight.kernels.detect_passes`)."""

import functools
import math
import time

import numpy as np

from dualsight.kernels.detect_passes import pixel_dtype_supported, sorted_clipped_stats

_SQRT2 = math.sqrt(2.0)


def _clip_var_factor(c: float) -> float:
    """Variance of a standard normal truncated to [-c, c]."""
    p = math.erf(c / _SQRT2)
    return 1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi) / p


def _sorted_mad(s: np.ndarray, med: np.ndarray) -> np.ndarray:
    """Exact median absolute deviation from ``med`` of each row of sorted ``s`` (T, N): the k-th smallest
    |s - med| (k = ceil(N / 2)) is min over windows [i, i + k) of max(med - s[i], s[i + k - 1] - med); the
    window's two ends move in opposite directions, so the best start is found by bisection (one gather per
    row and step)."""
    T, N = s.shape
    rows = np.arange(T)
    k = max((N + 1) // 2, 1)
    a, b = np.zeros(T, np.int64), np.full(T, N - k, np.int64)          # candidate starts [a, b]
    for _ in range(int(math.ceil(math.log2(N + 1))) + 1):
        m = (a + b) // 2
        g = (s[rows, m + k - 1] - med) - (med - s[rows, m])
        go = (g < 0) & (m < b)
        a = np.where(go, m + 1, a)
        b = np.where(go, b, m)
    ip = np.maximum(a - 1, 0)
    d1 = np.maximum(med - s[rows, a], s[rows, a + k - 1] - med)
    d0 = np.maximum(med - s[rows, ip], s[rows, ip + k - 1] - med)
    return np.minimum(d0, d1).astype(np.float64)


def _first_at_least(s: np.ndarray, v: np.ndarray, strict: bool) -> np.ndarray:
    """Per row of sorted ``s`` (T, N): the count of values < v (``strict`` False) or <= v (True), v (T,), by
    bisection over the rows at once (one gather per row and step)."""
    T, N = s.shape
    rows = np.arange(T)
    lo, hi = np.zeros(T, np.int64), np.full(T, N, np.int64)
    for _ in range(int(math.ceil(math.log2(N + 1))) + 1):
        m = (lo + hi) // 2
        x = s[rows, np.minimum(m, N - 1)]
        below = (x <= v) if strict else (x < v)
        go = below & (m < hi)
        lo = np.where(go, m + 1, lo)
        hi = np.where(go, hi, m)
    return lo


def lattice_quantiles(s: np.ndarray, p, counter=None) -> np.ndarray:
    """Quantiles ``p`` (P,) in (0, 1) of each row of sorted values ``s`` (T, N) on the 1-ADU lattice of integer
    counts, interpolated within the tied level (grouped-data quantile): a value v held by n_eq of the row's values,
    n_lo of them below it, stands for the interval [v - 1/2, v + 1/2), filled uniformly, so the quantile at rank
    p N is v - 1/2 + (p N - n_lo) / n_eq (continuous in p; for untied values it is within 1/2 ADU of the order
    statistic).  ``counter(v, strict)`` (optional) gives each row's count of values < v (<= v when strict), as
    a bisection over the rows does by default.  Returns (T, P) float64 (ADU)."""
    T, N = s.shape
    counter = counter or (lambda v, strict: _first_at_least(s, v, strict))
    out = np.empty((T, len(p)))
    for j, q in enumerate(p):
        k = q * N
        v = s[:, min(max(int(k), 0), N - 1)].astype(np.float64)
        n_lo = counter(v, False)
        n_eq = np.maximum(counter(v, True) - n_lo, 1)
        out[:, j] = v - 0.5 + np.clip((k - n_lo) / n_eq, 0.0, 1.0)
    return out


def lattice_start(s: np.ndarray, counter=None):
    """The clipping's starting centre and sigma of the rows of sorted ``s`` (T, N) whose median is a tied value
    (integer counts whose noise spans a few ADU, or a frame dark-subtracted and clipped at 0): there the median
    moves in whole ADU and the MAD rounds to one level or to 0 (a sigma of 0 would never widen the clipping
    window and every noise peak would be a star).  Their centre is the interpolated median and their sigma the
    interpolated interquartile range / 1.34898 (:func:`lattice_quantiles`; both exact for a normal distribution
    sampled finely, and sigma > 0 as soon as a quarter of the row differs from its median level).
    ``counter(rows, v, strict)`` (optional): the counts of values < v (<= v when strict) of the given rows.
    Returns (centre (R,), sigma (R,), row indices (R,)) float64, float64, int64, or None when no row is tied."""
    T, N = s.shape
    if N < 4:
        return None
    m = (N - 1) // 2
    tied = np.flatnonzero((s[:, m] == s[:, max(m - 1, 0)]) | (s[:, m] == s[:, min(m + 1, N - 1)]))
    if tied.size == 0:
        return None
    rc = None if counter is None else (lambda v, strict: counter(tied, v, strict))
    q = lattice_quantiles(s[tied], (0.25, 0.5, 0.75), rc)
    return q[:, 1], (q[:, 2] - q[:, 0]) / 1.3489795, tied


def clipped_stats(s: np.ndarray, clip: float, iters: int):
    """Sigma-clipped level and noise of each row of sorted values ``s`` (T, N), any real dtype (ADU): the median and
    1.4826 MAD, then ``iters`` windows of the values within ``clip`` sigma of the centre (clipped mean, clipped
    standard deviation corrected for the truncation; :mod:`dualsight.kernels.detect_local`, step 1).

    The kept pixels are always a contiguous run [lo, hi) of a sorted row: its bounds are counts of values
    below the window's ends and its sums one ``add.reduceat`` over all rows, on the values relative to the
    row's median (float32 is exact enough: a window never includes the bright tail).  For 8/16-bit frames
    the counts are one ``searchsorted`` over all rows at once on integer keys (row r's values offset by
    r x (max + 2); the window's ends rounded to the integers that give the same counts as the float32
    comparisons), else comparisons.
    Returns (level (T,), sigma (T,), kept fraction (T,)) float64."""
    T, N = s.shape
    rows = np.arange(T, dtype=np.int64)
    med = 0.5 * (s[:, (N - 1) // 2].astype(np.float64) + s[:, N // 2])
    sig = np.zeros(T)
    integer = s.dtype.kind == "u" and s.dtype.itemsize <= 2
    if integer:
        # integer keys row x B + s (B = max + 2): counts below a value of every row in one searchsorted
        vmax = int(np.iinfo(s.dtype).max) + 1
        B = vmax + 1
        kt = np.int32 if T * B < 2 ** 31 else np.int64
        base = rows.astype(kt) * kt(B)
        keys = (s.astype(kt) + base[:, None]).ravel()
        first = rows * N

        def lattice_count(r, v, strict):    # rows r: values < v (<= v when strict), v integer-valued
            return np.searchsorted(keys, base[r] + v.astype(kt), "right" if strict else "left") - first[r]
    tied = lattice_start(s, lattice_count if integer else None)
    untied = np.ones(T, bool)
    if tied is not None:             # quantised rows: interpolated median and quartiles (lattice_start)
        t_med, t_sig, t_rows = tied
        med[t_rows], sig[t_rows] = t_med, t_sig
        untied[t_rows] = False
    if untied.all():
        sig = 1.4826 * _sorted_mad(s, med)
    elif untied.any():
        sig[untied] = 1.4826 * _sorted_mad(s[untied], med[untied])
    if iters <= 0:
        return med, sig, np.ones(T)
    d = np.empty((T, N + 1), np.float32)            # a zero column ends every row: windows never run past it
    d[:, N] = 0.0
    np.subtract(s, med.astype(np.float32)[:, None], out=d[:, :N], casting="unsafe")
    dd = d * d
    flat, flat2 = d.ravel(), dd.ravel()
    if integer:
        # for integer s and the float32 threshold t (exactly, in float64):
        # s - med < t <=> s < ceil(med + t) and s - med <= t <=> s < floor(med + t) + 1

        def count(t, side):          # values of each row < t (side "left") or <= t ("right")
            x = med + t.astype(np.float64)
            q = np.ceil(x) if side == "left" else np.floor(x) + 1.0
            return np.searchsorted(keys, base + np.clip(q, 0, vmax).astype(kt), "left") - first
    else:
        def count(t, side):
            return (d[:, :N] < t[:, None]).sum(1) if side == "left" else (d[:, :N] <= t[:, None]).sum(1)
    corr = 1.0 / math.sqrt(_clip_var_factor(clip))
    centre = np.zeros(T)                             # relative to med
    lo, hi = np.zeros(T, np.int64), np.full(T, N, np.int64)
    idx = np.empty(2 * T, np.int64)
    for _ in range(iters):
        lo = count((centre - clip * sig).astype(np.float32), "left")
        hi = count((centre + clip * sig).astype(np.float32), "right")
        idx[0::2] = rows * (N + 1) + lo
        idx[1::2] = rows * (N + 1) + hi
        n = hi - lo
        good = n > 0
        m = np.maximum(n, 1)
        mean = np.add.reduceat(flat, idx)[0::2].astype(np.float64) / m
        var = np.maximum(np.add.reduceat(flat2, idx)[0::2].astype(np.float64) / m - mean * mean, 0.0)
        centre = np.where(good, mean, centre)
        sig = np.where(good & (sig > 0), np.sqrt(var) * corr, sig)
    return med + centre, sig, (hi - lo) / N


def _kth_pair(v: np.ndarray, k: int):
    """(k-th, (k + 1)-th) smallest values of 1-D ``v`` (0-based; both the k-th when k + 1 == v.size), exactly,
    as ``np.partition(v, (k, k + 1))`` gives them, for less: the values are bracketed by order statistics of a
    strided subsample (every 16th value, the bracket +-5 binomial standard deviations of the subsample's rank
    around k), the values below the bracket counted, and the k-th selected among the values in the bracket (a
    few % of v).  When the bracket misses (probability ~1e-6) it is one full ``np.partition``."""
    N = v.size
    k2 = min(k + 1, N - 1)
    if N >= 4096:
        sub = v[::16]
        ns = sub.size
        j = k * ns / N
        m = 5.0 * math.sqrt(ns * 0.25) + 2.0
        ja, jb = max(int(j - m), 0), min(int(j + m) + 1, ns - 1)
        ps = np.partition(sub, (ja, jb))
        lo, hi = ps[ja], ps[jb]
        below = int(np.count_nonzero(v < lo))
        mid = v[(v >= lo) & (v <= hi)]
        if below <= k and k2 < below + mid.size:
            p = np.partition(mid, (k - below, k2 - below))
            return p[k - below], p[k2 - below]
    p = np.partition(v, (k, k2))
    return p[k], p[k2]


def median_1d(v: np.ndarray) -> float:
    """Median of a 1-D sample ``v`` (N >= 1 values), equal to ``np.median(v)`` bit for bit (the mean of the two
    middle values for even N), as a float: the two middle order statistics by a bracketed selection on a strided
    subsample (a few % of a full partition's work for N >= 4096)."""
    N = v.size
    a, b = _kth_pair(v, (N - 1) // 2)
    return float(a) if N % 2 else 0.5 * (float(a) + float(b))


def order_statistic(v: np.ndarray, k: int) -> float:
    """The k-th smallest value (0-based) of a 1-D sample ``v``, exactly, as ``np.partition(v, k)[k]`` (the
    bracketed selection of :func:`median_1d`)."""
    return float(_kth_pair(v, int(k))[0])


def robust_std(v: np.ndarray, clip: float = 3.0, iters: int = 3, sub: int = 4) -> float:
    """The standard deviation of :func:`robust_stats` (its docstring)."""
    return robust_stats(v, clip, iters, sub)[1]


def robust_stats(v: np.ndarray, clip: float = 3.0, iters: int = 3, sub: int = 4) -> tuple[float, float]:
    """(Sigma-clipped mean, sigma-clipped standard deviation (truncation-corrected)) of a sample ``v`` (any shape,
    flattened; in its units, floats; (0, 0) for fewer than 8 values, (median, 0) for a sample whose MAD is 0):
    the median and 1.4826 MAD,
    then the first ``iters`` - 1 windows (clipped mean and standard deviation of the values with
    |v - c| <= clip sd) on every ``sub``-th value, the last window on all values (sample sizes >= 4096;
    smaller samples: every window on all values).  The last window's mean and standard deviation are the full
    sample's to ~1/sqrt(N) of the window's own statistical error (the window's edges sit where the normal
    density is 0.4 % of its peak).  A window's mean and standard deviation are computed in float64 from the
    kept values' sum and sum of squares relative to the previous centre (exact medians: :func:`median_1d`)."""
    v = np.asarray(v, np.float64).ravel()
    if v.size < 8:
        return 0.0, 0.0
    first = v[::sub] if v.size >= 4096 and iters > 1 else v
    c = median_1d(first)
    sd = 1.4826 * median_1d(np.abs(first - c))
    if sd <= 0:
        return c, 0.0
    corr = 1.0 / math.sqrt(_clip_var_factor(clip))
    for it in range(iters):
        dv = (v if it == iters - 1 else first) - c
        w = dv[np.abs(dv) <= clip * sd]
        n = w.size
        if n < 8:
            break
        m = float(w.sum()) / n
        # einsum's own loop, not BLAS: a threaded ddot splits the sum by thread count, and a frame must give the
        # same bits in a 1-thread worker as in a 2-thread process
        c, sd = c + m, math.sqrt(max(float(np.einsum("i,i->", w, w)) / n - m * m, 0.0)) * corr
    return c, sd


@functools.lru_cache(maxsize=4)
def row_sort_kind(dtype) -> str:
    """The faster ``numpy.sort`` kind, "stable" or "quicksort", for rows of 256 values of an 8 or 16-bit unsigned
    ``dtype`` (the tiles' quarter samples of :func:`tile_background`) on this machine, measured once per process and
    dtype on 256 such rows (~1 ms).  Both give the same sorted rows (plain values), so the choice changes the time
    only: numpy's "stable" is a radix sort for these types (~2 ns per value), its "quicksort" the x86-simd-sort
    kernels where the CPU has AVX-512 (16-bit keys: ~0.25 ns per value; 1024 rows of 256: 0.06 ms against 0.5 ms on
    this project's VMs, numpy 2.4, 2026-11-27), else an introsort several times slower than the radix sort (and
    for 8-bit keys always: 4.1 ms against 0.25)."""
    dt = np.dtype(dtype)
    rows = np.random.default_rng(0).integers(0, np.iinfo(dt).max, (256, 256), endpoint=True).astype(dt)
    best, pick = math.inf, "stable"
    for kind in ("stable", "quicksort"):
        np.sort(rows[:8], axis=1, kind=kind)           # warm
        t0 = time.perf_counter()
        np.sort(rows, axis=1, kind=kind)
        t = time.perf_counter() - t0
        if t < best:
            best, pick = t, kind
    return pick


def tile_background(img: np.ndarray, tile: int = 32, clip: float = 3.0, iters: int = 3, mesh: int = 3,
                    engine: str = "numpy"):
    """Level and noise sigma of every ``tile`` x ``tile`` square of one (H, W) frame (uint8, uint16 or float; ADU)
    (:mod:`dualsight.kernels.detect_local`, step 1): ``clip``-sigma clipping, ``iters`` windows, on a quarter of
    each square's pixels (even rows and columns; all of them for odd squares), squares keeping under half of their
    sample replaced by the frame's median square, then median filters over the grid: ``mesh`` x ``mesh`` for the
    level, ``mesh`` + 2 for the noise (where the grid has that many squares; ``mesh`` 1 = off).  ``engine``
    "taichi": the clipping of the sorted rows as one compiled pass
    (:func:`dualsight.kernels.detect_passes.sorted_clipped_stats`, float64 sums), "numpy": :func:`clipped_stats`.

    The sample's level errs by ~sigma / sqrt(T^2 / 4) (0.063 sigma for 32 px squares) and its sigma by ~1 /
    sqrt(T^2 / 2) (4.4 %) before the median filters (3 x 3: ~0.44 x that; 5 x 5: ~0.27 x).  The noise map takes the
    wider filter because its error, not the level's, sets most of the threshold's scatter: Z = F / sigma, so a
    relative error e of sigma moves a Z = 5 threshold by 5 e, a level error d (in sigma) by ~3.4 d at PSF sigma
    0.9 px; a median filter keeps a step between two flat regions where it is, and a sensor's noise varies over
    hundreds of pixels, not one square.  (Reading every pixel in the last window, as before 2026-11-28, halved both
    errors for ~0.5-1 ms per 1024 x 1024 frame, a fifth of the detector; ``benchmarks/bench_detect.py``, 96 frames
    per condition: the same completeness and false rate, docs/measurements.md.)

    Returns (level (ny, nx) float32, sigma (ny, nx) float32), ny = ceil(H / tile), nx = ceil(W / tile)."""
    import cv2

    H, W = img.shape
    ny, nx = -(-H // tile), -(-W // tile)
    a = img
    if a.dtype.kind == "u" and a.dtype.itemsize <= 2:
        kind = row_sort_kind(a.dtype)       # radix sort or numpy's SIMD quicksort, whichever is faster here
    else:
        a = a.astype(np.float32, copy=False)
        kind = "quicksort"
    if (ny * tile, nx * tile) != (H, W):
        a = np.pad(a, ((0, ny * tile - H), (0, nx * tile - W)), mode="symmetric")
    T = ny * nx
    if tile % 2 == 0:                      # every other row and column of each square
        h = tile // 2
        rows = np.ascontiguousarray(a[::2, ::2].reshape(ny, h, nx, h).transpose(0, 2, 1, 3)).reshape(T, h * h)
    else:
        rows = np.ascontiguousarray(a.reshape(ny, tile, nx, tile).transpose(0, 2, 1, 3)).reshape(T, tile * tile)
    if np.may_share_memory(rows, img):     # a one-tile-wide frame's rows can be a view of the caller's frame
        rows = rows.copy()
    rows.sort(axis=1, kind=kind)           # in place: a copy of the frame's pixels already
    if engine == "taichi" and pixel_dtype_supported(a.dtype):    # compiled, float64 sums
        level, sig, kept = sorted_clipped_stats(rows, clip, iters, 1.0 / math.sqrt(_clip_var_factor(clip)))
    else:                                                         # numpy, float32 sums
        level, sig, kept = clipped_stats(rows, clip, iters)
    bad = kept < 0.5
    if bad.any() and not bad.all():
        level[bad] = np.median(level[~bad])
        sig[bad] = np.median(sig[~bad])
    level = level.reshape(ny, nx).astype(np.float32)
    sig = sig.reshape(ny, nx).astype(np.float32)
    if mesh > 1 and ny * nx > 1:
        level = cv2.medianBlur(level, mesh)
        sig = cv2.medianBlur(sig, mesh + 2 if min(ny, nx) >= mesh + 2 else mesh)
    return level, sig


def interpolate_tiles(grid: np.ndarray, tile: int, H: int, W: int) -> np.ndarray:
    """(H, W) float32 bilinear interpolation of a tile grid between the tiles' centres (pixel (r, c) at
    grid coordinate ((r + 0.5) / tile - 0.5, (c + 0.5) / tile - 0.5); constant beyond the outer centres)."""
    import cv2

    ny, nx = grid.shape
    return cv2.resize(np.ascontiguousarray(grid, np.float32), (nx * tile, ny * tile),
                      interpolation=cv2.INTER_LINEAR)[:H, :W]
