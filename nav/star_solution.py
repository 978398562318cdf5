"""Observed stars -> identities -> attitude and its errors: stages 7-8 of docs/architecture.md on the
:class:`~dualsight.nav.observations.Observations` of a batch.

* :func:`identify`: geometric voting (``nav.starid``) over the pair catalog;
* :func:`solve`: SVD attitude from the accepted stars (Markley 1988, ``nav.attitude``), each identified
  star's residual, and, when the true attitude is known, the reference's Eqs. 4-7 per-axis errors and the
  case's status (``nav.errors``).  Stars are weighted equally unless ``weights`` are given, e.g.
  :func:`centroid_weights` from the detector's centroid uncertainties.

Angles in radians; attitude matrices map inertial (ICRS) vectors into the camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.nav.attitude import solve_identified
from dualsight.nav.errors import axis_errors, classify, total_error_angle
from dualsight.nav.observations import Observations, ragged_rank
from dualsight.nav.pair_index import VotingIndex
from dualsight.nav.starid import identify as vote_identify
from dualsight.scene.units import angle_between

__all__ = ["identify", "Solution", "solve", "centroid_weights"]


def identify(obs: Observations, cat_unit: np.ndarray, pairs, voting, cat_vmag: np.ndarray | None = None,
             chance: bool = True, engine: str = "taichi"):
    """Identities of the observed stars by geometric voting: ``nav.starid.identify``.

    cat_unit : (N, 3) ICRS unit vectors of the catalog; pairs : the pair catalog (``catalogs.pairs``:
    ``i``, ``j`` catalog rows and ``angle`` (rad), sorted by angle) or its ``nav.pair_index.VotingIndex``
    (e.g. :meth:`~dualsight.nav.pair_index.VotingIndex.load_or_build`'s, passed as is); voting : ``VotingConfig``.
    Returns ``nav.starid.Identification`` ((B, S) ``ids``, ``accepted``, ``votes``, ``verify_votes``; (B,) ``T``
    and ``p_chance``, the answer's chance-match probability, ``nav.chance``).  cat_vmag : optional (N,) V
    magnitudes of the catalog, for the blend test (only doubles of similar brightness are ambiguous).
    chance : compute ``p_chance`` (False skips it: NaN).  engine : "taichi" or "numpy" (bit-identical).
    """
    if isinstance(pairs, VotingIndex):
        return vote_identify(obs.vec, obs.valid, cat_unit, pairs, cfg=voting, cat_vmag=cat_vmag, chance=chance,
                             engine=engine)
    return vote_identify(obs.vec, obs.valid, cat_unit, pairs.i, pairs.j, pairs.angle, voting, cat_vmag=cat_vmag,
                         chance=chance, engine=engine)


@dataclass(frozen=True)
class Solution:
    """Attitude of each case from its accepted identities.

    A_est : (B, 3, 3) inertial -> camera, NaN where no attitude.
    ok : (B,) bool, an attitude was solved.
    axis_err : (B, 3) rad, Eqs. 4-7 error per axis (NaN without truth or attitude).
    total_err : (B,) rad, rotation angle of A_est^T A_true (NaN without truth or attitude).
    status : (B,) int8 codes of ``nav.errors.STATUS_NAMES`` (0 without truth).
    residual : (B, S) rad, angle between each identified star and its position predicted by A_est
        (NaN where not identified).
    """

    A_est: np.ndarray
    ok: np.ndarray
    axis_err: np.ndarray
    total_err: np.ndarray
    status: np.ndarray
    residual: np.ndarray


def centroid_weights(det, obs: Observations, floor_px: float = 0.0) -> np.ndarray | None:
    """(B, S) attitude weights w = 1 / (sigma_px^2 + floor_px^2) of the observations (Wahba's problem with
    w_k = 1 / sigma_k^2, Markley 1988), from the detections' centroid uncertainties ``det.sigma_px`` (px, per
    axis; matched to the observations by their rank in the frame, as ``nav.observations`` keeps them).

    ``floor_px`` adds a systematic centroid error in quadrature (PSF model, distortion, catalog): without it
    the brightest stars' Cramér-Rao bounds (~0.01 px) would outweigh all others.  Only relative weights
    matter for the attitude.  None when the detections state no uncertainty (equal weights)."""
    sig = getattr(det, "sigma_px", None)
    if sig is None:
        return None
    B, S = obs.valid.shape
    case, rank = ragged_rank(det.case, det.offsets)
    keep = rank < S
    w = np.zeros((B, S))
    s2 = np.asarray(sig, np.float64)[keep] ** 2 + float(floor_px) ** 2
    w[case[keep], rank[keep]] = np.where(np.isfinite(s2) & (s2 > 0), 1.0 / np.where(s2 > 0, s2, 1.0), 0.0)
    bad = obs.valid & ~(w > 0)
    if bad.any():        # no usable uncertainty: the frame's median weight
        med = np.array([np.median(w[b][w[b] > 0]) if (w[b] > 0).any() else 1.0 for b in range(B)])
        w = np.where(bad, med[:, None], w)
    return np.where(obs.valid, w, 0.0)


def solve(obs: Observations, ident, cat_unit: np.ndarray, A_true: np.ndarray | None,
          error_frame: str = "camera", weights: np.ndarray | None = None) -> Solution:
    """SVD attitude from the accepted stars; Eqs. 4-7 errors and status when ``A_true`` (B, 3, 3) is given.

    ident : ``nav.starid.Identification`` of ``obs``; cat_unit : (N, 3) ICRS unit vectors;
    error_frame : axes of the per-axis errors, ``"camera"`` or ``"inertial"`` (``nav.errors.axis_errors``);
    weights : optional (B, S) non-negative weight of each observation (e.g. :func:`centroid_weights`);
        None = every accepted star weighs 1 (the reference's method).
    """
    A, ok = solve_identified(obs.vec, ident.ids, ident.accepted, cat_unit, weights)
    B = A.shape[0]
    ids = ident.ids
    pred = np.einsum("bij,bsj->bsi", A, cat_unit[np.maximum(ids, 0)])
    residual = np.where((ids >= 0) & obs.valid, angle_between(pred, obs.vec), np.nan)
    if A_true is None:
        nan3 = np.full((B, 3), np.nan)
        return Solution(A, ok, nan3, np.full(B, np.nan), np.zeros(B, np.int8), residual)
    err = axis_errors(A, A_true, frame=error_frame)
    tot = total_error_angle(A, A_true)
    return Solution(A, ok, err, tot, classify(err, tot, ident.T), residual)
