"""Detections -> observed star directions: the input of star identification.

Between detection (``kernels.detect``: ragged centroids per frame, brightest first) and voting
(``nav.starid``): each case keeps its brightest ``max_obs`` detections, padded to (B, S), and their
centroids are back-projected through the camera model (distortion removed) to camera-frame unit vectors.
Pixel coordinates are (col, row) from the image's top-left corner (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MAX_OBS", "Observations", "observations", "ragged_rank"]

MAX_OBS = 100
"""Detections per case that are kept as observations by default (brightest first)."""


@dataclass(frozen=True)
class Observations:
    """Observed stars per case, padded to (B, S), brightest first.

    vec : (B, S, 3) float64 camera-frame unit vectors (NaN in padding).
    valid : (B, S) bool, a real observation.
    x, y : (B, S) float64 centroid (col, row) in pixels (NaN in padding).
    """

    vec: np.ndarray
    valid: np.ndarray
    x: np.ndarray
    y: np.ndarray


def ragged_rank(case: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(case (K,) int64, rank (K,) int64 of each entry within its case) of ragged per-case arrays whose
    case b holds entries ``offsets[b]:offsets[b + 1]``."""
    case = np.asarray(case).astype(np.int64)
    return case, np.arange(len(case)) - np.asarray(offsets)[case]


def observations(det, B: int, camera, max_obs: int = MAX_OBS) -> Observations:
    """Back-project the detections of B frames; keep at most ``max_obs`` per case.

    det : detections sorted by (case, flux descending), as ``kernels.detect.Detections``: ``case`` (K,)
        frame index, ``x``, ``y`` (K,) centroids (px), ``offsets`` (B + 1,) frame b's entries.
    camera : ``scene.camera.Camera`` (``backproject``: pixels -> unit vectors).
    S = max(1, min(max_obs, most detections in a frame)).
    """
    counts = np.diff(det.offsets)
    S = int(max(1, min(max_obs, counts.max() if B else 1)))
    case, rank = ragged_rank(det.case, det.offsets)
    keep = rank < S
    valid = np.zeros((B, S), dtype=bool)
    x = np.full((B, S), np.nan)
    y = np.full((B, S), np.nan)
    valid[case[keep], rank[keep]] = True
    x[case[keep], rank[keep]] = det.x[keep]
    y[case[keep], rank[keep]] = det.y[keep]
    vec = camera.backproject(np.stack([np.nan_to_num(x), np.nan_to_num(y)], axis=-1))
    vec[~valid] = np.nan
    return Observations(vec, valid, x, y)
