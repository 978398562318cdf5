"""Stage 2 of the real-sensor detector (:mod:`dualsight.kernels.detect_local`, steps 2 and 3 of its docstring):
the matched filter (:func:`matched_filter`: the background-subtracted frame correlated with the pixel-integrated
Gaussian PSF, in units of the filtered image's own noise) and the candidate stars above its threshold
(:func:`find_candidates`: OpenCV connected components of the foreground, their local maxima, deblending).  Pure
numpy/OpenCV functions over arrays; ``cfg`` is a :class:`~dualsight.kernels.detect_local.LocalDetectConfig`."""

import numpy as np

from dualsight.kernels.detect_background import robust_std
from dualsight.kernels.detect_psf import psf_kernel_1d


NOISE_SAMPLE_STRIDE = 4
"""Rows and columns between the pixels of the noise sample of :func:`matched_filter` (~48,000 pixels of a 1024 x 768
frame: the ratio sigma_F / sigma to ~0.3 %)."""


class FilteredNoise:
    """Noise sigma_F of the matched-filtered image at given pixels, without the (H, W) map: at pixel (r, c) it is
    max(sigma(r, c), floor) x ratio x e_row(r) x e_col(c), with e the edge factors of :func:`matched_filter`.

    ``noise[r, c]`` (integer index arrays, or scalars) gives float32 values like the map would."""

    def __init__(self, sig_map, floor, ratio, er, ec):
        self.sig_map, self.floor, self.ratio = sig_map, np.float32(floor), np.float32(ratio)
        H, W = sig_map.shape
        self.row = np.ones(H, np.float32)
        self.col = np.ones(W, np.float32)
        for v, e in ((self.row, er), (self.col, ec)):
            v[:e.size] *= e
            v[v.size - e.size:] *= e[::-1]

    def __getitem__(self, rc):
        r, c = rc
        return np.maximum(self.sig_map[r, c], self.floor) * self.ratio * self.row[r] * self.col[c]


def matched_filter(R, sig_map, s, floor, cache=None):
    """Matched-filtered SNR image Z ((H, W) float32, in units of its own noise), the noise ratio sigma_F / sigma
    (float), and Z's noise sigma_F (a :class:`FilteredNoise`: evaluated at pixels on demand) of the
    background-subtracted frame R ((H, W) float32, ADU) with PSF sigma ``s`` (px); ``floor`` (ADU, float32) is
    the smallest pixel noise used.

    Outside the frame R is 0 (its expectation), so near an edge F sums fewer pixels and its white-noise sigma
    is sigma sqrt(sum over the kernel's in-frame part of K^2): Z is normalised by that, exactly, per row and
    column.  ``sig_map`` (the pixel noise, (H, W) float32) is not modified; ``cache`` (a dict, one per R) keeps
    R's sample noise and 1 / max(sig_map, floor) between calls on the same R."""
    import cv2

    H, W = R.shape
    cache = {} if cache is None else cache
    k = psf_kernel_1d(s)
    h = len(k) // 2
    F = cv2.sepFilter2D(R, cv2.CV_32F, k.astype(np.float32), k.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    st = NOISE_SAMPLE_STRIDE  # the sample: every st-th row and column, from e >= h px from the edges (whole taps)
    e = 4 * -(-h // 4)
    inner = (slice(e, max(e + 1, H - e), st), slice(e, max(e + 1, W - e), st))
    sa = cache.get(e)         # R's noise at the sample: the same for both passes (unless their e differ)
    if sa is None:
        sa = cache[e] = robust_std(R[inner])
    sfv = robust_std(F[inner])
    k2 = k * k
    white = float(k2.sum())
    ratio = sfv / sa if sa > 0 and sfv > 0 else white
    inv = cache.get("inv")
    if inv is None:
        inv = cache["inv"] = 1.0 / np.maximum(sig_map, np.float32(floor))
    cum = np.concatenate([[0.0], np.cumsum(k2)])

    def edge(n):    # sqrt(in-frame sum of k_i^2 / sum k_i^2) for the first min(h, n) positions from an edge
        i = np.arange(min(h, n))
        return np.sqrt((cum[-1] - cum[np.maximum(h - i, 0)]) / cum[-1]).astype(np.float32)  # taps i - h .. h

    er, ec = edge(H), edge(W)
    Z = cv2.multiply(F, inv, dst=F, scale=1.0 / ratio)           # F / (max(sigma, floor) ratio)
    Z[:er.size] /= er[:, None]
    Z[H - er.size:] /= er[::-1, None]
    Z[:, :ec.size] /= ec[None, :]
    Z[:, W - ec.size:] /= ec[None, ::-1]
    return Z, ratio, FilteredNoise(sig_map, floor, ratio, er, ec)


def find_candidates(Z, cfg):
    """Candidate stars of the matched-filtered SNR image Z ((H, W) float32, :func:`matched_filter`): the 3 x 3
    local maxima of Z > ``cfg.k_sigma``, grouped into foreground components (``cfg.connectivity``) and deblended
    (``cfg.deblend_min_sep_px``, ``cfg.deblend_contrast``); components over ``cfg.max_blob_pixels`` are counted,
    not searched.

    Returns (rows, cols, npix of their component) (K,) int64 each of the kept maxima, and the number of large
    components (int)."""
    import cv2

    H, W = Z.shape
    # foreground Z > k_sigma (float32 compare equal to the float64 one: kernels.labelling.native_threshold)
    t = np.float32(cfg.k_sigma)
    if float(t) > cfg.k_sigma:
        t = np.nextafter(t, np.float32(-np.inf))
    fg = Z > t
    n_lab, lab = cv2.connectedComponents(fg.view(np.uint8), connectivity=cfg.connectivity, ltype=cv2.CV_32S)
    if n_lab <= 1:
        e = np.zeros(0, np.int64)
        return e, e, e, 0
    f = np.flatnonzero(fg)                       # the foreground pixels (a few thousand): work on them only
    lab_f = lab.ravel()[f]
    npix_c = np.bincount(lab_f, minlength=n_lab)[1:].astype(np.int64)
    # the 3 x 3 local maxima among the foreground pixels (outside the frame ignored: clipped indices repeat
    # an in-frame pixel of the neighbourhood), from their 8 neighbours' values
    fr, fc = np.divmod(f, W)
    zf = Z.ravel()[f]
    peak = np.ones(f.size, bool)
    for dr in (-1, 0, 1):
        rr = np.clip(fr + dr, 0, H - 1) * W
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= zf >= Z.ravel()[rr + np.clip(fc + dc, 0, W - 1)]
    f = f[peak]
    pr, pc = fr[peak].astype(np.int64), fc[peak].astype(np.int64)
    cid = lab_f[peak].astype(np.int64) - 1
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
