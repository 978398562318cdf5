"""Simulation truth of the detections: which rendered catalog star each detection is, and whether the
identities the voting accepted are right.

A detection is the rendered star (same case) whose true position is nearest to its centroid, when that
star lies within ``radius_px``; otherwise it has no truth (a false star, noise, or stars merged far
from both).  Pixel coordinates are (col, row) from the image's top-left corner (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.nav.observations import Observations, ragged_rank
from dualsight.scene.starfield_geometry import FieldStars

__all__ = ["Truth", "match_truth"]

_UNMATCHED = -2
"""True row of an observation without a matching star: never equal to an identity, so it counts as wrong."""


@dataclass(frozen=True)
class Truth:
    """Truth of each detection and of each observation.

    true_row : (K,) int64 catalog row of each detection, -1 = none.
    hip_true : (K,) HIP number of that star or -1.
    dist_px : (K,) float64 distance from the centroid to that star (px), NaN if none.
    obs_true_row : (B, S) int64 the same, laid out like :class:`~dualsight.nav.observations.Observations`
        (-2 where no star matches).
    """

    true_row: np.ndarray
    hip_true: np.ndarray
    dist_px: np.ndarray
    obs_true_row: np.ndarray

    def _assigned(self, ident):
        S = min(ident.ids.shape[1], self.obs_true_row.shape[1])
        ids = ident.ids[:, :S]
        acc = ident.accepted[:, :S] & (ids >= 0)
        return ids, acc, self.obs_true_row[:, :S]

    def n_correct(self, ident) -> np.ndarray:
        """(B,) accepted identities equal to the truth (``ident``: ``nav.starid.Identification``)."""
        ids, acc, tr = self._assigned(ident)
        return (acc & (ids == tr)).sum(axis=1)

    def n_wrong(self, ident) -> np.ndarray:
        """(B,) accepted identities that differ from the truth (or have none)."""
        ids, acc, tr = self._assigned(ident)
        return (acc & (ids != tr)).sum(axis=1)

    def id_correct(self, ident) -> np.ndarray:
        """(B,) every accepted identity is right and there are at least two of them."""
        ids, acc, tr = self._assigned(ident)
        return (acc.sum(1) >= 2) & ~(acc & (ids != tr)).any(axis=1)


def match_truth(det, field_: FieldStars, obs: Observations, cat_hip: np.ndarray, radius_px: float = 2.0) -> Truth:
    """Nearest rendered star (same case) of each detection, within ``radius_px``.

    det : detections as ``kernels.detect.Detections`` (``case``, ``x``, ``y`` (K,), ``offsets`` (B + 1,));
    field_ : the rendered stars (``scene.starfield_geometry.stars_in_field``); obs : the observations made
    from ``det`` (for the (B, S) layout); cat_hip : (N,) HIP number of each catalog row.
    """
    case, rank = ragged_rank(det.case, det.offsets)
    dx = det.x[:, None] - field_.x[case]
    dy = det.y[:, None] - field_.y[case]
    d2 = np.where(field_.valid[case], dx * dx + dy * dy, np.inf)
    k = np.argmin(d2, axis=1) if d2.shape[1] else np.zeros(len(case), dtype=np.int64)
    dist = np.sqrt(d2[np.arange(len(case)), k]) if len(case) else np.zeros(0)
    hit = dist <= radius_px
    row = np.where(hit, field_.cat_row[case, k] if len(case) else 0, -1)
    hip = np.where(row >= 0, cat_hip[np.maximum(row, 0)], -1)
    B, S = obs.valid.shape
    keep = rank < S
    otr = np.full((B, S), _UNMATCHED, dtype=np.int64)
    otr[case[keep], rank[keep]] = np.where(row[keep] >= 0, row[keep], _UNMATCHED)
    return Truth(row, hip, np.where(hit, dist, np.nan), otr)
