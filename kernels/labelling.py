"""Connected-component labelling of thresholded images (Taichi CPU): the one labeller of dualsight.

Star detection (:mod:`dualsight.kernels.detect`, on dense frames and on the sparse path's patches) and the
proximity blobber (:mod:`dualsight.kernels.blobs`) both call :func:`label_segments` / :func:`label_frames`.

Input: *segments*.  A segment is a block of ``rows x width`` consecutive image pixels stored row-major in a
flat pixel buffer, whose top-left pixel is image pixel (``row0``, ``col0``) of frame ``frame``.  A dense
(B, H, W) batch is B segments of H rows; a patch cut out of a frame is one segment.  Components never cross
a segment's border.  A pixel is foreground when ``value > threshold[frame]`` (exact comparison whatever the
pixel dtype: the threshold is converted by :func:`native_threshold`).

Algorithm: two-pass labelling on run-length codes (Rosenfeld & Pfaltz 1966; the run-based union-find form
of He, Chao & Suzuki 2008, "A run-based two-scan labeling algorithm", IEEE TIP 17, 749), four kernels:

1. ``count_runs``, parallel over rows: number of runs (maximal horizontal stretches) of foreground pixels.
   A prefix sum gives every row its first run.
2. ``fill_runs``, parallel over the rows that have runs: each run's columns and its pixel sums.
3. ``union_runs``, one thread per segment: runs of consecutive rows that touch (8-connectivity: also
   diagonally) are joined by union-find, the smaller root winning, so a component's root is its first run
   in raster order; counts the components.
4. ``number_components``, one thread per segment: numbers the components in raster order (after a prefix
   sum over segments), their pixel counts, bounding boxes, their moment sums (their runs' sums added in raster
   order) and the sums over all foreground pixels of the segment.

With a ``background`` (:class:`dualsight.kernels.background.Background` of dense frames), kernels 1-2 threshold
and sum ``value - background``, the smooth background evaluated per pixel from its block rows (float64, the same
bits as its numpy evaluation): a frame minus its background is labelled without a residual frame being made
(one read of the raw pixels instead of writing and reading a float32 residual; ``*_bg`` kernels).

Each kernel has a serial variant, used for small calls (a single frame: at most ``SERIAL_MAX_PIXELS`` pixels for
the row kernels 1-2, ``SERIAL_MAX_RUNS`` runs for the segment kernels 3-4): a parallel loop's launch costs a
round trip through Taichi's thread pool that outweighs the work there (:class:`KernelCache`).  Both give the same
output bit for bit.  Segments (pixel offset, width, first column, first row, frame) and runs (first column,
end column, row, segment) are passed as int32 tables, one argument each: every array argument of a launch
costs ~8.5 us in Taichi's Python launcher, ~2 us through :class:`~dualsight.kernels.taichi_runtime.FastKernel`
(``benchmarks/bench_taichi_threads.py``).

Only runs are stored: the cost is one or two reads of every pixel plus work proportional to the number of
runs.  Memory per run: 16 bytes of table, 40 of sums, 4 of label; per component 15 float64 moment sums (so
at most 120 more bytes per run, when every run is its own component: a threshold at the noise level).
Sums are float64 with pixel centres at (col + 0.5, row + 0.5) (docs/architecture.md), ``I = value - offset`` (offset: the
frame's background, 0 for none) and ``w`` the coverage (1 without a coverage buffer):

    0 n      1 sum x    2 sum y    3 sum x^2   4 sum x y   5 sum y^2         (whole pixels)
    6 sum I  7 sum I x  8 sum I y                                            (intensity)
    9 sum w  10 sum w x 11 sum w y 12 sum w x^2 13 sum w x y 14 sum w y^2   (coverage)
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from dualsight.kernels.taichi_runtime import KernelCache

__all__ = ["NSTAT", "STAT_NAMES", "Components", "label_segments", "label_frames", "native_threshold", "find", "union"]

_I32, _I32x2 = ti.types.ndarray(dtype=ti.i32, ndim=1), ti.types.ndarray(dtype=ti.i32, ndim=2)
_F32, _F32x2 = ti.types.ndarray(dtype=ti.f32, ndim=1), ti.types.ndarray(dtype=ti.f32, ndim=2)
_F64, _F64x2 = ti.types.ndarray(dtype=ti.f64, ndim=1), ti.types.ndarray(dtype=ti.f64, ndim=2)
_PIXEL_TYPES = {np.dtype(np.uint8).str: ti.u8, np.dtype(np.uint16).str: ti.u16,
                np.dtype(np.float32).str: ti.f32, np.dtype(np.float64).str: ti.f64}


# ============================================================================ output
NSTAT = 15
"""Moment sums of a component or a segment (the table in the module docstring); ``STAT_NAMES`` names them in order."""
STAT_NAMES = ("n", "sx", "sy", "sxx", "sxy", "syy", "sI", "sIx", "sIy", "sw", "swx", "swy", "swxx", "swxy", "swyy")


@dataclass(frozen=True, eq=False)
class Components:
    """Connected components of a batch of segments, and the runs of foreground pixels they are made of.

    Components are numbered segment by segment, in the raster order of their first pixel; runs are in
    raster order (segment, row, column).

    Attributes
    ----------
    npix : (NC,) int32 pixels of each component.
    box : (NC, 4) int32 inclusive bounding box [x0, y0, x1, y1] (image columns and rows).
    seg : (NC,) int32 segment of each component.
    offsets : (NS + 1,) int64; segment s's components are [offsets[s], offsets[s + 1]).
    seg_stats : (NS, NSTAT) float64 sums (module docstring) over all foreground pixels of each segment.
    run_c0, run_c1 : (R,) int32 image columns of each run, half-open [c0, c1).
    run_row : (R,) int32 image row of each run.
    run_seg : (R,) int32 segment of each run.
    run_label : (R,) int32 component of each run.
    run_sums : (R, 5) float64 sums of each run: sum I, sum I x, sum w, sum w x, sum w x^2.
    seg_runs : (NS + 1,) int32; segment s's runs are [seg_runs[s], seg_runs[s + 1]).
    comp_moments : (NC, NSTAT) float64 moment sums of each component (read through :meth:`moments`).
    """

    npix: np.ndarray
    box: np.ndarray
    seg: np.ndarray
    offsets: np.ndarray
    seg_stats: np.ndarray
    run_c0: np.ndarray
    run_c1: np.ndarray
    run_row: np.ndarray
    run_seg: np.ndarray
    run_label: np.ndarray
    run_sums: np.ndarray
    seg_runs: np.ndarray
    comp_moments: np.ndarray

    def __len__(self) -> int:
        return len(self.seg)

    @property
    def counts(self) -> np.ndarray:
        """(NS,) components per segment."""
        return np.diff(self.offsets)

    def moments(self, which=None) -> np.ndarray:
        """(K, NSTAT) float64 moment sums (module docstring) of components ``which`` ((K,) distinct indices;
        None = all), each the sum of its runs' sums in raster order (so bit-identical whatever else is asked)."""
        if which is None:
            return self.comp_moments.copy()
        return self.comp_moments[np.asarray(which, dtype=np.int64).reshape(-1)]

    def paint(self, out: np.ndarray, runs, values) -> np.ndarray:
        """Write ``values`` (a scalar or one value per selected run) into ``out[seg, row, col]`` over the pixels
        of the selected ``runs`` (indices or a bool mask over the runs) and return ``out``.  For dense frames
        (:func:`label_frames`, segment b = frame b) ``out`` is (B, H, W).  Vectorised over runs and pixels."""
        runs = np.flatnonzero(runs) if np.asarray(runs).dtype == bool else np.asarray(runs, dtype=np.int64)
        lens = (self.run_c1[runs] - self.run_c0[runs]).astype(np.int64)
        total = int(lens.sum())
        if total == 0:
            return out
        first = np.cumsum(lens) - lens
        xx = np.repeat(self.run_c0[runs].astype(np.int64), lens) + (np.arange(total) - np.repeat(first, lens))
        vals = values if np.ndim(values) == 0 else np.repeat(np.asarray(values), lens)
        out[np.repeat(self.run_seg[runs], lens), np.repeat(self.run_row[runs], lens), xx] = vals
        return out

    def label_image(self, shape) -> np.ndarray:
        """(B, H, W) int32 label image of dense frames: 0 = background, k + 1 - offsets[b] for component k
        of frame b (so 1..n per frame, like OpenCV's ``connectedComponents``)."""
        out = np.zeros(shape, np.int32)
        lab = self.run_label.astype(np.int64)
        return self.paint(out, np.arange(lab.size), lab + 1 - self.offsets[self.run_seg])


# ============================================================================ union-find (Taichi funcs)
@ti.func
def find(parent: ti.template(), base, i):
    """Root of local index ``i`` in the forest ``parent[base + .]`` (local indices; path halving)."""
    while parent[base + i] != i:
        parent[base + i] = parent[base + parent[base + i]]
        i = parent[base + i]
    return i


@ti.func
def union(parent: ti.template(), base, a, b):
    """Join the sets of local indices a and b; the smaller root wins (a set's root is its smallest index)."""
    ra = find(parent, base, a)
    rb = find(parent, base, b)
    if ra < rb:
        parent[base + rb] = ra
    elif rb < ra:
        parent[base + ra] = rb


# ============================================================================ kernels (built lazily)
_KERNELS = KernelCache()      # builders registered below


_PIX, _W, _C0, _R0, _FRAME = range(5)   # columns of the segment table


def _threshold_type(dtype):
    """Taichi type of the native threshold compared with pixels of ``dtype`` (see :func:`native_threshold`)."""
    dt = np.dtype(dtype)
    return ti.f64 if dt == np.float64 else (ti.f32 if dt == np.float32 else ti.i32)


@ti.func
def _pixel(pix: ti.template(), p, vt: ti.template(), bg: ti.template(), rows: ti.template(), ra, rb, w0, w1, x):
    """The value pixel ``p`` is thresholded and summed by: ``pix[p]`` as type ``vt``; with ``bg`` (static) the
    float64 ``pix[p]`` minus the smooth background (:class:`dualsight.kernels.background.Background`) at column x
    of an image row whose two block rows are ``rows[ra]``, ``rows[rb]`` with weights ``w0``, ``w1``
    (:func:`_row_weights`): both products are exact in float64 and every operation rounds once, so these are
    the very bits of ``Background.grid``."""
    v = ti.cast(pix[p], vt)
    if ti.static(bg):
        v = ti.cast(pix[p], ti.f64) - (w0 * ti.cast(rows[ra, x], ti.f64) + w1 * ti.cast(rows[rb, x], ti.f64))
    return v


@ti.func
def _row_weights(bg: ti.template(), vr: ti.template(), vw: ti.template(), rbase, y):
    """(ra, rb, w0, w1) of image row y for :func:`_pixel` (zeros without ``bg``)."""
    ra, rb, w0, w1 = 0, 0, ti.f64(0.0), ti.f64(0.0)
    if ti.static(bg):
        ra, rb, w0, w1 = rbase + vr[y, 0], rbase + vr[y, 1], vw[y, 0], vw[y, 1]
    return ra, rb, w0, w1


_CHUNK = 64
"""Pixels per chunk of ``fill_runs``' second read of a row: a chunk without a foreground pixel (one vectorised
test) is skipped, so only the chunks that hold runs are walked pixel by pixel."""


def _build_count_runs(dtype, serial: bool = False, bg: bool = False):
    pdt = _PIXEL_TYPES[np.dtype(dtype).str]
    tdt = ti.f64 if bg else _threshold_type(dtype)

    @ti.func
    def row_runs(pix: ti.template(), t, p0, w, c0, y, rows: ti.template(), vr: ti.template(), vw: ti.template(),
                 rbase):
        ra, rb, w0, w1 = _row_weights(bg, vr, vw, rbase, y)
        n = 0
        prev = 0
        for c in range(w):
            on = ti.cast(_pixel(pix, p0 + c, tdt, bg, rows, ra, rb, w0, w1, c0 + c) > t, ti.i32)
            n += on & (1 - prev)
            prev = on
        return n

    if bg:      # frames minus their smooth background (rows, vr, vw, nby: the Background's arrays)
        @ti.kernel
        def count_runs(pix: ti.types.ndarray(dtype=pdt, ndim=1), thr: ti.types.ndarray(dtype=tdt, ndim=1),
                       seg: _I32x2, seg_row: _I32, row_seg: _I32, counts: _I32, rows: _F32x2, vr: _I32x2,
                       vw: _F64x2, nby: ti.i32):
            ti.loop_config(serialize=serial)
            for q in range(row_seg.shape[0]):
                s = row_seg[q]
                w = seg[s, _W]
                counts[q] = row_runs(pix, thr[seg[s, _FRAME]], seg[s, _PIX] + (q - seg_row[s]) * w, w, seg[s, _C0],
                                     seg[s, _R0] + q - seg_row[s], rows, vr, vw, seg[s, _FRAME] * nby)
    else:
        @ti.kernel
        def count_runs(pix: ti.types.ndarray(dtype=pdt, ndim=1), thr: ti.types.ndarray(dtype=tdt, ndim=1),
                       seg: _I32x2, seg_row: _I32, row_seg: _I32, counts: _I32):
            ti.loop_config(serialize=serial)
            for q in range(row_seg.shape[0]):
                s = row_seg[q]
                w = seg[s, _W]
                counts[q] = row_runs(pix, thr[seg[s, _FRAME]], seg[s, _PIX] + (q - seg_row[s]) * w, w, 0, 0,
                                     counts, seg, seg, 0)
    return count_runs


def _build_fill_runs(dtype, serial: bool = False, bg: bool = False):
    pdt = _PIXEL_TYPES[np.dtype(dtype).str]
    tdt = ti.f64 if bg else _threshold_type(dtype)

    @ti.func
    def row_fill(pix: ti.template(), cov: ti.template(), use_cov, t, ofs, p0, w, c0, y, s, k, kend,
                 runs: ti.template(), rsum: ti.template(), rows: ti.template(), vr: ti.template(),
                 vw: ti.template(), rbase):
        """The runs of one row into slots k .. kend - 1 (never beyond: a row that finds more runs than were
        counted stores only those); returns the slot after the last run found."""
        ra, rb, w0, w1 = _row_weights(bg, vr, vw, rbase, y)
        start = 0
        inrun = 0
        sI, sIx = ti.f64(0.0), ti.f64(0.0)
        sw, swx, swxx = ti.f64(0.0), ti.f64(0.0), ti.f64(0.0)
        for ch in range((w + _CHUNK - 1) // _CHUNK):
            a = ch * _CHUNK
            e = ti.min(a + _CHUNK, w)
            hit = inrun                          # a run open at the chunk's start ends (or goes on) in it
            for c in range(a, e):
                hit |= ti.cast(_pixel(pix, p0 + c, tdt, bg, rows, ra, rb, w0, w1, c0 + c) > t, ti.i32)
            if hit != 0:
                for c in range(a, e):            # the chunk pixel by pixel: runs start, grow and end
                    val = _pixel(pix, p0 + c, tdt, bg, rows, ra, rb, w0, w1, c0 + c)
                    if val > t:
                        if inrun == 0:
                            inrun = 1
                            start = c
                            sI, sIx = ti.f64(0.0), ti.f64(0.0)
                            sw, swx, swxx = ti.f64(0.0), ti.f64(0.0), ti.f64(0.0)
                        xc = ti.cast(c0 + c, ti.f64) + ti.f64(0.5)
                        v = ti.cast(pix[p0 + c], ti.f64) - ofs
                        if ti.static(bg):
                            v = val - ofs
                        wc = ti.f64(1.0)
                        if use_cov != 0:
                            wc = ti.cast(cov[p0 + c], ti.f64)
                        sI += v
                        sIx += v * xc
                        sw += wc
                        swx += wc * xc
                        swxx += wc * xc * xc
                    elif inrun != 0:
                        inrun = 0
                        if k < kend:
                            _store_run(runs, rsum, k, c0 + start, c0 + c, y, s, sI, sIx, sw, swx, swxx)
                        k += 1
        if inrun != 0:
            if k < kend:
                _store_run(runs, rsum, k, c0 + start, c0 + w, y, s, sI, sIx, sw, swx, swxx)
            k += 1
        return k

    @ti.func
    def fill_row(q, pix: ti.template(), cov: ti.template(), use_cov, thr: ti.template(), off: ti.template(),
                 seg: ti.template(), seg_row: ti.template(), row_seg: ti.template(), run_off: ti.template(),
                 runs: ti.template(), rsum: ti.template(), counts: ti.template(), rows: ti.template(),
                 vr: ti.template(), vw: ti.template(), nby):
        if run_off[q + 1] > run_off[q]:  # only rows that have runs are read again; counts[q] = the runs found
            s = row_seg[q]
            w = seg[s, _W]
            fr = seg[s, _FRAME]
            counts[q] = row_fill(pix, cov, use_cov, thr[fr], off[fr], seg[s, _PIX] + (q - seg_row[s]) * w, w,
                                 seg[s, _C0], seg[s, _R0] + q - seg_row[s], s, run_off[q], run_off[q + 1], runs, rsum,
                                 rows, vr, vw, fr * nby) - run_off[q]

    if bg:      # frames minus their smooth background (rows, vr, vw, nby: the Background's arrays)
        @ti.kernel
        def fill_runs(pix: ti.types.ndarray(dtype=pdt, ndim=1), cov: _F32, use_cov: ti.i32,
                      thr: ti.types.ndarray(dtype=tdt, ndim=1), off: _F64, seg: _I32x2, seg_row: _I32, row_seg: _I32,
                      run_off: _I32, runs: _I32x2, rsum: _F64x2, counts: _I32, rows: _F32x2, vr: _I32x2, vw: _F64x2,
                      nby: ti.i32):
            ti.loop_config(serialize=serial)
            for q in range(row_seg.shape[0]):
                fill_row(q, pix, cov, use_cov, thr, off, seg, seg_row, row_seg, run_off, runs, rsum, counts, rows, vr,
                         vw, nby)
    else:       # (the background's arguments: placeholders, never read)
        @ti.kernel
        def fill_runs(pix: ti.types.ndarray(dtype=pdt, ndim=1), cov: _F32, use_cov: ti.i32,
                      thr: ti.types.ndarray(dtype=tdt, ndim=1), off: _F64, seg: _I32x2, seg_row: _I32, row_seg: _I32,
                      run_off: _I32, runs: _I32x2, rsum: _F64x2, counts: _I32):
            ti.loop_config(serialize=serial)
            for q in range(row_seg.shape[0]):
                fill_row(q, pix, cov, use_cov, thr, off, seg, seg_row, row_seg, run_off, runs, rsum, counts, runs, seg,
                         off, 0)
    return fill_runs


@ti.func
def _store_run(runs: ti.template(), rsum: ti.template(), k, c_start, c_end, y, s, sI, sIx, sw, swx, swxx):
    """Run k: columns [c_start, c_end) of image row y of segment s, and its sums."""
    runs[k, 0], runs[k, 1], runs[k, 2], runs[k, 3] = c_start, c_end, y, s
    rsum[k, 0], rsum[k, 1], rsum[k, 2], rsum[k, 3], rsum[k, 4] = sI, sIx, sw, swx, swxx


def _build_union_runs(_dtype=None, serial: bool = False):
    @ti.kernel
    def union_runs(seg_row: _I32, run_off: _I32, runs: _I32x2, conn8: ti.i32, parent: _I32, seg_ncomp: _I32):
        ti.loop_config(block_dim=1, serialize=serial)
        for s in range(seg_row.shape[0] - 1):  # one thread per segment
            q0 = seg_row[s]
            q1 = seg_row[s + 1]
            for k in range(run_off[q0], run_off[q1]):
                parent[k] = k
            d = 1 - conn8  # 8-connectivity: runs touching diagonally join
            for q in range(q0 + 1, q1):
                i = run_off[q - 1]
                iend = run_off[q]
                j = iend
                jend = run_off[q + 1]
                while i < iend and j < jend:
                    if runs[i, 0] + d <= runs[j, 1] and runs[j, 0] + d <= runs[i, 1]:
                        union(parent, 0, i, j)
                    if runs[i, 1] <= runs[j, 1]:
                        i += 1
                    else:
                        j += 1
            nc = 0
            for k in range(run_off[q0], run_off[q1]):  # increasing k: a root precedes its members
                rt = find(parent, 0, k)
                parent[k] = rt
                if rt == k:
                    nc += 1
            seg_ncomp[s] = nc
    return union_runs


@ti.func
def _run_sums(runs: ti.template(), rsum: ti.template(), k):
    """The NSTAT sums of run k as an f64 vector; whole-pixel sums in closed form."""
    a = ti.cast(runs[k, 0], ti.f64)
    e = ti.cast(runs[k, 1], ti.f64)
    yc = ti.cast(runs[k, 2], ti.f64) + 0.5
    n = e - a
    # pixel centres a+0.5 .. e-0.5 (exact: integers and quarters)
    sx = 0.5 * n * (a + e)
    sk = 0.5 * n * (a + e - 1.0)                                              # sum k, k = a..e-1
    skk = ((e - 1.0) * e * (2.0 * e - 1.0) - (a - 1.0) * a * (2.0 * a - 1.0)) / 6.0   # sum k^2
    sxx = skk + sk + 0.25 * n                                                 # sum (k + 1/2)^2
    sI, sIx, sw, swx, swxx = rsum[k, 0], rsum[k, 1], rsum[k, 2], rsum[k, 3], rsum[k, 4]
    return ti.Vector([n, sx, n * yc, sxx, sx * yc, n * yc * yc, sI, sIx, sI * yc,
                      sw, swx, sw * yc, swxx, swx * yc, sw * yc * yc], dt=ti.f64)


def _build_number_components(_dtype=None, serial: bool = False):
    @ti.kernel
    def number_components(seg_run: _I32, runs: _I32x2, rsum: _F64x2, comp_off: _I32, label: _I32, npix: _I32,
                          box: _I32x2, comp_seg: _I32, seg_stats: _F64x2, comp_mom: _F64x2):
        ti.loop_config(block_dim=1, serialize=serial)
        for s in range(seg_run.shape[0] - 1):  # one thread per segment; runs in raster order
            acc = ti.Vector.zero(ti.f64, NSTAT)
            cid = comp_off[s]
            for k in range(seg_run[s], seg_run[s + 1]):
                v = _run_sums(runs, rsum, k)
                acc += v
                rt = label[k]        # in: the root run (from union_runs); out: the component index
                rs, re, y = runs[k, 0], runs[k, 1], runs[k, 2]
                c = cid
                if rt == k:          # first run of a new component
                    npix[cid] = re - rs
                    box[cid, 0] = rs
                    box[cid, 1] = y
                    box[cid, 2] = re - 1
                    box[cid, 3] = y
                    comp_seg[cid] = s
                    cid += 1
                else:                # the root precedes k and already holds its component index
                    c = label[rt]
                    npix[c] += re - rs
                    box[c, 0] = ti.min(box[c, 0], rs)
                    box[c, 2] = ti.max(box[c, 2], re - 1)
                    box[c, 3] = y
                label[k] = c
                for m in ti.static(range(NSTAT)):   # the component's sums: its runs' in raster order, from 0
                    comp_mom[c, m] += v[m]
            for m in ti.static(range(NSTAT)):
                seg_stats[s, m] = acc[m]
    return number_components


_KERNELS.builders.update({"count_runs": _build_count_runs, "fill_runs": _build_fill_runs,
                          "count_runs_bg": lambda dtype, serial=False: _build_count_runs(dtype, serial, bg=True),
                          "fill_runs_bg": lambda dtype, serial=False: _build_fill_runs(dtype, serial, bg=True),
                          "union_runs": _build_union_runs, "number_components": _build_number_components})


SERIAL_MAX_PIXELS = 1 << 21
"""Row kernels (``count_runs``, ``fill_runs``) run serially on at most this many pixels per call: on one
1024 x 1024 frame the serial row kernels took 1.19 ms for the whole detection against 1.44 ms (1 Taichi thread)
and 1.32 against 1.58 ms (2 threads)."""
SERIAL_MAX_RUNS = 1 << 13
"""Segment kernels (``union_runs``, ``number_components``) run serially on at most this many runs per call
(on one frame: 70-115 us against 240-250 us each)."""


# ============================================================================ public API
def native_threshold(thr, dtype) -> np.ndarray:
    """Thresholds t' of the pixels' own comparison type with (v > t') == (v > t) for every pixel value v.

    thr : (F,) float64 thresholds; dtype : pixel dtype (uint8, uint16, float32 or float64).
    Returns int32 floor(t) (unsigned pixels), float32 (t rounded to float32, one step down where rounding went
    up) or float64 (t itself).
    """
    thr = np.asarray(thr, dtype=np.float64)
    dt = np.dtype(dtype)
    if dt.kind == "u":
        return np.clip(np.floor(thr), -1, np.iinfo(dt).max).astype(np.int32)
    if dt == np.float32:
        t32 = thr.astype(np.float32)
        down = t32.astype(np.float64) > thr
        t32[down] = np.nextafter(t32[down], np.float32(-np.inf))
        return t32
    return thr.astype(np.float64)


def label_segments(pixels, seg_pix, seg_w, seg_rows, seg_c0, seg_r0, seg_frame, threshold, *, offset=None,
                   coverage=None, connectivity: int = 8, background=None) -> Components:
    """Label the foreground of a set of segments (see the module docstring) and sum each component.

    Parameters
    ----------
    pixels : (N,) uint8, uint16, float32 or float64 flat pixel buffer, N < 2^31.
    seg_pix : (NS,) int index in ``pixels`` of each segment's top-left pixel.
    seg_w, seg_rows : (NS,) int widths and heights (px); segment s holds rows ``pixels[seg_pix[s] + r * w :
        ... + w]``, r < rows.
    seg_c0, seg_r0 : (NS,) int image column and row of each segment's top-left pixel.
    seg_frame : (NS,) int frame index of each segment (selects ``threshold`` and ``offset``).
    threshold : (F,) float64 per frame; foreground is ``value > threshold``.
    offset : (F,) float64 subtracted from the values in the intensity sums (None = 0).
    coverage : optional (N,) float32 coverage in [0, 1] beside ``pixels`` for the ``sw*`` sums (else w = 1).
    connectivity : 8 or 4.
    background : optional :class:`dualsight.kernels.background.Background` of the frames the segments lie in
        (segment columns and rows are image columns and rows; frame f = its frame ``f``): the pixels are then
        thresholded and summed as ``value - background`` (float64; ``threshold`` and ``offset`` apply to it).

    Returns
    -------
    :class:`Components`.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    pixels = np.ascontiguousarray(pixels).reshape(-1)
    if np.dtype(pixels.dtype).str not in _PIXEL_TYPES:
        raise ValueError(f"pixels must be uint8, uint16, float32 or float64, got {pixels.dtype}")
    seg_rows = np.asarray(seg_rows, dtype=np.int64)
    NS = seg_rows.size
    seg_row = np.zeros(NS + 1, np.int64)
    np.cumsum(seg_rows, out=seg_row[1:])
    NR = int(seg_row[-1])
    if NR >= 2 ** 31:
        raise ValueError(f"too many rows ({NR}) in one call")
    i32 = lambda a: np.ascontiguousarray(a, dtype=np.int32)
    if pixels.size >= 2 ** 31:
        raise ValueError(f"{pixels.size} pixels in one call; at most 2^31 - 1 (label chunks of frames)")
    seg = np.empty((max(NS, 1), 5), np.int32)          # the segment table (columns _PIX, _W, _C0, _R0, _FRAME)
    for col, a in ((_PIX, seg_pix), (_W, seg_w), (_C0, seg_c0), (_R0, seg_r0), (_FRAME, seg_frame)):
        seg[:NS, col] = np.asarray(a, dtype=np.int64).reshape(-1)
    seg_row = i32(seg_row)
    thr = np.asarray(threshold, dtype=np.float64).reshape(-1)
    off = np.zeros(thr.size) if offset is None else np.ascontiguousarray(offset, dtype=np.float64).reshape(-1)
    tn = native_threshold(thr, pixels.dtype) if background is None else np.ascontiguousarray(thr)
    bg, suffix = (), ""
    if background is not None:                       # the frames' smooth background, evaluated in the row kernels
        nby = background.rows.shape[1]
        bg = (np.ascontiguousarray(background.rows.reshape(-1, background.rows.shape[2]), np.float32),
              np.ascontiguousarray(background.r, np.int32), np.ascontiguousarray(background.w, np.float64), nby)
        suffix = "_bg"
    row_seg = i32(np.repeat(np.arange(NS), seg_rows))
    counts = np.zeros(max(NR, 1), np.int32)
    rows_serial = pixels.size <= SERIAL_MAX_PIXELS
    if NR:
        _KERNELS.get("count_runs" + suffix, pixels.dtype, serial=rows_serial)(pixels, tn, seg, seg_row,
                                                                                    row_seg, counts, *bg)
    run_off = np.zeros(NR + 1, np.int64)
    np.cumsum(counts[:NR], out=run_off[1:])
    R = int(run_off[-1])
    if R >= 2 ** 31 - 1:
        raise ValueError(f"too many foreground runs ({R}); raise the threshold")
    run_off = i32(run_off)
    segs_serial = R <= SERIAL_MAX_RUNS
    Ra = max(R, 1)  # Taichi wants non-empty arrays
    runs = np.empty((Ra, 4), np.int32)                 # first column, end column, row, segment
    rsum = np.empty((Ra, 5), np.float64)
    label = np.empty(Ra, np.int32)
    seg_ncomp = np.zeros(max(NS, 1), np.int32)
    seg_stats = np.zeros((max(NS, 1), NSTAT), np.float64)
    if R:
        cov = (np.ascontiguousarray(coverage, dtype=np.float32).reshape(-1) if coverage is not None
               else np.zeros(1, np.float32))
        _KERNELS.get("fill_runs" + suffix, pixels.dtype, serial=rows_serial)(
            pixels, cov, int(coverage is not None), tn, off, seg, seg_row, row_seg, run_off, runs, rsum, counts, *bg)
        if not np.array_equal(counts[:NR], np.diff(run_off)):   # fill found other runs than count: never written
            raise RuntimeError("labeller: the rows' second read found other runs than the first counted "
                               f"({int(np.abs(counts[:NR] - np.diff(run_off)).sum())} differ); no result")
        _KERNELS.get("union_runs", serial=segs_serial)(seg_row, run_off, runs, int(connectivity == 8), label,
                                                       seg_ncomp)
    comp_off = np.zeros(NS + 1, np.int64)
    np.cumsum(seg_ncomp[:NS], out=comp_off[1:])
    NC = int(comp_off[-1])
    npix = np.empty(max(NC, 1), np.int32)
    box = np.empty((max(NC, 1), 4), np.int32)
    comp_seg = np.empty(max(NC, 1), np.int32)
    comp_mom = np.zeros((max(NC, 1), NSTAT), np.float64)
    seg_runs = i32(run_off[seg_row])
    if R:
        _KERNELS.get("number_components", serial=segs_serial)(seg_runs, runs, rsum, i32(comp_off), label, npix,
                                                              box, comp_seg, seg_stats, comp_mom)
    return Components(npix=npix[:NC], box=box[:NC], seg=comp_seg[:NC], offsets=comp_off, seg_stats=seg_stats[:NS],
                      run_c0=runs[:R, 0], run_c1=runs[:R, 1], run_row=runs[:R, 2], run_seg=runs[:R, 3],
                      run_label=label[:R], run_sums=rsum[:R], seg_runs=seg_runs, comp_moments=comp_mom[:NC])


def label_frames(images, threshold, *, offset=None, coverage=None, connectivity: int = 8,
                 background=None) -> Components:
    """Label a batch of dense frames: segment b = frame b (see :func:`label_segments`).

    images : (B, H, W) uint8, uint16, float32 or float64; threshold, offset : scalar or (B,) float64;
    coverage : optional (B, H, W) float32; background : optional
    :class:`dualsight.kernels.background.Background` of the frames (their shape).  Returns :class:`Components`
    (segment = frame index).
    """
    images = np.ascontiguousarray(images)
    if images.ndim != 3:
        raise ValueError(f"images must have shape (B, H, W), got {images.shape}")
    B, H, W = images.shape
    if background is not None and tuple(background.shape) != (B, H, W):
        raise ValueError(f"background of frames {background.shape}, images {images.shape}")
    thr = np.broadcast_to(np.asarray(threshold, dtype=np.float64), (B,))
    off = None if offset is None else np.broadcast_to(np.asarray(offset, dtype=np.float64), (B,))
    z = np.zeros(B, np.int32)
    return label_segments(images.reshape(-1), np.arange(B, dtype=np.int64) * H * W, np.full(B, W), np.full(B, H),
                          z, z, np.arange(B), thr, offset=off, coverage=coverage, connectivity=connectivity,
                          background=background)
