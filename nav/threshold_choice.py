"""Choosing the binary threshold of the proximity blobber on real photos (``dualsight hil prox --sweep``): pure
functions over a sweep's range estimates.

Input: ``thresholds`` (T,) in image units, ascending; ``range_m`` (N, T) the range estimate (m) of each of N
images at each threshold, NaN where no blob was found; ``truth_m`` (N,) true ranges (m), NaN where unknown;
``rel_error_pct`` (T,) the average relative range error (%) per threshold, NaN where it is unknown.

* :func:`stable_threshold` chooses without the truth: where the estimates change least with the threshold.
* :func:`oracle_threshold` chooses WITH the truth (the smallest average error): an optimistic bound, not what a
  user without truth gets; :func:`cross_validated_error` is what that choice costs on an image it did not see.
"""

from __future__ import annotations

import numpy as np

__all__ = ["stable_threshold", "oracle_threshold", "cross_validated_error"]


def stable_threshold(thresholds, range_m) -> float | None:
    """The threshold where the images' range estimates change least with the threshold: the smallest mean
    |d ln range| to the neighbouring thresholds over the images with a blob at both (the middle of the
    flattest part of the sweep), among the thresholds that find the target in at least half as many images as
    the best one.  thresholds (T,), range_m (N, T) m (NaN: no blob).  None with fewer than 3 thresholds or
    when no threshold has a finite score."""
    th = np.asarray(thresholds, dtype=float)
    est = np.asarray(range_m, dtype=float)
    if len(th) < 3:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.diff(np.log(est), axis=1))                    # (N, T - 1)
        step = np.nanmean(d, axis=0)                                # per interval
    left = np.concatenate([[np.nan], step])
    right = np.concatenate([step, [np.nan]])
    score = np.nanmean(np.stack([left, right]), axis=0)
    found = np.isfinite(est).mean(axis=0)
    score = np.where(found >= 0.5 * found.max(), score, np.nan)     # a threshold that loses the target is no choice
    return float(th[int(np.nanargmin(score))]) if np.isfinite(score).any() else None


def oracle_threshold(thresholds, rel_error_pct) -> float | None:
    """The threshold with the smallest average relative error (the first one on a tie): chosen WITH the truth.
    thresholds (T,), rel_error_pct (T,) % (NaN: unknown).  None when no threshold has an error."""
    th = np.asarray(thresholds, dtype=float)
    rel = np.asarray(rel_error_pct, dtype=float)
    return float(th[int(np.nanargmin(rel))]) if np.isfinite(rel).any() else None


def cross_validated_error(range_m, truth_m) -> float | None:
    """Leave-one-image-out error of choosing the threshold with the truth: for each image with a truth, pick the
    threshold with the smallest mean relative error over the OTHER images, and take this image's relative error
    there (no blob counts as 100 %).  range_m (N, T) m (NaN: no blob), truth_m (N,) m (NaN: unknown).  Returns
    the mean, in %, or None (fewer than 2 images with a truth)."""
    est = np.asarray(range_m, dtype=float)
    truth = np.asarray(truth_m, dtype=float)
    keep = np.isfinite(truth)
    est, truth = est[keep], truth[keep]
    n = len(truth)
    if n < 2:
        return None
    rel = np.where(np.isfinite(est), np.abs(est - truth[:, None]) / truth[:, None], 1.0)   # (n, T)
    others = (rel.sum(axis=0)[None, :] - rel) / (n - 1)                                      # (n, T)
    pick = np.argmin(others, axis=1)
    return float(100.0 * rel[np.arange(n), pick].mean())
