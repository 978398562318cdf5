"""Blobs no star can make, kept out of star identification (issue 23, point 2).

A star is a point: its blob is the PSF above the detection threshold, and its size grows with its brightness only
through the PSF's wings and the saturated core.  So no star blob is larger than the blob of the brightest star
of the catalog (V -1.46, Sirius, for Hipparcos) through the same optics, sensor and detector: the caller measures
that size (``npix_brightest``: blobs of that star rendered at a few sub-pixel positions) and every blob above the
limit (with a margin for noise and for two stars merged) is a resolved object -- the target spacecraft, the Moon,
a planet's disk -- and never votes.  A point-like target passes this test and is left to the robust voting, which
rejects false stars (``nav/starid.py``, ``nav/verify.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dualsight.nav.observations import Observations, ragged_rank

__all__ = ["STAR_BLOB_FACTOR", "STAR_BLOB_MARGIN_PX", "star_blob_limit", "excluded_blobs", "without_excluded"]

STAR_BLOB_FACTOR = 1.5
"""A blob is larger than any star's when it has more than this many times the brightest star's pixels ..."""
STAR_BLOB_MARGIN_PX = 4
"""... plus this many pixels (shot noise along the threshold contour of a small blob)."""


def star_blob_limit(npix_brightest) -> int:
    """Most pixels a star's blob may have: ``ceil(STAR_BLOB_FACTOR * max(npix_brightest)) + STAR_BLOB_MARGIN_PX``.

    npix_brightest : (n,) pixel counts of the brightest catalog star's blobs rendered by the caller (n >= 1)."""
    n = np.asarray(npix_brightest)
    if n.size == 0:
        raise ValueError("star_blob_limit needs at least one blob of the brightest star")
    return int(np.ceil(STAR_BLOB_FACTOR * n.max())) + STAR_BLOB_MARGIN_PX


def excluded_blobs(npix, limit: int) -> np.ndarray:
    """(K,) bool: blobs with more than ``limit`` pixels (``npix`` (K,) pixel counts of the detections)."""
    return np.asarray(npix) > limit


def without_excluded(obs: Observations, case: np.ndarray, offsets: np.ndarray, excluded: np.ndarray) -> Observations:
    """``obs`` with the excluded detections made invalid (vector and centroid NaN), in place of nothing else.

    case, offsets : the detections' ragged layout (``kernels.detect.Detections``: frame of each blob, frame b's
    blobs ``offsets[b]:offsets[b + 1]``, in the order ``nav.observations.observations`` ranked them);
    excluded : (K,) bool.  Stars keep their slots, so the brightness ranks of the voters stay the order of the
    remaining valid stars (``nav/widen.valid_rank``)."""
    cl, rank = ragged_rank(case, offsets)
    S = obs.valid.shape[1]
    hit = np.asarray(excluded, bool) & (rank < S)
    valid, vec, x, y = obs.valid.copy(), obs.vec.copy(), obs.x.copy(), obs.y.copy()
    valid[cl[hit], rank[hit]] = False
    vec[cl[hit], rank[hit]] = np.nan
    x[cl[hit], rank[hit]] = np.nan
    y[cl[hit], rank[hit]] = np.nan
    return dataclasses.replace(obs, vec=vec, valid=valid, x=x, y=y)
