"""Blob extraction for the proximity blobber, batched over B frames: threshold, label, measure.

The labelling and the moment sums are :mod:`dualsight.kernels.labelling`'s (run-length union-find, 8- or
4-connectivity, the one labeller also used by star detection).  This module picks, per frame, the number of
blobs, the largest blob (most pixels; ties -> the first in raster order), its moment sums, bounding box and
optionally its mask, and the moment sums of all foreground pixels.

Moment sums (float64), pixel centres at (col + 0.5, row + 0.5) (docs/architecture.md, Conventions), ``I`` the
image value, ``w`` the coverage (1 when no coverage image is given):

    0 n      1 sum x    2 sum y    3 sum x^2   4 sum x y   5 sum y^2         (whole pixels)
    6 sum I  7 sum I x  8 sum I y                                            (intensity)
    9 sum w  10 sum w x 11 sum w y 12 sum w x^2 13 sum w x y 14 sum w y^2   (coverage)
"""

import numpy as np

from dualsight.kernels.labelling import NSTAT, label_frames

__all__ = ["label_blobs"]


def label_blobs(images, threshold=0.0, coverage=None, connectivity: int = 8, *, return_mask: bool = False,
                chunk_frames: int = 32) -> dict:
    """Threshold, label and measure blobs in a batch of frames.

    Parameters
    ----------
    images : (B, H, W) or (H, W) float image (any real dtype; converted to float32).
    threshold : scalar or (B,) (rounded to float32): foreground is ``image > threshold``.
    coverage : optional (B, H, W) per-pixel coverage in [0, 1] (the ``accurate`` renderer's); the
        ``sw*`` sums use it, else they equal the whole-pixel sums.
    connectivity : 8 (default) or 4.
    return_mask : also return ``mask`` (B, H, W) bool of the largest blob.
    chunk_frames : frames labelled per kernel call (bounds the run arrays' memory).

    Returns
    -------
    dict with ``n_blobs`` (B,) int32, ``best`` (B, 15) float64 moment sums of the largest blob (see
    module docstring), ``all`` (B, 15) sums over every foreground pixel, ``box`` (B, 4) int32
    [x0, y0, x1, y1] inclusive bounding box of the largest blob (x1 < 0: no blob), and ``mask``.
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    img = np.asarray(images)
    if img.ndim == 2:
        img = img[None]
    B, H, W = img.shape
    thr = np.broadcast_to(np.asarray(threshold, dtype=np.float32), (B,)).astype(np.float64)
    cov = None if coverage is None else np.asarray(coverage)
    if cov is not None and cov.ndim == 2:
        cov = cov[None]
    out = dict(n_blobs=np.zeros(B, np.int32), best=np.zeros((B, NSTAT)), all=np.zeros((B, NSTAT)),
               box=np.tile(np.array([1 << 30, 1 << 30, -1, -1], np.int32), (B, 1)))
    if return_mask:
        out["mask"] = np.zeros((B, H, W), bool)
    chunk = max(1, min(chunk_frames, (2 ** 31 - 1) // max(1, H * W)))
    for s in range(0, B, chunk):  # chunks of frames bound the run arrays' memory
        e = min(s + chunk, B)
        comp = label_frames(np.ascontiguousarray(img[s:e], dtype=np.float32), thr[s:e],
                            coverage=None if cov is None else np.ascontiguousarray(cov[s:e], dtype=np.float32),
                            connectivity=connectivity)
        out["all"][s:e] = comp.seg_stats
        out["n_blobs"][s:e] = comp.counts
        if len(comp) == 0:
            continue
        # largest blob per frame: most pixels, ties -> the first in raster order (lowest index)
        has = np.flatnonzero(comp.counts)
        most = np.maximum.reduceat(comp.npix, comp.offsets[has])
        cand = np.flatnonzero(comp.npix == np.repeat(most, comp.counts[has]))
        _, first = np.unique(comp.seg[cand], return_index=True)
        best = cand[first]
        out["best"][s + comp.seg[best]] = comp.moments(best)
        out["box"][s + comp.seg[best]] = comp.box[best]
        if return_mask:
            best_of_frame = np.full(e - s, -1, np.int64)
            best_of_frame[comp.seg[best]] = best
            comp.paint(out["mask"][s:e], comp.run_label == best_of_frame[comp.run_seg], True)
    return out
