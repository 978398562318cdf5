"""Stage 2 of the real-sensor detector (:mod:`dualsight.kernels.detect_local`, steps 2 and 3 of its docstring):
the matched filter (:func:`matched_filter`: the background-subtracted frame correlated with the pixel-integrated
Gaussian PSF, in units of the filtered image's own noise) and the candidate stars above its threshold
(:func:`find_candidates`: connected components of the foreground pixels (:func:`sparse_components`), their local
maxima, deblending), and whether a frame is clamped at its black level (:func:`clamped`).  Pure numpy/OpenCV
functions over arrays; ``cfg`` is a :class:`~dualsight.kernels.detect_local.LocalDetectConfig`."""

import numpy as np

from dualsight.kernels.detect_background import order_statistic, robust_stats
from dualsight.kernels.detect_passes import candidate_maxima
from dualsight.kernels.detect_psf import psf_kernel_1d


NOISE_SAMPLE_STRIDE = 8
"""Rows and columns between the pixels of the noise sample of :func:`matched_filter` (~12,000 pixels of a 1024 x 768
frame: the ratio sigma_F / sigma to ~0.65 %, 1 / sqrt(2 N), which moves a Z = 5 threshold by ~0.03; every 4th row
and column, as until 2026-11-28, halved that for ~0.25 ms per frame)."""


TAIL_P, TAIL_Z = (0.97725, 0.99865), (2.0, 3.0)
"""The matched filter's upper-tail check: the noise sample's quantiles ``TAIL_P``, ``TAIL_Z`` sigmas above the
centre for a normal noise (Phi(2), Phi(3)).  A noise whose right tail is heavier than its core (dark-subtracted
8-bit frames clamped at the black level: more than half of the sky pixels 0, the rest a few ADU) has a scale at 3
sigma, (q(Phi(3)) - centre) / 3, above its clipped standard deviation; when it is more than ``TAIL_MARGIN`` above,
the filtered image's sigma is that scale times its growth from 2 to 3 sigma, (q3 / 3) / (q2 / 2), carried once more
towards the threshold (measured on clamped, correlated 8-bit noise of 1-2 ADU: the scale that gives the normal
tail's pixel count at 1e-5 is 1.07-1.10 x the 3-sigma scale, the growth 1.07-1.11;
tests/test_detect_quantised.py)."""

TAIL_MARGIN = 1.05
"""The tail's scale replaces the clipped standard deviation only when it exceeds it by this factor (a normal sample
of ~48,000 values, every 4th row and column of a 1024 x 768 frame, the sample :func:`matched_filter` takes of a
clamped frame, puts the 3-sigma scale within ~1.2 % (1 sigma) of the standard deviation: 1.05 is ~4 of those
sigmas, so normal frames keep the clipped standard deviation)."""


class FilteredNoise:
    """Noise sigma_F of the matched-filtered image at given pixels, without the (H, W) map: at pixel (r, c) it is
    ratio x e_row(r) x e_col(c) / inv(r, c), with inv the inverse pixel-noise map and e the edge factors of
    :func:`matched_filter`.

    ``noise[r, c]`` (integer index arrays, or scalars) gives float32 values like the map would."""

    def __init__(self, inv, ratio, er, ec):
        self.inv, self.ratio = inv, np.float32(ratio)
        H, W = inv.shape
        self.row = np.ones(H, np.float32)
        self.col = np.ones(W, np.float32)
        for v, e in ((self.row, er), (self.col, ec)):
            v[:e.size] *= e
            v[v.size - e.size:] *= e[::-1]

    def __getitem__(self, rc):
        r, c = rc
        return self.ratio * self.row[r] * self.col[c] / self.inv[r, c]


def matched_filter(R, inv, s, tail=False):
    """Matched-filtered SNR image Z ((H, W) float32, in units of its own noise), the noise ratio sigma_F / sigma
    (float), and Z's noise sigma_F (a :class:`FilteredNoise`: evaluated at pixels on demand) of the
    background-subtracted frame R ((H, W) float32, ADU) with PSF sigma ``s`` (px); ``inv`` ((H, W) float32, 1/ADU)
    is the inverse of the pixel noise (floored), not modified.

    Outside the frame R is 0 (its expectation), so near an edge F sums fewer pixels and its white-noise sigma
    is sigma sqrt(sum over the kernel's in-frame part of K^2): Z is normalised by that, exactly, per row and
    column. Z's scale is measured on a strided sample of F x inv (every :data:`NOISE_SAMPLE_STRIDE`-th row and column,
    half that on a clamped frame; whole taps from the edges): its clipped mean is subtracted and Z divided by its
    clipped standard deviation (the ratio), so a noise correlated between pixels, or a pixel noise the tiles misjudge
    (quantised to one level), is normalised by the filtered noise's own sigma, never by sigma sqrt(sum k^2). ``tail``
    (a frame clamped at its black level, :func:`clamped`) also checks the sample's upper tail (:data:`TAIL_P`). Two
    passes over the frame after the filter: Z = F x inv / ratio, then the centre."""
    import cv2

    H, W = R.shape
    k = psf_kernel_1d(s)
    h = len(k) // 2
    F = cv2.sepFilter2D(R, cv2.CV_32F, k.astype(np.float32), k.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    # the sample: every st-th row and column, from e >= h px from the edges (whole taps); a clamped frame's upper
    # tail is measured on a sample four times larger (TAIL_MARGIN)
    st = NOISE_SAMPLE_STRIDE // 2 if tail else NOISE_SAMPLE_STRIDE
    e = 4 * -(-h // 4)
    inner = (slice(e, max(e + 1, H - e), st), slice(e, max(e + 1, W - e), st))
    sample = (F[inner] * inv[inner]).ravel()
    centre, ratio = robust_stats(sample)       # the filtered noise's own centre and sigma (relative to the map)
    k2 = k * k
    if not ratio > 0:
        centre, ratio = 0.0, float(k2.sum())   # a constant frame: the white-noise ratio
    elif tail and sample.size >= 4096:         # the upper tail's own scale (a clamped noise: TAIL_P)
        tail3 = (order_statistic(sample, int(TAIL_P[1] * sample.size)) - centre) / TAIL_Z[1]
        if tail3 > TAIL_MARGIN * ratio:
            tail2 = (order_statistic(sample, int(TAIL_P[0] * sample.size)) - centre) / TAIL_Z[0]
            ratio = tail3 * max(1.0, tail3 / tail2) if tail2 > 0 else tail3
    cum = np.concatenate([[0.0], np.cumsum(k2)])

    def edge(n):    # sqrt(in-frame sum of k_i^2 / sum k_i^2) for the first min(h, n) positions from an edge
        i = np.arange(min(h, n))
        return np.sqrt((cum[-1] - cum[np.maximum(h - i, 0)]) / cum[-1]).astype(np.float32)  # taps i - h .. h

    er, ec = edge(H), edge(W)
    Z = cv2.multiply(F, inv, dst=F, scale=1.0 / ratio)              # (F / sigma - centre) / ratio
    if centre:
        Z -= np.float32(centre / ratio)
    Z[:er.size] /= er[:, None]
    Z[H - er.size:] /= er[::-1, None]
    Z[:, :ec.size] /= ec[None, :]
    Z[:, W - ec.size:] /= ec[None, ::-1]
    return Z, ratio, FilteredNoise(inv, ratio, er, ec)


CLAMPED_FRACTION = 0.25
"""A frame is clamped at its black level (:func:`clamped`) when more than this fraction of a strided sample of its
pixels hold its smallest value (a normal noise of sigma >= 0.5 ADU puts ~2 % of its pixels at its lowest level only
when sigma < 0.3; a dark-subtracted frame clipped at 0 puts half or more of its sky there)."""


def clamped(img) -> bool:
    """Whether an (H, W) frame (ADU) is clamped at its black level: more than :data:`CLAMPED_FRACTION` of every 4th
    row and column's pixels equal the sample's minimum (and the sample is not constant): its noise is censored,
    skewed to the right (:func:`matched_filter`'s ``tail``)."""
    v = img[::4, ::4]
    if v.size == 0:
        return False
    lo = v.min()
    n_lo = int(np.count_nonzero(v == lo))
    return CLAMPED_FRACTION * v.size < n_lo < v.size


def sparse_components(f: np.ndarray, H: int, W: int, connectivity: int = 8) -> np.ndarray:
    """Connected components of the foreground pixels ``f`` ((n,) int64 flat indices r W + c, ascending) of an
    (H, W) frame, ``connectivity`` 8 or 4: (n,) int64 component of each pixel, numbered 0.. in the order of each
    component's first pixel in raster order (the partition of ``cv2.connectedComponents`` and of
    :mod:`dualsight.kernels.labelling`; tests/test_hil_speed.py).  Works on the foreground pixels only (a few
    thousand on a star frame, not the H W pixels): each pixel's forward neighbours (right; and the row below: left,
    centre, right) found by a binary search in ``f``, then union by minimum root (each edge hooks the larger of its
    two roots under the smaller) and pointer jumping, until no edge joins two roots."""
    n = f.size
    if n == 0:
        return np.zeros(0, np.int64)
    col = f % W
    steps = ((0, 1), (1, -1), (1, 0), (1, 1)) if connectivity == 8 else ((0, 1), (1, 0))
    ea, eb = [], []
    for dr, dc in steps:
        ok = (col + dc >= 0) & (col + dc < W) & (f + dr * W < H * W)
        src = np.flatnonzero(ok)
        tgt = f[src] + (dr * W + dc)
        j = np.searchsorted(f, tgt)
        hit = j < n
        hit[hit] = f[j[hit]] == tgt[hit]
        ea.append(src[hit])
        eb.append(j[hit])
    a, b = np.concatenate(ea), np.concatenate(eb)
    parent = np.arange(n, dtype=np.int64)
    while a.size:
        pa, pb = parent[a], parent[b]
        join = pa != pb
        if not join.any():
            break
        a, b, pa, pb = a[join], b[join], pa[join], pb[join]      # edges inside one tree are done for good
        np.minimum.at(parent, np.maximum(pa, pb), np.minimum(pa, pb))
        while True:                                                 # pointer jumping to the roots
            pp = parent[parent]
            if np.array_equal(pp, parent):
                break
            parent = pp
    roots = parent == np.arange(n)                   # a root is its component's smallest index: raster order
    return np.cumsum(roots)[parent] - 1


def find_candidates(Z, cfg):
    """Candidate stars of the matched-filtered SNR image Z ((H, W) float32, :func:`matched_filter`): the 3 x 3
    local maxima of Z > ``cfg.k_sigma``, grouped into foreground components (``cfg.connectivity``,
    :func:`sparse_components` over the foreground pixels only; with ``cfg.engine`` "taichi" components and
    maxima and deblending in one compiled pass, :func:`dualsight.kernels.detect_passes.candidate_maxima`) and deblended
    (``cfg.deblend_min_sep_px``, ``cfg.deblend_contrast``); components over ``cfg.max_blob_pixels`` are counted,
    not searched.

    Returns (rows, cols, npix of their component) (K,) int64 each of the kept maxima, and the number of large
    components (int)."""
    H, W = Z.shape
    # foreground Z > k_sigma (float32 compare equal to the float64 one: kernels.labelling.native_threshold)
    t = np.float32(cfg.k_sigma)
    if float(t) > cfg.k_sigma:
        t = np.nextafter(t, np.float32(-np.inf))
    f = np.flatnonzero(Z > t)                    # the foreground pixels (a few thousand): work on them only
    if f.size == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, 0
    if cfg.engine == "taichi":     # components, local maxima and deblending in one compiled pass over the foreground
        return candidate_maxima(f, Z, cfg.connectivity, cfg.max_blob_pixels, cfg.deblend_min_sep_px,
                                cfg.deblend_contrast)
    fr, fc = np.divmod(f, W)
    lab_f = sparse_components(f, H, W, cfg.connectivity)
    # the 3 x 3 local maxima among the foreground pixels (outside the frame ignored: clipped indices repeat
    # an in-frame pixel of the neighbourhood), from their 8 neighbours' values
    zf = Z.ravel()[f]
    peak = np.ones(f.size, bool)
    for dr in (-1, 0, 1):
        rr = np.clip(fr + dr, 0, H - 1) * W
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= zf >= Z.ravel()[rr + np.clip(fc + dc, 0, W - 1)]
    npix_c = np.bincount(lab_f).astype(np.int64)
    f = f[peak]
    pr, pc = fr[peak].astype(np.int64), fc[peak].astype(np.int64)
    cid = lab_f[peak]
    large = npix_c > cfg.max_blob_pixels
    n_large = int(large.sum())
    keep = ~large[cid]
    pr, pc, cid = pr[keep], pc[keep], cid[keep]
    z = Z[pr, pc]
    order = np.lexsort((pc, pr, -z, cid))
    pr, pc, cid, z = pr[order], pc[order], cid[order], z[order]
    first = np.ones(len(cid), bool)
    first[1:] = cid[1:] != cid[:-1]
    accept = first.copy()
    multi = np.flatnonzero(~first)
    if multi.size:
        # pairs (j, i): j a secondary maximum, i a brighter maximum of the same component
        start = np.searchsorted(cid, cid[multi], side="left")
        cnt = multi - start
        j = np.repeat(multi, cnt)
        i = np.repeat(start, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        dy, dx = (pr[j] - pr[i]).astype(np.float64), (pc[j] - pc[i]).astype(np.float64)
        far = np.hypot(dx, dy) >= cfg.deblend_min_sep_px
        dip = np.full(j.size, np.inf)
        for t in (0.25, 0.5, 0.75):
            rr = np.rint(pr[i] + t * dy).astype(np.int64)
            cc = np.rint(pc[i] + t * dx).astype(np.int64)
            dip = np.minimum(dip, Z[rr, cc])
        sep = far & (dip < (1.0 - cfg.deblend_contrast) * z[j])
        bad = np.zeros(len(cid), bool)
        np.logical_or.at(bad, j, ~sep)
        accept[multi] = ~bad[multi]
    return pr[accept], pc[accept], npix_c[cid[accept]], n_large
