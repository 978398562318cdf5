"""Observed stars -> identities -> attitude and its errors: stages 7-8 of docs/architecture.md on the
:class:`~dualsight.nav.observations.Observations` of a batch.

* :func:`identify`: geometric voting (``nav.starid``) over the pair catalog;
* :func:`solve`: SVD attitude from the accepted stars (Markley 1988, ``nav.attitude``), each identified
  star's residual, and, when the true attitude is known, the reference's Eqs. 4-7 per-axis errors and the
  case's status (``nav.errors``).

Angles in radians; attitude matrices map inertial (ICRS) vectors into the camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.nav.attitude import solve_identified
from dualsight.nav.errors import axis_errors, classify, total_error_angle
from dualsight.nav.observations import Observations
from dualsight.nav.starid import identify as vote_identify
from dualsight.scene.attitude import angle_between

__all__ = ["identify", "Solution", "solve"]


def identify(obs: Observations, cat_unit: np.ndarray, pairs, voting):
    """Identities of the observed stars by geometric voting: ``nav.starid.identify``.

    cat_unit : (N, 3) ICRS unit vectors of the catalog; pairs : the pair catalog (``catalogs.pairs``:
    ``i``, ``j`` catalog rows and ``angle`` (rad), sorted by angle); voting : ``VotingConfig``.
    Returns ``nav.starid.Identification`` ((B, S) ``ids``, ``accepted``, ``votes``, ``verify_votes``; (B,) ``T``).
    """
    return vote_identify(obs.vec, obs.valid, cat_unit, pairs.i, pairs.j, pairs.angle, voting)


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


def solve(obs: Observations, ident, cat_unit: np.ndarray, A_true: np.ndarray | None,
          error_frame: str = "camera") -> Solution:
    """SVD attitude from the accepted stars; Eqs. 4-7 errors and status when ``A_true`` (B, 3, 3) is given.

    ident : ``nav.starid.Identification`` of ``obs``; cat_unit : (N, 3) ICRS unit vectors;
    error_frame : axes of the per-axis errors, ``"camera"`` or ``"inertial"`` (``nav.errors.axis_errors``).
    """
    A, ok = solve_identified(obs.vec, ident.ids, ident.accepted, cat_unit)
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
