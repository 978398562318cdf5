"""The real-sensor detector's full-frame passes as compiled Taichi kernels (:mod:`dualsight.kernels.detect_local`
with ``fit_engine`` "taichi", the default), reading the frame in its own dtype (uint8, uint16, float32, float64):

* :func:`sorted_clipped_stats`: the tiles' median, MAD (or the 1-ADU lattice's quantiles) and first clipping
  windows on their sorted quarter samples (:func:`dualsight.kernels.detect_background.clipped_stats`' rounds of
  batched searches and reductions over all tiles): 0.28 ms against 0.85 ms on an ESA frame's 768 tiles.
* :func:`foreground_components`: the candidates' connected components (union-find over the foreground pixels in
  raster order) and their 3 x 3 local maxima (step 3; the numpy path: :func:`~dualsight.kernels.detect_candidates.
  sparse_components`' rounds of gathers and pointer jumping, and 8 gathers for the maxima).
* :func:`candidate_maxima`: the whole candidate search after the threshold (step 3) in the same pass: those
  components and maxima, then per component its maxima sorted and deblended (the numpy path: a lexsort and the pairs'
  distance and dip tests, ~40 numpy calls per pass); ``find_candidates`` (threshold included) 0.43 ms against 0.70 ms
  per ESA frame, both passes (one core, 2026-11-27), the same candidates in the same order.

Only passes a compiled loop does faster than numpy/OpenCV's vectorised calls live here: the bilinear background
and noise maps and the residual (OpenCV's ``resize`` and one subtraction, ~0.36 ms) took 4.2 ms as a Taichi loop
with the interpolation per pixel (measured 2026-11-27), the matched filter is OpenCV's ``sepFilter2D`` (SIMD).
Taichi's CPU backend does not vectorise these loops: a pass over a 1024 x 1024 16-bit frame costs ~0.5 ns per pixel
however it is written (the tiles' last clipping window over every pixel, as the detector had it until 2026-11-28,
with integer bounds and sums: 0.52 ms against 0.54 in float64; unrolled by 8 or 32 with separate accumulators, or
over the flat frame: 0.93-0.99 ms; measured 2026-11-27), ~4x an OpenCV or
numpy SIMD pass, so a fused compiled pass over the frame (background, filter and threshold in one loop) would be
slower than the OpenCV calls it replaced.
Each kernel runs its loop serially (one frame is well under 1 ms of work: a parallel launch's round trip through
Taichi's thread pool, ~0.1 ms, costs more than a second thread gains; frames run in parallel in the workers).
Equal to the numpy path up to rounding (float64 sums here, float32 there; tests/test_detect_passes.py)."""

import numpy as np

from dualsight.kernels.taichi_runtime import KernelCache

_PIXEL = {np.dtype(np.uint8).str: "u8", np.dtype(np.uint16).str: "u16", np.dtype(np.float32).str: "f32",
          np.dtype(np.float64).str: "f64"}


def pixel_type_name(dtype) -> str:
    """The Taichi type name ("u8", "u16", "f32", "f64") of frames of ``dtype`` (uint8, uint16, float32, float64)."""
    return _PIXEL[np.dtype(dtype).str]


def pixel_dtype_supported(dtype) -> bool:
    """Whether the kernels read frames of ``dtype`` directly (uint8, uint16, float32, float64)."""
    return np.dtype(dtype).str in _PIXEL


_KERNELS = KernelCache({})    # each kernel built on first use (the builders register below)


def _build_components(dtype=None):
    import taichi as ti

    i64 = ti.i64

    @ti.func
    def find(parent: ti.template(), i):
        while parent[i] != i:                          # path halving
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    @ti.func
    def label(f: ti.template(), Z: ti.template(), eight, parent: ti.template(), lab: ti.template(),
              peak: ti.template()):
        """Components (lab: numbered by their first pixel in raster order) and 3 x 3 peaks of the foreground pixels
        f of Z; returns the number of components."""
        n = f.shape[0]
        H, W = Z.shape[0], Z.shape[1]
        j = 0                                          # first foreground pixel at or after (r - 1, c - 1)
        for i in range(n):
            parent[i] = i
            p = f[i]
            r = ti.cast(p // W, ti.i32)
            c = ti.cast(p % W, ti.i32)
            while j < i and f[j] < p - W - 1:
                j += 1
            # backward neighbours: left, and the row above (left, centre, right; centre only for 4)
            for q in range(4):
                dr = -1
                dc = q - 1
                if q == 3:
                    dr, dc = 0, -1
                if (eight != 0 or dr == 0 or dc == 0) and r + dr >= 0 and 0 <= c + dc < W:
                    t = p + dr * W + dc
                    k = i - 1 if q == 3 else j
                    if q != 3:
                        while k < i and f[k] < t:
                            k += 1
                    if k >= 0 and k < i and f[k] == t:
                        a, b = find(parent, i), find(parent, k)
                        if a != b:                 # the larger root under the smaller
                            parent[ti.max(a, b)] = ti.min(a, b)
            # 3 x 3 local maximum (pixels outside the frame ignored)
            z = Z[r, c]
            pk = 1
            for dr2, dc2 in ti.ndrange((-1, 2), (-1, 2)):
                rr = r + dr2
                cc = c + dc2
                if 0 <= rr < H and 0 <= cc < W and z < Z[rr, cc]:
                    pk = 0
            peak[i] = ti.cast(pk, ti.u8)
        m = 0
        for i in range(n):                             # components numbered by their first pixel (raster order)
            root = find(parent, i)
            if root == i:
                lab[i] = m
                m += 1
            else:
                lab[i] = lab[root]
        return m

    @ti.kernel
    def components(f: ti.types.ndarray(dtype=i64, ndim=1), Z: ti.types.ndarray(dtype=ti.f32, ndim=2),
                   eight: ti.i32, parent: ti.types.ndarray(dtype=ti.i32, ndim=1),
                   lab: ti.types.ndarray(dtype=i64, ndim=1), peak: ti.types.ndarray(dtype=ti.u8, ndim=1)):
        ti.loop_config(serialize=True)
        for _ in range(1):
            label(f, Z, eight, parent, lab, peak)

    @ti.func
    def rint(v):
        """numpy.rint: the nearest integer, halves to even."""
        r = ti.floor(v + 0.5)
        if r - v == 0.5 and ti.cast(r, i64) % 2 != 0:
            r -= 1.0
        return ti.cast(r, ti.i32)

    @ti.kernel
    def candidates(f: ti.types.ndarray(dtype=i64, ndim=1), Z: ti.types.ndarray(dtype=ti.f32, ndim=2),
                   eight: ti.i32, max_pix: i64, min_sep: ti.f64, keep_z: ti.f64,
                   parent: ti.types.ndarray(dtype=ti.i32, ndim=1), lab: ti.types.ndarray(dtype=i64, ndim=1),
                   peak: ti.types.ndarray(dtype=ti.u8, ndim=1), size: ti.types.ndarray(dtype=i64, ndim=1),
                   start: ti.types.ndarray(dtype=i64, ndim=1), order: ti.types.ndarray(dtype=i64, ndim=1),
                   out: ti.types.ndarray(dtype=i64, ndim=2), counts: ti.types.ndarray(dtype=i64, ndim=1)):
        W = Z.shape[1]
        ti.loop_config(serialize=True)
        for _ in range(1):
            n = f.shape[0]
            m = label(f, Z, eight, parent, lab, peak)
            for c in range(m + 1):
                size[c] = 0
                start[c] = 0
            for i in range(n):                         # component sizes and peaks per component
                size[lab[i]] += 1
                if peak[i] != 0:
                    start[lab[i] + 1] += 1
            for c in range(m):
                start[c + 1] += start[c]
            for i in range(n):                         # the peaks grouped by component, raster order within
                if peak[i] != 0:
                    c = lab[i]
                    order[start[c]] = f[i]
                    start[c] += 1
            for c in range(m):                         # start[c] is now the end of component c's peaks
                start[m - c] = start[m - c - 1]
            start[0] = 0
            n_out, n_large = 0, 0
            for c in range(m):
                if size[c] > max_pix:                  # not a star: counted, not searched
                    n_large += 1
                else:
                    a, b = ti.cast(start[c], ti.i32), ti.cast(start[c + 1], ti.i32)
                    for u in range(a + 1, b):          # by Z descending; ties keep raster order (stable)
                        v = order[u]
                        zv = Z[v // W, v % W]
                        w = u
                        while w > a and Z[order[w - 1] // W, order[w - 1] % W] < zv:
                            order[w] = order[w - 1]
                            w -= 1
                        order[w] = v
                    for u in range(a, b):              # deblending: every brighter maximum of the component
                        pj = order[u]
                        rj = ti.cast(pj // W, ti.i32)
                        cj = ti.cast(pj % W, ti.i32)
                        zt = keep_z * ti.cast(Z[rj, cj], ti.f64)
                        ok = 1
                        for t in range(a, u):
                            if ok:
                                pi = order[t]
                                ri = ti.cast(pi // W, ti.i32)
                                ci = ti.cast(pi % W, ti.i32)
                                dy = ti.cast(rj - ri, ti.f64)
                                dx = ti.cast(cj - ci, ti.f64)
                                far = ti.sqrt(dx * dx + dy * dy) >= min_sep
                                dip = ti.cast(Z[rint(ri + 0.25 * dy), rint(ci + 0.25 * dx)], ti.f64)
                                dip = ti.min(dip, ti.cast(Z[rint(ri + 0.5 * dy), rint(ci + 0.5 * dx)], ti.f64))
                                dip = ti.min(dip, ti.cast(Z[rint(ri + 0.75 * dy), rint(ci + 0.75 * dx)], ti.f64))
                                if not (far and dip < zt):
                                    ok = 0
                        if ok:
                            out[n_out, 0] = rj
                            out[n_out, 1] = cj
                            out[n_out, 2] = size[c]
                            n_out += 1
            counts[0] = n_out
            counts[1] = n_large

    return components, candidates


_KERNELS.builders["components"] = lambda dtype=None: _build_components(dtype)[0]
_KERNELS.builders["candidates"] = lambda dtype=None: _build_components(dtype)[1]


def foreground_components(f: np.ndarray, Z: np.ndarray, connectivity: int = 8):
    """Connected components and 3 x 3 local maxima of the foreground pixels ``f`` ((n,) int64 flat indices
    r W + c, ascending) of the (H, W) float32 image ``Z``, in one serial pass over them: (labels (n,) int64, numbered
    0.. in the order of each component's first pixel in raster order, the partition of
    :func:`dualsight.kernels.detect_candidates.sparse_components`; peak (n,) bool, Z at the pixel >= Z at each of its
    in-frame 8 neighbours).  Union-find with the larger root under the smaller (a root is its component's first
    pixel), each pixel joined to its backward neighbours (left; the row above: left, centre, right, centre only for
    ``connectivity`` 4), found by a pointer that moves forward with the pixels."""
    n = f.size
    lab = np.empty(n, np.int64)
    peak = np.empty(n, np.uint8)
    if n:
        _KERNELS.get("components")(np.ascontiguousarray(f, np.int64), np.ascontiguousarray(Z, np.float32),
                                   int(connectivity == 8), np.empty(n, np.int32), lab, peak)
    return lab, peak.view(bool)


def candidate_maxima(f: np.ndarray, Z: np.ndarray, connectivity: int, max_pixels: int, min_sep: float,
                     contrast: float):
    """:func:`dualsight.kernels.detect_candidates.find_candidates` after the threshold, in one serial pass: the
    components and 3 x 3 maxima of the foreground pixels ``f`` ((n,) int64 flat indices r W + c, ascending) of the
    (H, W) float32 image ``Z`` (as :func:`foreground_components`), then per component (in the order of their first
    pixel; those of more than ``max_pixels`` pixels counted, not searched) its maxima by Z descending (ties in raster
    order), each secondary maximum kept when, against every brighter maximum of the component, it lies at least
    ``min_sep`` px away and Z at 1/4, 1/2 and 3/4 of the way (the pixels numpy.rint rounds to) dips below
    (1 - ``contrast``) times its own Z.  Returns (rows, cols, npix of their component) (K,) int64 each and the number
    of large components: the arrays, in the order, of the numpy path (components, a lexsort, the pairs' tests)."""
    n = f.size
    out = np.empty((n, 3), np.int64)
    counts = np.zeros(2, np.int64)
    if n:
        _KERNELS.get("candidates")(np.ascontiguousarray(f, np.int64), np.ascontiguousarray(Z, np.float32),
                                   int(connectivity == 8), int(max_pixels), float(min_sep), float(1.0 - contrast),
                                   np.empty(n, np.int32), np.empty(n, np.int64), np.empty(n, np.uint8),
                                   np.empty(n + 1, np.int64), np.empty(n + 1, np.int64), np.empty(n, np.int64), out,
                                   counts)
    k = int(counts[0])
    return out[:k, 0].copy(), out[:k, 1].copy(), out[:k, 2].copy(), int(counts[1])


def _build_clipped(dtype):
    import taichi as ti

    pt = getattr(ti, _PIXEL[np.dtype(dtype).str])
    f64 = ti.f64

    @ti.func
    def below_from(s: ti.template(), r, N, med, t, strict, start):
        """Count of the row's values v with v - med < t (``strict`` 0) or <= t (1), by a walk from index ``start``
        (0..N): down while the value before is not below, up while the value at the index is (the predicate is
        monotone on the sorted row: a binary search's count).  The windows'
        ends sit a few values from the row's ends (the first window: beyond 3 sigma) or from the last window's:
        a few predictable steps instead of ~8 mispredicted halvings (measured: the tiles' clipping 0.33 -> 0.14
        ms per 1024 x 1024 frame, one core, with :func:`narrowest_run`)."""
        i = start
        while i > 0:
            d = ti.cast(s[r, i - 1], f64) - med
            if d < t or (strict != 0 and d == t):
                break
            i -= 1
        while i < N:
            d = ti.cast(s[r, i], f64) - med
            if not (d < t or (strict != 0 and d == t)):
                break
            i += 1
        return i

    @ti.func
    def narrowest_run(s: ti.template(), r, N, med, k):
        """min over i of max(med - s_i, s_{i+k-1} - med) (the MAD when k = ceil(N / 2)): that function of i falls
        (weakly) then rises, so walks down and up from the middle start, each while the next value is no larger,
        reach its minimum (the full scan's value) in a few steps on a noise tile."""
        i0 = (N - k) // 2
        best = ti.max(med - ti.cast(s[r, i0], f64), ti.cast(s[r, i0 + k - 1], f64) - med)
        i = i0
        while i > 0:
            f = ti.max(med - ti.cast(s[r, i - 1], f64), ti.cast(s[r, i + k - 2], f64) - med)
            if f > best:
                break
            best = f
            i -= 1
        i = i0
        while i < N - k:
            f = ti.max(med - ti.cast(s[r, i + 1], f64), ti.cast(s[r, i + k], f64) - med)
            if f > best:
                break
            best = ti.min(best, f)
            i += 1
        return best

    @ti.func
    def moved(s: ti.template(), r, a, b, med, sign, s1, s2):
        """The window's sums s1 (of v - med) and s2 (of its square) with the row's values a..b-1 added (``sign``
        1) or taken out (-1), one by one in order (an empty range: unchanged)."""
        for i in range(a, b):
            d = sign * (ti.cast(s[r, i], f64) - med)
            s1 += d
            s2 += sign * (d * d)
        return s1, s2

    @ti.func
    def lattice(s: ti.template(), r, N, q):
        """The row's quantile q on the 1-ADU lattice (detect_background.lattice_quantiles): the run of values equal
        to the one at index q N, found by walks from that index, gives the counts below it and equal to it.  On a
        tied row the run is a few tens of values, a predictable loop, where the two binary searches this replaces
        each cost ~8 mispredicted halvings (the tiles' median and MAD on the issue-24 rendered 16-bit frames 0.34 ->
        0.16 ms per 1024 x 1024 frame, one core)."""
        k = q * N
        i = ti.min(ti.max(ti.cast(k, ti.i32), 0), N - 1)
        x = s[r, i]
        lo, hi = i, i + 1
        while lo > 0 and s[r, lo - 1] == x:
            lo -= 1
        while hi < N and s[r, hi] == x:
            hi += 1
        return ti.cast(x, f64) - f64(0.5) + ti.min(ti.max((k - lo) / ti.max(hi - lo, 1), f64(0.0)), f64(1.0))

    @ti.kernel
    def clipped(s: ti.types.ndarray(dtype=pt, ndim=2), clip: f64, iters: ti.i32, corr: f64,
                out: ti.types.ndarray(dtype=f64, ndim=2)):
        ti.loop_config(serialize=True)
        for r in range(s.shape[0]):
            N = s.shape[1]
            m = (N - 1) // 2
            med = f64(0.5) * (ti.cast(s[r, m], f64) + ti.cast(s[r, N // 2], f64))
            sig = f64(0.0)
            if N >= 4 and (s[r, m] == s[r, ti.max(m - 1, 0)] or s[r, m] == s[r, ti.min(m + 1, N - 1)]):
                q25 = lattice(s, r, N, f64(0.25))         # a tied median: the lattice's quantiles
                med = lattice(s, r, N, f64(0.5))
                sig = (lattice(s, r, N, f64(0.75)) - q25) / f64(1.3489795)
            else:                                        # 1.4826 MAD: the narrowest run of k sorted values
                sig = f64(1.4826) * narrowest_run(s, r, N, med, ti.max((N + 1) // 2, 1))
            centre = f64(0.0)
            kept = N
            plo, phi = 0, 0                              # the last window [plo, phi) and its sums s1, s2
            wlo, whi = 0, N                              # where the walks to the next window's ends start
            s1, s2 = f64(0.0), f64(0.0)
            for _ in range(iters):
                lo = below_from(s, r, N, med, centre - clip * sig, 0, wlo)       # first window: from the row's
                hi = below_from(s, r, N, med, centre + clip * sig, 1, whi)       # ends, then the last window's
                wlo, whi = lo, hi
                kept = hi - lo
                if hi > lo:
                    if phi <= lo or hi <= plo:           # no overlap with the last window: sum afresh
                        plo, phi = lo, lo
                        s1, s2 = f64(0.0), f64(0.0)
                    # the window's sums from the last one's: only the values at its moved ends are added or taken
                    # out (a window moves by a few values of the sorted row: ~1/3 of the work of summing it anew)
                    s1, s2 = moved(s, r, lo, plo, med, f64(1.0), s1, s2)     # entered at the low end
                    s1, s2 = moved(s, r, plo, lo, med, f64(-1.0), s1, s2)    # left at the low end
                    s1, s2 = moved(s, r, phi, hi, med, f64(1.0), s1, s2)     # entered at the high end
                    s1, s2 = moved(s, r, hi, phi, med, f64(-1.0), s1, s2)    # left at the high end
                    plo, phi = lo, hi
                    mean = s1 / (hi - lo)
                    if sig > 0:
                        sig = ti.sqrt(ti.max(s2 / (hi - lo) - mean * mean, f64(0.0))) * corr
                    centre = mean
            out[r, 0] = med + centre
            out[r, 1] = sig
            out[r, 2] = ti.cast(kept, f64) / N

    return clipped


_KERNELS.builders["clipped"] = _build_clipped


def sorted_clipped_stats(s: np.ndarray, clip: float, iters: int, corr: float):
    """:func:`dualsight.kernels.detect_background.clipped_stats` of the sorted rows ``s`` (T, N) (uint8, uint16 or
    float32; ADU) in one serial pass, one row after the other: the median and 1.4826 MAD (a tied median: the 1-ADU
    lattice's interpolated median and interquartile range / 1.34898, ``lattice_start``), then ``iters`` windows of
    the values within ``clip`` sigma of the centre, each a contiguous run of the row found by binary search, its
    mean and standard deviation x ``corr`` (the truncation correction) in float64.  Returns (level, sigma, kept
    fraction) (T,) float64 each."""
    T, N = s.shape
    out = np.zeros((T, 3))
    if T and N:
        _KERNELS.get("clipped", s.dtype)(np.ascontiguousarray(s), float(clip), int(iters), float(corr), out)
    return out[:, 0], out[:, 1], out[:, 2]
