"""Candidate stage of the real-sensor detector (:mod:`dualsight.kernels.detect_local`): the matched filter
(the pixel-integrated Gaussian PSF, in units of the filtered image's own noise) and the candidate blobs above
its threshold (OpenCV connected components on the foreground pixels only, with their local maxima).  Pure
numpy/OpenCV functions over arrays; ``cfg`` is a ``LocalDetectConfig``."""

import numpy as np

from dualsight.kernels.detect_background import _robust_std
from dualsight.kernels.detect_psf import psf_kernel_1d


def _filter(R, sig_map, s, floor, cache=None):
    """Matched-filtered SNR image Z (float32) of residual R with PSF sigma s, and the noise ratio sigma_F / sigma.

    Outside the frame R is 0 (its expectation), so near an edge F sums fewer pixels and its white-noise sigma
    is sigma sqrt(sum over the kernel's in-frame part of K^2): Z is normalised by that, exactly, per row and
    column.  ``sig_map`` is overwritten; ``cache`` (a dict) keeps R's sample noise between calls on the same R."""
    import cv2

    H, W = R.shape
    k = psf_kernel_1d(s)
    h = len(k) // 2
    F = cv2.sepFilter2D(R, cv2.CV_32F, k.astype(np.float32), k.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    inner = (slice(h, max(h + 1, H - h), 4), slice(h, max(h + 1, W - h), 4))
    sa = cache.get(h) if cache is not None else None       # R's noise at the sample: the same for both passes
    if sa is None:
        sa = _robust_std(R[inner])
        if cache is not None:
            cache[h] = sa
    sfv = _robust_std(F[inner])
    k2 = k * k
    white = float(k2.sum())
    ratio = sfv / sa if sa > 0 and sfv > 0 else white
    np.maximum(sig_map, floor, out=sig_map)
    sig_map *= np.float32(ratio)
    cum = np.concatenate([[0.0], np.cumsum(k2)])

    def edge(n):    # sqrt(in-frame sum of k_i^2 / sum k_i^2) for the first min(h, n) positions from an edge
        i = np.arange(min(h, n))
        return np.sqrt((cum[-1] - cum[np.maximum(h - i, 0)]) / cum[-1]).astype(np.float32)  # taps i - h .. h

    er, ec = edge(H), edge(W)
    sig_map[:er.size] *= er[:, None]
    sig_map[H - er.size:] *= er[::-1, None]
    sig_map[:, :ec.size] *= ec[None, :]
    sig_map[:, W - ec.size:] *= ec[None, ::-1]
    np.divide(F, sig_map, out=F)
    return F, ratio


def _candidates(Z, cfg):
    """Local maxima of Z above the threshold, grouped into components and deblended.

    Returns (rows, cols, npix of their component) of the kept maxima, number of large components."""
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
    # the 3 x 3 local maxima among the foreground pixels (outside the frame ignored, as clipped indices do)
    peak = Z.ravel()[f] >= cv2.dilate(Z, np.ones((3, 3), np.uint8)).ravel()[f]
    f = f[peak]
    pr, pc = np.divmod(f.astype(np.int64), W)
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
