"""Blob extraction for the proximity blobber (Taichi CPU), batched over B frames.

Threshold -> connected-component labelling -> per-blob moments, in three kernels:

1. ``count_runs`` (parallel over (frame, row)): number of horizontal runs of foreground pixels
   (``image > threshold``) in every row; a prefix sum gives each row's first run.
2. ``fill_runs`` (parallel over (frame, row)): each run's start/end column and its intensity and
   coverage sums (sum I, sum I x, sum w, sum w x, sum w x^2).
3. ``merge_runs`` (parallel over frames, serial inside): union-find over runs (Rosenfeld & Pfaltz
   1966 two-pass labelling on run-length codes, as in He et al. 2009 "Fast connected-component
   labeling"), 8- or 4-connectivity; then per frame the number of blobs, the largest blob (most
   pixels; ties -> the first in raster order) and the moment sums of that blob and of all
   foreground pixels.

Only runs are stored, so the cost is one or two reads of every pixel plus work proportional to
the number of runs (cheap for a target on a dark sky).

Moment sums (float64), pixel centres at (col + 0.5, row + 0.5) (DESIGN.md convention), ``I`` the
image value, ``w`` the coverage (1 when no coverage image is given):

    0 n      1 sum x    2 sum y    3 sum x^2   4 sum x y   5 sum y^2         (whole pixels)
    6 sum I  7 sum I x  8 sum I y                                            (intensity)
    9 sum w  10 sum w x 11 sum w y 12 sum w x^2 13 sum w x y 14 sum w y^2   (coverage)
"""

import numpy as np

from dualsight.kernels._runtime import ensure_init

NSTAT = 15
STAT_NAMES = ("n", "sx", "sy", "sxx", "sxy", "syy", "sI", "sIx", "sIy", "sw", "swx", "swy", "swxx", "swxy", "swyy")
_K: dict = {}


def _kernels() -> dict:
    if _K:
        return _K
    ti = ensure_init()
    nd = ti.types.ndarray
    f32, f64, i32 = ti.f32, ti.f64, ti.i32

    @ti.kernel
    def count_runs(img: nd(dtype=f32, ndim=3), thr: nd(dtype=f32, ndim=1), counts: nd(dtype=i32, ndim=2)):
        B, H, W = img.shape[0], img.shape[1], img.shape[2]
        ti.loop_config(block_dim=8)
        for b, y in ti.ndrange(B, H):
            th = thr[b]
            n = 0
            prev = 0
            for x in range(W):
                on = 1 if img[b, y, x] > th else 0
                n += on * (1 - prev)
                prev = on
            counts[b, y] = n

    @ti.kernel
    def fill_runs(img: nd(dtype=f32, ndim=3), cov: nd(dtype=f32, ndim=3), use_cov: i32, thr: nd(dtype=f32, ndim=1),
                  roff: nd(dtype=i32, ndim=1), rs: nd(dtype=i32, ndim=1), re: nd(dtype=i32, ndim=1),
                  rsum: nd(dtype=f64, ndim=2)):
        B, H, W = img.shape[0], img.shape[1], img.shape[2]
        ti.loop_config(block_dim=8)
        for b, y in ti.ndrange(B, H):
            r = roff[b * H + y]
            r_end = roff[b * H + y + 1]
            if r_end > r:
                th = thr[b]
                x = 0
                while x < W:
                    if img[b, y, x] > th:
                        s = x
                        sI, sIx, sw, swx, swxx = f64(0.0), f64(0.0), f64(0.0), f64(0.0), f64(0.0)
                        while x < W and img[b, y, x] > th:
                            xc = ti.cast(x, f64) + 0.5
                            v = ti.cast(img[b, y, x], f64)
                            w = f64(1.0)
                            if use_cov != 0:
                                w = ti.cast(cov[b, y, x], f64)
                            sI += v
                            sIx += v * xc
                            sw += w
                            swx += w * xc
                            swxx += w * xc * xc
                            x += 1
                        rs[r] = s
                        re[r] = x
                        rsum[r, 0] = sI
                        rsum[r, 1] = sIx
                        rsum[r, 2] = sw
                        rsum[r, 3] = swx
                        rsum[r, 4] = swxx
                        r += 1
                    else:
                        x += 1

    @ti.func
    def find(parent: ti.template(), r):
        while parent[r] != r:
            parent[r] = parent[parent[r]]
            r = parent[r]
        return r

    @ti.func
    def add_run(out: ti.template(), b, rs: ti.template(), re: ti.template(), rsum: ti.template(), r, y):
        s = ti.cast(rs[r], f64)
        e = ti.cast(re[r], f64)
        n = e - s
        yc = ti.cast(y, f64) + 0.5
        # pixel centres s+0.5 .. e-0.5: sum = n (s + e) / 2, sum of squares closed form
        sx = 0.5 * n * (s + e)
        sk = 0.5 * n * (s + e - 1.0)                                              # sum k, k = s..e-1
        skk = ((e - 1.0) * e * (2.0 * e - 1.0) - (s - 1.0) * s * (2.0 * s - 1.0)) / 6.0   # sum k^2
        sxx = skk + sk + 0.25 * n                                                 # sum (k + 1/2)^2
        out[b, 0] += n
        out[b, 1] += sx
        out[b, 2] += n * yc
        out[b, 3] += sxx
        out[b, 4] += sx * yc
        out[b, 5] += n * yc * yc
        out[b, 6] += rsum[r, 0]
        out[b, 7] += rsum[r, 1]
        out[b, 8] += rsum[r, 0] * yc
        out[b, 9] += rsum[r, 2]
        out[b, 10] += rsum[r, 3]
        out[b, 11] += rsum[r, 2] * yc
        out[b, 12] += rsum[r, 4]
        out[b, 13] += rsum[r, 3] * yc
        out[b, 14] += rsum[r, 2] * yc * yc

    @ti.kernel
    def merge_runs(H: i32, roff: nd(dtype=i32, ndim=1), rs: nd(dtype=i32, ndim=1), re: nd(dtype=i32, ndim=1),
                   rsum: nd(dtype=f64, ndim=2), conn8: i32, parent: nd(dtype=i32, ndim=1),
                   cnt: nd(dtype=ti.i64, ndim=1), nblobs: nd(dtype=i32, ndim=1), best: nd(dtype=i32, ndim=1),
                   out_best: nd(dtype=f64, ndim=2), out_all: nd(dtype=f64, ndim=2), box: nd(dtype=i32, ndim=2)):
        B = nblobs.shape[0]
        ti.loop_config(block_dim=1)
        for b in range(B):
            base = b * H
            r_lo = roff[base]
            r_hi = roff[base + H]
            for r in range(r_lo, r_hi):
                parent[r] = r
                cnt[r] = 0
            for y in range(1, H):
                a0 = roff[base + y]
                a1 = roff[base + y + 1]
                q0 = roff[base + y - 1]
                q1 = a0
                if a1 > a0 and q1 > q0:
                    j = q0
                    for a in range(a0, a1):
                        s = rs[a]
                        e = re[a]
                        while j < q1 and re[j] + conn8 <= s:
                            j += 1
                        k = j
                        while k < q1 and rs[k] < e + conn8:
                            ra = find(parent, a)
                            rk = find(parent, k)
                            if ra != rk:
                                if ra < rk:
                                    parent[rk] = ra
                                else:
                                    parent[ra] = rk
                            k += 1
            for r in range(r_lo, r_hi):
                root = find(parent, r)
                parent[r] = root
                cnt[root] += re[r] - rs[r]
            nb = 0
            bi = -1
            bn = ti.i64(0)
            for r in range(r_lo, r_hi):
                if parent[r] == r:
                    nb += 1
                    if cnt[r] > bn:
                        bn = cnt[r]
                        bi = r
            nblobs[b] = nb
            best[b] = bi
            for k in range(15):
                out_best[b, k] = 0.0
                out_all[b, k] = 0.0
            box[b, 0] = 1 << 30
            box[b, 1] = 1 << 30
            box[b, 2] = -1
            box[b, 3] = -1
            for y in range(H):
                for r in range(roff[base + y], roff[base + y + 1]):
                    add_run(out_all, b, rs, re, rsum, r, y)
                    if parent[r] == bi:
                        add_run(out_best, b, rs, re, rsum, r, y)
                        box[b, 0] = ti.min(box[b, 0], rs[r])
                        box[b, 1] = ti.min(box[b, 1], y)
                        box[b, 2] = ti.max(box[b, 2], re[r] - 1)
                        box[b, 3] = ti.max(box[b, 3], y)

    _K.update(count_runs=count_runs, fill_runs=fill_runs, merge_runs=merge_runs)
    return _K


def label_blobs(images, threshold=0.0, coverage=None, connectivity: int = 8, *, return_mask: bool = False,
                chunk_frames: int = 32) -> dict:
    """Threshold, label and measure blobs in a batch of frames.

    Parameters
    ----------
    images : (B, H, W) or (H, W) float image (any real dtype; converted to float32).
    threshold : scalar or (B,): foreground is ``image > threshold``.
    coverage : optional (B, H, W) per-pixel coverage in [0, 1] (the ``accurate`` renderer's); the
        ``sw*`` sums use it, else they equal the whole-pixel sums.
    connectivity : 8 (default) or 4.
    return_mask : also return ``mask`` (B, H, W) bool of the largest blob.

    Returns
    -------
    dict with ``n_blobs`` (B,) int32, ``best`` (B, 15) float64 moment sums of the largest blob (see
    module docstring), ``all`` (B, 15) sums over every foreground pixel, ``box`` (B, 4) int32
    [x0, y0, x1, y1] inclusive bounding box of the largest blob (x1 < 0: no blob), and ``mask``.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    K = _kernels()
    img = np.asarray(images)
    if img.ndim == 2:
        img = img[None]
    B, H, W = img.shape
    thr = np.ascontiguousarray(np.broadcast_to(np.asarray(threshold, dtype=np.float32), (B,)))
    cov = None if coverage is None else np.asarray(coverage)
    if cov is not None and cov.ndim == 2:
        cov = cov[None]
    out = dict(n_blobs=np.zeros(B, np.int32), best=np.zeros((B, NSTAT)), all=np.zeros((B, NSTAT)),
               box=np.zeros((B, 4), np.int32))
    if return_mask:
        out["mask"] = np.zeros((B, H, W), bool)
    for s in range(0, B, chunk_frames):  # chunks of frames bound the run arrays' memory
        e = min(s + chunk_frames, B)
        im = np.ascontiguousarray(img[s:e], dtype=np.float32)
        cv = np.ascontiguousarray(cov[s:e], dtype=np.float32) if cov is not None else im
        nb = e - s
        counts = np.zeros((nb, H), np.int32)
        K["count_runs"](im, thr[s:e], counts)
        roff = np.zeros(nb * H + 1, np.int32)
        np.cumsum(counts.ravel(), out=roff[1:])
        R = max(int(roff[-1]), 1)
        rs = np.empty(R, np.int32)
        re = np.empty(R, np.int32)
        rsum = np.empty((R, 5), np.float64)
        K["fill_runs"](im, cv, int(cov is not None), thr[s:e], roff, rs, re, rsum)
        parent = np.empty(R, np.int32)
        cnt = np.empty(R, np.int64)
        best = np.empty(nb, np.int32)
        K["merge_runs"](H, roff, rs, re, rsum, int(connectivity == 8), parent, cnt, out["n_blobs"][s:e], best,
                        out["best"][s:e], out["all"][s:e], out["box"][s:e])
        if return_mask and roff[-1] > 0:
            n_runs = int(roff[-1])
            row_of_run = np.repeat(np.arange(nb * H), counts.ravel())
            frame = row_of_run // H
            sel = parent[:n_runs] == best[frame]
            r_idx = np.nonzero(sel)[0]
            lens = re[r_idx] - rs[r_idx]
            f = np.repeat(frame[r_idx], lens)
            yy = np.repeat(row_of_run[r_idx] % H, lens)
            xx = np.repeat(rs[r_idx], lens) + (np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens))
            out["mask"][s + f, yy, xx] = True
    return out
